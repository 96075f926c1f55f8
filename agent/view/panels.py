"""The text of the view's page, as Markdown, from one look at the realm (pure functions):
the agents, their services with needs and abilities, the matches with their streams'
measured rate, latency and state, and the event log."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from agent.protocol import keys
from agent.view.events import match_name
from agent.view.taps import StreamFacts, stream_state
from agent.view.watch import Look

Facts = Callable[[str], StreamFacts | None]
#: event lines shown on the page (newest first)
EVENTS_SHOWN = 25
#: QoS attributes shown with an ability, in this order
QOS = ("frequency_hz", "latency_s", "pos_std_m", "rot_std_rad", "confidence", "cost", "static")


def realm_md(look: Look) -> str:
    """The agents: id, endpoints, alive, clock offset and delay to this viewer."""
    realm = look.realm
    if not realm["agents"]:
        return (f"**No agents in realm `{realm['realm']}` yet.** This page updates by itself "
                "when one appears.")
    rows = ["| agent | endpoints | alive | clock offset | delay | services |",
            "|---|---|---|---|---|---|"]
    for a in realm["agents"]:
        offset, delay = look.clocks.get(a["agent_id"], (None, None))
        rows.append(f"| {a['agent_id']} | {', '.join(a.get('endpoints', [])) or '-'} | yes | "
                    f"{_ms(offset)} | {_ms(delay)} | {len(a['services'])} |")
    problems = [f"- problem: {p}" for p in realm["problems"]]
    head = f"**Realm `{realm['realm']}`**: {len(realm['agents'])} agent(s)"
    return "\n".join([head, "", *rows, "", *problems])


def services_md(look: Look) -> str:
    """Every service with its abilities and needs and their QoS attributes."""
    lines = []
    for a in look.realm["agents"]:
        for s in a["services"]:
            lines.append(f"**{a['agent_id']}/{s['service_id']}**")
            for ab in s["abilities"]:
                where = " -> ".join(ab["edge"]) if "edge" in ab else ab.get("key", "")
                lines.append(f"- ability `{ab['name']}` {ab['type']} {where} "
                             f"{_qos(ab.get('attributes', {}))}")
            for n in s["needs"]:
                extra = "".join(f", {k} `{n[k]}`" for k in ("where", "prefer") if n.get(k))
                state = "" if n["satisfied"] else " **(unsatisfied)**"
                lines.append(f"- need `{n['name']}` {n['type']} {' -> '.join(n['edge'])}"
                             f"{extra}{state}")
            lines.append("")
    return "\n".join(lines) or "no services"


def matches_md(look: Look, facts: Facts) -> str:
    """The match graph as arrows ability -> need, each with its stream's measured rate and
    latency (as the consumer's agent measures them) and its state."""
    advertised = _advertised(look.realm)
    rows = ["| ability → need | rate | latency | state |", "|---|---|---|---|"]
    for a in look.realm["agents"]:
        for s in a["services"]:
            for n in s["needs"]:
                need = f"{a['agent_id']}/{s['service_id']}.{n['name']}"
                for m in n["matches"]:
                    meas = m.get("measured", {})
                    hz, lat = meas.get("measured_frequency_hz"), meas.get("measured_latency_s")
                    state = stream_state(True, facts(m["key"]), advertised.get(m["key"]), hz)
                    rows.append(f"| {match_name(m)} → {need} | {_num(hz, 'Hz')} | "
                                f"{_ms(None if lat is None else lat * 1e3)} | {state} |")
                if not n["matches"]:
                    rows.append(f"| nothing → {need} | - | - | no route |")
    return "\n".join(rows) if len(rows) > 2 else "no needs in the realm"


def events_md(look: Look) -> str:
    """The newest event lines first, with their wall-clock time."""
    if not look.events:
        return "no events yet"
    shown = list(look.events)[-EVENTS_SHOWN:][::-1]
    return "\n".join(f"- {time.strftime('%H:%M:%S', time.localtime(t))} {line}"
                     for t, line in shown)


def edge_md(name: str, look: Look, facts: Facts) -> str:
    """One edge: its source, rate and age of the newest sample, attributes."""
    e = look.edges.get(name)
    if e is None:
        return "no edge selected"
    lines = [f"**{e.parent} -> {e.child}**", f"- owner agent: {e.owner}",
             f"- source: {e.source} ({'static' if e.static else 'measured'}, {e.type})"]
    f = facts(e.key) if e.key else None
    if f is not None:
        age = "no sample yet" if f.age_s is None else f"{f.age_s * 1e3:.0f} ms"
        rate = "not measured yet" if f.rate_hz is None else f"{f.rate_hz:.1f} Hz"
        lines += [f"- rate: {rate}", f"- newest sample: {age} ago",
                  f"- its sequence number: {'-' if f.seq is None else f.seq}"]
    attrs = {k: v for k, v in e.attributes.items() if k not in ("position", "quaternion")}
    lines.append(f"- attributes: {_qos(attrs) or 'none'}")
    return "\n".join(lines)


def _advertised(realm: dict[str, Any]) -> dict[str, float]:
    """Each data key's advertised rate (Hz), for the stall limit."""
    out = {}
    for a in realm["agents"]:
        for s in a["services"]:
            for ab in s["abilities"]:
                hz = ab.get("attributes", {}).get("frequency_hz")
                if hz:
                    out[keys.data(realm["realm"], a["agent_id"], s["service_id"],
                                  ab["name"])] = float(hz)
    return out


def _qos(attrs: dict[str, Any]) -> str:
    shown = [f"{k}={attrs[k]:.4g}" if isinstance(attrs[k], float) else f"{k}={attrs[k]}"
             for k in QOS if attrs.get(k) not in (None, False)]
    return ", ".join(shown)


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f} ms"


def _num(v: float | None, unit: str) -> str:
    return "-" if v is None else f"{v:.1f} {unit}"
