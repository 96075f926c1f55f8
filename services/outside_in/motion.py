"""The filter that smooths and predicts a tracked body: Dorfmüller-Ulhaas's motion model.

The state is the body's pose (``p``, ``R``) with its velocity ``v`` and angular velocity
``omega`` (world frame).  Over ``dt`` the body moves as Theorem 1 of the paper says
(``services.fusion.predictor``'s ``motion_matrices``, eqs. 3-6): ``R' = W R``,
``p' = p + V v``, and the velocity turns with the body, ``v' = W v``, so the motion is
the screw the exponential map describes.  The acceleration of the paper's model is left
to the process noise (white, in both chains): at a marker camera's 120 Hz the pose
measurements pin the motion far better than an estimated acceleration would.

The covariance is an error state ``[dp, dtheta, dv, domega]`` with the world-frame (left)
rotation error, as the fusion filter keeps it (the quaternion outside the vector);
``point_motion_jacobian`` (eq. 16, corrected) gives the rows of ``F`` that depend on
``omega``.  A pose measurement farther than the gate from the prediction is refused;
several in a row restart the filter at the measurement (the body was lost and found).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent import geometry as geo
from services.fusion.predictor import motion_matrices, point_motion_jacobian

Array = np.ndarray

#: chi-square(6) at 99.9 %: a pose measurement further out is an outlier
GATE_6 = 22.458


@dataclass(frozen=True)
class MotionConfig:
    """Process noise (white accelerations) and start-up uncertainty."""

    accel_psd: float = 40.0          # (m/s^2)^2 / Hz
    angular_accel_psd: float = 100.0  # (rad/s^2)^2 / Hz
    initial_velocity_std: float = 2.0  # m/s
    initial_omega_std: float = 6.0     # rad/s
    gate: float = GATE_6
    restart_after: int = 3             # refused measurements in a row
    max_gap_s: float = 0.5             # a longer silence restarts the filter


class MotionFilter:
    """One body's pose and velocities, updated with pose measurements."""

    def __init__(self, config: MotionConfig | None = None):
        self.config = config or MotionConfig()
        self.t: float | None = None
        self.p = np.zeros(3)
        self.R = np.eye(3)
        self.v = np.zeros(3)
        self.omega = np.zeros(3)
        self.P = np.eye(12)
        self.refused_in_row = 0
        self.last_nis = float("nan")

    @property
    def ready(self) -> bool:
        return self.t is not None

    @property
    def pose_covariance(self) -> Array:
        """6x6 over ``[dp, phi]`` (decoupled, world-frame rotation error)."""
        return self.P[:6, :6].copy()

    def reset(self) -> None:
        """Forget the body: the next measurement starts the filter again."""
        self.t = None

    def start(self, t: float, p: Array, R: Array, cov: Array) -> None:
        cfg = self.config
        self.t, self.p, self.R = t, np.asarray(p, float).copy(), np.asarray(R, float).copy()
        self.v = np.zeros(3)
        self.omega = np.zeros(3)
        self.P = np.zeros((12, 12))
        self.P[:6, :6] = cov
        self.P[6:9, 6:9] = np.eye(3) * cfg.initial_velocity_std ** 2
        self.P[9:, 9:] = np.eye(3) * cfg.initial_omega_std ** 2
        self.refused_in_row = 0

    def predicted_pose(self, t: float) -> tuple[Array, Array]:
        """Pose ``(p, R)`` at ``t`` without its covariance (cheap: a marker's window)."""
        if self.t is None:
            raise ValueError("motion filter: not started")
        W, V, _ = motion_matrices(self.omega, t - self.t)
        return self.p + V @ self.v, W @ self.R

    def predicted(self, t: float) -> tuple[Array, Array, Array]:
        """Pose ``(p, R)`` and its 6x6 covariance at ``t`` (the state is not changed)."""
        p, R, _, _, P = self._propagate(t)
        return p, R, P[:6, :6]

    def advance(self, t: float) -> None:
        """Move the state to time ``t``."""
        self.p, self.R, self.v, self.omega, self.P = self._propagate(t)
        self.t = t

    def _propagate(self, t: float) -> tuple[Array, Array, Array, Array, Array]:
        if self.t is None:
            raise ValueError("motion filter: not started")
        dt = t - self.t
        if dt == 0.0:
            return self.p.copy(), self.R.copy(), self.v.copy(), self.omega.copy(), self.P.copy()
        W, V, _ = motion_matrices(self.omega, dt)
        zero = np.zeros(3)
        F = np.eye(12)
        F[0:3, 6:9] = V
        F[0:3, 9:12] = point_motion_jacobian(self.omega, zero, self.v, zero, dt)
        F[3:6, 3:6] = W
        F[3:6, 9:12] = dt * np.eye(3)
        F[6:9, 6:9] = W
        F[6:9, 9:12] = point_motion_jacobian(self.omega, self.v, zero, zero, dt)
        P = F @ self.P @ F.T + self._noise(abs(dt))
        return (self.p + V @ self.v, W @ self.R, W @ self.v, self.omega.copy(),
                0.5 * (P + P.T))

    def _noise(self, dt: float) -> Array:
        """White accelerations: ``[[dt^3/3, dt^2/2], [dt^2/2, dt]] psd`` per chain."""
        Q = np.zeros((12, 12))
        eye = np.eye(3)
        for (a, b), psd in (((0, 6), self.config.accel_psd),
                            ((3, 9), self.config.angular_accel_psd)):
            Q[a:a + 3, a:a + 3] = eye * psd * dt ** 3 / 3
            Q[a:a + 3, b:b + 3] = Q[b:b + 3, a:a + 3] = eye * psd * dt ** 2 / 2
            Q[b:b + 3, b:b + 3] = eye * psd * dt
        return Q

    def update(self, t: float, p: Array, R: Array, cov: Array) -> bool:
        """A pose measurement with its 6x6 covariance over ``[dp, phi]``; False when it
        was refused (beyond the gate) -- the filter then holds its prediction, and restarts
        at the measurement after ``restart_after`` refusals in a row or a long gap."""
        if self.t is None or t - self.t > self.config.max_gap_s:
            self.start(t, p, R, cov)
            return True
        if t > self.t:
            self.advance(t)
        y = np.concatenate([np.asarray(p, float) - self.p,
                            geo.rodrigues_inverse(np.asarray(R, float) @ self.R.T)])
        S = self.P[:6, :6] + cov
        nis = float(y @ np.linalg.solve(S, y))
        self.last_nis = nis
        if nis > self.config.gate:
            self.refused_in_row += 1
            if self.refused_in_row >= self.config.restart_after:
                self.start(t, p, R, cov)
                return True
            return False
        self.refused_in_row = 0
        K = np.linalg.solve(S, self.P[:6, :]).T       # P H^T S^-1, H = [I6 0]
        dx = K @ y
        self.p = self.p + dx[0:3]
        self.R = geo.rodrigues(dx[3:6]) @ self.R
        self.v = self.v + dx[6:9]
        self.omega = self.omega + dx[9:12]
        I_KH = np.eye(12)
        I_KH[:, :6] -= K
        P = I_KH @ self.P @ I_KH.T + K @ cov @ K.T
        self.P = 0.5 * (P + P.T)
        return True
