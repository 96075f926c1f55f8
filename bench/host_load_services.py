"""One process of ``bench_host_load``: K services written as the README's ``Service``
example, each publishing one pose6d ability at RATE Hz, or (``--bare``) K plain Zenoh
publishers of the same payload at the same rate: the anchor of what publishing costs.

    python bench/host_load_services.py REALM AGENT ENDPOINT FIRST K RATE SECONDS [--bare]

Prints ``started`` once everything publishes, then ``published N`` when it ends.
"""

from __future__ import annotations

import argparse
import sys
import time

WORLD = "ivy/world"


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="host_load_services")
    for name in ("realm", "agent", "endpoint"):
        p.add_argument(name)
    p.add_argument("first", type=int)
    p.add_argument("k", type=int)
    p.add_argument("rate", type=float)
    p.add_argument("seconds", type=float)
    p.add_argument("--bare", action="store_true")
    a = p.parse_args(argv)
    publish, close = (_bare if a.bare else _services)(a)
    print("started", flush=True)
    period, n = 1.0 / a.rate, 0
    start = time.monotonic()
    end = start + a.seconds
    while time.monotonic() < end:  # bounded: a.seconds
        publish(n)
        n += 1
        time.sleep(max(0.0, start + n * period - time.monotonic()))
    close()
    print(f"published {n}", flush=True)
    return 0


def _services(a: argparse.Namespace):
    from agent import Service

    services, outs = [], []
    for i in range(a.first, a.first + a.k):
        svc = Service(f"load{i}", realm=a.realm, agent=a.agent, connect=[a.endpoint])
        outs.append(svc.ability("pose", type="pose6d", edge=(WORLD, f"obj/{i}"),
                                frequency_hz=a.rate, latency_s=0.005, pos_std_m=0.002))
        services.append(svc.start())

    def publish(n: int) -> None:
        t = time.time_ns()
        for out in outs:
            out.publish(t, [0.001 * n, 0.0, 1.6], [0.0, 0.0, 0.0, 1.0])

    def close() -> None:
        for svc in services:
            svc.close()
    return publish, close


def _bare(a: argparse.Namespace):
    from agent.protocol import keys
    from agent.runtime.session import open_session
    from schemas.codec import encode_pose

    session = open_session("client", None, [a.endpoint])
    pubs = [session.declare_publisher(keys.data(a.realm, "bare", f"load{i}", "pose"))
            for i in range(a.first, a.first + a.k)]

    def publish(n: int) -> None:
        payload = encode_pose(time.time_ns(), [0.001 * n, 0.0, 1.6], [0.0, 0.0, 0.0, 1.0],
                              None, seq=n)
        for pub in pubs:
            pub.put(payload)
    return publish, session.close


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
