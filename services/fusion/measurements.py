"""The fusion filter's measurement models, each a pure ``h(x) -> (prediction, H)`` (the
``Hx`` / ``HJacobian`` pair of filterpy's ``ExtendedKalmanFilter`` in one call, since both
share their intermediate products).

``x`` is the error-state vector's nominal part (its rotation slot unused), ``q`` / ``R``
the head's orientation kept outside it; ``H`` is over the error state, whose rotation
error is the world-frame (left) ``dtheta`` of ``q_true = Exp(dtheta) q``.  Equation
numbers are those of Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial
tracking system* (MSc thesis, York University 2003).
"""

from __future__ import annotations

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.fusion.state import TH, WD, A, AccelModel, Array, P, StateLayout, W, size


def accel_reading(x: Array, R: Array, accel: AccelModel, j: int, gravity: Array,
                  layout: StateLayout) -> tuple[float, Array]:
    """Eq. 6.13 for accelerometer ``j`` and its Jacobian row over the error state.

    ``a_j = n_j . (R^T (alpha - g) + omega_dot x r_j + omega x (omega x r_j)) + b_j``,
    all in head axes (specific force: a resting head reads -g).  Written with dot
    products of precomputed vectors: this runs 1800 times a second.
    """
    r, n = accel.positions[j], accel.axes[j]
    w = x[W]
    u = x[A] - gravity
    Rn = R @ n                              # R n: the axis in world coordinates
    wr = float(w @ r)
    wn = float(w @ n)
    pred = (float(Rn @ u) + float(x[WD] @ accel.cross[j])
            + wn * wr - float(w @ w) * accel.n_dot_r[j])
    H = np.zeros(layout.dim)
    H[TH] = geo.cross3(Rn, u)               # n^T R^T [u]x, the left rotation error
    H[W] = wn * r + wr * n - 2.0 * accel.n_dot_r[j] * w
    H[WD] = accel.cross[j]
    H[A] = Rn
    if layout.n_bias:
        pred += x[layout.accel_bias.start + j]
        H[layout.accel_bias.start + j] = 1.0
    return pred, H


def accel_reading_spreads(x: Array, R: Array, C: Array, accel: AccelModel,
                          gravity: Array) -> Array:
    """Per accelerometer, the variance of what ``accel_reading``'s linearisation leaves
    out: eq. 6.13's second-order terms under the error state's covariance ``C`` of its
    rotation error and angular velocity (the first six rows, ``TH`` then ``W``).

    The reading is quadratic in the angular velocity (the centripetal ``n . w x (w x r)``)
    and, through gravity, in the rotation error (``n . R^T Exp(-dtheta) u`` holds
    ``n' . dtheta x (dtheta x u) / 2``, ``n' = R n``).  For a Gaussian error ``e`` of
    covariance ``C`` a quadratic form ``e^T Q e`` varies by ``2 tr((Q C)^2)``.  Right
    after a start the angular velocity is known to some 0.3-1 rad/s, and this spread
    (0.03-0.2 m/s^2) outweighs a reading's noise (0.008): left out, every reading shrinks
    the covariance as if the model were linear there, and the filter holds on to a rate
    it never measured (a start from two poses 0.47 s apart turned 2 deg away in 0.07 s
    while its covariance claimed 1.6 deg at 3 sigma).  Once the rate is known to a few
    hundredths of a rad/s the spread is about a hundredth of the noise.
    """
    Rn = accel.axes @ R.T                                   # (N, 3) the axes in world
    u = x[A] - gravity
    Q = np.zeros((accel.count, 6, 6))
    Q[:, 3:, 3:] = accel.centripetal
    Q[:, :3, :3] = 0.25 * (Rn[:, :, None] * u + u[:, None] * Rn[:, None, :])
    Q[:, :3, :3] -= 0.5 * (Rn @ u)[:, None, None] * np.eye(3)
    QC = Q @ C
    return 2.0 * np.einsum("nij,nji->n", QC, QC)


def optical_pose(x: Array, q: Array, layout: StateLayout) -> tuple[tuple[Array, Array], Array]:
    """The head pose an optical tracker should report, ``(p, q)``, and d [position,
    rotation] / d error state (6, dim): the head pose plus, in position, the tracker's
    persistent error when the filter models one."""
    H = np.zeros((6, layout.dim))
    H[0:3, P] = H[3:6, TH] = np.eye(3)
    if size(layout.optical_bias):
        H[0:3, layout.optical_bias] = np.eye(3)
    return (H[0:3] @ x, q), H


def pose_residual(p: Array, q: Array, predicted: tuple[Array, Array]) -> Array:
    """Measured minus predicted pose as ``[dp, dtheta]``, the rotation on the manifold."""
    return np.concatenate([p - predicted[0], geo.quat_to_rotvec(
        geo.quat_multiply(q, geo.quat_conjugate(predicted[1])))])


def laser_dot(x: Array, R: Array, layout: StateLayout, beam_rig: Array,
              plane: tuple[Array, float], mount: tuple[Array, Array]) -> tuple[Array, Array]:
    """Where one laser beam of the pose meets a wall, and d point / d error state (3, dim).

    The rig sits at ``mount`` (head -> rig) on the head; its beam ``beam_rig`` (rig
    frame) leaves the rig origin; the wall is the plane ``n . x = c`` (world).  With
    ``M = I - d n^T / (n . d)`` (moving the origin or turning the beam slides the hit
    along the wall): ``dx/dp = M``, ``dx/dtheta = -M ([R p_m]x + s [d]x)``.  A beam that
    runs parallel to the wall or away from it is a ``ValueError``.
    """
    n, c = np.asarray(plane[0], float), float(plane[1])
    arm = R @ np.asarray(mount[0], float)
    origin = x[P] + arm
    d = R @ geo.quat_rotate(mount[1], np.asarray(beam_rig, float))
    nd = float(n @ d)
    if nd <= 1e-6:
        raise InvalidInputError("fusion: the predicted beam does not reach that wall")
    s = (c - float(n @ origin)) / nd
    if s <= 0:
        raise InvalidInputError("fusion: the wall is behind the predicted beam")
    M = np.eye(3) - np.outer(d, n) / nd
    J = np.zeros((3, layout.dim))
    J[:, P] = M
    J[:, TH] = -M @ (geo.skew3(arm) + s * geo.skew3(d))
    return origin + s * d, J
