"""The grammar of the commands the outside-in tracker adds: ``uma calibrate rig``.

Only argparse here (``uma --help`` imports it); the work is in ``services.outside_in.cli``.
"""

from __future__ import annotations

import argparse

from agent.runtime import CommandPlugin


def named(text: str) -> tuple[str, str]:
    """A ``CAMERA=VALUE`` argument (a file, a device index, a URL)."""
    name, eq, value = text.partition("=")
    if not eq or not name or not value:
        raise argparse.ArgumentTypeError(f"{text!r}: expected CAMERA=VALUE, e.g. "
                                         "cam0=cam0.avi")
    return name, value


def _distances(text: str) -> tuple[float, float, float]:
    try:
        d = tuple(float(x) for x in text.split(","))
    except ValueError:
        d = ()
    if len(d) != 3:
        raise argparse.ArgumentTypeError(f"{text!r}: three distances in metres, e.g. "
                                         "0,0.16,0.5")
    return d  # type: ignore[return-value]


def _rig_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_argument_group("recordings (one per camera, frames matched by their times)")
    src.add_argument("--wand-video", type=named, action="append", default=[],
                     metavar="NAME=FILE", help="a camera's video (or image folder) of the wand "
                     "waved through the volume; repeat for every camera")
    src.add_argument("--lframe-video", type=named, action="append", default=[],
                     metavar="NAME=FILE", help="the same camera's video of the L-frame lying "
                     "still on the floor (a second or two is enough)")
    src.add_argument("--intrinsics", type=named, action="append", default=[],
                     metavar="NAME=FILE", help="the camera's calibration file ('uma calibrate "
                     "camera'); with --refine-intrinsics a starting value")
    p.add_argument("--sim", type=int, metavar="SEED", default=None,
                   help="calibrate a simulated rig instead: renders the wand and L-frame "
                        "videos into --videos DIR, calibrates from them and compares with "
                        "the simulated truth")
    p.add_argument("--cameras", type=int, default=6, metavar="N",
                   help="simulated cameras (with --sim; default 6)")
    p.add_argument("--frames", type=int, default=400, metavar="N",
                   help="simulated wand frame sets at 20 Hz (with --sim; default 400)")
    p.add_argument("--videos", default=None, metavar="DIR",
                   help="where --sim writes its videos (default: a temporary folder)")
    p.add_argument("--wand", type=_distances, default=(0.0, 0.16, 0.5), metavar="D0,D1,D2",
                   help="the wand's marker positions from one end, metres (default "
                        "0,0.16,0.5; the middle one must sit off centre)")
    p.add_argument("--refine-intrinsics", action="store_true",
                   help="estimate focal lengths, principal points and k1, k2 too (the "
                        "one-step calibration); by default the intrinsics files are kept")
    p.add_argument("--world", default="lab/world", metavar="FRAME",
                   help="the world frame the L-frame defines (default lab/world)")
    p.add_argument("--site", default="lab", metavar="SITE",
                   help="site prefix of the camera frames, SITE/NAME (default lab)")
    p.add_argument("--output", "-o", default="rig.toml", metavar="FILE",
                   help="the rig file to write (default rig.toml; intrinsics files beside it)")
    p.add_argument("--agent-config", default=None, metavar="FILE",
                   help="also write the cameras as [[static]] edges world -> camera for "
                        "'uma agent --config'")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")


def _body_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="the body's name (its frame will be SITE/NAME)")
    p.add_argument("--rig", required=True, metavar="FILE",
                   help="the rig file of 'uma calibrate rig'")
    p.add_argument("--video", type=named, action="append", default=[], metavar="NAME=FILE",
                   help="a camera's video of the body held still in the volume, alone "
                        "(a few seconds; repeat for every camera)")
    p.add_argument("--sim", type=int, default=None, metavar="SEED",
                   help="use the simulated rig instead, with its body --sim-body held still")
    p.add_argument("--sim-body", default="wand", metavar="BODY",
                   help="which simulated body (head, wand, hand; default wand)")
    p.add_argument("--frames", type=int, default=60, metavar="N",
                   help="simulated frame sets to average (with --sim; default 60)")
    p.add_argument("--bodies", default="bodies.toml", metavar="FILE",
                   help="the bodies file to add it to (created if missing; default "
                        "bodies.toml); a body of the same name is replaced")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")


BODY = CommandPlugin(
    name="body",
    help="define a rigid body from a few seconds of its markers held still",
    description="Triangulate the markers of one body held still in a calibrated rig, keep "
                "those seen in most frames, and add the body (markers relative to their "
                "centroid, world axes) to a bodies file; warns when its distances are not "
                "distinguishable from another body's beyond the measured noise, which "
                "would let the tracker mistake one for the other.",
    add_arguments=_body_arguments,
    run="services.outside_in.cli:calibrate_body_command")

RIG = CommandPlugin(
    name="rig",
    help="calibrate an outside-in camera rig with a wand and an L-frame",
    description="Estimate every marker camera's pose (and, with --refine-intrinsics, its "
                "intrinsics) from videos of a three-marker wand waved through the volume "
                "and of an L-frame lying on the floor, which defines the world frame. "
                "Sparse bundle adjustment; prints each camera's pose standard deviation and "
                "the reprojection RMS; writes rig.toml for 'uma service run outside-in' and "
                "static edges for the agents.",
    add_arguments=_rig_arguments,
    run="services.outside_in.cli:calibrate_rig_command")
