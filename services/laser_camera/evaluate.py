"""``uma eval laser-camera``: the whole optical pipeline against simulated ground truth.

The simulated IVY display is calibrated from its rendered calibration images (or a given
calibration file is loaded), then the head trajectory of ``--seed`` is rendered at
``--rate-hz`` and every frame set goes through ``LaserTracker``: detection, homographies,
labeling, temporal coherence, gating.  The figures compare each pose with the true pose of
``marvin/laser_rig`` (Hogue 2003, tables 5.2-5.3 report 0.1 deg mean / 0.3-0.35 deg max
orientation error and 1.13 cm mean position error on the real IVY).  Deterministic for a
seed: rendering depends only on (seed, t).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.consistency import nees_figures
from services.laser_camera.calibration import Calibration, calibrate_sim
from services.laser_camera.detection import AREA, FLUX, STD, UV, DetectorParams
from services.laser_camera.plugin import estimate_installation
from services.laser_camera.tracker import (
    GATE_REASONS,
    NO_POSE_REASONS,
    LaserTracker,
    PoseEstimate,
    TrackerParams,
)
from services.sim.world import Frame, IvyWorld, WorldConfig

#: a labeled dot farther than this from its diode's true spot is a labeling error
LABEL_TOLERANCE_M = 0.02


def run(args: argparse.Namespace) -> dict[str, Any]:
    if not args.rate_hz > 0:
        raise InvalidInputError(f"--rate-hz must be positive, got {args.rate_hz}")
    # every seed is another housing, screens and camera residual of the same installation
    world = IvyWorld(n_cameras=args.cameras, seed=args.seed, config=world_config(args),
                     imperfection_seed=args.seed)
    t0 = time.perf_counter()
    if args.calibration:
        cal = Calibration.load(args.calibration)
        missing = {c.name for c in world.cameras} - {c.name for c in cal.cameras}
        if missing:
            raise InvalidInputError(f"calibration {args.calibration} lacks cameras "
                                    f"{sorted(missing)} of the {args.cameras}-camera world")
    else:
        cal = _calibration(world)
    calib_s = time.perf_counter() - t0
    make = TrackerParams.ideal if args.ideal else TrackerParams
    estimate = estimate_installation(args)
    params = make(model_pos_std_m=args.model_pos_std_mm / 1000,
                  model_rot_std_rad=np.radians(args.model_rot_std_deg),
                  estimate_installation=estimate)
    figures = evaluate(world, cal, args.seconds, args.rate_hz, params)
    figures["calibration_s"] = round(calib_s, 2)
    figures["seed"] = args.seed
    c = world.config
    figures["installation"] = "ideal" if args.ideal else "realistic"
    figures["installation_estimate"] = estimate
    figures["imperfections"] = {"housing_error_deg": c.housing_error_deg,
                                "housing_offset_mm": c.housing_offset_m * 1e3,
                                "screen_bulge_mm": c.screen_bulge_m * 1e3,
                                "calibration_residual_deg": c.calibration_residual_deg,
                                "projection_peak_dn": c.projection_peak_dn}
    return figures


_CALIBRATIONS: dict[str, Calibration] = {}


def _calibration(world: IvyWorld) -> Calibration:
    """The world's calibration, made once per installation in this process (``--seeds``
    runs share it: the seed changes the trajectory and the imperfections, not the
    calibration images)."""
    key = repr(sorted(world.installation.items()))
    if key not in _CALIBRATIONS:
        _CALIBRATIONS[key] = calibrate_sim(world)
    return _CALIBRATIONS[key]


def world_config(args: argparse.Namespace) -> WorldConfig:
    """The installation the options ask for: realistic or ideal, with any imperfection
    given on the command line instead of its default."""
    given = {k: v for k, v in (("housing_error_deg", args.housing_error_deg),
                               ("housing_offset_m", _mm(args.housing_offset_mm)),
                               ("screen_bulge_m", _mm(args.screen_bulge_mm)))
             if v is not None}
    if args.ideal:
        return WorldConfig.ideal(n_cameras=args.cameras, **given)
    return WorldConfig(n_cameras=args.cameras, **given)


def _mm(x: float | None) -> float | None:
    return None if x is None else x / 1000


def evaluate(world: IvyWorld, cal: Calibration, seconds: float, rate_hz: float = 30.0,
             params: TrackerParams | None = None) -> dict[str, Any]:
    """Run the tracker over ``seconds`` of the world's trajectory; figures as a dict.

    Beside it a second tracker gets every spot's true pixel (no detector, no blur): its
    pose errs by the installation alone, the measured pose by that plus the measurement
    (``nees_parts``), so a seed whose NEES is off shows which part its covariance misses.
    With the online installation estimate the two trackers' estimates differ by the
    measured misses' noise, which neither pose's covariance splits off: no parts then."""
    tracker = LaserTracker(cal, params)
    exact = None if tracker.installation is not None else LaserTracker(cal, params)
    n = round(seconds * rate_hz)
    rot, pos, errors, covs, t_total, t_detect = [], [], [], [], [], []
    parts: dict[str, list[list[np.ndarray]]] = {"installation": [[], []],
                                                "measurement": [[], []]}
    four_truth = four_posed = labeled_ok = labeled_bad = 0
    for i in range(n):
        t = i / rate_hz
        frame = world.render(t)
        four_truth += len(frame.visible_labels) == 4
        res = tracker.process(frame.images, t)
        ref = None if exact is None else exact.solve(exact.locate(true_detections(frame)), t)
        t_total.append(res.timing_s["total"])
        t_detect.append(res.timing_s["detect"] / len(frame.images))
        if not isinstance(res, PoseEstimate):
            continue
        if isinstance(ref, PoseEstimate):
            _split(parts, res, ref, frame)
        four_posed += len(frame.visible_labels) == 4
        dp, da = geo.pose_error(res.position, res.quaternion, frame.rig_position,
                                frame.rig_quaternion)
        pos.append(float(dp))
        rot.append(float(da))
        errors.append(_error(res, frame))
        covs.append(geo.se3_to_decoupled(res.position, res.covariance))
        if _labels_correct(res, frame):
            labeled_ok += 1
        else:
            labeled_bad += 1
    rot_deg = np.degrees(rot) if rot else np.array([np.nan])
    pos_cm = np.array(pos) * 100 if pos else np.array([np.nan])
    poses = labeled_ok + labeled_bad
    return {
        "seconds": seconds,
        "rate_hz": rate_hz,
        "cameras": len(world.cameras),
        "frames": n,
        "frames_with_four_visible_dots": four_truth,
        "pose_pct_when_four_visible": round(100.0 * four_posed / four_truth, 3)
        if four_truth else None,
        "poses": poses,
        "frames_without_pose": n - poses,
        "no_pose_reasons": {r: tracker.counts[r] for r in NO_POSE_REASONS if tracker.counts[r]},
        "frames_refused_by_labeling_gate": sum(tracker.counts[r] for r in GATE_REASONS),
        "poses_covering_a_stray": tracker.counts["covered_stray"],
        "labeling_correct_pct": round(100.0 * labeled_ok / poses, 3) if poses else None,
        "labeling_errors": labeled_bad,
        "orientation_error_deg": _stats(rot_deg),
        "position_error_cm": _stats(pos_cm),
        "nees": nees_figures(np.array(errors), np.array(covs)) if errors else None,
        "nees_parts": None if exact is None else {
            name: nees_figures(np.array(e), np.array(c)) if e else None
            for name, (e, c) in parts.items()},
        "detection_ms_per_image_median": round(1e3 * float(np.median(t_detect)), 3),
        "pipeline_ms_per_frame_set_median": round(1e3 * float(np.median(t_total)), 3),
        "pipeline_ms_per_frame_set_p99": round(1e3 * float(np.percentile(t_total, 99)), 3),
    }


def true_detections(frame: Frame) -> dict[str, np.ndarray]:
    """Per camera, the detector's rows for the true pixels of the spots it sees (their
    centres at ``frame.t``): what a perfect detector would report."""
    out = {}
    for name, spots in frame.image_points.items():
        rows = np.zeros((len(spots), 5))
        rows[:, UV] = list(spots.values()) if spots else np.zeros((0, 2))
        rows[:, [FLUX, AREA]] = 1.0  # unused past detection
        rows[:, STD] = DetectorParams().floor_px
        out[name] = rows
    return out


def _split(parts: dict[str, list[list[np.ndarray]]], res: PoseEstimate, ref: PoseEstimate,
           frame: Frame) -> None:
    """Add one frame set to ``parts``: the exact tracker's error (true pose - ``ref``)
    against ``ref``'s installation covariance, and the measurement's (``ref - res``)
    against the rest of ``res``'s covariance (decoupled form, as ``_error``).  Without an
    installation covariance (the ideal tracker) only the measurement part is kept."""
    if np.any(ref.systematic):
        parts["installation"][0].append(_difference(frame.rig_position, frame.rig_quaternion,
                                                    ref))
        parts["installation"][1].append(geo.se3_to_decoupled(ref.position, ref.systematic))
    parts["measurement"][0].append(_difference(ref.position, ref.quaternion, res))
    parts["measurement"][1].append(geo.se3_to_decoupled(res.position,
                                                        res.covariance - res.systematic))


def _labels_correct(res: PoseEstimate, frame: Frame) -> bool:
    """Every labeled dot lies on its own diode's true spot."""
    return all(np.linalg.norm(res.dots[k] - frame.hits[k].point) < LABEL_TOLERANCE_M
               for k in res.dots)


def _error(res: PoseEstimate, frame: Frame) -> np.ndarray:
    """The pose error [position, world-frame rotation vector], in the order of the
    decoupled covariance."""
    return _difference(frame.rig_position, frame.rig_quaternion, res)


def _difference(position: np.ndarray, quaternion: np.ndarray, res: PoseEstimate
                ) -> np.ndarray:
    """``(position, quaternion)`` less ``res``'s pose: [position, world-frame rotation
    vector]."""
    phi = geo.quat_to_rotvec(geo.quat_multiply(quaternion, geo.quat_conjugate(res.quaternion)))
    return np.concatenate([position - res.position, phi])


def _stats(x: np.ndarray) -> dict[str, float]:
    return {"mean": round(float(np.mean(x)), 4), "p95": round(float(np.percentile(x, 95)), 4),
            "max": round(float(np.max(x)), 4)}
