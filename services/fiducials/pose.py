"""Rigid objects' poses from their markers' corners, with a first-order covariance.

Every object (one square marker, or a bundle of markers) is solved the same way, from
corners in *ideal* pixels (lens distortion already removed, :mod:`services.fiducials.edges`):

1. **Candidates**: a marker's two IPPE solutions
   (``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)``), moved into the object's frame.
   A planar square seen from far away fits both of them almost equally well: the
   *planar ambiguity* (the marker tilted one way or the mirror way).
2. **Refinement**: Gauss-Newton steps (a lone marker's candidates) or
   ``cv2.solvePnPRefineLM`` (a bundle's, and a lone marker's rival candidate that lies in
   the flat valley between the two solutions) over all the object's corners; the
   distinct local minima are kept, ordered by their residual sum of squares; then
   (:func:`reweigh`) a step to the minimum weighted by the corners' covariances.
3. **Covariance** (:func:`weighted_covariance`): ``(Jᵀ W J)⁻¹`` with ``J`` the
   reprojection Jacobian and ``W`` the corners' inverse covariances (or
   :func:`covariance`, ``(Jᵀ J)⁻¹ σ²`` for one corner noise ``σ`` per axis).

The Jacobian is taken directly in the *decoupled* form the covariance is reported in,
[position (m), rotation (rad) in the camera frame] (``R_true = exp(φ) R``;
:func:`agent.geometry.decoupled_to_se3` gives uma's wire form), and everything after
the candidates is computed for a whole stack of objects at once (a frame's lone markers
together): the numbers are a marker's own, the Python and OpenCV call overhead is paid
once per frame instead of once per marker.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from agent.runtime import compiled_twin
from services.camera.markers import marker_corners
from services.linalg import solve_stack

#: LM iterations for a bundle, which starts from one of its markers' poses
LM_ITERATIONS_BUNDLE = 15
#: a lone marker's candidates are refined by this many undamped Gauss-Newton steps
GAUSS_NEWTON_STEPS = 2
#: ... and a rival candidate whose last step turned it further than this (rad), not yet
#: at a minimum, by this many LM iterations
CONVERGED_RAD = 1e-4
LM_ITERATIONS_SINGLE = 4
#: two refined solutions closer than this (rad) are the same minimum
SAME_SOLUTION_RAD = np.deg2rad(2.0)
_UNIT_SQUARE = marker_corners(1.0)
_NO_DIST = np.zeros(0)


@dataclass(frozen=True)
class Solution:
    """One refined pose of an object in the camera frame and how well it fits."""

    rotation: np.ndarray  # (3, 3) object -> camera
    tvec: np.ndarray  # (3,)
    rss_px2: float  # residual sum of squares over all corners
    n_points: int
    jacobian: np.ndarray  # (2n, 6): d(pixels) / d(position, camera-frame rotation)
    residual: np.ndarray  # (2n,): observed - projected pixels

    @property
    def dof(self) -> int:
        """Residual degrees of freedom: the noise's evidence in this fit."""
        return 2 * self.n_points - 6


@dataclass(frozen=True)
class Fits:
    """A stack of ``m`` poses of objects of ``n`` points each and their fits."""

    R: np.ndarray  # (m, 3, 3)
    t: np.ndarray  # (m, 3)
    residual: np.ndarray  # (m, 2n)
    jacobian: np.ndarray  # (m, 2n, 6)

    @property
    def rss(self) -> np.ndarray:
        return np.einsum("mk,mk->m", self.residual, self.residual)

    def solution(self, i: int) -> Solution:
        r = self.residual[i]
        return Solution(self.R[i], self.t[i], float(r @ r), len(r) // 2, self.jacobian[i], r)

    @staticmethod
    def of(solutions: list[Solution]) -> Fits:
        return Fits(np.stack([s.rotation for s in solutions]),
                    np.stack([s.tvec for s in solutions]),
                    np.stack([s.residual for s in solutions]),
                    np.stack([s.jacobian for s in solutions]))


def project(obj: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray]:
    """Ideal pixels (m, n, 2) of the object points ``obj`` (m, n, 3) at poses ``R`` (m, 3, 3),
    ``t`` (m, 3), and the Jacobian (m, 2n, 6) of each pixel by [position, rotation].
    No skew, as OpenCV's solvers."""
    q = obj @ np.swapaxes(R, 1, 2)  # the points turned, relative to the origin
    X = q + t[:, None, :]
    iz = 1.0 / X[..., 2]
    xn, yn = X[..., 0] * iz, X[..., 1] * iz
    pixels = np.empty((*X.shape[:2], 2))
    pixels[..., 0] = K[0, 0] * xn + K[0, 2]
    pixels[..., 1] = K[1, 1] * yn + K[1, 2]
    # d(u, v)/dX: rows (a, 0, c) and (0, b, d); X(φ) = exp(φ) q + t, dX/dφ = -[q]x, so
    # a row r of d(u, v)/dX becomes q x r
    a, b = K[0, 0] * iz, K[1, 1] * iz
    c, d = -xn * a, -yn * b
    q0, q1, q2 = q[..., 0], q[..., 1], q[..., 2]
    J = np.zeros((*X.shape[:2], 2, 6))
    J[..., 0, 0], J[..., 0, 2], J[..., 1, 1], J[..., 1, 2] = a, c, b, d
    J[..., 0, 3], J[..., 0, 4], J[..., 0, 5] = q1 * c, q2 * a - q0 * c, -q1 * a
    J[..., 1, 3], J[..., 1, 4], J[..., 1, 5] = q1 * d - q2 * b, -q0 * d, q0 * b
    return pixels, J.reshape(len(R), -1, 6)


def fits(obj: np.ndarray, img: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
         ) -> Fits:
    """The fits of poses ``R``, ``t`` to the observed ideal pixels ``img`` (m, n, 2)."""
    if NATIVE is not None and len(R):
        c = _contiguous
        R, t = c(R), c(t)
        m, n = obj.shape[:2]
        residual, J = np.empty((m, 2 * n)), np.empty((m, 2 * n, 6))
        NATIVE.fits(c(obj), c(img), _intrinsics(K), R, t, residual, J)
        return Fits(R, t, residual, J)
    pixels, J = project(obj, K, R, t)
    return Fits(R, t, (img - pixels).reshape(len(R), -1), J)


def _contiguous(a: np.ndarray) -> np.ndarray:
    """``a`` as the compiled twin reads it: C-contiguous float64 (a copy only if needed)."""
    return np.ascontiguousarray(a, np.float64)


def _intrinsics(K: np.ndarray) -> np.ndarray:
    """fx, fy, cx, cy: what the compiled twin takes of the camera matrix (no skew)."""
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float64)


def exp_rotation(phi: np.ndarray) -> np.ndarray:
    """Rotation matrices (m, 3, 3) of rotation vectors ``phi`` (m, 3): Rodrigues' formula
    ``I + sin θ/θ W + (1 - cos θ)/θ² (φφᵀ - θ² I)``, ``W`` = [φ]x."""
    theta2 = np.einsum("mi,mi->m", phi, phi)
    half = np.sinc(np.sqrt(theta2) / (2 * np.pi))  # sin(θ/2) / (θ/2)
    a = half * np.cos(np.sqrt(theta2) / 2)  # sin θ / θ
    b = half * half / 2  # (1 - cos θ) / θ²
    out = b[:, None, None] * (phi[:, :, None] * phi[:, None, :])
    out[:, _DIAGONAL, _DIAGONAL] += (1 - b * theta2)[:, None]
    aphi = a[:, None] * phi
    out[:, _SKEW_ROW, _SKEW_COL] += aphi[:, _SKEW_AXIS]
    out[:, _SKEW_COL, _SKEW_ROW] -= aphi[:, _SKEW_AXIS]
    return out


#: [φ]x's entries: +φ_axis at (row, col), -φ_axis at (col, row)
_DIAGONAL = np.arange(3)
_SKEW_ROW, _SKEW_COL, _SKEW_AXIS = np.array([1, 0, 2]), np.array([0, 2, 1]), np.array([2, 1, 0])


def _moved(fit: Fits, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The poses of ``fit`` stepped by ``delta`` (m, 6) [position, rotation]."""
    if NATIVE is not None and len(delta):
        c = _contiguous
        R, t = np.empty(fit.R.shape), np.empty(fit.t.shape)
        NATIVE.moved(c(fit.R), c(fit.t), c(delta), R, t)
        return R, t
    return exp_rotation(delta[:, 3:]) @ fit.R, fit.t + delta[:, :3]


def gauss_newton(obj: np.ndarray, img: np.ndarray, K: np.ndarray, fit: Fits,
                 steps: int = GAUSS_NEWTON_STEPS) -> tuple[Fits, np.ndarray]:
    """Undamped Gauss-Newton steps on the reprojection error from the poses of ``fit``,
    and how far (rad) the last step turned each.  From IPPE's start each step squares
    the error."""
    if NATIVE is not None and len(fit.R):
        c = _contiguous
        R, t = c(fit.R).copy(), c(fit.t).copy()
        m, n = obj.shape[:2]
        residual, J, turned = np.empty((m, 2 * n)), np.empty((m, 2 * n, 6)), np.empty(m)
        NATIVE.gauss_newton(c(obj), c(img), _intrinsics(K), R, t, residual, J, turned, steps)
        return Fits(R, t, residual, J), turned
    turned = np.zeros(len(fit.R))
    for _ in range(steps):
        J = fit.jacobian
        delta = solve_stack(_gram(J, J), _gram(J, fit.residual))
        turned = np.sqrt(np.einsum("mi,mi->m", delta[:, 3:], delta[:, 3:]))
        fit = fits(obj, img, K, *_moved(fit, delta))
    return fit, turned


#: the compiled twin of :func:`fits`, :func:`gauss_newton` and the step of :func:`reweigh`
#: (``_kernels.c``; tests set it to None to run the numpy code)
NATIVE: Any = compiled_twin("services.fiducials._kernels", "UMA_FIDUCIALS_PURE_PYTHON")


def refine_lm(obj: np.ndarray, img: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
              iterations: int) -> Fits:
    """``cv2.solvePnPRefineLM`` from each pose ``R`` (m, 3, 3), ``t`` (m, 3) of objects of
    points ``obj`` (m, n, 3) seen at ideal pixels ``img`` (m, n, 2)."""
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-10)
    Rs, ts = np.empty_like(R), np.empty_like(t)
    for i in range(len(R)):
        rvec, tvec = cv2.solvePnPRefineLM(obj[i], img[i], K, _NO_DIST, cv2.Rodrigues(R[i])[0],
                                          t[i].reshape(3, 1).copy(), criteria)
        Rs[i], ts[i] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    return fits(obj, img, K, Rs, ts)


def square_candidates(corners: np.ndarray, size_m: float, K: np.ndarray,
                      ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Both IPPE solutions (R, t) of one square marker of side ``size_m`` in the camera
    frame, from its corners (4, 2) in ideal pixels."""
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(_UNIT_SQUARE * size_m, corners.reshape(-1, 1, 2),
                                             K, _NO_DIST, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    return [(cv2.Rodrigues(rvecs[i])[0], np.asarray(tvecs[i], np.float64).ravel())
            for i in range(n)]


def solve(object_points: np.ndarray, image_points: np.ndarray, K: np.ndarray,
          candidates: list[tuple[np.ndarray, np.ndarray]], within_px2: float = np.inf,
          iterations: int = LM_ITERATIONS_BUNDLE) -> list[Solution]:
    """The distinct solutions refined by LM from ``candidates`` (R, t) of one object,
    best (smallest RSS) first.

    Candidates are ranked by their unrefined fit first; one whose RSS exceeds the best's
    by more than ``within_px2`` cannot become a rival and is not refined."""
    obj = np.ascontiguousarray(object_points, np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(image_points, np.float64).reshape(-1, 2)
    candidates = [(R, t) for R, t in candidates if t[2] > 0]
    if not candidates:
        return []
    m = len(candidates)
    start = fits(np.repeat(obj[None], m, 0), np.repeat(img[None], m, 0), K,
                 np.stack([c[0] for c in candidates]), np.stack([c[1] for c in candidates]))
    rss0 = start.rss
    found: list[Solution] = []
    for k in np.argsort(rss0, kind="stable"):
        if found and rss0[k] - found[0].rss_px2 > within_px2:
            break
        sol = refine_lm(obj[None], img[None], K, start.R[k:k + 1], start.t[k:k + 1],
                        iterations).solution(0)
        if not any(_same(sol, f) for f in found):
            found.append(sol)
    return sorted(found, key=lambda s: s.rss_px2)


def solve_squares(corners: np.ndarray, sizes: np.ndarray, K: np.ndarray,
                  within_px2: np.ndarray) -> list[list[Solution]]:
    """:func:`solve` for ``m`` lone square markers at once: corners (m, 4, 2) in ideal
    pixels, sides ``sizes`` (m,); per marker its distinct solutions, best first.

    Both IPPE candidates of every marker are refined together by Gauss-Newton steps;
    the worse-fitting one is a rival if its unrefined RSS lies within ``within_px2``
    (m,) of the refined best's.  A rival whose last step still turned it by more than
    ``CONVERGED_RAD`` started in the flat valley between the two planar solutions,
    where undamped steps wander: it is refined by ``solvePnPRefineLM`` instead (on
    simulated frames the others land where LM does, to 0.03 degrees)."""
    m = len(corners)
    obj = np.repeat(_UNIT_SQUARE[None] * np.asarray(sizes, np.float64)[:, None, None], 2, 0)
    img = np.repeat(np.asarray(corners, np.float64).reshape(m, 4, 2), 2, 0)
    R0, t0 = np.tile(np.eye(3), (2 * m, 1, 1)), np.tile([0.0, 0.0, 1.0], (2 * m, 1))
    valid = np.zeros(2 * m, bool)
    for i in range(m):
        for k, (R, t) in enumerate(square_candidates(img[2 * i], float(sizes[i]), K)[:2]):
            R0[2 * i + k], t0[2 * i + k], valid[2 * i + k] = R, t, t[2] > 0
    start = fits(obj, img, K, R0, t0)
    rss0 = np.where(valid, start.rss, np.inf).reshape(m, 2)
    refined, turned = gauss_newton(obj, img, K, start)
    rss = refined.rss.reshape(m, 2)
    first = np.argmin(rss0, axis=1)
    second = 1 - first
    rows = np.arange(m)
    rival = np.isfinite(rss0[rows, second]) & (rss0[rows, second] - rss[rows, first]
                                               <= np.asarray(within_px2))
    valley = 2 * rows[rival] + second[rival]
    valley = valley[turned[valley] > CONVERGED_RAD]
    damped = dict(zip(valley.tolist(), range(len(valley)), strict=True))
    if len(valley):
        lm = refine_lm(obj[valley], img[valley], K, R0[valley], t0[valley],
                       LM_ITERATIONS_SINGLE)
    out: list[list[Solution]] = []
    for i in range(m):
        if not np.isfinite(rss0[i, first[i]]):
            out.append([])
            continue
        found = [refined.solution(2 * i + first[i])]
        if rival[i]:
            k = 2 * i + second[i]
            other = lm.solution(damped[k]) if k in damped else refined.solution(k)
            if not _same(other, found[0]):
                found.append(other)
                found.sort(key=lambda s: s.rss_px2)
        out.append(found)
    return out


def _same(a: Solution, b: Solution) -> bool:
    return rotation_angle(a.rotation, b.rotation) < SAME_SOLUTION_RAD


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (rad) between two rotations."""
    c = (float(np.vdot(Ra, Rb)) - 1) / 2
    return float(np.arccos(min(max(c, -1.0), 1.0)))


def covariance(fit: Fits, sigma_px: np.ndarray) -> np.ndarray:
    """Decoupled covariances (m, 6, 6) [position, camera-frame rotation] of the poses of
    ``fit`` for corner noise ``sigma_px`` (m,) per axis; ``inf`` variances where the
    corners do not fix the pose."""
    J = fit.jacobian
    return _inverse(_gram(J, J) / np.asarray(sigma_px)[:, None, None] ** 2)


def weighted_covariance(fit: Fits, information: np.ndarray) -> np.ndarray:
    """Decoupled covariances (m, 6, 6) of the poses of ``fit`` for corners of known joint
    inverse covariance ``information`` (m, 2n, 2n): ``(Jᵀ W J)⁻¹``, exact for the weighted
    fit (:func:`reweigh`)."""
    return _inverse(_gram(information @ fit.jacobian, fit.jacobian))


def _gram(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``Aᵀ B`` for stacks (m, k, i) and (m, k, j) or (m, k): a batched ``matmul``, several
    times faster than the equivalent ``einsum`` on these small shapes."""
    if B.ndim == 2:
        return (B[:, None, :] @ A)[:, 0]
    return np.swapaxes(A, 1, 2) @ B


def _inverse(normal: np.ndarray) -> np.ndarray:
    """Symmetric inverses of a stack of normal matrices; ``inf`` variances where one is
    not positive definite (the corners do not fix that pose)."""
    try:
        np.linalg.cholesky(normal)
        out = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        out = np.stack([_inverse_one(n) for n in normal])
    return (out + np.swapaxes(out, -1, -2)) / 2


def _inverse_one(normal: np.ndarray) -> np.ndarray:
    ok, inverse = cv2.invert(normal, flags=cv2.DECOMP_CHOLESKY)
    return inverse if ok else np.diag(np.full(6, np.inf))


def reweigh(fit: Fits, information: np.ndarray) -> Fits:
    """The poses of ``fit`` moved to the minimum of the corners' residuals weighted by
    their joint inverse covariance ``information`` (m, 2n, 2n) (Gauss-Newton and LM weigh
    every corner alike: a corner whose edges were found on a short or noisy side would
    pull the pose as hard as a sharp one).  One Gauss-Newton step from the unweighted minimum with
    its Jacobian: the step is a fraction of a standard deviation, over which the Jacobian
    does not change to first order."""
    WJ = information @ fit.jacobian
    delta = solve_stack(_gram(WJ, fit.jacobian), _gram(WJ, fit.residual))
    R, t = _moved(fit, delta)
    residual = fit.residual - (fit.jacobian @ delta[..., None])[..., 0]
    return Fits(R, t, residual, fit.jacobian)


def difference(a: Solution, b: Solution) -> np.ndarray:
    """[position, rotation] of ``b`` relative to ``a`` in the decoupled form (6,)."""
    phi = cv2.Rodrigues(b.rotation @ a.rotation.T)[0].ravel()
    return np.concatenate([b.tvec - a.tvec, phi])
