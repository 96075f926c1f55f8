"""A rigid object's pose from its markers' corners, with a first-order covariance.

Every object (one square marker, or a bundle of markers) is solved the same way:

1. **Candidates**: each visible marker's two IPPE solutions
   (``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)``), moved into the object's frame.
   A planar square seen from far away fits both of them almost equally well: the
   *planar ambiguity* (the marker tilted one way or the mirror way).
2. **Refinement**: Gauss-Newton steps (a lone marker's best candidate) or
   ``cv2.solvePnPRefineLM`` from each candidate over all the object's corners; the
   distinct local minima are kept, ordered by their residual sum of squares; then
   (:func:`reweigh`) a step to the minimum weighted by the corners' covariances.
3. **Covariance** (:func:`weighted_covariance`): ``(Jᵀ W J)⁻¹`` with ``J`` the
   reprojection Jacobian over (rvec, tvec) that ``cv2.projectPoints`` returns and ``W``
   the corners' inverse covariances (or :func:`covariance`, ``(Jᵀ J)⁻¹ σ²`` for one
   corner noise ``σ`` per axis).  It is returned in the
   *decoupled* form, [position error (m), rotation error (rad) in the camera frame]
   (``R_true = exp(φ) R``); :func:`agent.geometry.decoupled_to_se3` gives uma's wire form.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: LM iterations: IPPE starts a lone marker within a millimetre of the optimum, where
#: four iterations reach it to 1e-8 m; a bundle starts from one of its markers
LM_ITERATIONS_SINGLE = 4
LM_ITERATIONS_BUNDLE = 15
#: a lone marker's best candidate is refined by this many undamped Gauss-Newton steps
#: instead (one ``projectPoints`` each, where an LM iteration costs several); a rival
#: candidate, near a flat valley between the two solutions, keeps LM's damping
GAUSS_NEWTON_STEPS = 2
#: two refined solutions closer than this (rad) are the same minimum
SAME_SOLUTION_RAD = np.deg2rad(2.0)


@dataclass(frozen=True)
class Solution:
    """One refined pose of an object in the camera frame and how well it fits."""

    rvec: np.ndarray  # (3,)
    tvec: np.ndarray  # (3,)
    rss_px2: float  # residual sum of squares over all corners
    n_points: int
    jacobian: np.ndarray  # (2n, 6): d(pixels) / d(rvec, tvec)
    rotation: np.ndarray  # (3, 3), from rvec
    residual: np.ndarray  # (2n,): observed - projected pixels

    @property
    def dof(self) -> int:
        """Residual degrees of freedom: the noise's evidence in this fit."""
        return 2 * self.n_points - 6


def square_candidates(corners: np.ndarray, object_corners: np.ndarray, K: np.ndarray,
                      dist: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Both IPPE solutions (rvec, tvec) of one square marker in the camera frame."""
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(object_corners, corners.reshape(-1, 1, 2), K,
                                             dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    return [(np.asarray(rvecs[i], np.float64).ravel(), np.asarray(tvecs[i], np.float64).ravel())
            for i in range(n)]


def solve(object_points: np.ndarray, image_points: np.ndarray, K: np.ndarray,
          dist: np.ndarray, candidates: list[tuple[np.ndarray, np.ndarray]],
          within_px2: float = np.inf, iterations: int = LM_ITERATIONS_BUNDLE,
          ) -> list[Solution]:
    """The distinct refined solutions from ``candidates``, best (smallest RSS) first.

    Candidates are ranked by their unrefined fit first; one whose RSS exceeds the best's
    by more than ``within_px2`` cannot become a rival and is not refined (the LM
    refinement is most of a marker's cost)."""
    obj = np.ascontiguousarray(object_points, np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(image_points, np.float64).reshape(-1, 2)
    scored = []
    for rvec0, tvec0 in candidates:
        if tvec0[2] > 0:
            proj, _ = cv2.projectPoints(obj, rvec0, tvec0, K, dist)
            scored.append((float(((img - proj.reshape(-1, 2)) ** 2).sum()), rvec0, tvec0))
    scored.sort(key=lambda c: c[0])
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-10)
    found: list[Solution] = []
    for rss0, rvec0, tvec0 in scored:
        if found and rss0 - found[0].rss_px2 > within_px2:
            break
        if found or iterations > LM_ITERATIONS_SINGLE:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec0.reshape(3, 1).copy(),
                                              tvec0.reshape(3, 1).copy(), criteria)
            rvec, tvec = rvec.ravel(), tvec.ravel()
        else:
            rvec, tvec = _gauss_newton(obj, img, K, dist, rvec0, tvec0, GAUSS_NEWTON_STEPS)
        proj, jac = cv2.projectPoints(obj, rvec, tvec, K, dist)
        residual = (img - proj.reshape(-1, 2)).ravel()
        sol = Solution(rvec, tvec, float(residual @ residual), len(obj), jac[:, :6].copy(),
                       cv2.Rodrigues(rvec)[0], residual)
        if not any(_same(sol, f) for f in found):
            found.append(sol)
    return sorted(found, key=lambda s: s.rss_px2)


def _gauss_newton(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray,
                  rvec: np.ndarray, tvec: np.ndarray, steps: int,
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Undamped Gauss-Newton steps on the reprojection error: from IPPE's start, within a
    millimetre of the minimum, each step squares the error, and one costs a
    ``projectPoints`` where ``solvePnPRefineLM``'s iteration costs several."""
    for _ in range(steps):
        proj, jac = cv2.projectPoints(obj, rvec, tvec, K, dist)
        J = jac[:, :6]
        ok, delta = cv2.solve(J.T @ J, J.T @ (img - proj.reshape(-1, 2)).ravel(),
                              flags=cv2.DECOMP_CHOLESKY)
        if not ok:
            break
        rvec, tvec = rvec + delta[:3, 0], tvec + delta[3:, 0]
    return rvec, tvec


def _same(a: Solution, b: Solution) -> bool:
    return rotation_angle(a.rotation, b.rotation) < SAME_SOLUTION_RAD


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (rad) between two rotations."""
    c = (np.trace(Ra @ Rb.T) - 1) / 2
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def covariance(sol: Solution, sigma_px: float) -> np.ndarray:
    """Decoupled 6x6 covariance [position, camera-frame rotation] of ``sol`` for corner
    noise ``sigma_px`` per axis; ``inf`` variances if the corners do not fix the pose."""
    return _decoupled(sol, sol.jacobian.T @ sol.jacobian / sigma_px ** 2)


def weighted_covariance(sol: Solution, information: np.ndarray) -> np.ndarray:
    """Decoupled 6x6 covariance of ``sol`` for corners of known inverse covariances
    ``information`` (n, 2, 2): ``(Jᵀ W J)⁻¹``, exact for the weighted fit
    (:func:`reweigh`)."""
    return _decoupled(sol, _weighted_jacobian(sol, information).T @ sol.jacobian)


def _weighted_jacobian(sol: Solution, information: np.ndarray) -> np.ndarray:
    """``W J`` (2n, 6) for the block-diagonal ``W`` of the corners' 2x2 ``information``."""
    return np.matmul(information, sol.jacobian.reshape(-1, 2, 6)).reshape(-1, 6)


def _decoupled(sol: Solution, normal_matrix: np.ndarray) -> np.ndarray:
    ok, cov_rt = cv2.invert(normal_matrix, flags=cv2.DECOMP_CHOLESKY)
    if not ok:
        return np.diag(np.full(6, np.inf))
    G = np.zeros((6, 6))
    G[:3, 3:] = np.eye(3)
    G[3:, :3] = rotation_jacobian(sol.rvec)
    cov = G @ cov_rt @ G.T
    return (cov + cov.T) / 2


def reweigh(sol: Solution, information: np.ndarray) -> Solution:
    """``sol`` moved to the minimum of the corners' residuals weighted by their inverse
    covariances ``information`` (n, 2, 2) (``solvePnPRefineLM`` weighs every corner
    alike: a corner whose edges were found on a short or noisy side would pull the pose
    as hard as a sharp one).  One Gauss-Newton step from the unweighted minimum with its
    Jacobian: the step is a fraction of a standard deviation, over which the Jacobian
    does not change to first order."""
    WJ = _weighted_jacobian(sol, information)
    ok, delta = cv2.solve(WJ.T @ sol.jacobian, WJ.T @ sol.residual, flags=cv2.DECOMP_CHOLESKY)
    if not ok:
        return sol
    rvec, tvec = sol.rvec + delta[:3, 0], sol.tvec + delta[3:, 0]
    residual = sol.residual - sol.jacobian @ delta[:, 0]
    return Solution(rvec, tvec, float(residual @ residual), sol.n_points, sol.jacobian,
                    cv2.Rodrigues(rvec)[0], residual)


def rotation_jacobian(rvec: np.ndarray) -> np.ndarray:
    """d(φ)/d(rvec) where ``R(rvec + d) = exp(φ) R(rvec)``: SO(3)'s left Jacobian."""
    theta = float(np.linalg.norm(rvec))
    W = np.array([[0, -rvec[2], rvec[1]], [rvec[2], 0, -rvec[0]], [-rvec[1], rvec[0], 0]])
    if theta < 1e-6:
        return np.eye(3) + W / 2
    return (np.eye(3) + (1 - np.cos(theta)) / theta ** 2 * W
            + (theta - np.sin(theta)) / theta ** 3 * W @ W)


def difference(a: Solution, b: Solution) -> np.ndarray:
    """[position, rotation] of ``b`` relative to ``a`` in the decoupled form (6,)."""
    phi = cv2.Rodrigues(b.rotation @ a.rotation.T)[0].ravel()
    return np.concatenate([b.tvec - a.tvec, phi])
