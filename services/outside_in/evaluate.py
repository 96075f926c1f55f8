"""``uma eval outside-in``: the outside-in tracker against simulated ground truth, side by
side with a baseline built from OpenCV alone, in the same run on the same images.

Each seed is another rig (6 cameras by default around a 3 x 3 x 2.5 m volume, 640 x 480
at 120 Hz, 5 false blobs per camera) and other paths of the three bodies (4-5 markers
each).  Every frame set is rendered, its blobs found, and then:

* **uma, all cameras**: ``OutsideInTracker`` on every camera.  Camera 0 is covered for
  2 s (or 30 % of a shorter run) from 40 % of the run: its frames are dark.  Poses are
  binned by how many cameras' rays they were fitted to (3 or more; exactly 2).
* **uma, two cameras**: a second tracker on cameras 1 and 2 only, the
  "exactly 2 cameras" case on the same frames.
* **OpenCV baseline**, for both rigs: per body, the camera pair sharing the most of its
  markers, ``cv2.triangulatePoints`` on their (undistorted) blobs' centroids -- the
  intensity-weighted ones OpenCV's ``moments`` give over each blob and its rim, with the
  same segmentation as uma's blobs, where uma fits a ball's image to the pixels
  (``blob_model``) -- the body's markers
  aligned to the points by ``cv2.estimateAffine3D(force_rotation=True)`` (Umeyama); no
  refinement, no filter.  It is handed the simulator's truth of which blob is which
  marker (the nearest blob within 1 px of each marker's true image), so its errors are
  its geometry's alone, never a wrong correspondence.

With ``--bump-deg`` camera 3 is turned half-way through (its calibration kept): the run
says when the tracker noticed (``health``) and re-estimated it, and how far the new pose
is from the truth.

Figures: position and orientation RMSE per case, uma / OpenCV ratios (and the same on the
poses both gave, ``common_*``), mean NEES against
its 95 % band (``services.consistency``), identity swaps (a body's pose nearer another
body's truth than its own), poses further than 2 cm or 2 deg (wrong), poses from fewer than
two cameras (must be none), the share of body frames with a pose where two cameras saw
three markers of the body, and the tracker's time per frame set.  The cameras are the
simulated truth: ``uma calibrate rig --sim`` measures the calibration separately.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.consistency import nees_figures
from services.outside_in.blobs import BlobParams, Blobs, find_blobs
from services.outside_in.bodies import RigidBody
from services.outside_in.rig import RigCamera
from services.outside_in.simulator import Frame, SimConfig, Simulation
from services.outside_in.tracker import (
    BodyEstimate,
    CameraFrame,
    OutsideInTracker,
    TrackerParams,
)

Array = np.ndarray
#: a pose further off than this is wrong (a lost or swapped body), not noise
WRONG_M = 0.02
WRONG_RAD = np.radians(2.0)
#: the cameras of the two-camera rig
PAIR = (1, 2)
#: the camera ``--bump-deg`` turns
BUMPED = 3
#: the baseline's blobs: intensity-weighted centroids over each blob and its rim, made
#: of OpenCV's threshold, connectedComponents, dilate and moments
CENTROIDS = BlobParams(model_fit=False)


@dataclass
class _Case:
    """Errors and covariances of one tracker on one rig."""

    errors: list[Array] = field(default_factory=list)
    covs: list[Array] = field(default_factory=list)
    wrong: int = 0
    swaps: int = 0
    #: the same errors by (frame set, body), to hold two cases on the poses both gave
    keyed: dict[tuple[int, int], Array] = field(default_factory=dict)
    #: each pose's fit before the filter (its error and covariance, at the same time)
    fit_errors: list[Array] = field(default_factory=list)
    fit_covs: list[Array] = field(default_factory=list)

    def figures(self) -> dict[str, Any]:
        if not self.errors:
            return {"poses": 0, "wrong_poses": self.wrong, "identity_swaps": self.swaps}
        e = np.array(self.errors)
        out = {"poses": len(e), "wrong_poses": self.wrong, "identity_swaps": self.swaps,
               "position_rmse_mm": round(float(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, 1))))
                                         * 1e3, 4),
               "orientation_rmse_deg": round(float(np.degrees(np.sqrt(np.mean(
                   np.sum(e[:, 3:] ** 2, 1))))), 4)}
        if self.covs:
            out["nees"] = nees_figures(e, np.array(self.covs))
        if self.fit_covs:
            out["nees_fit"] = nees_figures(np.array(self.fit_errors), np.array(self.fit_covs))
        return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    if not args.rate_hz > 0:
        raise InvalidInputError(f"--rate-hz must be positive, got {args.rate_hz}")
    if not 1 <= args.track_every <= 100:
        raise InvalidInputError(f"--track-every must be in [1, 100], got {args.track_every}")
    sim = Simulation(seed=args.seed, config=SimConfig(
        n_cameras=args.cameras, rate_hz=args.rate_hz, synchronized=not args.unsynchronized))
    return evaluate(sim, args.seconds, bump_deg=args.bump_deg, every=args.track_every)


def evaluate(sim: Simulation, seconds: float, params: TrackerParams | None = None,
             bump_deg: float = 0.0, every: int = 1) -> dict[str, Any]:
    """The figures of one run; the trackers and the baseline take every ``every``-th frame
    set only (``--track-every``)."""
    n = max(round(seconds * sim.config.rate_hz), 1)
    bump_at = -(-(n // 2) // every) * every if bump_deg else None   # a frame set taken
    hide_from = round(0.4 * n)
    hide_to = hide_from + round(min(2.0, 0.3 * seconds) * sim.config.rate_hz)
    calibrated = list(sim.cameras)      # what the trackers and the baseline were told
    pair_cams = [calibrated[c] for c in PAIR]
    full = OutsideInTracker(calibrated, sim.bodies, params)
    pair = OutsideInTracker(pair_cams, sim.bodies, params)
    cases = {k: _Case() for k in ("uma_3plus", "uma_2", "uma_2cam_rig", "opencv_3plus",
                                  "opencv_2cam_rig")}
    fewer_than_two = 0
    coverage = [0, 0]   # body frames seeable, with a uma pose
    t_track, t_detect = [], []
    for i in range(0, n, every):
        sim.hidden = {0} if hide_from <= i < hide_to else set()
        if i == bump_at:
            sim.cameras[BUMPED] = bumped(sim.cameras[BUMPED], bump_deg)
        frames = [sim.render(c, i) for c in range(len(sim.cameras))]
        t0 = time.perf_counter()
        blobs = [find_blobs(f.image) for f in frames]
        t_detect.append((time.perf_counter() - t0) / len(frames))
        centroids = [find_blobs(f.image, CENTROIDS) for f in frames]
        t0 = time.perf_counter()
        est_full = full.process([CameraFrame(c, f.t, b)
                                 for c, (f, b) in enumerate(zip(frames, blobs, strict=True))])
        t_track.append(time.perf_counter() - t0)
        est_pair = pair.process([CameraFrame(k, frames[c].t, blobs[c])
                                 for k, c in enumerate(PAIR)])
        fewer_than_two += sum(e.cameras < 2 for e in est_full + est_pair)
        posed = {e.body for e in est_full}
        for k, body in enumerate(sim.bodies):
            if _seeable(frames, k, len(body.markers)):
                coverage[0] += 1
                coverage[1] += body.name in posed
        for e in est_full:
            _score(sim, i, e, cases["uma_3plus" if e.cameras >= 3 else "uma_2"])
        for e in est_pair:
            _score(sim, i, e, cases["uma_2cam_rig"])
        for k, body in enumerate(sim.bodies):
            for cams, idx, case in ((calibrated, range(len(sim.cameras)), "opencv_3plus"),
                                    (pair_cams, PAIR, "opencv_2cam_rig")):
                got = opencv_baseline(cams, [frames[c] for c in idx],
                                      [centroids[c] for c in idx], k, body)
                if got is not None:
                    _score_pose(sim, (i, k), frames[idx[0]].t, got[0], got[1], None,
                                cases[case])
    figures: dict[str, Any] = {
        "cameras": len(sim.cameras), "rate_hz": sim.config.rate_hz, "frames": n,
        "track_every": every,
        "synchronized": sim.config.synchronized,
        "occluded_camera": {"camera": sim.cameras[0].name,
                            "from_s": round(hide_from / sim.config.rate_hz, 3),
                            "to_s": round(hide_to / sim.config.rate_hz, 3)},
        **{k: c.figures() for k, c in cases.items()},
        "poses_from_fewer_than_two_cameras": fewer_than_two,
        "identity_swaps": sum(c.swaps for k, c in cases.items() if k.startswith("uma")),
        "pose_pct_when_seeable": round(100.0 * coverage[1] / coverage[0], 2)
        if coverage[0] else None,
        "detection_ms_per_image_median": round(1e3 * float(np.median(t_detect)), 3),
        "tracker_ms_per_frame_set_median": round(1e3 * float(np.median(t_track)), 3),
        "tracker_ms_per_frame_set_p99": round(1e3 * float(np.percentile(t_track, 99)), 3),
        "counts": dict(full.counts),
    }
    if bump_at is not None:
        figures["bump"] = bump_figures(full, sim, bump_at / sim.config.rate_hz, bump_deg)
    for rig, ours, theirs in (("3plus", "uma_3plus", "opencv_3plus"),
                              ("2cam_rig", "uma_2cam_rig", "opencv_2cam_rig")):
        a, b = figures[ours], figures[theirs]
        for what in ("position_rmse_mm", "orientation_rmse_deg"):
            if a.get(what) and b.get(what):
                figures[f"ratio_{what.split('_')[0]}_{rig}"] = round(a[what] / b[what], 4)
        figures[f"common_{rig}"] = common_ratios(cases[ours], cases[theirs])
    return figures


def common_ratios(ours: _Case, theirs: _Case) -> dict[str, Any]:
    """uma's RMSE over the baseline's on the (frame set, body) poses both gave: each case
    poses what it can (the baseline a body from three markers two cameras share, uma once
    it has found four), and a hard pose one of them gave and the other did not weighs in
    its RMSE alone."""
    both = [key for key in ours.keyed if key in theirs.keyed]
    out: dict[str, Any] = {"poses": len(both)}
    if both:
        a = np.array([ours.keyed[key] for key in both])
        b = np.array([theirs.keyed[key] for key in both])
        for what, cols in (("position", slice(0, 3)), ("orientation", slice(3, 6))):
            out[f"ratio_{what}"] = round(float(np.sqrt(
                np.sum(a[:, cols] ** 2) / np.sum(b[:, cols] ** 2))), 4)
    return out


def bumped(cam: RigCamera, deg: float) -> RigCamera:
    """The camera turned by ``deg`` about an axis across its view (a knock on its mount)."""
    turn = geo.rotvec_to_quat(np.radians(deg) * geo.quat_rotate(cam.quaternion, [0.6, 0.8, 0]))
    return cam.moved(cam.position, geo.quat_multiply(turn, cam.quaternion))


def bump_figures(tracker: OutsideInTracker, sim: Simulation, t_bump: float,
                 deg: float) -> dict[str, Any]:
    """When the bumped camera was noticed and re-estimated, and the new pose's error."""
    name = sim.cameras[BUMPED].name
    ev = {e["event"]: e["t"] for e in tracker.health.events if e["camera"] == name}
    others = [e for e in tracker.health.events if e["camera"] != name]
    est = tracker.cameras[BUMPED]
    truth = sim.cameras[BUMPED]
    out: dict[str, Any] = {"camera": name, "turned_deg": deg, "at_s": round(t_bump, 3),
                           "false_alarms": len(others)}
    if "disagrees" in ev:
        out["detected_after_s"] = round(ev["disagrees"] - t_bump, 3)
    if "re-estimated" in ev:
        out["reestimated_after_s"] = round(ev["re-estimated"] - t_bump, 3)
        out["reestimated_rot_error_deg"] = round(float(np.degrees(
            geo.quat_angle(est.quaternion, truth.quaternion))), 4)
        out["reestimated_pos_error_mm"] = round(
            float(np.linalg.norm(est.position - truth.position)) * 1e3, 3)
    return out


def _seeable(frames: list[Frame], body: int, n_markers: int) -> bool:
    """Two cameras or more saw three of the body's markers or more."""
    per_cam = [sum(k == body for k, _ in f.marker_uv) for f in frames]
    return sum(c >= 3 for c in per_cam) >= 2 and n_markers >= 3


def _score(sim: Simulation, frame_set: int, e: BodyEstimate, case: _Case) -> None:
    """The filtered pose, and where it counts, the fit it was updated with: that fit's
    NEES against its own covariance (the centroids' noise and, with unsynchronised
    cameras, the filter's motion error moved into it) apart from the filter's says which
    of the two a covariance that is off comes from."""
    k = [b.name for b in sim.bodies].index(e.body)
    n = len(case.errors)
    _score_pose(sim, (frame_set, k), e.t, e.p, geo.quat_to_matrix(e.q), e.cov, case)
    if len(case.errors) > n:
        case.fit_errors.append(_pose_error(sim, k, e.t, e.fit.p, e.fit.R))
        case.fit_covs.append(e.fit.cov)


def _score_pose(sim: Simulation, key: tuple[int, int], t: float, p: Array, R: Array,
                cov: Array | None, case: _Case) -> None:
    """Body ``key[1]``'s pose of frame set ``key[0]`` against the truth."""
    k = key[1]
    err = _pose_error(sim, k, t, p, R)
    if np.linalg.norm(err[:3]) > WRONG_M or np.linalg.norm(err[3:]) > WRONG_RAD:
        case.wrong += 1
        others = [np.linalg.norm(sim.body_pose(j, t)[0] - p) for j in range(len(sim.bodies))]
        if int(np.argmin(others)) != k:
            case.swaps += 1
        return
    case.errors.append(err)
    case.keyed[key] = err
    if cov is not None:
        case.covs.append(cov)


def _pose_error(sim: Simulation, k: int, t: float, p: Array, R: Array) -> Array:
    """Body ``k``'s pose error at ``t`` over ``[dp, phi]`` (truth less the pose)."""
    p_true, q_true = sim.body_pose(k, t)
    return np.concatenate([p_true - p, geo.rodrigues_inverse(geo.quat_to_matrix(q_true) @ R.T)])


def opencv_baseline(cams: list[RigCamera], frames: list[Frame], blobs: list[Blobs], body: int,
                    rb: RigidBody) -> tuple[Array, Array] | None:
    """Body ``body``'s pose from the camera pair sharing most of its markers:
    ``cv2.triangulatePoints`` and ``cv2.estimateAffine3D`` (no refinement, no filter)."""
    labeled = [_labels(f, b, body) for f, b in zip(frames, blobs, strict=True)]
    best = None
    for i in range(len(cams)):
        for j in range(i + 1, len(cams)):
            common = sorted(set(labeled[i]) & set(labeled[j]))
            if len(common) >= 3 and (best is None or len(common) > len(best[2])):
                best = (i, j, common)
    if best is None:
        return None
    i, j, common = best
    xi = cams[i].normalize(np.array([labeled[i][m] for m in common]))
    xj = cams[j].normalize(np.array([labeled[j][m] for m in common]))
    h = cv2.triangulatePoints(cams[i].projection, cams[j].projection, xi.T, xj.T)
    X = (h[:3] / h[3]).T
    M, scale = cv2.estimateAffine3D(rb.markers[common], X, force_rotation=True)
    if M is None or not scale > 0:
        return None
    return M[:, 3].copy(), M[:, :3] / scale


def _labels(frame: Frame, blobs: Blobs, body: int) -> dict[int, Array]:
    """Marker -> detected blob pixel, for the markers of ``body`` whose true image has a
    blob within 1 px (the truth tells the baseline which blob is which marker)."""
    out = {}
    if len(blobs) == 0:
        return out
    for (k, m), uv in frame.marker_uv.items():
        if k != body:
            continue
        d = np.linalg.norm(blobs.uv - uv, axis=1)
        j = int(np.argmin(d))
        if d[j] < 1.0:
            out[m] = blobs.uv[j]
    return out
