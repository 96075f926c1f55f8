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
from typing import Any

from agent.errors import UmaError
from agent.runtime.session import close_session, open_session, sdk_mode
from agent.sdk.inventory import SETTLE_S, collect_realm


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
        realm = collect_realm(session, args.realm, args.timeout,
                        settle_s=0.0 if mode == "client" else SETTLE_S)
    finally:
        close_session(session)
    print(json.dumps(realm) if args.json else format_realm(realm))
    return 0
