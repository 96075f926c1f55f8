"""The ``laser-camera`` service's declaration: its options and where it runs
(:func:`services.laser_camera.service.run`); light to import, as ``uma service run
laser-camera --help`` needs no Zenoh."""

from __future__ import annotations

import argparse

from agent.runtime import ServicePlugin


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", default="laser-camera", help="service id (default: "
                        "laser-camera)")
    parser.add_argument("--source", action="append", default=[], metavar="SRC",
                        help="'sim' (default: the simulated IVY display) or, per camera of "
                             "the calibration, CAMERA=video:FILE or CAMERA=camera:INDEX "
                             "(repeatable)")
    parser.add_argument("--calibration", metavar="FILE", default=None,
                        help="calibration file to load (required for real sources; with the "
                             "simulator, missing means: calibrate at start, about 15 s); "
                             "with --calibrate: where to write it")
    parser.add_argument("--calibrate", action="store_true",
                        help="calibrate the simulated cameras from rendered checkerboards, "
                             "write --calibration (default laser_calibration.json) and exit")
    parser.add_argument("--rate-hz", type=float, default=30.0,
                        help="simulated camera frame rate (default 30)")
    parser.add_argument("--seed", type=int, default=1,
                        help="simulated trajectory seed (default 1; as the sim service)")
    parser.add_argument("--cameras", type=int, choices=(6, 8), default=6,
                        help="simulated display: 6 cameras (default) or 8 as in the thesis")
    parser.add_argument("--ideal", action="store_true",
                        help="simulate the ideal installation (docs/SIMULATION.md) and track "
                             "it without the realistic installation's tolerances")
    parser.add_argument("--model-rot-std-deg", type=float, default=0.0, metavar="DEG",
                        help="rotation error added to every covariance for what the dots "
                             "cannot show, e.g. the housing's tolerance (default 0)")
    parser.add_argument("--model-pos-std-mm", type=float, default=0.0, metavar="MM",
                        help="the same for position (default 0)")


LASER_CAMERA = ServicePlugin(
    name="laser-camera",
    help="MARVIN's laser-dot camera tracker (Hogue 2003, ch. 5): finds the four laser spots in "
         "the images of the cameras behind IVY's screens and publishes the pose of "
         "marvin/laser_rig in ivy/world with its covariance, plus the labeled spots as "
         "points3d. Input: the simulated display (default) or one video/camera per screen "
         "with a calibration file. '--calibrate' writes the simulated display's calibration.",
    add_arguments=add_arguments,
    run="services.laser_camera.service:run",
)
