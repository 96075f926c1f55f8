"""A consumer: a need with a predicate and a preference; its agent connects the best match.

    python examples/consumer.py --realm lab --agent hostA --connect tcp/127.0.0.1:7447
"""

import argparse
import threading

from agent import Service

parser = argparse.ArgumentParser(prog="consumer", description=__doc__.splitlines()[0])
parser.add_argument("--realm", default="lab")
parser.add_argument("--agent", default="hostA", help="the agent of this host")
parser.add_argument("--connect", action="append", default=[], metavar="EP",
                    help="the agent's endpoint (default tcp/127.0.0.1:7447)")
parser.add_argument("--count", type=int, default=10, help="samples to print, then exit")
parser.add_argument("--timeout", type=float, default=30.0, help="give up after this many s")
args = parser.parse_args()

done = threading.Event()
seen = []


def on_sample(m):  # the service's own thread, one sample at a time
    if done.is_set():
        return
    seen.append(m)
    position = ", ".join(f"{x:.3f}" for x in m.position)
    print(f"sample from {m.source}: {m.edge[0]} -> {m.edge[1]} at {m.t_ns} ns, "
          f"position [{position}]", flush=True)
    if len(seen) >= args.count:
        done.set()


with Service("consumer", realm=args.realm, agent=args.agent,
             connect=args.connect or ["tcp/127.0.0.1:7447"]) as svc:
    # any head of the realm, at 30 Hz or more, the one with the lowest latency
    svc.need("head", type="pose6d", edge=("ivy/world", "*/head"),
             where="frequency_hz >= 30", prefer="latency_s", on_sample=on_sample)
    svc.start()
    if not done.wait(args.timeout):
        raise SystemExit(f"{len(seen)} samples within {args.timeout} s: is a tracker running?")
