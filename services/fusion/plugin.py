"""The ``fusion`` and ``predictor`` services' declarations: their options and where they
run (:func:`services.fusion.service.run`, :func:`services.fusion.predictor_service.run`);
light to import, as ``uma service run fusion --help`` needs no Zenoh."""

from __future__ import annotations

import argparse

from agent.runtime import ServicePlugin
from services import frames
from services.fusion.state import MODEL_FLOOR
from services.fusion.tracker import MAX_COAST_S


def add_fusion_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", default="fusion", help="service id (default: fusion)")
    parser.add_argument("--world", default=frames.WORLD, help="world frame (ivy/world)")
    parser.add_argument("--head", default=frames.HEAD, help="fused frame (alice/head)")
    parser.add_argument("--optical-rig", default=frames.LASER_RIG,
                        help=f"frame of the optical rig (default {frames.LASER_RIG})")
    parser.add_argument("--accel-rig", default=frames.ACCEL_RIG,
                        help=f"frame of the inertial rig (default {frames.ACCEL_RIG})")
    parser.add_argument("--horizon-ms", type=float, default=0.0,
                        help="publish the pose predicted this far ahead (default 0)")
    parser.add_argument("--model-floor", type=float, default=MODEL_FLOOR,
                        help="extra accelerometer noise std for what the calibration does "
                             f"not capture, m/s^2 (default {MODEL_FLOOR:g})")
    parser.add_argument("--optical-bias-mm", type=float, default=0.0,
                        help="std of the optical tracker's persistent position error (its "
                             "calibration error), estimated as a slowly varying bias; 0: "
                             "the tracker's errors are white (default)")
    parser.add_argument("--optical-bias-tau-s", type=float, default=30.0,
                        help="how long that error persists, seconds (default 30)")
    parser.add_argument("--max-coast-s", type=float, default=MAX_COAST_S,
                        help="publish accelerometer-only poses for at most this long after "
                             "the last optical pose, then none until the optics return "
                             f"(default {MAX_COAST_S:g} s)")
    parser.add_argument("--optical", choices=("pose", "dots"), default="pose",
                        help="optical update: the tracker's poses (default) or one SCAAT "
                             "update per labeled laser dot, also of frame sets without a "
                             "pose (needs --display-calibration)")
    parser.add_argument("--display-calibration", metavar="FILE", default=None,
                        help="with --optical dots: the laser tracker's calibration file, "
                             "whose walls the dots lie on")


FUSION = ServicePlugin(
    name="fusion",
    help="EKF/SCAAT fusion of an absolute optical pose (laser rig, 15-60 Hz) and raw "
         "accelerometers (300 Hz) into the head pose at the inertial rate with covariance "
         "(Hogue 2003, ch. 6); rig mountings from the SRG's static edges.",
    add_arguments=add_fusion_arguments,
    run="services.fusion.service:run",
)


def add_predictor_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", default="predictor", help="service id (default: predictor)")
    parser.add_argument("--source", default=frames.WORLD, help="parent frame (ivy/world)")
    parser.add_argument("--target", default=frames.HEAD,
                        help=f"frame whose pose is predicted (default {frames.HEAD})")
    parser.add_argument("--output", default=None,
                        help="frame of the predicted pose (default: <target>_predicted)")
    parser.add_argument("--horizon-ms", type=float, default=20.0,
                        help="how far ahead to predict (default 20 ms)")
    parser.add_argument("--point-std-m", type=float, default=None,
                        help="noise of the input (default: from the ability's pos_std_m, "
                             "else 1 mm)")


PREDICTOR = ServicePlugin(
    name="predictor",
    help="Dorfmüller-Ulhaas's EKF motion predictor on any pose6d stream: publishes the "
         "pose predicted --horizon-ms ahead on <target>_predicted.",
    add_arguments=add_predictor_arguments,
    run="services.fusion.predictor_service:run",
)
