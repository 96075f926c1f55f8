"""``uma services``: every agent, service, need, ability and current match of a realm.

Attaches to the agent (or router) it connects to as a Zenoh client, which routes its
questions to every agent of the realm; waits until the set of live agents is stable, then
asks every agent's ``uma/R/agent/A/services`` queryable for its snapshot
(:mod:`agent.protocol.registration`).  Without ``--connect`` it is a listening peer.

``--json`` prints one object: ``{"realm", "agents": [{agent_id, realm, version, started_ns,
endpoints, "services": [{service_id, instance, attributes, "abilities": [Ability...],
"needs": [{...Need, "matches": [{key, agent_id, service_id, ability, score, local,
"measured": {measured_frequency_hz, measured_latency_s}}], "satisfied", "excluded":
{data key: reason}}]}]}], "problems": [text...]}`` (agents sorted by id).
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import zenoh

from agent.errors import UmaError
from agent.protocol import keys
from agent.protocol.registration import parse_snapshot
from agent.runtime.session import close_session, open_session, query, sdk_mode
from schemas.codec import DecodeError
from schemas.models import ServiceDescriptor

#: how long the set of live agents must stay unchanged before asking them, when this command
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
    settles at 0 s; waiting there only adds to every run (measured with 20 agents in
    network namespaces: 0.15 s of a 0.22 s collect, ``bench/bench_site_scale.py``).
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


def collect(session: zenoh.Session, realm: str, timeout: float,
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


def format_realm(realm: dict[str, Any]) -> str:
    """The realm for people: one block per agent."""
    lines = [f"realm {realm['realm']}: {len(realm['agents'])} agent(s)"]
    for a in realm["agents"]:
        lines.append(f"agent {a['agent_id']}  ({', '.join(a.get('endpoints', [])) or '-'})")
        if not a["services"]:
            lines.append("  (no services)")
        for s in a["services"]:
            lines.append(f"  service {s['service_id']}")
            for ab in s["abilities"]:
                where = " -> ".join(ab["edge"]) if "edge" in ab else ab.get("key", "")
                attrs = ", ".join(f"{k}={v}" for k, v in ab.get("attributes", {}).items()
                                  if k != "static" or v)
                lines.append(f"    ability {ab['name']} [{ab['type']}] {where}  {attrs}")
            for n in s["needs"]:
                flag = "" if n["satisfied"] else "  (UNSATISFIED)"
                extra = "".join(f"  {k} {n[k]!r}" for k in ("where", "prefer") if n.get(k))
                lines.append(f"    need {n['name']} [{n['type']}] {' -> '.join(n['edge'])}"
                             f"{extra}{flag}")
                for m in n["matches"]:
                    meas = ", ".join(f"{k}={v:.4g}" for k, v in m.get("measured", {}).items())
                    lines.append(f"      => {m['agent_id']}/{m['service_id']}/{m['ability']}"
                                 f"{'  (local)' if m.get('local') else ''}"
                                 f"{'  ' + meas if meas else ''}")
                for key, why in n.get("excluded", {}).items():
                    lines.append(f"      excluded {key}: {why}")
    for p in realm["problems"]:
        lines.append(f"problem: {p}")
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    """Handler of ``uma services``."""
    if args.timeout <= 0:
        raise UmaError(f"--timeout must be positive, got {args.timeout}")
    mode = sdk_mode(None, args.connect)
    session = open_session(mode, None, args.connect, args.realm,
                           require_connection=bool(args.connect))
    try:
        realm = collect(session, args.realm, args.timeout,
                        settle_s=0.0 if mode == "client" else SETTLE_S)
    finally:
        close_session(session)
    print(json.dumps(realm) if args.json else format_realm(realm))
    return 0
