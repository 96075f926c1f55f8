"""The ``accel-rig`` service's and evaluation's declarations: their options and where they
run (:func:`services.accel_rig.service.run`, :func:`services.accel_rig.evaluate.run`); light
to import, as ``uma service run accel-rig --help`` needs no Zenoh and ``uma eval accel-rig
--help`` not the evaluation."""

from __future__ import annotations

import argparse

from agent.runtime import EvalPlugin, ServicePlugin
from services import frames
from services.accel_rig.calibration import POSE_SETS
from services.accel_rig.device_options import add_device_arguments
from services.accel_rig.rig import DEFAULT_DELTA_M, LAYOUTS
from services.accel_rig.simulator import DEFAULT_RATE_HZ


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", default="accel-rig", help="service id (default: accel-rig)")
    parser.add_argument("--source", default="sim", metavar="SRC",
                        help="'sim' (default: the simulated rig on the head trajectory), "
                             "'csv:FILE' (replay lines 't v1 .. vN') or 'serial:DEVICE' (the "
                             "same lines read live from a configured tty or a pipe)")
    parser.add_argument("--calibration", metavar="FILE", default=None,
                        help="calibration file (JSON) to load; required for csv/serial; "
                             "with the simulator, missing means: calibrate at start; with "
                             "--calibrate: where to write it (default accel_calibration.json)")
    parser.add_argument("--calibrate", action="store_true",
                        help="run the static calibration (Hogue 2003, §4.4.2): the simulated "
                             "rig, or the recordings given by --pose; write --calibration "
                             "and exit")
    parser.add_argument("--pose", action="append", default=[], metavar="LABEL=CSV",
                        help="with --calibrate: a recording of the rig held still with axis "
                             "LABEL (+x -x +y -y +z -z) pointing down, lines 't v1 .. vN'; at "
                             "least 4 (repeatable; write --pose=-x=FILE for a minus sign)")
    parser.add_argument("--pose-seconds", type=float, default=20.0,
                        help="seconds per simulated calibration pose (default 20)")
    parser.add_argument("--layout", default="marvin-six", choices=sorted(LAYOUTS),
                        help="nominal accelerometer layout: positions (default marvin-six)")
    parser.add_argument("--delta", type=float, default=DEFAULT_DELTA_M,
                        help=f"accelerometer distance from the rig centre, m (default "
                             f"{DEFAULT_DELTA_M})")
    parser.add_argument("--rate-hz", type=float, default=DEFAULT_RATE_HZ,
                        help="sample rate (default 300, appendix C.1)")
    parser.add_argument("--seed", type=int, default=1,
                        help="simulated trajectory seed (default 1; as the sim service)")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="csv replay speed (1 = as recorded, 0 = as fast as possible)")
    parser.add_argument("--reset-frame", default="*/head", metavar="FRAME",
                        help="frame whose absolute pose in ivy/world resets the integrator: "
                             "a head (pattern, composed with --mount; default */head) or "
                             f"{frames.ACCEL_RIG} itself")
    parser.add_argument("--reset-every", type=float, default=1.0,
                        help="seconds between resets from the absolute pose (default 1; 0: "
                             "at every absolute pose)")
    parser.add_argument("--mount", default=None, metavar="X,Y,Z,QX,QY,QZ,QW",
                        help="pose of the rig in the head frame (default: the simulated "
                             "head mounting)")
    parser.add_argument("--ttl-s", type=float, default=1.0,
                        help="advertised validity of a dead-reckoned pose (default 1 s)")


ACCEL_RIG = ServicePlugin(
    name="accel-rig",
    help="MARVIN's six-accelerometer inertial tracker (Hogue 2003, ch. 4): publishes each "
         "sample's accelerations (accel_raw, with the rig geometry and calibration as "
         "attributes) and the dead-reckoned pose of marvin/accel_rig in ivy/world since the "
         "last absolute pose (need 'reset'). Input: the simulated rig (default), a CSV replay "
         "or a serial line, with a calibration file; '--calibrate' writes one.",
    add_arguments=add_arguments,
    run="services.accel_rig.service:run",
)


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=int, default=100,
                        help="dead-reckoning runs from random starting points (default 100)")
    parser.add_argument("--layout", default="marvin-six", choices=sorted(LAYOUTS),
                        help="nominal accelerometer layout (default marvin-six; the simulated "
                             "device has the table 4.1 axes for it)")
    parser.add_argument("--poses", default="six", choices=sorted(POSE_SETS),
                        help="calibration orientations: 'thesis' = +x -x +y -z down (the "
                             "minimum of §4.4.2), 'six' = every face down, least squares "
                             "(default six)")
    parser.add_argument("--pose-seconds", type=float, default=20.0,
                        help="seconds held still per calibration pose (default 20: the "
                             "calibration error is shared by every run, so it is kept well "
                             "below the noise of one run)")
    parser.add_argument("--noise-draws", type=int, default=0, metavar="K",
                        help="repeat the runs K more times with fresh sensor noise on the "
                             "same device, calibration, trajectory and start times and report "
                             "each repeat's mean NEES (nees.*.noise_draws): a seed outside its "
                             "band in the eval's draw but inside in fresh ones missed by its "
                             "draw, one outside in all of them by its rig (default 0; each "
                             "repeat costs as much as the eval)")
    add_device_arguments(parser)


EVAL = EvalPlugin(
    name="accel-rig",
    help="Accuracy of MARVIN's six-accelerometer tracker (Hogue 2003, ch. 4) on simulated data: "
         "calibration errors from static poses, then orientation/position drift after "
         "0.25/0.5/1/2 s of dead reckoning from random starting points, and the NEES of the "
         "reported covariance. --seconds is the span of trajectory the runs start in.",
    add_arguments=add_eval_arguments,
    run="services.accel_rig.evaluate:run",
    higher_is_better=frozenset({"draws_within_bounds"}),
)
