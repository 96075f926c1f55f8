"""Closed-form solvers of the tracker-alignment equation ``A X = X B`` (Klinker, Bauer
2005, §3.4).

Convention (used by every module of ``services.alignment``):

* Two sensors ``a`` and ``b`` are rigidly connected.  Tracker a reports ``A_k``, the pose of
  ``sensor_a`` in ``world_a`` (SRG edge ``world_a -> sensor_a``); tracker b reports ``B_k``,
  the pose of ``sensor_b`` in ``world_b``.  The two worlds are unrelated.
* ``X`` is the pose of ``sensor_b`` in ``sensor_a`` (edge ``sensor_a -> sensor_b``,
  ``x_a = R_X x_b + t_X``), the static edge the alignment service publishes.
* A *motion pair* ``(A_ij, B_ij)`` is the relative motion of each sensor between stations
  (instants) i and j in its own body frame: ``A_ij = A_i^-1 A_j`` and ``B_ij = B_i^-1 B_j``.
  Since ``B_k = Y A_k X`` for a fixed world-to-world ``Y``, ``A_ij X = X B_ij``.
* OpenCV's ``cv2.calibrateHandEye`` solves the same problem with gripper = sensor a,
  base = world_a, camera = sensor b, target = world_b: pass ``R/t_gripper2base = A_k`` and
  ``R/t_target2cam = B_k^-1``; its ``R/t_cam2gripper`` is ``X``.

All quaternion and pose arithmetic goes through ``agent.geometry`` (xyzw, Hamilton).

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from agent import geometry as geo
from agent.errors import UmaError

#: Motions rotating less than this are too small to carry a rotation axis (solver check).
MIN_ANGLE_RAD = np.radians(2.0)
#: Smallest accepted spread of the motions' rotation axes (see ``axis_spread``).
MIN_AXIS_SPREAD_RAD = np.radians(3.0)
_RANK_TOL = 1e-7


class AlignmentError(UmaError, ValueError):
    """The input cannot determine X (too few, degenerate or invalid motions)."""


class DegenerateMotionError(AlignmentError):
    """The motions do not constrain X: too small, or all about parallel axes."""


class Pose(NamedTuple):
    """A rigid transform: ``position`` (3,) in metres and unit ``quaternion`` (4,) xyzw."""

    position: np.ndarray
    quaternion: np.ndarray


@dataclass(frozen=True)
class MotionPairs:
    """``n`` relative motions ``A_i`` (sensor a) and ``B_i`` (sensor b) with ``A_i X = X B_i``.

    Quaternions are stored canonical (w >= 0), so that motion i of each sensor is
    represented with the same sign; the dual-quaternion solver relies on that.
    """

    pa: np.ndarray  # (n, 3)
    qa: np.ndarray  # (n, 4)
    pb: np.ndarray  # (n, 3)
    qb: np.ndarray  # (n, 4)

    def __post_init__(self) -> None:
        pa = geo.check_vector(self.pa, "motion A position")
        pb = geo.check_vector(self.pb, "motion B position")
        qa = geo.quat_canonical(geo.check_quaternion(self.qa, "motion A quaternion"))
        qb = geo.quat_canonical(geo.check_quaternion(self.qb, "motion B quaternion"))
        n = {pa.reshape(-1, 3).shape[0], qa.reshape(-1, 4).shape[0],
             pb.reshape(-1, 3).shape[0], qb.reshape(-1, 4).shape[0]}
        if len(n) != 1:
            raise AlignmentError(f"motion pairs: A and B hold different numbers of motions {n}")
        for name, value in (("pa", pa), ("qa", qa), ("pb", pb), ("qb", qb)):
            object.__setattr__(self, name, value.reshape(-1, value.shape[-1]))

    def __len__(self) -> int:
        return self.pa.shape[0]

    def subset(self, index: np.ndarray) -> MotionPairs:
        """The motions selected by an index array or boolean mask."""
        return MotionPairs(self.pa[index], self.qa[index], self.pb[index], self.qb[index])

    @property
    def angles_a(self) -> np.ndarray:
        """Rotation angle (rad, [0, pi]) of each motion of sensor a."""
        return np.linalg.norm(geo.quat_to_rotvec(self.qa), axis=-1)

    @property
    def axes_a(self) -> np.ndarray:
        """Unit rotation axis of each motion of sensor a (zero for a zero rotation)."""
        v = self.qa[:, :3]
        n = np.linalg.norm(v, axis=-1, keepdims=True)
        return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def relative_motions(pa: np.ndarray, qa: np.ndarray, pb: np.ndarray, qb: np.ndarray,
                     pairs: np.ndarray) -> MotionPairs:
    """Motion pairs ``A_i^-1 A_j``, ``B_i^-1 B_j`` for station index pairs ``(i, j)``.

    ``pa, qa`` / ``pb, qb`` are the stations: poses of each sensor in its world at the
    same instants (k-th row of a and of b measured together).
    """
    pa = geo.check_vector(pa, "A position")
    pb = geo.check_vector(pb, "B position")
    qa = geo.check_quaternion(qa, "A quaternion")
    qb = geo.check_quaternion(qb, "B quaternion")
    if not (len(pa) == len(qa) == len(pb) == len(qb)):
        raise AlignmentError(f"stations: {len(pa)} A positions, {len(qa)} A quaternions, "
                             f"{len(pb)} B positions, {len(qb)} B quaternions; must be equal")
    ij = np.asarray(pairs, dtype=int).reshape(-1, 2)
    i, j = ij[:, 0], ij[:, 1]
    pai, qai = geo.inverse(pa[i], qa[i])
    pbi, qbi = geo.inverse(pb[i], qb[i])
    ma = geo.compose(pai, qai, pa[j], qa[j])
    mb = geo.compose(pbi, qbi, pb[j], qb[j])
    return MotionPairs(ma[0], ma[1], mb[0], mb[1])


def all_pairs(n: int) -> np.ndarray:
    """Every station index pair ``(i, j)`` with ``i < j`` (what ``cv2.calibrateHandEye`` uses)."""
    i, j = np.triu_indices(n, 1)
    return np.stack([i, j], axis=-1)


def axis_spread(axes: np.ndarray) -> float:
    """How far apart unit rotation axes point (rad): 0 if all are parallel.

    For two axes it is the angle between them (sign ignored); for many it is the angle of
    the two-axis set with the same middle eigenvalue of the scatter ``mean(a a^T)``.  X is
    determined only if at least two axes are not parallel (Klinker, Bauer 2005, §3.4.3).
    """
    if len(axes) < 2:
        return 0.0
    scatter = np.einsum("ni,nj->ij", axes, axes) / len(axes)
    middle = np.linalg.eigvalsh(scatter)[1]
    return float(np.arccos(np.clip(1.0 - 2.0 * middle, -1.0, 1.0)))


def check_conditioning(pairs: MotionPairs, min_angle_rad: float = MIN_ANGLE_RAD,
                       min_axis_spread_rad: float = MIN_AXIS_SPREAD_RAD) -> None:
    """Raise ``DegenerateMotionError`` unless the motions determine X.

    Needs two motions rotating by at least ``min_angle_rad`` whose axes spread by at least
    ``min_axis_spread_rad``: smaller rotations have axes dominated by noise, and with
    parallel axes the rotation about that axis and the translation along it are free.
    """
    if len(pairs) < 2:
        raise DegenerateMotionError(f"need at least 2 motion pairs, got {len(pairs)}")
    turning = pairs.angles_a >= min_angle_rad
    if turning.sum() < 2:
        raise DegenerateMotionError(
            f"only {int(turning.sum())} of {len(pairs)} motions rotate by at least "
            f"{np.degrees(min_angle_rad):.3g} deg (pure translations do not determine X)")
    spread = axis_spread(pairs.axes_a[turning])
    if spread < min_axis_spread_rad:
        raise DegenerateMotionError(
            f"rotation axes of the motions are (nearly) parallel: spread "
            f"{np.degrees(spread):.3g} deg < {np.degrees(min_axis_spread_rad):.3g} deg; "
            "rotate about at least two different axes")


def _normal_matrix(M: np.ndarray, what: str) -> np.ndarray:
    """``M^T M``, refused if M is rank deficient (smallest/largest singular value < tol).

    Normal equations rather than SVD/QR of the tall M (3n or 6n rows, at most 8 columns):
    multithreaded LAPACK on tall-thin matrices is far slower on a loaded machine, and
    the rank test keeps the squared condition number harmless.
    """
    N = M.T @ M
    ev = np.linalg.eigvalsh(N)
    if ev[-1] <= 0 or ev[0] <= _RANK_TOL**2 * ev[-1]:
        sv = np.sqrt(np.clip(ev[::-1], 0.0, None))
        raise DegenerateMotionError(f"{what}: the equations are rank deficient "
                                    f"(singular values {np.array2string(sv, precision=3)})")
    return N


def _lstsq_full_rank(M: np.ndarray, rhs: np.ndarray, what: str) -> np.ndarray:
    """Least squares that refuses a rank-deficient system instead of guessing."""
    return np.linalg.solve(_normal_matrix(M, what), M.T @ rhs)


def _row_weights(weights: np.ndarray | None, n: int) -> np.ndarray:
    """Square roots of per-motion weights, the factor for each motion's equations."""
    if weights is None:
        return np.ones(n)
    w = np.asarray(weights, dtype=float)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise AlignmentError(f"weights: expected {n} finite non-negative values, got {w!r}")
    return np.sqrt(w)


def tsai_lenz(pairs: MotionPairs, weights: np.ndarray | None = None,
              min_angle_rad: float = MIN_ANGLE_RAD,
              min_axis_spread_rad: float = MIN_AXIS_SPREAD_RAD) -> Pose:
    """Tsai and Lenz's two-step solution (Klinker, Bauer 2005, §3.4.1, eqs. 3.2-3.5).

    Rotation first, with the modified Rodrigues vector ``r = 2 sin(theta/2) n`` (for a
    canonical quaternion that is twice its vector part): ``[r_A + r_B]x r'_X = r_B - r_A``
    (eq. 3.5) by linear least squares, then ``r_X = 2 r'_X / sqrt(1 + |r'_X|^2)`` (the seed
    prints ``sqrt(1 + |r'_X|)``, a typo).  Then the translation from
    ``(R_A - I) t_X = R_X t_B - t_A`` (from eq. 3.3).  Cannot represent |X| rotations of
    180 degrees (``r'_X = tan(theta/2) n`` diverges), like the original.  ``weights`` (n,)
    scale each motion's equations, e.g. bootstrap multiplicities.
    """
    check_conditioning(pairs, min_angle_rad, min_axis_spread_rad)
    w = _row_weights(weights, len(pairs))
    r_a = 2.0 * pairs.qa[:, :3]
    r_b = 2.0 * pairs.qb[:, :3]
    M = (geo.skew(r_a + r_b) * w[:, None, None]).reshape(-1, 3)
    r_prime = _lstsq_full_rank(M, ((r_b - r_a) * w[:, None]).reshape(-1), "Tsai-Lenz rotation")
    r_x = 2.0 * r_prime / np.sqrt(1.0 + r_prime @ r_prime)
    half = 0.5 * r_x
    q_x = np.append(half, np.sqrt(max(0.0, 1.0 - half @ half)))
    R_a = geo.quat_to_matrix(pairs.qa)
    C = ((R_a - np.eye(3)) * w[:, None, None]).reshape(-1, 3)
    d = ((geo.quat_rotate(q_x, pairs.pb) - pairs.pa) * w[:, None]).reshape(-1)
    t_x = _lstsq_full_rank(C, d, "Tsai-Lenz translation")
    return Pose(t_x, geo.quat_canonical(q_x))


def _dual_parts(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vector parts of the real and dual quaternion of motions: ``q`` and ``q' = t q / 2``."""
    t = np.concatenate([p, np.zeros((len(p), 1))], axis=-1)
    return q[:, :3], 0.5 * geo.quat_multiply(t, q)[:, :3]


def _motion_matrix(pairs: MotionPairs) -> np.ndarray:
    """The 6n x 8 matrix T of stacked 6 x 8 blocks S (Klinker, Bauer 2005, §3.4.2).

    Unknown ordering ``(q_w, q_x, q_y, q_z, q'_w, q'_x, q'_y, q'_z)`` (scalar first, as in
    the seed); the result is converted to xyzw afterwards.
    """
    a, a_d = _dual_parts(pairs.pa, pairs.qa)
    b, b_d = _dual_parts(pairs.pb, pairs.qb)
    n = len(pairs)
    S = np.zeros((n, 6, 8))
    S[:, :3, 0] = a - b
    S[:, :3, 1:4] = geo.skew(a + b)
    S[:, 3:, 0] = a_d - b_d
    S[:, 3:, 1:4] = geo.skew(a_d + b_d)
    S[:, 3:, 4] = a - b
    S[:, 3:, 5:8] = geo.skew(a + b)
    return S


def _null_directions(a: float, b: float, c: float) -> list[np.ndarray]:
    """Directions ``(lambda1, lambda2)`` with ``a l1^2 + b l1 l2 + c l2^2 = 0`` (eq. 3.10).

    The seed solves for ``s = lambda1 / lambda2``; when ``a = x1.y1`` is the smaller
    coefficient that root is near infinity, so we solve for ``1/s`` instead.  A slightly
    negative discriminant (noise) is clamped to zero.
    """
    disc = np.sqrt(max(b * b - 4.0 * a * c, 0.0))
    if abs(a) >= abs(c):
        return [np.array([(-b + sg * disc) / (2.0 * a), 1.0]) for sg in (1.0, -1.0)]
    return [np.array([1.0, (-b + sg * disc) / (2.0 * c)]) for sg in (1.0, -1.0)]


def daniilidis(pairs: MotionPairs, weights: np.ndarray | None = None,
               min_angle_rad: float = MIN_ANGLE_RAD,
               min_axis_spread_rad: float = MIN_AXIS_SPREAD_RAD) -> Pose:
    """Daniilidis' simultaneous dual-quaternion solution (Klinker, Bauer 2005, §3.4.2,
    eqs. 3.8-3.11).

    Stacks ``S_i (q, q')^T = 0`` into T (6n x 8), takes the two right singular vectors of
    the smallest singular values, ``(q, q') = l1 v7 + l2 v8`` (eq. 3.8), and fixes
    ``l1, l2`` by ``q^T q' = 0`` (eq. 3.10, a quadratic in ``s = l1/l2``) and
    ``q^T q = 1`` (eqs. 3.9/3.11), choosing the root with the larger ``|q|`` per unit
    ``|(l1, l2)|`` (the seed's "largest value"; the other root has ``q`` near 0).
    ``weights`` (n,) scale each motion's equations, e.g. bootstrap multiplicities.
    """
    check_conditioning(pairs, min_angle_rad, min_axis_spread_rad)
    S = _motion_matrix(pairs) * _row_weights(weights, len(pairs))[:, None, None]
    # Right singular vectors of T = eigenvectors of T^T T (8 x 8; see _normal_matrix).
    T = S.reshape(-1, 8)
    ev, V = np.linalg.eigh(T.T @ T)
    if ev[-1] <= 0 or ev[2] <= _RANK_TOL**2 * ev[-1]:
        raise DegenerateMotionError(
            "Daniilidis: T has rank < 6 (screw axes parallel); rotate about two different axes")
    v7, v8 = V[:, 1], V[:, 0]
    x1, y1, x2, y2 = v7[:4], v7[4:], v8[:4], v8[4:]
    G = np.array([[x1 @ x1, x1 @ x2], [x1 @ x2, x2 @ x2]])
    best = max(_null_directions(x1 @ y1, x1 @ y2 + x2 @ y1, x2 @ y2),
               key=lambda d: (d @ G @ d) / (d @ d))
    lam = best / np.sqrt(best @ G @ best)  # eq. 3.11: |q| = 1
    dq = lam[0] * v7 + lam[1] * v8
    q = np.append(dq[1:4], dq[0])
    q_dual = np.append(dq[5:8], dq[4])
    t = 2.0 * geo.quat_multiply(q_dual, geo.quat_conjugate(q))[:3]
    norm = np.linalg.norm(q)
    return Pose(t / norm**2, geo.quat_canonical(q / norm))


class Residuals(NamedTuple):
    """Per-pair misfit of ``A X = X B``: rotation angle (rad) and translation (m)."""

    rot_rad: np.ndarray
    pos_m: np.ndarray


def pair_residuals(pairs: MotionPairs, x: Pose) -> Residuals:
    """How far ``A_i X`` is from ``X B_i`` for each pair (eqs. 3.2 and 3.3)."""
    p_ax, q_ax = geo.compose(pairs.pa, pairs.qa, x.position, x.quaternion)
    p_xb, q_xb = geo.compose(x.position, x.quaternion, pairs.pb, pairs.qb)
    return Residuals(geo.quat_angle(q_ax, q_xb), np.linalg.norm(p_ax - p_xb, axis=-1))


def linearised_residuals(pairs: MotionPairs, x: Pose,
                         scale: tuple[float, float] | None = None,
                         ) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """``refine``'s residuals (n, 6: translation, rotation) at ``x``, their Jacobian (n, 6,
    6) over the left perturbation of X, and the RMS of each group, by which both are
    divided (or by ``scale``, to compare other motions on the same footing)."""
    p, q = np.asarray(x.position, float), np.asarray(x.quaternion, float)
    D = geo.quat_to_matrix(pairs.qa) - np.eye(3)
    rot = geo.quat_to_rotvec(geo.quat_multiply(geo.quat_multiply(pairs.qa, q),
                                               geo.quat_conjugate(geo.quat_multiply(q, pairs.qb))))
    x_tb = geo.quat_rotate(q, pairs.pb)
    pos = D @ p + pairs.pa - x_tb
    if scale is None:
        scale = (float(np.sqrt(np.mean(pos**2))), float(np.sqrt(np.mean(rot**2))))
    s_pos, s_rot = max(scale[0], 1e-13), max(scale[1], 1e-13)
    J = np.zeros((len(pairs), 6, 6))
    J[:, :3, :3] = D / s_pos
    J[:, :3, 3:] = (geo.skew(x_tb) - D @ geo.skew(p)) / s_pos
    J[:, 3:, 3:] = D / s_rot
    return np.concatenate([pos / s_pos, rot / s_rot], axis=-1), J, scale


def refine(pairs: MotionPairs, x0: Pose, weights: np.ndarray | None = None,
           iterations: int = 10) -> Pose:
    """Gauss-Newton on the geometric residuals of eqs. 3.2 and 3.3, from a closed-form X.

    Tsai-Lenz and Daniilidis minimise algebraic errors, which weigh the motions unevenly;
    this minimises the rotation residual ``log(R_A R_X R_B^T R_X^T)`` and the translation
    residual ``R_A t_X + t_A - R_X t_B - t_X`` of all pairs, each group scaled by its RMS
    (re-estimated every step), over the left perturbation ``X <- Exp(xi) X`` of geometry's
    convention.  Linearised: ``d rot = (R_A - I) phi`` and
    ``d pos = (R_A - I) rho + ([R_X t_B]x - (R_A - I)[t_X]x) phi``.
    """
    w = _row_weights(weights, len(pairs))
    p, q = np.asarray(x0.position, float), np.asarray(x0.quaternion, float)
    for _ in range(iterations):
        r, J, scale = linearised_residuals(pairs, Pose(p, q))
        if max(scale) < 1e-13:
            break  # exact already: nothing to weigh
        step = _lstsq_full_rank((J * w[:, None, None]).reshape(-1, 6),
                                -(r * w[:, None]).reshape(-1), "refinement")
        dq = geo.rotvec_to_quat(step[3:])
        p, q = geo.quat_rotate(dq, p) + step[:3], geo.quat_multiply(dq, q)
        if np.linalg.norm(step) < 1e-10:
            break  # below 0.1 nm and 0.1 nrad: converged
    return Pose(p, geo.quat_canonical(q / np.linalg.norm(q)))
