"""Pose of the laser housing from its four wall hits (Hogue 2003, §5.3, fig. 5.4, eqs. 5.6-5.9).

With the hits labeled P1..P4 (beams 1 and 2 opposite, 3 and 4 orthogonal to them and to
each other, all through P0):

* P0 is the foot of the perpendicular from P3 on the line P1P2 (§5.3);
* beam 3 points from P0 to P3; the normal ``n = P0P1 x P0P3`` points along beam 4;
* in the rig frame of ``services.installation.laser_housing`` (beams +y, -y, -x, +z) the rig's x
  axis is ``-unit(P0P3)``, its z axis ``unit(n)`` and y = z x x.

The labels are unknown: all 24 assignments are scored by eq. 5.6,
``eps = eps_perp + D + F``: ``eps_perp`` sums the five |dot products| of directions that
must be perpendicular (eq. 5.7; unit vectors here, so the term is a sum of cosines and does
not grow with the size of the cube), ``D`` the squared distance (m^2) between P0 and the
P0' found from P4 instead of P3 (eq. 5.8), ``F`` is 1 when the normal points away from P4
(eq. 5.9).  The correct labeling and its reflection (2, 1, 4, 3) -- the housing turned
180 degrees about the bisector of beams 3 and 4 -- score exactly alike; the tracker picks
between them by temporal coherence (``tracker``).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from agent.runtime import compiled_twin

#: every assignment of four points to the diodes: PERMUTATIONS[i][k] = index of the point
#: labeled diode k + 1
PERMUTATIONS = np.array(list(permutations(range(4))), np.int64)
_ORDERS = list(permutations(range(4)))  # the same, as the tuples LabeledPose holds


@dataclass(frozen=True)
class LabeledPose:
    """A rig pose computed from one labeling of four wall points."""

    position: np.ndarray  # P0, world
    quaternion: np.ndarray  # rig in world, xyzw
    order: tuple[int, int, int, int]  # indices of the points labeled diodes 1..4
    error: float  # eps of eq. 5.6


def frame_from_points(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rig pose (P0, rotation matrix) from four labeled hits ``P`` (4, 3), rows P1..P4.

    Raises ``ValueError`` when P1 and P2 coincide or P3 lies on the line P1P2 (no frame).
    """
    P0, R = frames_from_points(np.asarray(P, float)[None])
    if not np.all(np.isfinite(R)):
        raise InvalidInputError("pose: P1 and P2 coincide or P3 lies on the line P1P2")
    return P0[0], R[0]


def frames_from_points(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``frame_from_points`` for a stack of labeled hits (m, 4, 3): P0 (m, 3), R (m, 3, 3);
    NaN where no frame exists.

    The stack holds a handful of frames (the labelings that fit, the covariance's nine
    perturbed copies), so numpy's per-call overhead, not arithmetic, is the cost: compiled
    where the laser kernels are built (``KERNELS``); in numpy each norm is taken once and R
    is filled in place rather than stacked."""
    if KERNELS is not None:
        P = np.ascontiguousarray(P, float)
        P0, R = np.empty((len(P), 3)), np.empty((len(P), 3, 3))
        KERNELS.frames(P, P0, R)
        return P0, R
    P1, P2, P3 = P[:, 0], P[:, 1], P[:, 2]
    d12 = P2 - P1
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = _dot(P3 - P1, d12) / _dot(d12, d12)
        P0 = P1 + lam[:, None] * d12
        v1, v3 = P1 - P0, P3 - P0
    return P0, _rotations(v1, v3)


def _rotations(v1: np.ndarray, v3: np.ndarray) -> np.ndarray:
    """The rig's rotations (m, 3, 3) from the directions P0 -> P1 and P0 -> P3 (m, 3); NaN
    where they define no frame."""
    R = np.empty((len(v3), 3, 3))
    if KERNELS is not None:
        KERNELS.rotations(np.ascontiguousarray(v1), np.ascontiguousarray(v3), R)
        return R
    with np.errstate(divide="ignore", invalid="ignore"):
        n = geo.cross(v1, v3)
        len_v3, len_n = row_norms(v3), row_norms(n)
        x = R[:, :, 0] = -v3 / len_v3[:, None]
        z = R[:, :, 2] = n / len_n[:, None]
    R[:, :, 1] = geo.cross(z, x)
    bad = ~np.isfinite(R).all(axis=(1, 2)) | (len_v3 < 1e-9) | (len_n < 1e-12)
    R[bad] = np.nan
    return R


def labeling_errors(points: np.ndarray) -> np.ndarray:
    """eps(i) of eq. 5.6 for all 24 labelings of four points (4, 3), vectorised; ``inf``
    where a labeling defines no frame."""
    return _labelings(points)[0]


def _labelings(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``labeling_errors`` and, per labeling, P0 (24, 3) and the rays from it to the
    points labeled diodes 1..4 (24, 4, 3): the frame of a labeling is made of these
    (``_rotations``), so its candidates need not be solved again.  (The directions from
    P0 to all four points are one (24, 4, 3) array: a numpy call per labeling array, not
    per point.)  Compiled where the laser kernels are built (``KERNELS``)."""
    if KERNELS is not None:
        eps, P0, rays = np.empty(len(PERMUTATIONS)), np.empty((len(PERMUTATIONS), 3)), \
            np.empty((len(PERMUTATIONS), 4, 3))
        KERNELS.labelings(np.ascontiguousarray(points, float), PERMUTATIONS, eps, P0, rays)
        return eps, P0, rays
    P = points[PERMUTATIONS]  # (24, 4, 3): P[i, k] = point labeled diode k + 1
    P1 = P[:, 0]
    d12 = P[:, 1] - P1
    with np.errstate(divide="ignore", invalid="ignore"):
        # the feet of P3 (P0, eq. 5.6's frame) and of P4 (P0', eq. 5.8) on the line P1P2
        lam = np.einsum("ikj,ij->ik", P[:, 2:] - P1[:, None], d12) / _dot(d12, d12)[:, None]
        feet = P1[:, None] + lam[:, :, None] * d12[:, None]
        P0 = feet[:, 0]
        rays = P - P0[:, None]  # rays[:, k] = P(k+1) - P0
        u = rays / row_norms(rays)[..., None]
        # eq. 5.7's pairs: beam 4 with 1, 2, 3; beam 3 with 1, 2
        cosines = np.einsum("ikj,ikj->ik", u.take(_PERP_A, 1), u.take(_PERP_B, 1))
        perp = np.add.reduce(np.abs(cosines), axis=1)
        apart = P0 - feet[:, 1]
        D = _dot(apart, apart)
        n = geo.cross(rays[:, 0], rays[:, 2])
        F = _dot(n, rays[:, 3]) <= 0  # adds as 0 or 1
        eps = perp + D + F
    return np.where(np.isfinite(eps), eps, np.inf), P0, rays


#: the compiled twin of the labelings and frames (None: the numpy code runs)
KERNELS: Any = compiled_twin("services.laser_camera._kernels", "UMA_LASER_PURE_PYTHON")
#: the direction pairs of eq. 5.7 that must be perpendicular (diode indices - 1)
_PERP_A, _PERP_B = np.array([3, 3, 3, 0, 1]), np.array([0, 1, 2, 2, 2])


def candidate_poses(points: np.ndarray, max_error: float) -> list[LabeledPose]:
    """Poses of the labelings with ``eps <= max_error``, best first (the thesis keeps the
    two best: the correct one and its reflection)."""
    points = np.asarray(points, float)
    if points.shape != (4, 3) or not np.all(np.isfinite(points)):
        raise InvalidInputError(f"pose: need four finite 3-D points, got shape {points.shape}")
    eps, P0, rays = _labelings(points)
    best = np.argsort(eps, kind="stable")
    best = best[eps[best] <= max_error]
    if not len(best):
        return []
    # all frames in one batch: per labeling, numpy's call overhead is the cost
    P0, R = P0[best], _rotations(rays[best, 0], rays[best, 2])
    found = ~np.isnan(R[:, 0, 0])  # the others define no frame (NaN throughout)
    best = best[found]
    return [LabeledPose(p0, q, _ORDERS[i], e)
            for p0, q, i, e in zip(P0[found], geo.matrix_to_quat(R[found]), best.tolist(),
                                   eps[best].tolist(), strict=True)]


def reflection(order: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """The labeling that scores like ``order``: diodes (1, 2, 3, 4) -> (2, 1, 4, 3)."""
    return (order[1], order[0], order[3], order[2])


def row_norms(v: np.ndarray) -> np.ndarray:
    """Euclidean norms along the last axis: what np.linalg.norm computes (the same sum),
    without its argument handling, which costs more than the sum on a few 3-vectors."""
    return np.sqrt(np.add.reduce(v * v, axis=-1))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)
