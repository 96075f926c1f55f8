"""The outside-in services' declarations, ``marker-camera`` (one per camera, any host) and
``outside-in`` (the reconstruction), and the evaluation's (``uma eval outside-in``, run by
:func:`services.outside_in.evaluate.run`); light to import (``uma service run NAME --help``,
``uma eval outside-in --help``)."""

from __future__ import annotations

import argparse

from agent.runtime import EvalPlugin, ServicePlugin
from services.outside_in.commands import named


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rig", required=True, metavar="FILE",
                        help="the rig file of 'uma calibrate rig' (cameras' intrinsics and "
                             "poses; its content is the calibration's version)")
    parser.add_argument("--world", default="lab/world", help="world frame (default lab/world)")
    parser.add_argument("--site", default="lab",
                        help="site prefix of camera and body frames, SITE/NAME (default lab)")


def marker_camera_arguments(parser: argparse.ArgumentParser) -> None:
    _common(parser)
    parser.add_argument("--camera", action="append", default=[], metavar="NAME",
                        help="a camera of the rig this process serves (repeatable; each is "
                             "its own service 'markers-NAME')")
    parser.add_argument("--source", type=named, action="append", default=[],
                        metavar="NAME=SOURCE", help="the camera's frames: a device index, a "
                        "video file, an image folder or a stream URL (repeatable)")
    parser.add_argument("--sim", type=int, default=None, metavar="SEED",
                        help="render the simulated rig's view instead (the rig file must be "
                             "that simulation's, e.g. from 'uma calibrate rig --sim SEED')")
    parser.add_argument("--rate-hz", type=float, default=30.0,
                        help="frame rate of the simulated cameras (default 30)")
    parser.add_argument("--max-frames", type=int, default=None, metavar="N",
                        help="stop after N frames per camera (default: never / the file's end)")
    parser.add_argument("--prerender", type=float, default=0.0, metavar="SECONDS",
                        help="with --sim: render SECONDS of frames first and replay them at "
                             "their exposure times, so that the process's CPU is the "
                             "segmentation's and not the simulator's (a real camera hands "
                             "over finished images); frames after them are rendered live "
                             "(default 0: all live)")
    parser.add_argument("--replay-at", type=float, default=None, metavar="UNIX_TIME",
                        help="with --prerender: the rendered frames start at this time (unix "
                             "seconds), so that cameras in several processes replay one "
                             "world (default: once this process has rendered them)")


def outside_in_arguments(parser: argparse.ArgumentParser) -> None:
    _common(parser)
    parser.add_argument("--id", default="outside-in", help="service id (default outside-in)")
    parser.add_argument("--bodies", required=True, metavar="FILE",
                        help="TOML file of rigid bodies: [[body]] name, markers = [[x, y, z], "
                             "...] (metres, body frame)")
    parser.add_argument("--rate-hz", type=float, default=30.0,
                        help="the cameras' frame rate, advertised as the poses' (default 30)")


MARKER_CAMERA = ServicePlugin(
    name="marker-camera",
    help="An infrared marker camera of an outside-in rig: finds the bright round blobs of "
         "every frame and publishes their sub-pixel centroids with their std as a "
         "markers2d ability (capture time in this host's clock, the camera's id and its "
         "calibration's version).",
    add_arguments=marker_camera_arguments,
    run="services.outside_in.service:run_marker_camera",
)

OUTSIDE_IN = ServicePlugin(
    name="outside-in",
    help="The outside-in reconstruction (Dorfmüller-Ulhaas §2): needs markers2d from every "
         "camera of the rig, wherever it runs, and publishes each rigid body's pose6d "
         "world -> SITE/BODY with covariance (matching, triangulation, identification, "
         "refinement on the images, the EKF).",
    add_arguments=outside_in_arguments,
    run="services.outside_in.service:run_outside_in",
)


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cameras", type=int, default=6, choices=range(4, 9),
                        metavar="N", help="cameras around the volume, 4-8 (default 6)")
    parser.add_argument("--rate-hz", type=float, default=120.0,
                        help="camera frame rate (default 120); about 0.1 s of computing per "
                             "frame set here: --seconds 3 is a quick look")
    parser.add_argument("--bump-deg", type=float, default=0.0, metavar="DEG",
                        help="turn camera 3 by this much half-way through the run (the "
                             "tracker keeps its calibration): when it is noticed and "
                             "re-estimated, and how far the new pose is from the truth")
    parser.add_argument("--unsynchronized", action="store_true",
                        help="every camera exposes at its own phase within the frame period "
                             "(cheap cameras without a sync cable)")
    parser.add_argument("--track-every", type=int, default=1, metavar="N",
                        help="the trackers take every N-th frame set only, as a "
                             "reconstruction behind on a busy host does (default 1: all)")


EVAL = EvalPlugin(
    name="outside-in",
    help="The outside-in marker tracker (Dorfmüller-Ulhaas §2) on a simulated rig of IR "
         "cameras with false blobs and a camera covered for 2 s: position and orientation "
         "RMSE with 3+ cameras and with exactly 2, NEES, identity swaps, side by side with "
         "an OpenCV-only baseline (triangulatePoints + estimateAffine3D) on the same images.",
    add_arguments=add_eval_arguments,
    run="services.outside_in.evaluate:run",
    higher_is_better=frozenset({"poses", "pose_pct_when_seeable", "effective_samples",
                                "share_inside_single_95"}),
)
