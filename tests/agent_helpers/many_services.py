"""K services in one process (sharing its Zenoh session), each with one ``pose6d`` ability
published at a low rate: the load of a host full of small trackers.

    python -m tests.agent_helpers.many_services --realm R --agent A --connect EP \\
        [--count 10] [--rate 10] [--prefix s]

Services are ``<prefix>0 .. <prefix>K-1``, each publishing the edge ``A/world -> A/<id>``.
stdout: ``{"event": "started", "services": [ids], "registered": n}`` once every service
started (``registered``: how many the agent confirmed within the start), then nothing.
SIGTERM closes them all.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

from agent.sdk.service import AbilityHandle, Service


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--realm", required=True)
    ap.add_argument("--agent", required=True)
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--count", type=int, default=10)
    ap.add_argument("--rate", type=float, default=10.0, help="Hz per service")
    ap.add_argument("--prefix", default="s")
    args = ap.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    services: list[Service] = []
    outs: list[AbilityHandle] = []
    try:
        for i in range(args.count):
            svc = Service(f"{args.prefix}{i}", realm=args.realm, agent=args.agent,
                          connect=args.connect)
            services.append(svc)
            outs.append(svc.ability("pose", type="pose6d",
                                    edge=(f"{args.agent}/world", f"{args.agent}/{svc.service_id}"),
                                    frequency_hz=args.rate))
            svc.start()
        registered = sum(svc.wait_registered(0) for svc in services)
        print(json.dumps({"event": "started", "services": [s.service_id for s in services],
                          "registered": registered}), flush=True)
        publish(outs, args.rate, stop)
    finally:
        for svc in services:
            svc.close()
    return 0


def publish(outs: list[AbilityHandle], rate: float, stop: threading.Event) -> None:
    """Every ability once per period, until ``stop``; a late round is not made up for."""
    period = 1.0 / rate
    next_round = time.monotonic()
    while not stop.is_set():
        t_ns = time.time_ns()
        for out in outs:
            out.publish(t_ns, [0.1, 0.2, 0.3], [0.0, 0.0, 0.0, 1.0])
        next_round = max(next_round + period, time.monotonic())
        stop.wait(next_round - time.monotonic())


if __name__ == "__main__":
    sys.exit(main())
