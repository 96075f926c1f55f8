"""``uma play``: a recording's services live again, with the recorded timing.

Every recorded service that has data in the recording re-appears as a live service
(``agent.Service``) of ``--realm``, registered with ``--agent``, with the same abilities and
attributes as recorded (the channels' ``uma.ability`` metadata), so agents match needs to it
as they did live and the SRG, queries and subscriptions work on it.  Its samples are
published in log-time order at ``start + (log time - first log time) / rate``: the exact
recorded bytes, or with ``--now`` every sample time shifted by one offset (re-encoded, the
sequence numbers kept) so the recording happens now.  The figures it prints include the
timing error, |actual - scheduled| publish time, median and p99.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent.errors import UmaError
from agent.record import layout
from agent.record.reader import Message, Recording, read
from agent.record.recorder import key_filter
from schemas.codec import DecodeError, decode_measurement, encode_measurement
from schemas.models import Ability


@dataclass(frozen=True)
class Stream:
    """One recorded data channel to play: where it came from and what it offered."""

    agent_id: str
    service_id: str
    ability: Ability
    service_attributes: dict[str, Any]


def recorded_realm(rec: Recording) -> str | None:
    return rec.metadata.get(layout.META_START, {}).get("realm")


def streams(rec: Recording, patterns: list[str]) -> dict[int, Stream]:
    """The data channels to play, by channel id (``--keys`` applied to recorded keys)."""
    realm = recorded_realm(rec)
    wanted = key_filter(realm, patterns) if realm else (lambda key: True)
    out = {}
    for ch in rec.channels.values():
        parts = ch.topic.split("/")
        if ch.metadata.get("uma.kind") != layout.DATA or len(parts) != 6 or not wanted(ch.topic):
            continue
        ability = layout.ability_of(ch.metadata)
        if ability is None:
            print(f"uma play: warning: {ch.topic} has no recorded descriptor; not played",
                  file=sys.stderr)
            continue
        out[ch.id] = Stream(parts[3], parts[4], ability, layout.service_attributes_of(ch.metadata))
    return out


def _services(chosen: dict[int, Stream]) -> dict[str, list[Stream]]:
    """Streams grouped by service id; two recorded agents' services of one id cannot both
    register with one agent, so that is refused with a way out."""
    by_id: dict[str, list[Stream]] = {}
    for s in chosen.values():
        by_id.setdefault(s.service_id, []).append(s)
    for sid, ss in by_id.items():
        agents = sorted({s.agent_id for s in ss})
        if len(agents) > 1:
            raise UmaError(f"service {sid!r} was recorded on agents {', '.join(agents)}; play "
                           f"one at a time with --keys AGENT/{sid}/*")
    return by_id


def _window(rec: Recording, chosen: dict[int, Stream], args: argparse.Namespace,
            ) -> list[Message]:
    msgs = [m for m in rec.messages if m.channel.id in chosen]
    if not msgs:
        raise UmaError(f"{rec.path}: no data to play" + (" for --keys " + " ".join(args.keys)
                                                          if args.keys else ""))
    first = msgs[0].log_ns
    lo = first + int(args.start * 1e9)
    hi = math.inf if args.end is None else first + int(args.end * 1e9)
    window = [m for m in msgs if lo <= m.log_ns <= hi]
    if not window:
        raise UmaError(f"--start {args.start:g} / --end {args.end} leaves nothing of the "
                       f"{(msgs[-1].log_ns - first) / 1e9:.3f} s recorded")
    return window


class Playback:
    """Publishes one pass of ``messages`` on ``handles`` (by channel id) at ``rate``."""

    def __init__(self, handles: dict[int, Any], rate: float, now: bool) -> None:
        self.handles = handles
        self.rate = rate
        self.now = now
        self.errors_s: list[float] = []
        self.published = 0
        self.undecodable = 0
        #: how long each complete pass took, first to last publication
        self.pass_s: list[float] = []

    def run(self, messages: list[Message], stop: threading.Event, status: Any) -> None:
        first = messages[0].log_ns
        start = time.monotonic()
        offset = time.time_ns() - messages[0].publish_ns if self.now else 0
        next_status = start + 1.0
        for m in messages:
            due = start + (m.log_ns - first) / 1e9 / self.rate
            delay = due - time.monotonic()
            if delay > 0 and stop.wait(delay):
                return
            try:
                data = _shifted(m.data, offset)
                late = abs(time.monotonic() - due)   # at the moment of the put
                self.handles[m.channel.id].publish_encoded(data)
            except DecodeError:   # recorded as received, not a sample: never published
                self.undecodable += 1
                continue
            self.errors_s.append(late)
            self.published += 1
            if status and time.monotonic() >= next_status:
                next_status += 1.0
                status((m.log_ns - first) / 1e9, (messages[-1].log_ns - first) / 1e9)
        self.pass_s.append(time.monotonic() - start)


def _shifted(data: bytes, offset: int) -> bytes:
    """The sample with its time moved by ``offset`` ns (the exact bytes if 0)."""
    if not offset:
        return data
    m = decode_measurement(data)
    m.t_ns += offset
    return encode_measurement(m)


def _status(at_s: float, total_s: float) -> None:
    print(f"\rplaying {at_s:7.1f} / {total_s:.1f} s  ", end="", file=sys.stderr, flush=True)


def play(args: argparse.Namespace, stop: threading.Event) -> dict[str, Any]:
    """Play the recording (see the module docstring); the figures."""
    from agent import Service

    rec = read(args.file)
    if rec.damage:
        print(f"uma play: warning: {rec.damage}", file=sys.stderr)
    chosen = streams(rec, list(args.keys))
    messages = _window(rec, chosen, args)
    services: list[Any] = []
    handles: dict[int, Any] = {}
    playback = Playback(handles, args.rate, args.now)
    live = not args.json and sys.stderr.isatty()
    t0 = time.monotonic()
    try:
        for sid, ss in sorted(_services(chosen).items()):
            svc = Service(sid, realm=args.realm, agent=args.agent, connect=args.connect,
                          attributes=ss[0].service_attributes)
            services.append(svc)
            for s in ss:
                attrs = s.ability.attributes.model_dump(exclude_none=True, exclude_defaults=True)
                handle = svc.ability(s.ability.name, s.ability.type, s.ability.edge,
                                     s.ability.key, **attrs)
                for cid, st in chosen.items():
                    if st is s:
                        handles[cid] = handle
            svc.start()
        while not stop.is_set():
            playback.run(messages, stop, _status if live else None)
            if not args.loop:
                break
    finally:
        for svc in services:
            with contextlib.suppress(Exception):
                svc.close()
    if live:
        print(file=sys.stderr)
    err = np.asarray(playback.errors_s) * 1e3
    return {"file": args.file, "realm": args.realm, "services": sorted(s.service_id
                                                                       for s in services),
            "published": playback.published, "passes": len(playback.pass_s),
            "recorded_s": (messages[-1].log_ns - messages[0].log_ns) / 1e9,
            "wall_s": time.monotonic() - t0, "rate": args.rate, "pass_s": playback.pass_s,
            "timing_error_ms": {"median": float(np.median(err)) if len(err) else None,
                                "p99": float(np.percentile(err, 99)) if len(err) else None},
            "undecodable_not_played": playback.undecodable, "damage": rec.damage}


def main(args: argparse.Namespace) -> int:
    """Handler of ``uma play``."""
    from agent.runtime import stop_on_signals

    if not (math.isfinite(args.rate) and 0 < args.rate <= 1000):
        raise UmaError(f"--rate must be in (0, 1000], got {args.rate}")
    if not (math.isfinite(args.start) and args.start >= 0):
        raise UmaError(f"--start must be >= 0 seconds, got {args.start}")
    if args.end is not None and not (math.isfinite(args.end) and args.end > args.start):
        raise UmaError(f"--end must be after --start ({args.start:g}), got {args.end}")
    report = play(args, stop_on_signals())
    if args.json:
        print(json.dumps(report))
    else:
        e = report["timing_error_ms"]
        print(f"played {report['published']} samples of {', '.join(report['services'])} "
              f"({report['recorded_s']:.1f} s recorded) in {report['wall_s']:.1f} s at rate "
              f"{report['rate']:g}; timing error median {e['median']:.3f} ms, p99 "
              f"{e['p99']:.3f} ms")
    return 0
