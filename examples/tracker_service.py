"""A tracker service: declare an ability and publish poses on it.

    uma agent --realm lab --id hostA --listen tcp/127.0.0.1:7447    # first, in another shell
    python examples/tracker_service.py --realm lab --agent hostA --connect tcp/127.0.0.1:7447
"""

import argparse
import math
import time

from agent import Service

parser = argparse.ArgumentParser(prog="tracker_service", description=__doc__.splitlines()[0])
parser.add_argument("--realm", default="lab")
parser.add_argument("--agent", default="hostA", help="the agent of this host")
parser.add_argument("--connect", action="append", default=[], metavar="EP",
                    help="the agent's endpoint (default tcp/127.0.0.1:7447)")
parser.add_argument("--rate", type=float, default=100.0, help="poses per second")
parser.add_argument("--seconds", type=float, default=10.0, help="how long to publish")
args = parser.parse_args()

with Service("tracker", realm=args.realm, agent=args.agent,
             connect=args.connect or ["tcp/127.0.0.1:7447"]) as svc:
    head = svc.ability("pose", type="pose6d", edge=("ivy/world", "alice/head"),
                       frequency_hz=args.rate, latency_s=0.005, pos_std_m=0.002)
    svc.start()
    print(f"publishing ivy/world -> alice/head at {args.rate:g} Hz", flush=True)
    for i in range(int(args.seconds * args.rate)):
        angle = i / args.rate                      # walk a 1 m circle at head height
        yaw = [0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)]
        head.publish(time.time_ns(), [math.cos(angle), math.sin(angle), 1.6], yaw)
        time.sleep(1.0 / args.rate)
