"""A subscription: a pose pushed at every sample of the route's fastest edge.

    python examples/subscription.py ivy/world alice/head --connect tcp/127.0.0.1:7447
"""

import argparse
import threading

from agent import Client

parser = argparse.ArgumentParser(prog="subscription", description=__doc__.splitlines()[0])
parser.add_argument("source", nargs="?", default="ivy/world")
parser.add_argument("target", nargs="?", default="alice/head")
parser.add_argument("--realm", default="lab")
parser.add_argument("--connect", action="append", default=[], metavar="EP",
                    help="any agent's endpoint (default tcp/127.0.0.1:7447)")
parser.add_argument("--count", type=int, default=10, help="poses to print, then exit")
parser.add_argument("--timeout", type=float, default=30.0, help="give up after this many s")
args = parser.parse_args()

done = threading.Event()
seen = []


def on_pose(r):  # the subscription's thread
    if done.is_set():
        return
    seen.append(r)
    position = ", ".join(f"{x:.3f}" for x in r.position)
    print(f"pose at {r.t_ns} ns: [{position}]", flush=True)
    if len(seen) >= args.count:
        done.set()


with Client(realm=args.realm, connect=args.connect or ["tcp/127.0.0.1:7447"]) as client:
    sub = client.subscribe(args.source, args.target, on_pose=on_pose)
    if not done.wait(args.timeout):
        raise SystemExit(f"{len(seen)} poses within {args.timeout} s; status: {sub.status}")
    sub.close()
