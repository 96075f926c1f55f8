"""The ``alignment`` service's and evaluation's declarations: their options and where they
run (:func:`services.alignment.service.run`, :func:`services.alignment.evaluate.run`); light
to import, as ``uma service run alignment --help`` needs no Zenoh and ``uma eval alignment
--help`` not the evaluation."""

from __future__ import annotations

import argparse

from agent.runtime import EvalPlugin, ServicePlugin
from services.alignment import records
from services.alignment.covariance import MIN_RESAMPLES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", default="alignment", help="service id (default: alignment)")
    parser.add_argument("--a", required=True, metavar="PARENT:CHILD",
                        help="edge (pattern) of tracker a's pose stream, world_a:sensor_a")
    parser.add_argument("--b", required=True, metavar="PARENT:CHILD",
                        help="edge (pattern) of tracker b's pose stream, world_b:sensor_b")
    parser.add_argument("--from-file", metavar="CSV", default=None,
                        help="align recorded pose pairs instead of live streams (columns: "
                             + ",".join(records.COLUMNS) + "); no network")
    parser.add_argument("--stations", action="store_true",
                        help="with --from-file: each row is one synchronous station (a robot "
                             "stopped at a pose); no time offset is estimated")
    parser.add_argument("--output", default="alignment.toml", metavar="FILE",
                        help="calibration file to write ([[static]] TOML for 'uma agent "
                             "--config'; default alignment.toml)")
    parser.add_argument("--method", default="daniilidis", choices=["daniilidis", "tsai-lenz"],
                        help="closed-form solver before refinement (default daniilidis)")
    parser.add_argument("--min-angle-deg", type=float, default=5.0,
                        help="before solving, --min-pairs motion pairs must rotate by at "
                             "least this (default 5); the solver's own selection follows "
                             "the motions' noise")
    parser.add_argument("--min-spread-deg", type=float, default=30.0,
                        help="rotation axes must spread by at least this before solving "
                             "(default 30)")
    parser.add_argument("--min-seconds", type=float, default=20.0,
                        help="seconds of overlapping data needed before solving (default 20)")
    parser.add_argument("--min-pairs", type=int, default=50,
                        help="motion pairs needed before solving (default 50)")
    parser.add_argument("--max-pos-std-mm", type=float, default=2.0,
                        help="publish only when the position std (bootstrap, RMS per axis) "
                             "is at most this; otherwise keep collecting (default 2)")
    parser.add_argument("--max-rot-std-deg", type=float, default=0.2,
                        help="likewise for the rotation std (default 0.2)")
    parser.add_argument("--max-stations", type=int, default=40,
                        help="stations used per solve (default 40: 780 motion pairs)")
    parser.add_argument("--max-offset-ms", type=float, default=500.0,
                        help="largest clock offset searched between the streams (default 500)")
    parser.add_argument("--offset-ms", type=float, default=None,
                        help="use this clock offset (t_b = t_a + offset) instead of "
                             "estimating it")
    parser.add_argument("--window-s", type=float, default=120.0,
                        help="seconds of both streams kept (default 120)")
    parser.add_argument("--recalibrate-every", type=float, default=0.0, metavar="S",
                        help="also re-solve on the sliding window every S seconds (default 0: "
                             "only on request)")
    parser.add_argument("--bootstrap", type=int, default=100,
                        help=f"resamples for the covariance (default 100, at least "
                             f"{MIN_RESAMPLES})")
    parser.add_argument("--seed", type=int, default=0, help="random seed (RANSAC, bootstrap)")
    parser.add_argument("--json", action="store_true",
                        help="with --from-file: print one JSON object")


ALIGNMENT = ServicePlugin(
    name="alignment",
    help="Tracker alignment (AX = XB, Klinker, Bauer 2005, ch. 3): needs two pose6d streams of "
         "rigidly joined sensors (--a world_a:sensor_a, --b world_b:sensor_b), estimates their "
         "clock offset and the pose of sensor_b in sensor_a once the motions are well "
         "conditioned, publishes it as the static edge sensor_a -> sensor_b with residuals and "
         "covariance, and writes it to a [[static]] TOML file for agents. --from-file aligns "
         "recorded pose pairs offline.",
    add_arguments=add_arguments,
    run="services.alignment.service:run",
)


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--trials", type=int, default=20,
                        help="number of random trials (default 20)")
    parser.add_argument("--outliers", type=float, default=0.2,
                        help="fraction of b's poses replaced by gross errors in the outlier "
                             "case (default 0.2)")
    parser.add_argument("--pos-noise-mm", type=float, default=1.0,
                        help="tracker b's position noise per pose sample, mm per axis "
                             "(default 1)")
    parser.add_argument("--rot-noise-deg", type=float, default=0.1,
                        help="tracker b's rotation noise per pose sample, degrees per axis "
                             "(default 0.1)")
    parser.add_argument("--ideal", action="store_true",
                        help="tracker a on the ideal installation instead of the realistic "
                             "default of docs/SIMULATION.md")


EVAL = EvalPlugin(
    name="alignment",
    help="Tracker alignment AX = XB on simulated pose streams with noise, a clock offset and "
         "outliers: rotation (deg) and translation (mm) errors of Daniilidis and Tsai-Lenz, "
         "with and without RANSAC, next to cv2.calibrateHandEye (TSAI, DANIILIDIS) on the same "
         "stations; the time-offset error; the consistency of the reported covariance (NEES). "
         "--seconds is the length of each trial's recording.",
    add_arguments=add_eval_arguments,
    run="services.alignment.evaluate:run",
    higher_is_better=frozenset({"within_2ms_fraction",
                                "within_chi2_95_fraction (ideal 0.95)",
                                "within_chi2_95_fraction_honest_5pct"}),
)
