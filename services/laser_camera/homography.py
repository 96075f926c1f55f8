"""Plane-to-plane homography by the normalised Direct Linear Transformation (Hogue 2003
§5.4.1, eqs. 5.19-5.37; Hartley and Zisserman's algorithm 4.2).

Both point clouds are first moved to their centroid and scaled to a mean distance of
sqrt(2) from it (eqs. 5.19-5.23) -- without that, the 2n x 9 system mixes pixel-sized and
metre-sized entries and its smallest singular vector is numerically meaningless.  Each
correspondence contributes the two independent rows of ``P' x H P = 0`` (eq. 5.34); the
solution is the right singular vector of the smallest singular value, de-normalised by
``H = T'^-1 H_n T``.  (The thesis prints eq. 5.37 as ``T'^T H T``; only the inverse maps
normalised screen points back, so that is what is computed.)

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import numpy as np

from agent.errors import InvalidInputError


def normalising_transform(points: np.ndarray) -> np.ndarray:
    """``T`` of eqs. 5.19-5.22: centroid to the origin, mean distance sqrt(2)."""
    m = points.mean(axis=0)
    mean_dist = np.linalg.norm(points - m, axis=1).mean()
    if not mean_dist > 0:
        raise InvalidInputError("homography: all points coincide")
    s = np.sqrt(2.0) / mean_dist
    return np.array([[s, 0.0, -s * m[0]], [0.0, s, -s * m[1]], [0.0, 0.0, 1.0]])


def dlt_homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The 3x3 homography ``H`` with ``dst ~ H src`` (least squares in the algebraic
    error), scaled so that ``H[2, 2] == 1`` like ``cv2.findHomography``."""
    src = _points(src, "src")
    dst = _points(dst, "dst")
    if len(src) != len(dst):
        raise InvalidInputError(f"homography: {len(src)} source points but {len(dst)} destination")
    if len(src) < 4:
        raise InvalidInputError(f"homography: need at least 4 correspondences, got {len(src)}")
    T, Tp = normalising_transform(src), normalising_transform(dst)
    P = _homogeneous(src) @ T.T  # rows x_i, y_i, w_i
    Pp = _homogeneous(dst) @ Tp.T
    n = len(P)
    A = np.zeros((2 * n, 9))
    xp, yp, wp = Pp[:, 0:1], Pp[:, 1:2], Pp[:, 2:3]
    A[0::2, 3:6] = -wp * P
    A[0::2, 6:9] = yp * P
    A[1::2, 0:3] = wp * P
    A[1::2, 6:9] = -xp * P
    _, sv, Vt = np.linalg.svd(A)
    if n > 4 and sv[-2] < 1e-12 * sv[0]:
        raise InvalidInputError("homography: degenerate configuration (points nearly collinear)")
    H = np.linalg.solve(Tp, Vt[-1].reshape(3, 3) @ T)
    if abs(H[2, 2]) < 1e-15:
        raise InvalidInputError("homography: maps a source point to infinity (H[2,2] = 0)")
    return H / H[2, 2]


def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map 2-D points (n, 2) through ``H`` (eq. 5.39): one (3, 3), or one per point
    (n, 3, 3).  (The tracker maps its few dots a frame set in plain floats instead:
    ``tracker._ScreenMap``.)"""
    p = np.asarray(H, float) @ _homogeneous(np.atleast_2d(points))[:, :, None]
    return p[:, :2, 0] / p[:, 2:3, 0]


def homography_jacobian(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """d(H(x))/dx: (2, 2) at one point (2,), (n, 2, 2) at points (n, 2) (with one ``H`` or
    one per point, (n, 3, 3)) -- how image errors become screen errors."""
    x = np.asarray(points, float)
    w = np.einsum("...j,...j->...", H[..., 2, :2], x) + H[..., 2, 2]
    y = ((H[..., :2, :2] @ x[..., None])[..., 0] + H[..., :2, 2]) / w[..., None]
    return (H[..., :2, :2] - y[..., :, None] * H[..., None, 2, :2]) / w[..., None, None]


def homography_scale(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Linear scale of the map at points (n, 2): the square root of the Jacobian's
    determinant, (n,) (``H`` as for ``homography_jacobian``)."""
    J = homography_jacobian(H, points)
    return np.sqrt(np.abs(J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]))


def _points(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=float).reshape(-1, 2)
    if not np.all(np.isfinite(a)):
        raise InvalidInputError(f"homography: {name} has non-finite coordinates")
    return a


def _homogeneous(a: np.ndarray) -> np.ndarray:
    return np.column_stack([a, np.ones(len(a))])
