"""``uma record``: the realm's data streams and its agents' publications into an MCAP file.

Attaches like ``uma services`` (a Zenoh client of the agent it connects to, which routes
every stream of the realm to it; a listening peer without ``--connect``), subscribes to the
data keys that match ``--keys`` and to every agent's snapshots and SRG summaries, asks for
the current ones at the start, and hands everything to a :class:`RecordingSink`.  Callbacks
do no more than stamp the receive time and queue the bytes.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from typing import Any

import zenoh

from agent.errors import UmaError
from agent.protocol import keys
from agent.record.sink import RecordingSink, SinkStats
from agent.record.statics import StaticEdges
from agent.runtime import close_session, open_session, query, sdk_mode

#: how long to wait for the agents' current snapshots and summaries at the start
ASK_TIMEOUT_S = 2.0


def data_selectors(realm: str, patterns: list[str]) -> list[str]:
    """The key expressions of ``--keys`` (``AGENT/SERVICE/ABILITY`` with Zenoh's ``*`` and
    ``**``), or every data key of the realm; ``UmaError`` names a bad pattern."""
    root = f"{keys.realm_root(realm)}/data/"
    if not patterns:
        return [keys.all_data(realm)]
    out = []
    for p in patterns:
        full = p if p.startswith(root) else root + p.strip("/")
        try:
            zenoh.KeyExpr(full)
        except zenoh.ZError as exc:
            reason = str(exc).split(" at /")[0]
            raise UmaError(f"--keys {p!r} is not a key expression ({reason})") from None
        out.append(full)
    return out


def key_filter(realm: str, patterns: list[str]) -> Any:
    """A predicate on data keys: does the key match one of ``patterns``?"""
    selectors = [zenoh.KeyExpr(s) for s in data_selectors(realm, patterns)]
    return lambda key: any(s.intersects(zenoh.KeyExpr(key)) for s in selectors)


class Recorder:
    """Subscriptions of one recording; ``close()`` undeclares them and closes the sink."""

    def __init__(self, session: zenoh.Session, sink: RecordingSink, realm: str,
                 patterns: list[str]) -> None:
        self.sink = sink
        offer = sink.offer

        def on_sample(sample: zenoh.Sample) -> None:
            offer(str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())

        def on_summary(sample: zenoh.Sample) -> None:
            on_sample(sample)
            self.statics.changed()

        self.statics = StaticEdges(session, realm, offer)
        realm_keys = [keys.all_agent_services(realm), keys.all_agent_supernodes(realm)]
        self._subs = [session.declare_subscriber(s, on_sample)
                      for s in [*data_selectors(realm, patterns), realm_keys[0]]]
        self._subs.append(session.declare_subscriber(realm_keys[1], on_summary))
        for selector in realm_keys:
            for reply in query(session, selector, ASK_TIMEOUT_S):
                if reply.ok is not None:
                    offer(str(reply.ok.key_expr), reply.ok.payload.to_bytes(), time.time_ns())

    def close(self) -> SinkStats:
        self.statics.close()
        for sub in self._subs:
            sub.undeclare()
        return self.sink.close()


def _status(stats: SinkStats, started: float) -> str:
    n = sum(stats.messages.values())
    dropped = sum(stats.dropped.values())
    return (f"\rrecording {time.monotonic() - started:7.1f} s | {n} messages | "
            f"{stats.bytes_in / 1e6:.1f} MB | dropped {dropped}  ")


def record(args: argparse.Namespace, stop: threading.Event) -> dict[str, Any]:
    """Record until ``stop``, ``--duration`` or a write error; the figures."""
    mode = sdk_mode(None, args.connect)
    session = open_session(mode, None, args.connect, args.realm,
                           require_connection=bool(args.connect))
    live = not args.json and sys.stderr.isatty()
    try:
        sink = RecordingSink(args.file, args.realm, list(args.keys), ros=not args.no_ros)
        recorder = Recorder(session, sink, args.realm, list(args.keys))
        started = time.monotonic()   # --duration counts from here: everything is subscribed
        end = started + args.duration if args.duration else math.inf
        while not stop.is_set() and not sink.stopped.is_set() and time.monotonic() < end:
            stop.wait(min(1.0, max(0.0, end - time.monotonic())))
            if live:
                print(_status(sink.stats, started), end="", file=sys.stderr, flush=True)
        stats = recorder.close()
    finally:
        close_session(session)
    if live:
        print(file=sys.stderr)
    return {"file": args.file, "realm": args.realm, "seconds": time.monotonic() - started,
            "messages": dict(sorted(stats.messages.items())),
            "dropped": dict(stats.dropped), "undecodable": stats.undecodable,
            "error": stats.error}


def main(args: argparse.Namespace) -> int:
    """Handler of ``uma record``."""
    from agent.runtime import stop_on_signals

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise UmaError(f"--duration must be a positive number of seconds, got {args.duration}")
    data_selectors(args.realm, list(args.keys))
    report = record(args, stop_on_signals())
    if args.json:
        print(json.dumps(report))
    else:
        total = sum(report["messages"].values())
        print(f"recorded {total} messages in {report['seconds']:.1f} s to {report['file']}")
        for topic, n in report["messages"].items():
            print(f"  {topic}: {n}")
        dropped = sum(report["dropped"].values())
        if dropped or report["undecodable"]:
            print(f"  not written (disk too slow): {dropped}; undecodable, kept as received: "
                  f"{report['undecodable']}")
    if report["error"]:
        print(f"uma record: error: {report['error']}", file=sys.stderr)
        return 1
    return 0
