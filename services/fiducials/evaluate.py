"""``uma eval fiducials``: marker poses against simulated ground truth, beside two oracles.

A simulated 640x480 webcam (:func:`services.fiducials.simulate.webcam`: about 62 degrees
of view, barrel distortion, blur, shot and read noise, motion blur, each pixel the mean
over its area, :data:`~services.camera.simulator.FAITHFUL`) watches one 8 cm
AprilTag (36h11) moving smoothly between 0.5 and 3 m, tilting up to 40 degrees; frames at
``--fps`` for ``--seconds``.  The same frames go to

* **uma**: :class:`~services.fiducials.tracker.FiducialTracker` (edge-fitted corners, IPPE
  candidates refined by LM and weighted Gauss-Newton, covariance from the corners' edge
  fits, ambiguity handling);
* **bare**: ``cv2.aruco.ArucoDetector`` (OpenCV's defaults) + ``cv2.solvePnP`` with
  ``SOLVEPNP_IPPE_SQUARE`` and the lens distortion;
* **apriltag**: ``pupil-apriltags`` (AprilTag 3's detector at full resolution, edge
  refinement and pose) on the image undistorted by ``cv2.remap`` (it knows no
  distortion), in a child process (:class:`_AprilTag`); skipped, and said so, when
  ``pupil_apriltags`` is not installed.

Per true-distance bin (0.5 m wide): detections, position error (mm) and orientation error
(deg), median / p95 / max, each method over the frames it detected, and (``same_frames``)
uma beside each other method over the frames both detected; for uma also the NEES of its
6-dof covariance against chi2(6)
(:func:`services.consistency.nees_figures`, over the samples not ``covered``: a covered
sample's covariance carries a deliberate allowance for the other solution), how
many samples were flagged (``covered``: covariance inflated over both IPPE solutions;
``history``: the solution the track's accumulated evidence supports, with its own
covariance and the other's chance beside it), and **silent
flips**: samples whose rotation error lies beyond chi2(3)'s 99.9 % point of their own
rotation covariance and exceeds 5 degrees.

A second scene puts four such tags on a 21 cm plate (a bundle, solved as one body) and
compares the bundle's position error and claimed standard deviation with its single
tags' (solved alone, on the same frames): pooled, and (``best_*``) the most accurate
tag's, the one of least RMS error (chosen by its measured error, so even an honest
covariance measures a smaller gain over it than it claims: the luckiest of four);
(``prior_*``) the tag whose own covariance claims it most accurate (chosen before its
errors are seen); ``least_gain_share``: the least over the tags of the measured gain
over it in units of the claimed (the goal read strictly: at least 1 against every tag);
and the NEES of the bundle's own 6-dof covariance (``nees``): whether the factor it
claims rests on a covariance of the right size.
"""

from __future__ import annotations

import argparse
import itertools
import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import cv2
import numpy as np
from scipy.stats import chi2

from agent.errors import InvalidInputError
from services.camera.markers import dictionary, marker_corners
from services.camera.simulator import FAITHFUL, SceneObject, SimCamera
from services.consistency import nees_figures
from services.fiducials.bodies import Body
from services.fiducials.simulate import tags, wandering, webcam
from services.fiducials.tracker import FiducialTracker

FAMILY = "apriltag36h11"
SIZE_M = 0.08
BINS = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
FLIP_CHI2 = float(chi2.ppf(0.999, 3))
FLIP_MIN_DEG = 5.0
#: pupil-apriltags' tag frame is OpenCV's marker frame turned half a turn about y
APRILTAG_TO_OPENCV = np.diag([-1.0, 1.0, -1.0])
PLATE_OFFSET_M = 0.055


def run(args: argparse.Namespace) -> dict[str, Any]:
    if not args.fps > 0:
        raise InvalidInputError(f"--fps must be positive, got {args.fps}")
    rng = np.random.default_rng(args.seed)
    camera = webcam(rng)
    sim = SimCamera(camera, supersampling=FAITHFUL)
    n = max(int(args.seconds * args.fps), 1)
    times = np.arange(n) / args.fps
    period = min(max(args.seconds, 4.0), 20.0)
    traj = wandering(rng, camera, (BINS[0], BINS[-1]), period)
    scene = tags(FAMILY, [args.seed % 500], SIZE_M, [traj])
    oracle = _AprilTag(camera)
    methods = {"uma": _Uma(camera), "bare": _Bare(camera)}
    if oracle.available:
        methods["apriltag"] = oracle
    rows: dict[str, list] = {k: [] for k in methods}
    try:
        for k, t in enumerate(times):
            image = sim.render(scene, float(t), rng)
            truth = traj(float(t))
            for name, method in methods.items():
                got = method(image, round(t * 1e9))
                if got is not None:
                    rows[name].append((k, truth, *got))
    finally:
        oracle.close()
    out: dict[str, Any] = {"frames": n, "apriltag": "pupil-apriltags" if oracle.available
                           else f"skipped: {oracle.missing}",
                           "apriltag_restarts": oracle.restarts}
    depth = np.array([traj(float(t))[2, 3] for t in times])
    out["bins"] = {f"{lo:g}-{hi:g} m": _bin(rows, lo, hi, int(np.sum((depth >= lo) & (depth < hi))))
                   for lo, hi in itertools.pairwise(BINS)}
    out["silent_flips"] = sum(b["uma"].get("silent_flips", 0) for b in out["bins"].values())
    out["bundle"] = _bundle(rng, camera, sim, n, args.fps)
    return out


class _Uma:
    def __init__(self, camera: Any) -> None:
        self.tracker = FiducialTracker(camera, FAMILY, SIZE_M)

    def __call__(self, image: np.ndarray, t_ns: int) -> tuple | None:
        est = self.tracker.process(image, t_ns)
        if not est:
            return None
        e = est[0]
        return e.R, e.t, e.covariance, e.ambiguity


class _Bare:
    def __init__(self, camera: Any) -> None:
        self.camera = camera
        self.detector = cv2.aruco.ArucoDetector(dictionary(FAMILY))

    def __call__(self, image: np.ndarray, t_ns: int) -> tuple | None:
        corners, ids, _ = self.detector.detectMarkers(image)
        if ids is None:
            return None
        ok, rvec, tvec = cv2.solvePnP(marker_corners(SIZE_M), corners[0].reshape(4, 2),
                                      self.camera.K, self.camera.dist,
                                      flags=cv2.SOLVEPNP_IPPE_SQUARE)
        return (cv2.Rodrigues(rvec)[0], tvec.ravel(), None, None) if ok else None


class _AprilTag:
    """AprilTag 3 (``pupil-apriltags``) in a child process of its own: its pose code
    corrupts the heap now and then (a ``malloc()`` abort after "Error, more than one new
    minima found", AprilRobotics/apriltag#130; twice in about thirty seeds of this eval).
    A frame whose detection kills the child is given to a fresh one once more, and the
    restarts are counted; a frame that kills that one too counts as not detected."""

    def __init__(self, camera: Any) -> None:
        try:
            import pupil_apriltags  # noqa: F401
        except ImportError as exc:
            self.available, self.missing = False, f"pupil_apriltags not importable ({exc})"
        else:
            self.available, self.missing = True, ""
        self.camera = camera
        self.restarts = 0
        self._pool: ProcessPoolExecutor | None = None

    def __call__(self, image: np.ndarray, t_ns: int) -> tuple | None:
        for _ in range(2):
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    1, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_apriltag_start,
                    initargs=(self.camera.K, self.camera.dist, self.camera.size))
            try:
                return self._pool.submit(_apriltag_detect, image).result()
            except BrokenProcessPool:
                self._pool.shutdown(wait=False)
                self._pool = None
                self.restarts += 1
        return None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


_apriltag: dict[str, Any] = {}


def _apriltag_start(K: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> None:
    """The child's detector, undistortion maps and camera parameters."""
    import pupil_apriltags

    _apriltag["detector"] = pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0)
    _apriltag["maps"] = cv2.initUndistortRectifyMap(K, dist, None, K, size, cv2.CV_32FC1)
    # AprilTag puts a pixel's centre at +0.5 (its corners came out 0.50 px right and down
    # of OpenCV's), so its principal point is OpenCV's + 0.5
    _apriltag["params"] = tuple(K[[0, 1, 0, 1], [0, 1, 2, 2]] + [0, 0, 0.5, 0.5])


def _apriltag_detect(image: np.ndarray) -> tuple | None:
    """AprilTag 3's pose of the tag in ``image`` (distorted), in OpenCV's marker frame."""
    flat = cv2.remap(image, *_apriltag["maps"], cv2.INTER_LINEAR)
    found = _apriltag["detector"].detect(flat, estimate_tag_pose=True,
                                         camera_params=_apriltag["params"], tag_size=SIZE_M)
    if not found:
        return None
    return found[0].pose_R @ APRILTAG_TO_OPENCV, found[0].pose_t.ravel(), None, None


def _errors(truth: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Decoupled error [p_true - p, log(R_true R^T)], position error mm, rotation deg."""
    dp = truth[:3, 3] - t
    phi = cv2.Rodrigues(truth[:3, :3] @ R.T)[0].ravel()
    return np.concatenate([dp, phi]), 1000 * float(np.linalg.norm(dp)), \
        math.degrees(float(np.linalg.norm(phi)))


def _stats(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    v = np.asarray(values)
    return {"median": round(float(np.median(v)), 3), "p95": round(float(np.percentile(v, 95)), 3),
            "max": round(float(v.max()), 3)}


def _bin(rows: dict[str, list], lo: float, hi: float, n_frames: int) -> dict[str, Any]:
    out: dict[str, Any] = {"frames": n_frames}
    for name, samples in rows.items():
        inside = [s[1:] for s in samples if lo <= s[1][2, 3] < hi]
        pos, rot, errs, covs = [], [], [], []
        flags = {"covered": 0, "history": 0}
        flips = 0
        for truth, R, t, cov, ambiguity in inside:
            e, p_mm, r_deg = _errors(truth, R, t)
            pos.append(p_mm)
            rot.append(r_deg)
            if cov is None:
                continue
            if ambiguity in flags:
                flags[ambiguity] += 1
            rot_m = float(e[3:] @ np.linalg.solve(cov[3:, 3:], e[3:]))
            if rot_m > FLIP_CHI2 and r_deg > FLIP_MIN_DEG:
                flips += 1
            if ambiguity != "covered":
                errs.append(e)
                covs.append(cov)
        entry: dict[str, Any] = {"detected": len(inside), "position_mm": _stats(pos),
                                 "orientation_deg": _stats(rot)}
        if name == "uma":
            entry.update(flags, silent_flips=flips,
                         nees=nees_figures(np.array(errs), np.array(covs)) if len(errs) > 2
                         else None)
        out[name] = entry
    out["same_frames"] = {other: _same_frames(rows, other, lo, hi) for other in rows
                          if other != "uma"}
    return out


def _same_frames(rows: dict[str, list], other: str, lo: float, hi: float) -> dict[str, Any]:
    """uma's and ``other``'s errors on the frames of the bin both detected."""
    theirs = {s[0]: s for s in rows[other] if lo <= s[1][2, 3] < hi}
    pairs = [(s, theirs[s[0]]) for s in rows["uma"] if s[0] in theirs]
    out: dict[str, Any] = {"frames": len(pairs)}
    for name, column in (("uma", 0), (other, 1)):
        errors = [_errors(p[column][1], p[column][2], p[column][3])[1:] for p in pairs]
        out[name] = {"position_mm": _stats([e[0] for e in errors]),
                     "orientation_deg": _stats([e[1] for e in errors])}
    return out


def _bundle(rng: np.random.Generator, camera: Any, sim: SimCamera, n: int,
            fps: float) -> dict[str, Any]:
    """Four tags on a plate: the bundle's position error and claimed std vs its tags'
    (pooled, the most accurate one's, the one claimed most accurate, and every one's).
    Where the bundle was never solved whole, or no tag of it alone, there is nothing to
    compare: the counts and why (``skipped``)."""
    ids = [int(i) for i in rng.choice(500, 4, replace=False)]
    offsets = [(-1, 1), (1, 1), (1, -1), (-1, -1)]
    in_plate = []
    for dx, dy in offsets:
        T = np.eye(4)
        T[:2, 3] = (dx * PLATE_OFFSET_M, dy * PLATE_OFFSET_M)
        in_plate.append(T)
    plate = wandering(rng, camera, (1.0, 2.5), 12.0, max_tilt_rad=0.5)
    scene = [SceneObject(o.name, o.drawable, (lambda t, T=T: plate(t) @ T))
             for o, T in zip(tags(FAMILY, ids, SIZE_M, [plate] * 4), in_plate, strict=True)]
    body = Body("plate", {i: marker_corners(SIZE_M) @ T[:3, :3].T + T[:3, 3]
                          for i, T in zip(ids, in_plate, strict=True)})
    together = FiducialTracker(camera, FAMILY, None, bundles=[body])
    alone = FiducialTracker(camera, FAMILY, SIZE_M)
    bundle_err, bundle_std, bundle_e, bundle_cov = [], [], [], []
    per_tag: dict[int, tuple[list[float], list[float]]] = {i: ([], []) for i in ids}
    for k in range(n):
        t = k / fps
        image = sim.render(scene, t, rng)
        seen, noise = alone.observe(image)
        for est in together.estimate(seen, round(t * 1e9), noise):
            if len(est.markers) == 4:
                e, p_mm, _ = _errors(plate(t), est.R, est.t)
                bundle_err.append(p_mm)
                bundle_std.append(1000 * math.sqrt(np.trace(est.covariance[:3, :3])))
                bundle_e.append(e)
                bundle_cov.append(est.covariance)
        for est in alone.estimate({i: c for i, c in seen.items() if i in ids}, round(t * 1e9),
                                  noise):
            marker = int(est.name.rsplit("-", 1)[1])
            truth = plate(t) @ in_plate[ids.index(marker)]
            per_tag[marker][0].append(_errors(truth, est.R, est.t)[1])
            per_tag[marker][1].append(1000 * math.sqrt(np.trace(est.covariance[:3, :3])))
    single_err = [e for errs, _ in per_tag.values() for e in errs]
    if not bundle_err or not single_err:
        return {"frames": n, "bundle_samples": len(bundle_err), "single_samples": len(single_err),
                "skipped": "the bundle was never solved from all four of its tags"
                if not bundle_err else "no tag of the bundle was solved alone"}
    single_std = [s for _, stds in per_tag.values() for s in stds]
    rms_b, rms_s = _rms(bundle_err), _rms(single_err)
    claimed_b, claimed_s = _rms(bundle_std), _rms(single_std)
    seen = [i for i in ids if per_tag[i][0]]
    rms_of = {i: _rms(per_tag[i][0]) for i in seen}
    claimed_of = {i: _rms(per_tag[i][1]) for i in seen}
    best = min(seen, key=rms_of.__getitem__)
    prior = min(seen, key=claimed_of.__getitem__)
    rms_t, claimed_t = rms_of[best], claimed_of[best]
    return {"frames": n, "bundle_samples": len(bundle_err), "single_samples": len(single_err),
            "bundle_rms_mm": round(rms_b, 3), "single_rms_mm": round(rms_s, 3),
            "bundle_claimed_mm": round(claimed_b, 3), "single_claimed_mm": round(claimed_s, 3),
            "gain_measured": round(rms_s / rms_b, 3),
            "gain_claimed": round(claimed_s / claimed_b, 3),
            "best_tag": f"{FAMILY}-{best}", "best_tag_samples": len(per_tag[best][0]),
            "best_tag_rms_mm": round(rms_t, 3), "best_tag_claimed_mm": round(claimed_t, 3),
            "best_gain_measured": round(rms_t / rms_b, 3),
            "best_gain_claimed": round(claimed_t / claimed_b, 3),
            "prior_tag": f"{FAMILY}-{prior}",
            "prior_gain_measured": round(rms_of[prior] / rms_b, 3),
            "prior_gain_claimed": round(claimed_of[prior] / claimed_b, 3),
            "least_gain_share": round(min(rms_of[i] / claimed_of[i] for i in seen)
                                      * claimed_b / rms_b, 3),
            "nees": nees_figures(np.array(bundle_e), np.array(bundle_cov))
            if len(bundle_e) > 2 else None}


def _rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values))))
