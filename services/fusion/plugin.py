"""The ``fusion`` and ``predictor`` services' and evaluations' declarations: their options
and where they run (:func:`services.fusion.service.run`,
:func:`services.fusion.predictor_service.run`, :func:`services.fusion.evaluate.run`,
:func:`services.fusion.evaluate_predictor.run`); light to import, as ``uma service run
fusion --help`` needs no Zenoh and ``uma eval fusion --help`` not the evaluation."""

from __future__ import annotations

import argparse

from agent.runtime import EvalPlugin, ServicePlugin
from services import frames
from services.accel_rig.device_options import add_device_arguments
from services.fusion.state import MODEL_FLOOR
from services.laser_camera.plugin import add_estimate_argument

#: seconds of normal tracking between two scheduled gaps (``uma eval fusion``)
GAP_SPACING_S = 4.0


def add_fusion_arguments(parser: argparse.ArgumentParser) -> None:
    """The service's options; the tracker (and its filter's scipy) is imported here for its
    coasting default, when the service's parser is built, not for the evaluations'."""
    from services.fusion.tracker import MAX_COAST_S

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


def add_fusion_eval_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gaps", default="0.25,0.5,1", metavar="S,S,...",
                        help="lengths of the optical dropouts to schedule, cycled every "
                             f"{GAP_SPACING_S:g} s after the warm-up (default 0.25,0.5,1)")
    parser.add_argument("--horizon-ms", type=float, default=None,
                        help="prediction horizon evaluated (default 20 ms; with --from, the "
                             "recorded fusion's own)")
    parser.add_argument("--optical", choices=("pose", "dots"), default="pose",
                        help="optical update: the tracker's pose (default) or SCAAT with "
                             "each labeled laser dot (predicted dot = beam of the predicted "
                             "pose intersected with the wall)")
    add_device_arguments(parser)
    parser.add_argument("--ideal", action="store_true",
                        help="the ideal simulated installation instead of the realistic "
                             "default (docs/SIMULATION.md)")
    add_estimate_argument(parser)
    parser.add_argument("--from", dest="from_file", default=None, metavar="FILE.mcap",
                        help="run the fusion filter on a recording's optical and accelerometer "
                             "samples instead of the simulator (uma record, uma demo --record); "
                             "compared with its ground truth if it holds the simulator's")
    parser.add_argument("--display-calibration", metavar="FILE", default=None,
                        help="with --from and --optical dots: the laser tracker's calibration "
                             "file, whose walls the recorded dots lie on (the one uma demo "
                             "gives its fusion)")
    parser.add_argument("--no-cache", action="store_true",
                        help="recalibrate the laser tracker instead of reusing "
                             "~/.cache/uma/laser_calibration_*.json")


FUSION_EVAL = EvalPlugin(
    name="fusion",
    help="The simulated MARVIN end to end: rendered camera images -> laser-dot tracker at "
         "15 Hz, simulated accelerometers at 300 Hz -> EKF/SCAAT fusion, against ground "
         "truth at 300 Hz: RMSE/max of the fused pose and of optical-only baselines (hold "
         "the last pose; extrapolate at most one frame) over all samples, inside and "
         "outside the gaps; errors through optical gaps and recovery, +20 ms prediction "
         "error, NEES, updates/s.  Samples left out, filter restarts and rejections are "
         "counted; 'resets': the worst error in the 2 s after each (re)start against the "
         "starting optical pose's error plus what the filter's covariance claims (its "
         "99.73 % ellipsoid along the error; 'largest_axis_3_sigma': three standard "
         "deviations of its largest axis in every direction); "
         "'given_by_simulator' lists what the run takes from the simulator's truth (the "
         "accelerometers' noise model and latency).",
    add_arguments=add_fusion_eval_arguments,
    run="services.fusion.evaluate:run",
    higher_is_better=frozenset({"output_rate_hz", "optical_poses",
                                "filter_updates_per_cpu_s"}),
)


def add_predictor_eval_arguments(parser: argparse.ArgumentParser) -> None:
    """No options of its own: --seed drives the perturbations, --seconds the head run."""


PREDICTOR_EVAL = EvalPlugin(
    name="predictor",
    help="Dorfmüller-Ulhaas's EKF motion predictor (§3.3): convergence of omega, v and a "
         "on exact and perturbed simulated rigid-body motion, re-convergence after an "
         "abrupt change (figs. 9-15), and +20 ms prediction on the simulated head "
         "trajectory for --seconds. --seed drives the perturbations.",
    add_arguments=add_predictor_eval_arguments,
    run="services.fusion.evaluate_predictor:run",
)
