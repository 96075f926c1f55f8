"""``uma info FILE.mcap``: what a recording holds.

Duration, start and end (log time), every channel with its message count and rate, and the
services, abilities and matches of the agents' last recorded snapshots.  A damaged file is
summarised up to the damage, which is named (exit code 0: what could be read is shown; the
damage is on stderr too).  ``--json`` prints ``{file, bytes, start_ns, end_ns, duration_s,
messages, channels: [{topic, encoding, messages, rate_hz, ability}], services: [{agent_id,
service_id, abilities, matches: {need: [data key...]}}], dropped, damage}``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from datetime import UTC, datetime
from typing import Any

from agent.protocol import parse_snapshot
from agent.record import layout
from agent.record.reader import Recording, read
from schemas.codec import DecodeError


def summarise(rec: Recording) -> dict[str, Any]:
    """The recording as one JSON-able dict (see the module docstring)."""
    stamps: dict[int, list[int]] = defaultdict(list)   # channel -> log times, in order
    for m in rec.messages:
        stamps[m.channel.id].append(m.log_ns)
    times = [m.log_ns for m in rec.messages]
    start, end = (min(times), max(times)) if times else (None, None)
    channels = []
    for ch in sorted(rec.channels.values(), key=lambda c: c.topic):
        own = stamps[ch.id]
        span = (own[-1] - own[0]) / 1e9 if len(own) > 1 else 0.0
        ability = layout.ability_of(ch.metadata)
        channels.append({
            "topic": ch.topic, "encoding": ch.message_encoding, "messages": len(own),
            "rate_hz": (len(own) - 1) / span if span > 0 else 0.0,
            "ability": None if ability is None else ability.model_dump(mode="json",
                                                                       exclude_none=True)})
    end_meta = rec.metadata.get(layout.META_END, {})
    return {"file": rec.path, "bytes": rec.size, "start_ns": start, "end_ns": end,
            "duration_s": (end - start) / 1e9 if times else 0.0,
            "messages": len(rec.messages), "channels": channels,
            "services": services(rec),
            "dropped": json.loads(end_meta.get("dropped", "{}")), "damage": rec.damage}


def services(rec: Recording) -> list[dict[str, Any]]:
    """Each agent's services in its last readable snapshot, with their matches."""
    last: dict[str, Any] = {}
    for m in rec.messages:
        if m.channel.metadata.get("uma.kind") == layout.SNAPSHOT:
            try:
                snap = parse_snapshot(m.data)
            except DecodeError:
                continue
            last[snap.agent_id] = snap
    out = []
    for agent_id, snap in sorted(last.items()):
        for sid, desc in sorted(snap.services.items()):
            matches = snap.status.get(sid, {}).get("matches", {})
            out.append({"agent_id": agent_id, "service_id": sid,
                        "abilities": [a.name for a in desc.abilities],
                        "needs": [n.name for n in desc.needs],
                        "matches": {need: [x.get("key") for x in ms if isinstance(x, dict)]
                                    for need, ms in matches.items()}})
    return out


def _utc(t_ns: int | None) -> str:
    if t_ns is None:
        return "-"
    stamp = datetime.fromtimestamp(t_ns / 1e9, tz=UTC)
    return stamp.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def format_info(s: dict[str, Any]) -> str:
    lines = [f"file      {s['file']} ({s['bytes']} bytes)",
             f"duration  {s['duration_s']:.3f} s  ({_utc(s['start_ns'])} .. {_utc(s['end_ns'])})",
             f"messages  {s['messages']}", "channels:"]
    for c in s["channels"]:
        lines.append(f"  {c['topic']:<60} {c['encoding']:<8} {c['messages']:>8} msgs "
                     f"{c['rate_hz']:8.1f} Hz")
    lines.append("services:")
    for sv in s["services"]:
        lines.append(f"  {sv['agent_id']}/{sv['service_id']}: abilities "
                     f"{', '.join(sv['abilities']) or '-'}; needs {', '.join(sv['needs']) or '-'}")
        for need, ms in sv["matches"].items():
            lines.append(f"    {need} => {', '.join(ms) or 'none'}")
    if any(s["dropped"].values()):
        lines.append(f"not written while recording: {s['dropped']}")
    if s["damage"]:
        lines.append(f"DAMAGED: {s['damage']}")
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    """Handler of ``uma info``."""
    rec = read(args.file)
    s = summarise(rec)
    print(json.dumps(s) if args.json else format_info(s))
    if rec.damage:
        print(f"uma info: warning: {rec.damage}", file=sys.stderr)
    return 0
