"""The ``sim`` service's declaration: its options and where it runs
(:func:`services.sim.service.run`); light to import, as ``uma service run sim --help``
needs no Zenoh."""

from __future__ import annotations

import argparse

from agent.runtime import ServicePlugin
from services import frames
from services.sim import mounts

_LASER = ("head_to_laser_rig", frames.LASER_RIG, mounts.HEAD_TO_LASER_RIG)
_ACCEL = ("head_to_accel_rig", frames.ACCEL_RIG, mounts.HEAD_TO_ACCEL_RIG)
#: --mountings choice -> the static mounting abilities published
MOUNTINGS = {"all": (_LASER, _ACCEL), "laser": (_LASER,), "none": ()}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", default="sim", help="service id (default: sim)")
    parser.add_argument("--seed", type=int, default=1,
                        help="trajectory seed (default 1); other simulators must use the same")
    parser.add_argument("--rate-hz", type=float, default=100.0,
                        help="ground-truth publication rate (default 100)")
    parser.add_argument("--mountings", choices=sorted(MOUNTINGS), default="all",
                        help="which true rig mountings to publish as static edges: all "
                             "(default), laser (the accelerometer rig's must then come from "
                             "tracker alignment), none")
    parser.add_argument("--head-frame", default=frames.HEAD, metavar="FRAME",
                        help=f"frame of the true head (default {frames.HEAD}); another name "
                             "keeps the truth off the tracked edge, so queries of the head "
                             "still reach the trackers ('uma demo --record' records it so)")


SIM = ServicePlugin(
    name="sim",
    help="The simulated IVY world's ground truth: the head pose ivy/world -> alice/head "
         "(ground_truth: true) of a seeded random trajectory, and the true laser and "
         "accelerometer rig mountings as static edges.",
    add_arguments=add_arguments,
    run="services.sim.service:run",
)
