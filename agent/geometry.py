"""SE(3) geometry: the one place in uma where poses, quaternions and covariances are computed.

Conventions (everything in uma follows them):

* A pose ``(p, q)`` of frame B in frame A maps B-coordinates to A-coordinates:
  ``x_A = R(q) @ x_B + p``.  This is the edge ``A -> B`` of the spatial relationship graph.
* Quaternions are stored **x, y, z, w** (scalar last, like ROS, Eigen's coeffs() and
  scipy), Hamilton product, unit norm.
* A rotation vector ``r`` is axis * angle (radians); ``exp`` maps it to a quaternion and
  ``log`` back (angle in [0, pi]).
* A 6x6 pose covariance is over the **left** (parent-frame) perturbation
  ``T_true = Exp(xi) @ T`` with ``xi = [rho (translation, m), phi (rotation, rad)]``.
  Composition and inversion then propagate by the SE(3) adjoint to first order.
  ``decoupled_to_se3`` / ``se3_to_decoupled`` convert to and from the more intuitive
  "independent position error + parent-frame rotation error" form that sensors report.

Functions broadcast over leading axes where it is natural (``(..., 3)``, ``(..., 4)``).
Inputs that cross a trust boundary go through the ``check_*`` functions, which raise
``ValueError`` naming the value and why it was refused.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from agent.errors import InvalidInputError
from schemas.quaternion import QUAT_NORM_TOL

Array = np.ndarray

#: Largest accepted deviation of R^T R from I for a rotation matrix.
ROT_ORTHO_TOL = 1e-4
_SMALL_ANGLE = 1e-8


# --------------------------------------------------------------------------- validation


def _finite(x: Any, name: str, shape_tail: tuple[int, ...]) -> Array:
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name}: not a numeric array ({exc})") from None
    if a.shape[a.ndim - len(shape_tail):] != shape_tail or a.ndim < len(shape_tail):
        raise InvalidInputError(f"{name}: expected shape (..., {', '.join(map(str, shape_tail))}), "
                                f"got {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        index = tuple(int(i) for i in bad)  # plain ints: numpy 2 reprs would say np.int64(2)
        raise InvalidInputError(f"{name}: non-finite value {float(a[index])!r} at index {index}")
    return a


def _plain(x: Any, n: int) -> list[float] | None:
    """The values of one float64 vector of length ``n``, else None.

    Checking a single 3- or 4-vector element by element in plain Python costs a tenth of
    the numpy calls the general path makes; the SRG checks every sample it receives.
    """
    if type(x) is np.ndarray and x.shape == (n,) and x.dtype == np.float64:
        return x.tolist()
    return None


def check_vector(v: Any, name: str = "position") -> Array:
    """A finite (..., 3) array, or ``ValueError`` naming what was wrong."""
    values = _plain(v, 3)
    if values is not None and all(map(math.isfinite, values)):
        return v
    return _finite(v, name, (3,))


def check_quaternion(q: Any, name: str = "quaternion", tol: float = QUAT_NORM_TOL) -> Array:
    """A finite unit (..., 4) xyzw quaternion, renormalised; refuses norms off by > tol."""
    values = _plain(q, 4)
    if values is not None and all(map(math.isfinite, values)):
        x, y, z, w = values
        n = math.sqrt(x * x + y * y + z * z + w * w)
        if abs(n - 1.0) <= tol:
            return q / n
    a = _finite(q, name, (4,))
    n = np.linalg.norm(a, axis=-1)
    off = np.abs(n - 1.0)
    if np.any(off > tol):
        worst = float(np.max(off))
        norm = float(n.flat[np.argmax(off)])
        raise InvalidInputError(f"{name}: not a unit quaternion (norm {norm:.6g}, off by "
                                f"{worst:.3g} > tolerance {tol:g}); quaternions are x, y, z, w")
    return a / n[..., None]


def check_rotation_matrix(R: Any, name: str = "rotation") -> Array:
    """A finite (..., 3, 3) proper rotation matrix, or ``ValueError`` saying why not."""
    a = _finite(R, name, (3, 3))
    err = np.abs(np.swapaxes(a, -1, -2) @ a - np.eye(3)).max()
    if err > ROT_ORTHO_TOL:
        raise InvalidInputError(f"{name}: not orthonormal "
                                f"(max |R^T R - I| = {err:.3g} > {ROT_ORTHO_TOL:g})")
    det = np.linalg.det(a)
    if np.any(det < 0):
        raise InvalidInputError(f"{name}: determinant {float(np.min(det)):.3g} < 0, a reflection, "
                                "not a rotation")
    return a


def check_matrix(T: Any, name: str = "transform") -> Array:
    """A finite (..., 4, 4) homogeneous rigid transform, or ``ValueError`` saying why not."""
    a = _finite(T, name, (4, 4))
    bottom = a[..., 3, :]
    if np.abs(bottom - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        raise InvalidInputError(f"{name}: last row must be [0, 0, 0, 1], got {bottom.tolist()}")
    check_rotation_matrix(a[..., :3, :3], f"{name} rotation block")
    return a


def check_covariance(C: Any, name: str = "covariance", dim: int = 6) -> Array:
    """A finite, symmetric, positive semi-definite (dim, dim) matrix."""
    a = _finite(C, name, (dim, dim))
    if a.ndim != 2:
        raise InvalidInputError(f"{name}: expected one ({dim}, {dim}) matrix, got shape {a.shape}")
    scale = max(1.0, float(np.abs(a).max()))
    if np.abs(a - a.T).max() > 1e-9 * scale:
        raise InvalidInputError(f"{name}: not symmetric")
    w = np.linalg.eigvalsh(a)
    if w[0] < -1e-9 * scale:
        raise InvalidInputError(f"{name}: not positive semi-definite (smallest eigenvalue "
                                f"{w[0]:.3g})")
    return a


# --------------------------------------------------------------------------- quaternions


def quat_identity(shape: tuple[int, ...] = ()) -> Array:
    q = np.zeros((*shape, 4))
    q[..., 3] = 1.0
    return q


def _bilinear(pairs: dict[int, list[tuple[int, int, float]]], width: int) -> Array:
    """The (16, width) matrix taking the flattened outer product ``a_i * b_j`` (index
    ``4 i + j``) to ``out[k] = sum of coefficient * a_i * b_j`` over ``pairs[k]``."""
    K = np.zeros((16, width))
    for k, terms in pairs.items():
        for i, j, c in terms:
            K[4 * i + j, k] = c
    return K


_X, _Y, _Z, _W = range(4)
#: up to this many numbers in, the outer-product forms below are the fast ones (several
#: times faster for a few quaternions, much slower for large batches)
_SMALL = 256
#: the Hamilton product as one outer product and one matrix product: a handful of numpy
#: calls, where one call per component and term cost more than the arithmetic on the few
#: quaternions of a query (exact coefficients: the same products, summed in another order)
_HAMILTON = _bilinear({
    0: [(_W, _X, 1), (_X, _W, 1), (_Y, _Z, 1), (_Z, _Y, -1)],
    1: [(_W, _Y, 1), (_X, _Z, -1), (_Y, _W, 1), (_Z, _X, 1)],
    2: [(_W, _Z, 1), (_X, _Y, 1), (_Y, _X, -1), (_Z, _W, 1)],
    3: [(_W, _W, 1), (_X, _X, -1), (_Y, _Y, -1), (_Z, _Z, -1)],
}, 4)
#: ``R - I`` of a unit quaternion, row-major, from the outer product ``q q^T``
_ROTATION = _bilinear({
    0: [(_Y, _Y, -2), (_Z, _Z, -2)], 1: [(_X, _Y, 2), (_Z, _W, -2)], 2: [(_X, _Z, 2), (_Y, _W, 2)],
    3: [(_X, _Y, 2), (_Z, _W, 2)], 4: [(_X, _X, -2), (_Z, _Z, -2)], 5: [(_Y, _Z, 2), (_X, _W, -2)],
    6: [(_X, _Z, 2), (_Y, _W, -2)], 7: [(_Y, _Z, 2), (_X, _W, 2)], 8: [(_X, _X, -2), (_Y, _Y, -2)],
}, 9)


def cross(a: Array, b: Array) -> Array:
    """``np.cross(a, b)`` of (..., 3) float arrays, broadcast: each component
    ``a_j b_k - a_k b_j`` as np.cross takes it (the same bits, a zero's sign too), from four
    ``take`` gathers. np.cross's general axis handling costs several times the arithmetic on
    the few vectors of a query or of one frame set's rays."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return a.take(_NEXT, -1) * b.take(_LAST, -1) - a.take(_LAST, -1) * b.take(_NEXT, -1)


#: component j of a cross product pairs components _NEXT[j] and _LAST[j]
_NEXT, _LAST = np.array([1, 2, 0]), np.array([2, 0, 1])


def _outer_flat(a: Array, b: Array) -> Array:
    outer = a[..., :, None] * b[..., None, :]
    return outer.reshape(*outer.shape[:-2], 16)


def quat_multiply(a: Array, b: Array) -> Array:
    """Hamilton product ``a * b`` (apply b first, then a), xyzw."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.size + b.size <= _SMALL:
        return _outer_flat(a, b) @ _HAMILTON
    # a large batch: per component (the matrix product above is slower there)
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = aw * bx + ax * bw + ay * bz - az * by
    out[..., 1] = aw * by - ax * bz + ay * bw + az * bx
    out[..., 2] = aw * bz + ax * by - ay * bx + az * bw
    out[..., 3] = aw * bw - ax * bx - ay * by - az * bz
    return out


def quat_conjugate(q: Array) -> Array:
    """Conjugate, the inverse of a unit quaternion."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def quat_canonical(q: Array) -> Array:
    """The representative of ``q`` / ``-q`` with w >= 0 (same rotation)."""
    q = np.asarray(q, dtype=float)
    return np.where(q[..., 3:4] < 0, -q, q)


def quat_rotate(q: Array, v: Array) -> Array:
    """Rotate vectors ``v`` (..., 3) by unit quaternions ``q`` (..., 4)."""
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    u = q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * cross(u, v)
    return v + w * t + cross(u, t)


def quat_to_matrix(q: Array) -> Array:
    """Unit quaternion(s) (..., 4) to rotation matrices (..., 3, 3)."""
    q = np.asarray(q, dtype=float)
    if q.size <= _SMALL:
        R = _outer_flat(q, q) @ _ROTATION
        R = R.reshape(*R.shape[:-1], 3, 3)
        R += _EYE3
        return R
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty((*q.shape[:-1], 3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


_EYE3 = np.eye(3)


def matrix_to_quat(R: Array) -> Array:
    """Rotation matrices (..., 3, 3) to unit quaternions (w >= 0), Shepperd's method.

    The four candidates are written into one array rather than stacked (five np.stack
    calls were most of the cost on the few matrices of a tracker's frame set); one matrix,
    or each of a few (``_FEW_MATRICES``: a frame set's candidate poses), goes through plain
    floats, the same operations in the same order."""
    R = np.asarray(R, dtype=float)
    if R.shape == (3, 3):
        return _matrix_to_quat_one(R)
    lead = R.shape[:-2]
    if R.size <= 9 * _FEW_MATRICES:
        return np.array([_matrix_to_quat_one(r) for r in R.reshape(-1, 3, 3)]).reshape(*lead, 4)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = R.reshape(-1, 9).T
    trace = m00 + m11 + m22
    # Four candidate solutions; pick per element the one with the largest pivot (stable).
    cand = np.empty((4, 4, len(m00)))
    cand[0] = m21 - m12, m02 - m20, m10 - m01, 1 + trace
    cand[1] = 1 + m00 - m11 - m22, m01 + m10, m02 + m20, m21 - m12
    cand[2] = m01 + m10, 1 - m00 + m11 - m22, m12 + m21, m02 - m20
    cand[3] = m02 + m20, m12 + m21, 1 - m00 - m11 + m22, m10 - m01
    idx = np.argmax(cand[_PIVOT_ROWS, _PIVOT_COLS], axis=0)  # the pivots: the four 4 w^2 ..
    q = cand[idx, :, np.arange(len(idx))]  # (n, 4)
    q = q / np.sqrt(np.add.reduce(q * q, axis=-1))[:, None]  # np.linalg.norm's sum
    return quat_canonical(q.reshape(*lead, 4))


def _matrix_to_quat_one(R: Array) -> Array:
    """:func:`matrix_to_quat` of one matrix on floats (equal to the bit): a tracker asks it
    a few times per body and frame set, where the array form's dozen numpy calls cost
    ten times its arithmetic."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = R.ravel().tolist()
    trace = m00 + m11 + m22
    pivots = (1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22)
    best = pivots.index(max(pivots))   # the first of equal pivots, as np.argmax
    if best == 0:
        q = (m21 - m12, m02 - m20, m10 - m01, pivots[0])
    elif best == 1:
        q = (pivots[1], m01 + m10, m02 + m20, m21 - m12)
    elif best == 2:
        q = (m01 + m10, pivots[2], m12 + m21, m02 - m20)
    else:
        q = (m02 + m20, m12 + m21, pivots[3], m10 - m01)
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w)
    s = -1.0 if w / n < 0 else 1.0
    return np.array([s * (x / n), s * (y / n), s * (z / n), s * (w / n)])


#: up to this many matrices ``matrix_to_quat`` takes one by one on floats: below it the
#: array form's dozen numpy calls cost more than a loop over the matrices
_FEW_MATRICES = 8
#: where each candidate of ``matrix_to_quat`` holds its pivot (4 w^2, 4 x^2, 4 y^2, 4 z^2)
_PIVOT_ROWS, _PIVOT_COLS = np.arange(4), np.array([3, 0, 1, 2])


def rotvec_to_quat(r: Array) -> Array:
    """Exponential map: rotation vector(s) (..., 3) to unit quaternion(s)."""
    r = np.asarray(r, dtype=float)
    if r.size == 3:  # one vector, the interpolation of a tracker's segment: plain floats
        x, y, z = r.ravel().tolist()
        th = math.sqrt(x * x + y * y + z * z)
        k1 = 0.5 - th * th / 48.0 if th < _SMALL_ANGLE else math.sin(0.5 * th) / th
        q = np.array([x * k1, y * k1, z * k1, math.cos(0.5 * th)])
        return q.reshape((*r.shape[:-1], 4))
    theta = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * theta
    small = theta < _SMALL_ANGLE
    # sin(theta/2)/theta with its Taylor series near 0
    k = np.where(small, 0.5 - theta**2 / 48.0, np.sin(half) / np.where(small, 1.0, theta))
    return np.concatenate([r * k, np.cos(half)], axis=-1)


def quat_to_rotvec(q: Array) -> Array:
    """Logarithm map: unit quaternion(s) to rotation vector(s), angle in [0, pi]."""
    q = np.asarray(q, dtype=float)
    if q.shape == (4,):   # one quaternion, as a tracker's filter update asks: plain floats
        x, y, z, w = q.tolist()
        if w < 0:
            x, y, z, w = -x, -y, -z, -w
        s = math.sqrt(x * x + y * y + z * z)
        # numpy's arctan2, not math's: they differ in the last bit on some inputs
        k = 2.0 / w if s < _SMALL_ANGLE else 2.0 * float(np.arctan2(s, w)) / s
        return np.array([x * k, y * k, z * k])
    q = quat_canonical(q)
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    w = q[..., 3:4]
    theta = 2.0 * np.arctan2(s, w)
    small = s < _SMALL_ANGLE
    # theta / s -> 2 / w as s -> 0 (w is then close to 1)
    k = np.where(small, 2.0 / np.where(small, w, 1.0), theta / np.where(small, 1.0, s))
    return v * k


def rodrigues(r: Array) -> Array:
    """Rotation vector(s) to rotation matrices (Rodrigues' formula, like ``cv2.Rodrigues``)."""
    return quat_to_matrix(rotvec_to_quat(r))


def rodrigues_inverse(R: Array) -> Array:
    """Rotation matrices to rotation vectors (the inverse direction of ``cv2.Rodrigues``)."""
    return quat_to_rotvec(matrix_to_quat(R))


def skew(v: Array) -> Array:
    """Cross-product matrices ``[v]x`` (..., 3, 3) with ``[v]x @ u == cross(v, u)``."""
    v = np.asarray(v, dtype=float)
    S = np.zeros((*v.shape[:-1], 3, 3))  # filled in place: stacking costs ~10x on small inputs
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    S[..., 0, 1], S[..., 0, 2] = -z, y
    S[..., 1, 0], S[..., 1, 2] = z, -x
    S[..., 2, 0], S[..., 2, 1] = -y, x
    return S


def skew3(v: Array) -> Array:
    """``[v]x`` of one 3-vector: the hot-path form (filters' per-sample updates), where the
    broadcasting :func:`skew` costs more than the arithmetic."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def cross3(a: Array, b: Array) -> Array:
    """``a x b`` of two 3-vectors, the hot-path form (``np.cross`` is ~10x slower here)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def quat_angle(a: Array, b: Array) -> Array:
    """Rotation angle (rad, [0, pi]) between orientations ``a`` and ``b``."""
    d = quat_multiply(quat_conjugate(a), b)  # atan2 keeps precision near 0 (arccos does not)
    return 2.0 * np.arctan2(np.linalg.norm(d[..., :3], axis=-1), np.abs(d[..., 3]))


def slerp(q0: Array, q1: Array, alpha: Array | float) -> Array:
    """Spherical linear interpolation, shortest arc; ``alpha`` 0 gives q0, 1 gives q1.

    ``alpha`` outside [0, 1] extrapolates along the same great circle.
    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    alpha = np.asarray(alpha, dtype=float)
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    # q(alpha) = q0 * exp(alpha * log(q0^-1 q1)): exact, also for tiny angles.
    delta = quat_to_rotvec(quat_multiply(quat_conjugate(q0), q1))
    a = alpha[..., None] if alpha.ndim else alpha
    return quat_multiply(q0, rotvec_to_quat(delta * a))


# --------------------------------------------------------------------------- poses


def compose(p1: Array, q1: Array, p2: Array, q2: Array) -> tuple[Array, Array]:
    """``T1 @ T2``: the pose of C in A from B in A (p1, q1) and C in B (p2, q2)."""
    return np.asarray(p1, float) + quat_rotate(q1, p2), quat_multiply(q1, q2)


def inverse(p: Array, q: Array) -> tuple[Array, Array]:
    """``T^-1``: from the pose of B in A to the pose of A in B."""
    qi = quat_conjugate(q)
    return -quat_rotate(qi, p), qi


def transform_points(p: Array, q: Array, points: Array) -> Array:
    """Map points (..., 3) given in the child frame into the parent frame."""
    return quat_rotate(q, points) + np.asarray(p, float)


def to_matrix(p: Array, q: Array) -> Array:
    """Pose(s) to 4x4 homogeneous matrices."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    shape = np.broadcast_shapes(p.shape[:-1], q.shape[:-1])
    T = np.zeros((*shape, 4, 4))
    T[..., :3, :3] = quat_to_matrix(q)
    T[..., :3, 3] = p
    T[..., 3, 3] = 1.0
    return T


def from_matrix(T: Array) -> tuple[Array, Array]:
    """4x4 homogeneous matrices to poses (translation, xyzw quaternion)."""
    T = np.asarray(T, dtype=float)
    return T[..., :3, 3].copy(), matrix_to_quat(T[..., :3, :3])


def interpolate(p0: Array, q0: Array, p1: Array, q1: Array,
                alpha: Array | float) -> tuple[Array, Array]:
    """Pose interpolation: linear in translation, slerp in rotation."""
    a = np.asarray(alpha, dtype=float)
    ap = a[..., None] if a.ndim else a
    p0 = np.asarray(p0, dtype=float)
    return p0 + (np.asarray(p1, float) - p0) * ap, slerp(q0, q1, a)


def pose_error(p_est: Array, q_est: Array, p_true: Array, q_true: Array) -> tuple[Array, Array]:
    """Position error (m) and orientation error (rad) of estimates against ground truth."""
    dp = np.linalg.norm(np.asarray(p_est, float) - np.asarray(p_true, float), axis=-1)
    return dp, quat_angle(q_est, q_true)


# --------------------------------------------------------------------------- covariance


def adjoint(p: Array, q: Array) -> Array:
    """SE(3) adjoint (6x6) of a pose for ``xi = [rho, phi]``: ``Exp(Ad xi) T = T Exp(xi)``."""
    if np.ndim(q) == 1 and np.ndim(p) == 1:
        return _adjoint_one(p, q)
    R = quat_to_matrix(q)
    Ad = np.zeros((*R.shape[:-2], 6, 6))
    Ad[..., :3, :3] = R
    Ad[..., 3:, 3:] = R
    Ad[..., :3, 3:] = skew(p) @ R
    return Ad


def _adjoint_one(p: Array, q: Array) -> Array:
    """``adjoint`` of one pose in plain floats: a client composes one per segment answer,
    and numpy's per-call overhead is most of the batched form's cost for a single pose."""
    return adjoint_of_rows(np.asarray(p, float).ravel().tolist(),
                           rotation_rows(np.asarray(q, float).ravel().tolist()))


def quat_product(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float, float]:
    """``a b`` of two quaternions (x, y, z, w) on plain floats, for code that composes single
    poses (the SRG's kernel, a client's composition), where numpy's per-call cost dominates;
    :func:`quat_multiply` is the batched form."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)


def rotation_rows(q: Sequence[float]) -> tuple[tuple[float, float, float], ...]:
    """The rotation matrix of one unit quaternion (x, y, z, w) on plain floats, rows as
    tuples (for code that composes single poses, where numpy's per-call cost dominates)."""
    x, y, z, w = q
    return ((1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
            (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
            (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)))


def adjoint_of_rows(p: Sequence[float], R: Sequence[Sequence[float]]) -> Array:
    """``adjoint`` from a position and rotation rows on plain floats:
    ``[[R, [p]x R], [0, R]]``."""
    px, py, pz = p
    (a, b, c), (d, e, f), (g, h, k) = R
    return np.array([
        (a, b, c, py * g - pz * d, py * h - pz * e, py * k - pz * f),
        (d, e, f, pz * a - px * g, pz * b - px * h, pz * c - px * k),
        (g, h, k, px * d - py * a, px * e - py * b, px * f - py * c),
        (0.0, 0.0, 0.0, a, b, c), (0.0, 0.0, 0.0, d, e, f), (0.0, 0.0, 0.0, g, h, k)])


def compose_covariance(p1: Array, q1: Array, C1: Array | None,
                       C2: Array | None) -> Array | None:
    """Covariance of ``T1 @ T2`` from independent covariances of T1 and T2 (first order).

    ``Exp(xi1) T1 Exp(xi2) T2 = Exp(xi1 + Ad(T1) xi2) T1 T2``, hence
    ``C = C1 + Ad(T1) C2 Ad(T1)^T``.  ``None`` means "exactly known" (zero).
    """
    if C1 is None and C2 is None:
        return None
    out = np.zeros((6, 6)) if C1 is None else np.array(C1, dtype=float)
    if C2 is not None:
        Ad = adjoint(p1, q1)
        out = out + Ad @ np.asarray(C2, float) @ Ad.T
    return out


def inverse_covariance(p: Array, q: Array, C: Array | None) -> Array | None:
    """Covariance of ``T^-1``: ``T^-1 Exp(-xi) = Exp(-Ad(T^-1) xi) T^-1``."""
    if C is None:
        return None
    pi, qi = inverse(p, q)
    Ad = adjoint(pi, qi)
    return Ad @ np.asarray(C, float) @ Ad.T


def decoupled_to_se3(p: Array, C: Array) -> Array:
    """Convert a covariance of [position error, parent-frame rotation error] to ``xi`` form.

    Sensors report position noise independent of the rotation noise; in the SE(3) left
    perturbation the translation part is ``rho = dp - phi x p``.
    """
    J = np.eye(6)
    J[:3, 3:] = skew3(np.asarray(p, float).reshape(3))  # one 3-vector: the hot-path form
    return J @ np.asarray(C, float) @ J.T


def se3_to_decoupled(p: Array, C: Array) -> Array:
    """Inverse of ``decoupled_to_se3``: ``dp = rho + phi x p``."""
    J = np.eye(6)
    J[:3, 3:] = -skew3(np.asarray(p, float).reshape(3))  # one 3-vector: the hot-path form
    return J @ np.asarray(C, float) @ J.T


def decoupled_traces(p: Array, C: Array) -> tuple[float, float, float]:
    """Traces of the position and rotation blocks of ``se3_to_decoupled(p, C)``, without
    building it, and the trace of ``C`` itself (summed in ``np.trace``'s order): path
    attributes need only these three numbers, once per answer.

    With ``dp = rho - [p]x phi``: tr Cov(dp) = tr C_rr - 2 tr([p]x C_fr) + |p|^2 tr C_ff
    - p^T C_ff p (``[p]x^T [p]x = |p|^2 I - p p^T``); the rotation block is unchanged.
    """
    c = np.asarray(C, float).tolist()
    x, y, z = np.asarray(p, float).reshape(3).tolist()
    rot = c[3][3] + c[4][4] + c[5][5]
    # tr([p]x M) with M = C_fr (rows phi, columns rho)
    cross = (x * (c[4][2] - c[5][1]) + y * (c[5][0] - c[3][2]) + z * (c[3][1] - c[4][0]))
    pCp = (x * x * c[3][3] + y * y * c[4][4] + z * z * c[5][5] + x * y * (c[3][4] + c[4][3])
           + x * z * (c[3][5] + c[5][3]) + y * z * (c[4][5] + c[5][4]))
    pos = c[0][0] + c[1][1] + c[2][2] - 2.0 * cross + (x * x + y * y + z * z) * rot - pCp
    return pos, rot, c[0][0] + c[1][1] + c[2][2] + c[3][3] + c[4][4] + c[5][5]


def covariance_from_std(p: Array, pos_std_m: float | None,
                        rot_std_rad: float | None) -> Array | None:
    """A 6x6 ``xi`` covariance from isotropic position and rotation standard deviations."""
    if pos_std_m is None and rot_std_rad is None:
        return None
    d = np.zeros(6)
    d[:3] = (pos_std_m or 0.0) ** 2
    d[3:] = (rot_std_rad or 0.0) ** 2
    return decoupled_to_se3(p, np.diag(d))
