"""The realm's inventory: which agents are alive, once their set has settled, and every
agent's snapshot of its services, needs, abilities and matches, as one JSON-able dict.

``uma services`` prints it and ``uma view`` draws it; both pass the Zenoh session of the
process (``Client.session``, or one of their own).  The snapshot's wire format is in
:mod:`agent.protocol.registration`.
"""

from __future__ import annotations

import time
from typing import Any

import zenoh

from agent.protocol import keys
from agent.protocol.registration import parse_snapshot
from agent.runtime.session import query
from schemas.codec import DecodeError
from schemas.models import ServiceDescriptor

#: how long the set of live agents must stay unchanged before asking them, when the caller
#: is a listening peer that is still discovering the realm by itself (no ``--connect``)
SETTLE_S = 0.15


def live_agents(session: zenoh.Session, realm: str, timeout: float) -> set[str]:
    """Agent ids whose liveliness token is visible now."""
    found = set()
    for reply in query(session, keys.all_agent_tokens(realm), timeout, liveliness=True):
        if reply.ok is not None:
            agent_id = keys.parse_agent_token(str(reply.ok.key_expr), realm)
            if agent_id:
                found.add(agent_id)
    return found


def settled_agents(session: zenoh.Session, realm: str, deadline: float,
                   settle_s: float) -> set[str]:
    """The live agents once their set has not changed for ``settle_s`` (at least one seen).

    A client of an agent sees the agent's view of the realm in its first answer, so it
    settles at 0 s; waiting there only adds to every call (``bench/bench_site_scale.py``
    measures what it costs).
    """
    seen: set[str] = set()
    stable_since = time.monotonic()
    while time.monotonic() < deadline:
        now_seen = live_agents(session, realm, min(0.5, max(0.05, deadline - time.monotonic())))
        if now_seen != seen:
            seen, stable_since = now_seen, time.monotonic()
        if seen and time.monotonic() - stable_since >= settle_s:
            break
        time.sleep(0.03)
    return seen


def collect_realm(session: zenoh.Session, realm: str, timeout: float,
            settle_s: float = SETTLE_S) -> dict[str, Any]:
    """The realm as one JSON-able dict (agents sorted by id), asked once the set of live
    agents has settled (:func:`settled_agents`)."""
    deadline = time.monotonic() + timeout
    seen = settled_agents(session, realm, deadline, settle_s)
    agents: dict[str, Any] = {}
    problems: list[str] = []
    left = max(0.2, deadline - time.monotonic())
    for reply in query(session, keys.all_agent_services(realm), left):
        if reply.ok is None:
            problems.append(f"an agent answered with an error: {_text(reply.err.payload)}")
            continue
        key = str(reply.ok.key_expr)
        try:
            snap = parse_snapshot(reply.ok.payload.to_bytes(),
                                  keys.parse_agent_services(key, realm))
        except DecodeError as exc:
            problems.append(f"{key}: unreadable snapshot ({exc})")
            continue
        problems += [f"{key}: {e}" for e in snap.errors]
        agents[snap.agent_id] = {
            **snap.info,
            "services": [_service(desc, snap.status.get(sid, {}))
                         for sid, desc in sorted(snap.services.items())]}
    for agent_id in sorted(seen - agents.keys()):
        problems.append(f"agent {agent_id} is alive but did not answer in time")
    return {"realm": realm, "agents": [agents[a] for a in sorted(agents)],
            "problems": problems}


def _text(payload: zenoh.ZBytes) -> str:
    try:
        return payload.to_bytes().decode("utf-8", "replace")[:200]
    except Exception:
        return "?"


def _service(desc: ServiceDescriptor, status: dict[str, Any]) -> dict[str, Any]:
    matches = status.get("matches", {})
    satisfied = status.get("satisfied", {})
    excluded = status.get("excluded", {})
    return {
        "service_id": desc.service_id,
        "instance": status.get("instance"),
        "attributes": desc.attributes,
        "abilities": [a.model_dump(mode="json", exclude_none=True) for a in desc.abilities],
        "needs": [{**n.model_dump(mode="json", exclude_none=True),
                   "matches": matches.get(n.name, []),
                   "satisfied": satisfied.get(n.name, False),
                   "excluded": excluded.get(n.name, {})} for n in desc.needs],
    }
