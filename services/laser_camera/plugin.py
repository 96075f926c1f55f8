"""The ``laser-camera`` service's and evaluation's declarations: their options and where
they run (:func:`services.laser_camera.service.run`,
:func:`services.laser_camera.evaluate.run`); light to import, as ``uma service run
laser-camera --help`` needs no Zenoh and ``uma eval laser-camera --help`` not the
evaluation."""

from __future__ import annotations

import argparse

from agent.runtime import EvalPlugin, ServicePlugin


def add_estimate_argument(parser: argparse.ArgumentParser) -> None:
    """``--estimate-installation`` / ``--no-estimate-installation``: the laser tracker's
    online installation estimate (the service, its evaluation and the fusion's evaluation
    take it alike; :func:`estimate_installation` reads it)."""
    parser.add_argument("--estimate-installation", action=argparse.BooleanOptionalAction,
                        default=None,
                        help="--estimate-installation (the default, except with --ideal): "
                             "the laser tracker estimates the installation's errors (its "
                             "beams, the screens' bend, the cameras' turn and screen maps) "
                             "from the fourth beam's miss, frame set by frame set, and "
                             "corrects each pose and its dots by the estimate so far; their "
                             "covariance then carries what the estimate has not pinned down "
                             "yet. --no-estimate-installation (the default with --ideal, "
                             "which has no installation errors): no correction, every pose "
                             "carries the installation's whole tolerances as covariance")


def estimate_installation(args: argparse.Namespace) -> bool:
    """Whether the laser tracker estimates the installation: as asked, else on unless
    ``--ideal`` (an ideal installation has nothing to estimate)."""
    given = getattr(args, "estimate_installation", None)
    return not getattr(args, "ideal", False) if given is None else bool(given)


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
    add_estimate_argument(parser)


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


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    """The evaluation's options; the realistic installation's defaults in their help come
    from the simulator, imported here, when an evaluation's parser is built."""
    from services.sim.world import WorldConfig

    real = WorldConfig()
    parser.add_argument("--rate-hz", type=float, default=30.0,
                        help="camera frame rate (default 30; the thesis ran at 15-20)")
    parser.add_argument("--cameras", type=int, choices=(6, 8), default=6,
                        help="6: one camera per screen (default); 8: floor and ceiling split "
                             "in two, as in the thesis")
    parser.add_argument("--ideal", action="store_true",
                        help="the ideal installation (black screens, perfect housing, flat "
                             "screens, no calibration residual) instead of the realistic "
                             "default of docs/SIMULATION.md")
    parser.add_argument("--housing-error-deg", type=float, default=None, metavar="DEG",
                        help="laser housing whose beams are off by this much (std; default "
                             f"{real.housing_error_deg:g}, ideal 0)")
    parser.add_argument("--housing-offset-mm", type=float, default=None, metavar="MM",
                        help="... and whose beams miss the common point P0 by this much "
                             f"(std; default {real.housing_offset_m * 1e3:g}, ideal 0)")
    parser.add_argument("--screen-bulge-mm", type=float, default=None, metavar="MM",
                        help="fabric screens bent inwards by this much at their centres "
                             f"(std; default {real.screen_bulge_m * 1e3:g}, ideal 0: flat)")
    parser.add_argument("--model-rot-std-deg", type=float, default=0.0, metavar="DEG",
                        help="rotation error the tracker adds to its covariance for what the "
                             "dots cannot show (default 0)")
    parser.add_argument("--model-pos-std-mm", type=float, default=0.0, metavar="MM",
                        help="the same for position (default 0)")
    parser.add_argument("--calibration", metavar="FILE", default=None,
                        help="load this calibration instead of calibrating the simulated "
                             "cameras first (about 15 s); it must match --cameras")
    add_estimate_argument(parser)


EVAL = EvalPlugin(
    name="laser-camera",
    help="MARVIN's laser-dot camera tracker on the simulated IVY display: calibrates the "
         "simulated cameras, renders the head trajectory of --seed, runs the whole pipeline "
         "(dot detection, homographies, 24 labelings, the labeling gate, temporal coherence) "
         "and prints frames, labeling accuracy, frames the labeling gate refused, "
         "orientation/position errors against ground truth and timings.",
    add_arguments=add_eval_arguments,
    run="services.laser_camera.evaluate:run",
    higher_is_better=frozenset({"pose_pct_when_four_visible", "poses", "labeling_correct_pct",
                                "frames_with_four_visible_dots", "share_inside_single_95",
                                "effective_samples"}),
)
