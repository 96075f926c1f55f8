"""One process of ``bench_host_load``, in one of three roles:

- ``services``: K services written as the README's ``Service`` example, each publishing one
  pose6d ability at RATE Hz (``--needs N``: each also needs the next service's pose, as the
  README's service needs a head), through whatever session the SDK gives them by default;
- ``bare``: K plain Zenoh publishers of the same payload at the same rate, in client mode
  of ENDPOINT: the anchor of what publishing itself costs;
- ``sink``: one plain Zenoh subscriber listening at ENDPOINT to a key expression, that
  prints how many samples it has received each time a line arrives on its stdin (the
  anchor's consumer, and the proof that the anchor's samples were really delivered).

    python bench/host_load_services.py services REALM AGENT ENDPOINT FIRST K RATE SECONDS
        [--needs N]
    python bench/host_load_services.py bare REALM ENDPOINT FIRST K RATE SECONDS
    python bench/host_load_services.py sink ENDPOINT KEYEXPR

Prints ``started`` once everything publishes (or subscribes); publishers end by themselves
after SECONDS, the sink at the end of its stdin.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable

WORLD = "ivy/world"
#: one publishing round of every publisher of the process (``n``: the round's number)
Publish = Callable[[int], None]


def main(argv: list[str]) -> int:
    a = _parser().parse_args(argv)
    if a.role == "sink":
        return _sink(a.endpoint, a.keyexpr)
    publish, close = (_services if a.role == "services" else _bare)(a)
    print("started", flush=True)
    try:
        _publish_for(publish, a.rate, a.seconds)
    finally:
        close()
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="host_load_services")
    roles = p.add_subparsers(dest="role", required=True)
    services = roles.add_parser("services")
    bare = roles.add_parser("bare")
    for role in (services, bare):
        role.add_argument("realm")
        if role is services:
            role.add_argument("agent")
        role.add_argument("endpoint")
        role.add_argument("first", type=int)
        role.add_argument("k", type=int)
        role.add_argument("rate", type=float)
        role.add_argument("seconds", type=float)
    services.add_argument("--needs", type=int, default=0, metavar="N",
                          help="each service i also needs obj/(i+1 mod N)'s pose")
    sink = roles.add_parser("sink")
    sink.add_argument("endpoint")
    sink.add_argument("keyexpr")
    return p


def _publish_for(publish: Publish, rate: float, seconds: float) -> None:
    """Publish rounds at ``rate`` Hz on a fixed schedule (a late round is not made up by a
    burst of sleeps skipped: the schedule catches up) for ``seconds``."""
    period, n = 1.0 / rate, 0
    start = time.monotonic()
    end = start + seconds
    while time.monotonic() < end:  # bounded: seconds
        publish(n)
        n += 1
        time.sleep(max(0.0, start + n * period - time.monotonic()))


def _services(a: argparse.Namespace) -> tuple[Publish, Callable[[], None]]:
    from agent import Service

    services, outs = [], []
    for i in range(a.first, a.first + a.k):
        svc = Service(f"load{i}", realm=a.realm, agent=a.agent, connect=[a.endpoint])
        services.append(svc)
        outs.append(svc.ability("pose", type="pose6d", edge=(WORLD, f"obj/{i}"),
                                frequency_hz=a.rate, latency_s=0.005, pos_std_m=0.002))
        if a.needs:
            svc.need("next", type="pose6d", edge=(WORLD, f"obj/{(i + 1) % a.needs}"),
                     on_sample=lambda m: None)
        svc.start()

    def publish(n: int) -> None:
        t = time.time_ns()
        for out in outs:
            out.publish(t, [0.001 * n, 0.0, 1.6], [0.0, 0.0, 0.0, 1.0])

    def close() -> None:
        for svc in services:
            svc.close()
    return publish, close


def _bare(a: argparse.Namespace) -> tuple[Publish, Callable[[], None]]:
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


def _sink(endpoint: str, keyexpr: str) -> int:
    from agent.runtime.session import open_session

    received, lock = [0], threading.Lock()

    def count(_sample: object) -> None:  # Zenoh may call it from several threads at once
        with lock:
            received[0] += 1
    with open_session("peer", [endpoint], []) as session:
        session.declare_subscriber(keyexpr, count)
        print("started", flush=True)
        for _ in sys.stdin:  # bounded: ends with the parent's stdin
            print(f"received {received[0]}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
