"""A pose query whose path spans several agents, optimal for an error function.

    python examples/cross_agent_query.py cam/nw alice/head --connect tcp/127.0.0.1:7447
"""

import argparse

from agent import Client

parser = argparse.ArgumentParser(prog="cross_agent_query", description=__doc__.splitlines()[0])
parser.add_argument("source", nargs="?", default="cam/nw", help="frame to express the pose in")
parser.add_argument("target", nargs="?", default="alice/head", help="frame whose pose to get")
parser.add_argument("--realm", default="lab")
parser.add_argument("--connect", action="append", default=[], metavar="EP",
                    help="any agent's endpoint (default tcp/127.0.0.1:7447)")
parser.add_argument("--error", default="latency",
                    help="hops, latency, accuracy, confidence, cost or an expression")
args = parser.parse_args()

with Client(realm=args.realm, connect=args.connect or ["tcp/127.0.0.1:7447"]) as client:
    r = client.pose(args.source, args.target, at=None, error=args.error)
    print("position", ", ".join(f"{x:.4f}" for x in r.position))
    print("quaternion", ", ".join(f"{x:.4f}" for x in r.quaternion))
    print("path", " -> ".join(r.path))
    print("agents", ", ".join(dict.fromkeys(e["owner"] for e in r.edges)))
    print("extrapolated", f"{r.extrapolated_s:.4f} s")
