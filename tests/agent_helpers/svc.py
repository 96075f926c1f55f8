"""A scriptable test service: publishes a pose ability and/or receives a need, and reports
what happens as JSON lines on stdout.  Commands on stdin change it while it runs.

    python -m tests.agent_helpers.svc --id cam1 --realm R --agent A --connect EP \\
        [--ability pose --edge ivy/world alice/head --rate 100 --attr frequency_hz=100] \\
        [--need head --need-edge ivy/world '*/head' --where 'frequency_hz >= 30' \\
         --prefer latency_s]

stdout events: ``{"event": "started"}``, ``{"event": "refused", "error": ...}``,
``{"event": "match", "need", "keys"}``, ``{"event": "first", "source", "recv_ns", "t_ns"}``
(first sample from a source since the last change of source), ``{"event": "counts",
"counts": {source: n}}`` every 0.25 s, and with ``--each-sample`` ``{"event": "sample",
"source", "t_ns", "seq", "recv_ns"}`` for every sample received.
stdin commands: ``rate HZ`` (publishing rate), ``update NAME=VALUE ...`` (attributes).
SIGTERM closes the service cleanly.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

from agent.errors import UmaError
from agent.sdk.service import Service

_EMIT_LOCK = threading.Lock()


def emit(**event: object) -> None:
    """One JSON line.  Samples arrive on the SDK's thread while the main loop reports: one
    write per line under a lock, or two threads' ``print`` interleave their text and
    newlines and the harness loses both events (seen once: a 'first' never arrived)."""
    line = json.dumps(event) + "\n"
    with _EMIT_LOCK:
        sys.stdout.write(line)
        sys.stdout.flush()


def attr(text: str) -> tuple[str, object]:
    name, _, value = text.partition("=")
    try:
        return name, json.loads(value)
    except ValueError:
        return name, value


def read_late(n: int, late_ns: int) -> None:
    """The answers of the first ``n`` round trips of every sample clock of this process
    read ``late_ns`` late: each offset is ``late_ns / 2`` off, its bound says as much."""
    from agent.sdk import sampleclock

    left = [n]

    class LateQueries(sampleclock.AgentQueries):
        def answers(self, request, agents=()):
            for who, reply, t1, t4 in super().answers(request, agents):
                if left[0] > 0:
                    left[0] -= 1
                    t4 += late_ns
                yield who, reply, t1, t4

    sampleclock.AgentQueries = LateQueries


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--id", required=True)
    ap.add_argument("--realm", required=True)
    ap.add_argument("--agent", required=True)
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--ability")
    ap.add_argument("--edge", nargs=2, default=["ivy/world", "alice/head"])
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--attr", action="append", default=[], type=attr)
    ap.add_argument("--need")
    ap.add_argument("--need-edge", nargs=2, default=["ivy/world", "*/head"])
    ap.add_argument("--where")
    ap.add_argument("--prefer")
    ap.add_argument("--max-count", type=int, default=1)
    ap.add_argument("--each-sample", action="store_true")
    ap.add_argument("--skew-ns", type=int, default=0,
                    help="stamp samples this far ahead (a host whose clock is off)")
    ap.add_argument("--late-round-trips", type=int, default=0,
                    help="the first N clock round trips of the needs' sample clock are read "
                         "100 ms late (a host too busy to read their answers in time)")
    args = ap.parse_args()
    if args.late_round_trips:
        read_late(args.late_round_trips, 100_000_000)

    counts: dict[str, int] = {}
    last_source: list[str | None] = [None]
    lock = threading.Lock()

    def on_sample(m) -> None:
        with lock:
            counts[m.source] = counts.get(m.source, 0) + 1
            if args.each_sample:
                emit(event="sample", source=m.source, t_ns=m.t_ns, seq=m.seq,
                     recv_ns=time.time_ns(), time_error_ns=m.time_error_ns)
            if m.source != last_source[0]:
                last_source[0] = m.source
                emit(event="first", source=m.source, recv_ns=time.time_ns(), t_ns=m.t_ns,
                     attributes=m.attributes, edge=m.edge)

    svc = Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect)
    out = None
    if args.ability:
        out = svc.ability(args.ability, type="pose6d", edge=tuple(args.edge), **dict(args.attr))
    if args.need:
        svc.need(args.need, type="pose6d", edge=tuple(args.need_edge), where=args.where,
                 prefer=args.prefer, max_count=args.max_count, on_sample=on_sample)
    try:
        svc.start()
    except UmaError as exc:
        emit(event="refused", error=str(exc))
        svc.close()  # its session's callbacks must not outlive the interpreter
        return 3
    emit(event="started", registered=svc.wait_registered(0))
    rate = [args.rate]
    reschedule = threading.Event()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def commands() -> None:
        for line in sys.stdin:
            words = line.split()
            if not words:
                continue
            if words[0] == "rate":
                rate[0] = float(words[1])
                reschedule.set()  # a slow rate's next sample may be far ahead
            elif words[0] == "update" and out is not None:
                out.update(**dict(attr(w) for w in words[1:]))
            emit(event="ack", command=words[0])

    threading.Thread(target=commands, daemon=True).start()
    last_keys: list[str] | None = None
    next_pub = next_report = time.monotonic()
    try:
        while not stop.is_set():
            now = time.monotonic()
            if reschedule.is_set():
                reschedule.clear()
                next_pub = now
            if out is not None and now >= next_pub:
                out.publish(time.time_ns() + args.skew_ns, [0.1, 0.2, 0.3], [0, 0, 0, 1])
                next_pub = max(next_pub + 1.0 / rate[0], now - 0.1)
            if args.need:
                keys = [m.key for m in svc.matches(args.need)]
                if keys != last_keys:
                    last_keys = keys
                    emit(event="match", need=args.need, keys=keys)
            if now >= next_report:
                next_report = now + 0.25
                with lock:
                    emit(event="counts", counts=dict(counts))
            # every 10 ms (a match to report, a command to follow), sooner for a sample due;
            # a service without an ability has none due, so its next_pub never gates
            wake = now + 0.01 if out is None else min(next_pub, now + 0.01)
            time.sleep(max(0.0, wake - time.monotonic()))
    finally:
        svc.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
