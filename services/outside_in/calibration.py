"""Wand calibration of an outside-in rig: every camera's pose (and intrinsics if asked).

The procedure of commercial systems and of Dorfmüller-Ulhaas §2's one-step calibration:

1. **Wand**: three markers on a line at known distances (``Wand``) waved through the
   volume.  In each camera's frames the static blobs (reflections, lamps: the same place
   in many frames) are masked; a frame with exactly three other blobs on a line is a
   wand observation, its ends told apart by the middle marker's position (it sits nearer
   one end, and projection keeps the order of points on a line).
2. **Initial extrinsics**: the essential matrix between camera pairs that saw the wand
   together (``cv2.findEssentialMat`` + ``recoverPose``), scaled by the wand's length,
   chained along the strongest pairs from the camera that saw the wand most.
3. **Bundle adjustment** (``scipy.optimize.least_squares`` with ``jac_sparsity``): camera
   extrinsics (and ``fx, fy, cx, cy, k1, k2`` when asked) and each wand frame's pose (an
   end point and a direction: the distances are fixed, which fixes the scale), residuals
   in pixels through ``cv2.projectPoints``, first with that camera fixed; wand views the
   adjusted rig cannot explain (a wand taken end for end) are dropped and it runs again.
4. **World frame**: an L-frame of four markers on the floor (located in each camera's
   average of its still frames, ``cli.still_blobs``), triangulated and identified
   (``bodies.identify``), gives world -> rig by absolute orientation; the adjustment then
   runs again with every camera free and the L-frame's markers fixed at their known world
   positions -- they are what defines the world -- so each camera's covariance (from the
   Jacobian, the wand frames marginalised) includes the uncertainty of the world frame.

The result is a ``RigCalibration``: cameras with poses ``world -> camera`` and their
6x6 covariances over ``[dp, phi]``, the reprojection RMS, and what was used.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from agent import geometry as geo
from agent.errors import InvalidInputError, UmaError
from services.camera.model import CameraModel
from services.outside_in.bodies import RigidBody, identify
from services.outside_in.pose import absolute_orientation
from services.outside_in.rig import RigCamera
from services.outside_in.triangulation import MatchParams, match_and_triangulate, triangulate_dlt

Array = np.ndarray

#: an L-frame of four 14 mm markers lying on the floor: origin, two on the x arm, one on y
LFRAME = RigidBody("lframe", np.array([[0.0, 0.0, 0.007], [0.25, 0.0, 0.007],
                                       [0.6, 0.0, 0.007], [0.0, 0.4, 0.007]]))


class CalibrationError(UmaError):
    """A rig that cannot be calibrated from what was recorded: says what is missing."""


@dataclass(frozen=True)
class Wand:
    """Marker positions along the wand from its first end (m), the middle one off-centre."""

    distances: tuple[float, float, float] = (0.0, 0.16, 0.5)

    def __post_init__(self) -> None:
        a, b, c = self.distances
        if not (a == 0.0 < b < c) or abs(b - c / 2) < 0.1 * c:
            raise InvalidInputError(
                f"wand distances must be 0 < middle < end with the middle off "
                f"centre by a tenth of the length at least, got {self.distances}")

    @property
    def length(self) -> float:
        return self.distances[2]


# ---------------------------------------------------------------------- observations


def static_blobs(frames: list[Array], radius_px: float = 2.0, share: float = 0.3) -> Array:
    """Places (k, 2) where a camera found a blob in more than ``share`` of its frames
    (each frame an (n, 2) array of blob pixels): reflections and lamps, not the wand."""
    centres: list[Array] = []
    members: list[set[int]] = []
    for f, uv in enumerate(frames):
        for p in np.asarray(uv, float).reshape(-1, 2):
            d = [np.linalg.norm(p - c) for c in centres]
            if d and min(d) < radius_px:
                members[int(np.argmin(d))].add(f)
            else:
                centres.append(p)
                members.append({f})
    keep = [c for c, m in zip(centres, members, strict=True) if len(m) > share * len(frames)]
    return np.array(keep).reshape(-1, 2)


def wand_observations(models: list[CameraModel], frames: list[list[Array]],
                      wand: Wand) -> Array:
    """(frames, cameras, 3, 2) wand marker pixels, NaN where a camera did not see the
    wand alone; ``frames[f][c]`` are camera c's blob pixels in frame set f."""
    C = len(models)
    static = [static_blobs([fr[c] for fr in frames]) for c in range(C)]
    out = np.full((len(frames), C, 3, 2), np.nan)
    for f, fr in enumerate(frames):
        for c in range(C):
            w = wand_in_image(fr[c], models[c], static[c], wand)
            if w is not None:
                out[f, c] = w
    return out


def wand_in_image(uv: Array, camera: CameraModel, static: Array, wand: Wand,
                  line_px: float = 1.5, static_px: float = 3.0) -> Array | None:
    """The wand's three marker images (3, 2) in wand order, or None when the blobs left
    after masking the static ones are not exactly three on a line."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    if len(static):
        d = np.linalg.norm(uv[:, None] - static[None], axis=2)
        uv = uv[np.min(d, axis=1) > static_px]
    if len(uv) != 3:
        return None
    n = camera.undistort(uv)
    f = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
    pair = max(((0, 1), (0, 2), (1, 2)), key=lambda ij: np.linalg.norm(n[ij[0]] - n[ij[1]]))
    mid = 3 - sum(pair)
    a, b = n[pair[0]], n[pair[1]]
    ab = b - a
    off = abs(ab[0] * (n[mid] - a)[1] - ab[1] * (n[mid] - a)[0]) / np.linalg.norm(ab)
    if off * f > line_px:
        return None
    near, far = pair if np.linalg.norm(n[mid] - a) < np.linalg.norm(n[mid] - b) else pair[::-1]
    first_is_near = wand.distances[1] < wand.length / 2
    ends = (near, far) if first_is_near else (far, near)
    return uv[[ends[0], mid, ends[1]]]


# ---------------------------------------------------------------------- initial guess


def initial_extrinsics(models: list[CameraModel], obs: Array, wand: Wand,
                       min_frames: int = 20) -> list[tuple[Array, Array]]:
    """``(R_cw, t_cw)`` of every camera in the frame of the camera that saw the wand most
    (``reference_camera``), from essential matrices of camera pairs scaled by the wand,
    chained along the strongest pairs.
    ``obs`` is (frames, cameras, 3, 2) distorted pixels, NaN where not seen."""
    C = len(models)
    seen = ~np.isnan(obs[:, :, 0, 0])
    norm = np.full(obs.shape, np.nan)
    for c, m in enumerate(models):
        rows = np.nonzero(seen[:, c])[0]
        if len(rows):
            norm[rows, c] = m.undistort(obs[rows, c].reshape(-1, 2)).reshape(-1, 3, 2)
    common = np.array([[np.sum(seen[:, i] & seen[:, j]) for j in range(C)] for i in range(C)])
    ref = reference_camera(obs)
    poses: dict[int, tuple[Array, Array]] = {ref: (np.eye(3), np.zeros(3))}
    while len(poses) < C:
        cands = [(common[i, j], i, j) for i in poses for j in range(C)
                 if j not in poses and common[i, j] >= min_frames]
        if not cands:
            missing = sorted(models[j].name or f"#{j}" for j in range(C) if j not in poses)
            raise CalibrationError(f"cameras {', '.join(missing)} saw the wand together with "
                                   f"the others in fewer than {min_frames} frames: wave it "
                                   "where they overlap")
        _, i, j = max(cands)
        R_ij, t_ij = _pair_pose(norm, seen, i, j, wand)
        R_i, t_i = poses[i]
        poses[j] = (R_ij @ R_i, R_ij @ t_i + t_ij)
    return [poses[c] for c in range(C)]


def reference_camera(obs: Array) -> int:
    """The camera that saw the wand most often: the rig's frame until the L-frame's."""
    return int(np.argmax(np.sum(~np.isnan(obs[:, :, 0, 0]), axis=0)))


def _pair_pose(norm: Array, seen: Array, i: int, j: int, wand: Wand) -> tuple[Array, Array]:
    """Pose of camera j in camera i's frame (``x_j = R x_i + t``), metric."""
    rows = np.nonzero(seen[:, i] & seen[:, j])[0]
    a = norm[rows, i].reshape(-1, 2)
    b = norm[rows, j].reshape(-1, 2)
    E, inl = cv2.findEssentialMat(a, b, np.eye(3), method=cv2.RANSAC, prob=0.9999,
                                  threshold=2e-3)
    if E is None:
        raise CalibrationError(f"cameras #{i} and #{j}: no essential matrix from "
                               f"{len(rows)} wand frames")
    _, R, t, _ = cv2.recoverPose(E[:3], a, b, np.eye(3), mask=inl.copy())
    t = t.ravel()
    P = np.stack([np.hstack([np.eye(3), np.zeros((3, 1))]), np.hstack([R, t[:, None]])])
    ends = []
    for k in (0, 2):
        x = np.stack([norm[rows, i, k], norm[rows, j, k]], axis=1)
        ends.append(triangulate_dlt(np.broadcast_to(P, (len(rows), 2, 3, 4)), x))
    scale = wand.length / np.median(np.linalg.norm(ends[1] - ends[0], axis=1))
    return R, t * scale


# ---------------------------------------------------------------------- adjustment


@dataclass
class _Problem:
    """The unknowns of the adjustment and how residuals depend on them."""

    models: list[CameraModel]
    obs: Array                 # (F, C, 3, 2) wand marker pixels, NaN: not seen
    wand: Wand
    points: Array              # (P, 3) fixed world points (L-frame), may be empty
    point_obs: Array           # (C, P, 2) their mean pixels, NaN: not seen
    point_weight: float        # sqrt of frames averaged into point_obs
    sigma_px: float
    fixed_camera: int | None
    intrinsics: bool
    u_basis: Array = field(init=False)  # (F, 3, 3): u0, e1, e2 of each wand direction

    @property
    def n_cam_params(self) -> int:
        return 12 if self.intrinsics else 6

    def free_cameras(self) -> list[int]:
        return [c for c in range(len(self.models)) if c != self.fixed_camera]

    def pack(self, extr: list[tuple[Array, Array]], ends: Array, dirs: Array) -> Array:
        cam = []
        for c in self.free_cameras():
            R, t = extr[c]
            v = [cv2.Rodrigues(R)[0].ravel(), t]
            if self.intrinsics:
                m = self.models[c]
                v.append(np.array([m.K[0, 0], m.K[1, 1], m.K[0, 2], m.K[1, 2],
                                   m.dist[0] if m.dist.size else 0.0,
                                   m.dist[1] if m.dist.size else 0.0]))
            cam.append(np.concatenate(v))
        self.u_basis = np.stack([_basis(d) for d in dirs])
        return np.concatenate([np.concatenate(cam) if cam else np.zeros(0),
                               np.hstack([ends, np.zeros((len(ends), 2))]).ravel()])

    def cameras(self, x: Array, fixed: tuple[Array, Array]) -> list[tuple[Array, Array,
                                                                          Array, Array]]:
        """``(rvec, tvec, K, dist)`` of each camera for parameters ``x``."""
        out = []
        k = 0
        n = self.n_cam_params
        for c, m in enumerate(self.models):
            if c == self.fixed_camera:
                out.append((cv2.Rodrigues(fixed[0])[0].ravel(), fixed[1], m.K, m.dist))
                continue
            v = x[k * n:(k + 1) * n]
            k += 1
            K, dist = m.K, m.dist
            if self.intrinsics:
                K = np.array([[v[6], 0, v[8]], [0, v[7], v[9]], [0, 0, 1.0]])
                dist = m.dist.copy() if m.dist.size else np.zeros(5)
                dist[0], dist[1] = v[10], v[11]
            out.append((v[:3], v[3:6], K, dist))
        return out

    def wand_points(self, x: Array) -> Array:
        """(F, 3, 3) marker positions of every wand frame."""
        w = x[len(self.free_cameras()) * self.n_cam_params:].reshape(-1, 5)
        u = (self.u_basis[:, 0] + w[:, 3:4] * self.u_basis[:, 1]
             + w[:, 4:5] * self.u_basis[:, 2])
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        d = np.array(self.wand.distances)
        return w[:, None, :3] + d[None, :, None] * u[:, None, :]

    def residuals(self, x: Array, fixed: tuple[Array, Array]) -> Array:
        cams = self.cameras(x, fixed)
        X = self.wand_points(x)
        out = []
        for c, (rvec, tvec, K, dist) in enumerate(cams):
            rows = self._rows[c]
            if len(rows):
                uv, _ = cv2.projectPoints(X[rows].reshape(-1, 3), rvec, tvec, K, dist)
                out.append((uv.reshape(-1, 3, 2) - self.obs[rows, c]).ravel() / self.sigma_px)
            pts = self._point_rows[c]
            if len(pts):
                uv, _ = cv2.projectPoints(self.points[pts], rvec, tvec, K, dist)
                out.append((uv.reshape(-1, 2) - self.point_obs[c, pts]).ravel()
                           * self.point_weight / self.sigma_px)
        return np.concatenate(out)

    def prepare(self) -> None:
        seen = ~np.isnan(self.obs[:, :, 0, 0])
        self._rows = [np.nonzero(seen[:, c])[0] for c in range(len(self.models))]
        pseen = ~np.isnan(self.point_obs[:, :, 0]) if len(self.points) else np.zeros(
            (len(self.models), 0), bool)
        self._point_rows = [np.nonzero(pseen[c])[0] for c in range(len(self.models))]

    def sparsity(self) -> sp.csr_matrix:
        """Which parameters each residual depends on (the order of ``residuals``)."""
        n = self.n_cam_params
        free = {c: k for k, c in enumerate(self.free_cameras())}
        base = len(free) * n
        rows, cols = [], []
        r = 0
        for c in range(len(self.models)):
            for f in self._rows[c]:
                for _ in range(6):
                    if c in free:
                        rows += [r] * n
                        cols += list(range(free[c] * n, free[c] * n + n))
                    rows += [r] * 5
                    cols += list(range(base + 5 * f, base + 5 * f + 5))
                    r += 1
            for _ in range(2 * len(self._point_rows[c])):
                if c in free:
                    rows += [r] * n
                    cols += list(range(free[c] * n, free[c] * n + n))
                r += 1
        size = base + 5 * len(self.obs)
        return sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(r, size))


def _basis(u: Array) -> Array:
    """``u`` and two unit vectors perpendicular to it and each other, as rows."""
    u = u / np.linalg.norm(u)
    e1 = np.cross(u, [1.0, 0, 0] if abs(u[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    return np.stack([u, e1, np.cross(u, e1)])


@dataclass(frozen=True)
class Adjusted:
    """What one adjustment gives."""

    extrinsics: list[tuple[Array, Array]]      # (R_cw, t_cw) per camera
    models: list[CameraModel]
    camera_cov: Array                           # (n_free * p, n_free * p) over camera params
    rms_px: float                               # per axis, over wand observations
    residuals_px: Array
    wand_points: Array


def adjust(models: list[CameraModel], extr: list[tuple[Array, Array]], obs: Array,
           wand: Wand, sigma_px: float, fixed_camera: int | None = 0,
           points: Array | None = None, point_obs: Array | None = None,
           point_weight: float = 1.0, intrinsics: bool = False) -> Adjusted:
    """Sparse bundle adjustment of the rig and the wand frames."""
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, float)
    pobs = (np.full((len(models), 0, 2), np.nan) if point_obs is None
            else np.asarray(point_obs, float))
    # a wand frame fewer than two cameras saw has no triangulated start and tells almost
    # nothing of the rig: the adjustment has the others (``wand_points`` NaN for it)
    used = np.sum(~np.isnan(obs[:, :, 0, 0]), axis=1) >= 2
    full, obs = obs, obs[used]
    prob = _Problem(models, obs, wand, pts, pobs, point_weight, sigma_px, fixed_camera,
                    intrinsics)
    prob.prepare()
    ends, dirs = _wand_start(models, extr, obs, wand)
    x0 = prob.pack(extr, ends, dirs)
    fixed = extr[fixed_camera] if fixed_camera is not None else (np.eye(3), np.zeros(3))
    sol = least_squares(prob.residuals, x0, jac_sparsity=prob.sparsity(), method="trf",
                        x_scale="jac", xtol=1e-10, ftol=1e-10, max_nfev=300,
                        args=(fixed,))
    cams = prob.cameras(sol.x, fixed)
    out_extr = [(cv2.Rodrigues(np.asarray(r, float))[0], np.asarray(t, float))
                for r, t, _, _ in cams]
    out_models = [CameraModel(K, dist, m.width, m.height, m.pixel_std, m.name)
                  for (_, _, K, dist), m in zip(cams, models, strict=True)]
    n_cam = len(prob.free_cameras()) * prob.n_cam_params
    cov = _camera_covariance(sp.csr_matrix(sol.jac), n_cam)
    res = prob.residuals(sol.x, fixed) * sigma_px
    n_wand = sum(6 * len(r) for r in prob._rows)
    wand_res = _wand_part(res, prob)
    dof = max(len(res) - len(sol.x), 1)
    rms = float(np.sqrt(np.sum(wand_res ** 2) / (n_wand * dof / len(res))))
    points = np.full((len(full), 3, 3), np.nan)
    points[used] = prob.wand_points(sol.x)
    return Adjusted(out_extr, out_models, cov, rms, wand_res, points)


def _wand_part(res: Array, prob: _Problem) -> Array:
    out, r = [], 0
    for c in range(len(prob.models)):
        n = 6 * len(prob._rows[c])
        out.append(res[r:r + n])
        r += n + 2 * len(prob._point_rows[c])
    return np.concatenate(out)


def _camera_covariance(J: sp.csr_matrix, n_cam: int) -> Array:
    """Covariance of the camera parameters with the wand frames marginalised: the inverse
    of the Schur complement of ``J^T J`` (the wand blocks are 5 x 5 per frame)."""
    JtJ = (J.T @ J).tocsr()
    A = JtJ[:n_cam, :n_cam].toarray()
    B = JtJ[:n_cam, n_cam:].toarray()
    D = JtJ[n_cam:, n_cam:]
    m = D.shape[0] // 5
    Dinv_Bt = np.zeros((D.shape[0], n_cam))
    Bt = B.T
    for f in range(m):
        s = slice(5 * f, 5 * f + 5)
        block = D[s, s].toarray()
        Dinv_Bt[s] = np.linalg.lstsq(block, Bt[s], rcond=None)[0]
    S = A - B @ Dinv_Bt
    return np.linalg.pinv(0.5 * (S + S.T))


def _wand_start(models: list[CameraModel], extr: list[tuple[Array, Array]], obs: Array,
                wand: Wand) -> tuple[Array, Array]:
    """Each wand frame's first end and direction, triangulated from every camera."""
    F = len(obs)
    ends = np.zeros((F, 3))
    dirs = np.tile([0.0, 0.0, 1.0], (F, 1))
    P = [np.hstack([R, t[:, None]]) for R, t in extr]
    for f in range(F):
        cams = [c for c in range(len(models)) if not np.isnan(obs[f, c, 0, 0])]
        if len(cams) < 2:
            continue
        X = []
        for k in (0, 2):
            x = np.array([models[c].undistort(obs[f, c, k][None])[0] for c in cams])
            X.append(triangulate_dlt(np.array([P[c] for c in cams])[None], x[None])[0])
        ends[f] = X[0]
        if np.linalg.norm(X[1] - X[0]) > 1e-6:
            dirs[f] = (X[1] - X[0]) / np.linalg.norm(X[1] - X[0])
    return ends, dirs


# ---------------------------------------------------------------------- the whole rig


@dataclass(frozen=True)
class RigCalibration:
    """A calibrated rig: cameras with poses in the world and their covariances."""

    cameras: list[RigCamera]
    covariances: Array          # (C, 6, 6) over [dp, phi] of each world -> camera pose
    rms_px: float
    wand_frames: int
    lframe_frames: int
    observations: int
    wand_obs: Array             # (frames, cameras, 3, 2) the wand marker pixels used

    def std(self, c: int) -> tuple[float, float]:
        """Position (m) and rotation (rad) std of camera ``c``: sqrt of trace / 3."""
        C = self.covariances[c]
        return (float(np.sqrt(np.trace(C[:3, :3]) / 3)), float(np.sqrt(np.trace(C[3:, 3:]) / 3)))


def lframe_observations(models: list[CameraModel], extr: list[tuple[Array, Array]],
                        frames: list[list[Array]], lframe: RigidBody = LFRAME,
                        tolerance_m: float = 0.01) -> tuple[Array, Array, int]:
    """The L-frame in a rig of known relative poses: its markers' positions in the rig's
    frame (4, 3) and their mean pixels per camera (C, 4, 2) (NaN: not seen), over the
    frames where it was identified; ``frames[f][c]`` are camera c's blob pixels."""
    cams = [RigCamera(m.name or f"#{c}", m, -R.T @ t, geo.matrix_to_quat(R.T))
            for c, (m, (R, t)) in enumerate(zip(models, extr, strict=True))]
    sums = np.zeros((len(models), len(lframe.markers), 2))
    counts = np.zeros((len(models), len(lframe.markers)))
    world = []
    for per_cam in frames:
        norm = [cams[c].normalize(uv) for c, uv in enumerate(per_cam)]
        points = match_and_triangulate(cams, norm, MatchParams(epipolar_px=4.0,
                                                               support_px=4.0,
                                                               max_rms_px=3.0))
        if len(points) < 3:
            continue
        X = np.array([q.X for q in points])
        ident = identify(lframe, X, tolerance_m, min_markers=len(lframe.markers))
        if ident is None:
            continue
        world.append(X[list(ident.points)])
        for m, i in enumerate(ident.points):
            for c, b in points[i].views:
                sums[c, m] += per_cam[c][b]
                counts[c, m] += 1
    if not world:
        raise CalibrationError("the L-frame was not found: all four of its markers must be "
                               "seen by two cameras at least, and nothing else shaped like it")
    mean = np.where(counts[..., None] > 0, sums / np.maximum(counts, 1)[..., None], np.nan)
    return np.mean(world, axis=0), mean, len(world)


def calibrate_rig(models: list[CameraModel], wand_obs: Array, lframe_frames: list[list[Array]],
                  wand: Wand = Wand(), lframe: RigidBody = LFRAME, sigma_px: float = 0.05,
                  static_px: float = 0.003, intrinsics: bool = False,
                  lframe_averaged: int = 1) -> RigCalibration:
    """The whole calibration (steps 2-4 of the module's docstring).  ``sigma_px`` is a
    wand marker image's noise, ``static_px`` the part of a still marker's centroid error
    that does not average out over frames (pixel sampling); each of ``lframe_frames`` may
    be the average of ``lframe_averaged`` images of the still L-frame."""
    wand_obs = _seen_twice(wand_obs)
    counts = np.sum(~np.isnan(wand_obs[:, :, 0, 0]), axis=0)
    if np.any(counts < 20):
        few = [models[c].name or f"#{c}" for c in np.nonzero(counts < 20)[0]]
        raise CalibrationError(f"cameras {', '.join(few)} saw the wand in fewer than 20 "
                               "frames")
    extr = initial_extrinsics(models, wand_obs, wand)
    ref = reference_camera(wand_obs)
    rel = adjust(models, extr, wand_obs, wand, sigma_px, fixed_camera=ref)
    # a wand taken end for end, or a stray blob on its line, fits no pose of the rig:
    # views further than OUTLIER_SIGMAS from the adjusted rig are dropped, then the rig
    # adjusted again -- unless so many are that the rig itself did not converge
    kept = _without_outliers(rel, wand_obs, sigma_px)
    dropped = np.sum(np.isnan(kept[:, :, 0, 0])) - np.sum(np.isnan(wand_obs[:, :, 0, 0]))
    if 0 < dropped <= MAX_OUTLIER_SHARE * np.sum(~np.isnan(wand_obs[:, :, 0, 0])):
        wand_obs = _seen_twice(kept)
        rel = adjust(rel.models, rel.extrinsics, wand_obs, wand, sigma_px, fixed_camera=ref)
    rig_pts, lobs, n_l = lframe_observations(rel.models, rel.extrinsics, lframe_frames, lframe)
    # world -> rig (the reference camera's frame): the L-frame's known markers onto its points
    R_rw, p_rw = absolute_orientation(lframe.markers, rig_pts)
    world_extr = [(R @ R_rw, R @ p_rw + t) for R, t in rel.extrinsics]
    # a static marker's centroid keeps its pixel-sampling error in every frame: averaging
    # n frames divides the noise by sqrt(n), never that part (``static_px``)
    weight = sigma_px / np.sqrt(sigma_px ** 2 / (n_l * lframe_averaged) + static_px ** 2)
    final = adjust(rel.models, world_extr, wand_obs, wand, sigma_px, fixed_camera=None,
                   points=lframe.markers, point_obs=lobs, point_weight=weight,
                   intrinsics=intrinsics)
    n = 12 if intrinsics else 6
    cams, covs = [], []
    for c, ((R, t), m) in enumerate(zip(final.extrinsics, final.models, strict=True)):
        cams.append(RigCamera(m.name or f"cam{c}", m, -R.T @ t, geo.matrix_to_quat(R.T)))
        cov = _pose_covariance(R, t, final.camera_cov[c * n:c * n + 6, c * n:c * n + 6])
        covs.append(0.5 * (cov + cov.T))
    seen = int(np.sum(~np.isnan(wand_obs[:, :, 0, 0])))
    return RigCalibration(cams, np.array(covs), final.rms_px, len(wand_obs), n_l, seen,
                          wand_obs)


def _seen_twice(obs: Array) -> Array:
    """``obs`` with the wand frames fewer than two cameras saw set to NaN (``adjust``
    leaves them out: their start, untriangulated, was the reference camera's centre,
    where a projection overflows)."""
    out = obs.copy()
    out[np.sum(~np.isnan(obs[:, :, 0, 0]), axis=1) < 2] = np.nan
    return out


#: a wand view whose worst marker is this many noise stds from the adjusted rig is an
#: outlier; more than MAX_OUTLIER_SHARE of them say the adjustment failed, not the views
OUTLIER_SIGMAS = 8.0
MAX_OUTLIER_SHARE = 0.05


def _without_outliers(adj: Adjusted, obs: Array, sigma_px: float) -> Array:
    """``obs`` with the camera views of the wand that the adjusted rig cannot explain
    set to NaN."""
    out = obs.copy()
    for c, ((R, t), m) in enumerate(zip(adj.extrinsics, adj.models, strict=True)):
        rows = np.nonzero(~np.isnan(obs[:, c, 0, 0]))[0]
        if not len(rows):
            continue
        uv, _ = cv2.projectPoints(adj.wand_points[rows].reshape(-1, 3),
                                  cv2.Rodrigues(R)[0], t, m.K, m.dist)
        err = np.linalg.norm(uv.reshape(-1, 3, 2) - obs[rows, c], axis=2).max(axis=1)
        out[rows[err > OUTLIER_SIGMAS * sigma_px], c] = np.nan
    return out


def _pose_covariance(R: Array, t: Array, cov_rt: Array) -> Array:
    """Covariance of ``world -> camera`` over ``[dp, phi]`` from that of (rvec, tvec)."""
    r0 = cv2.Rodrigues(R)[0].ravel()
    p0 = -R.T @ t
    J = np.zeros((6, 6))
    eps = 1e-7
    for k in range(6):
        x = np.concatenate([r0, t])
        x[k] += eps
        Rk = cv2.Rodrigues(x[:3])[0]
        pk = -Rk.T @ x[3:]
        J[:3, k] = (pk - p0) / eps
        J[3:, k] = geo.rodrigues_inverse(Rk.T @ R) / eps
    return J @ cov_rt @ J.T
