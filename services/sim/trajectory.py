"""Smooth random head motion with exact derivatives, the ground truth of every simulation.

Position and the yaw/pitch/roll angles are sums of sinusoids drawn from a seed, so
velocity, acceleration, angular velocity and angular acceleration are analytic (the
accelerometer simulator needs them exactly, Hogue 2003, §4.5).  Amplitudes are scaled so the
motion stays inside the IVY cube and never exceeds the configured linear and angular
speeds (defaults: 1 m/s and 200 deg/s, fast human head motion).

Frames: ``ivy/world`` has its origin at the centre of the cube, z up.  The trajectory is
the pose of the head frame in the world (x forward, y left, z up).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import numpy as np

from agent import geometry as geo
from services.kinematics import KinematicState


class _Sinusoids:
    """``f(t) = offset + sum a_i sin(2 pi f_i t + phi_i)`` with its first two derivatives."""

    def __init__(self, rng: np.random.Generator, n: int, amp: float, rate: float,
                 offset: float, f_range: tuple[float, float]):
        self.f = rng.uniform(*f_range, n)
        self.phase = rng.uniform(0, 2 * np.pi, n)
        a = rng.uniform(0.3, 1.0, n)
        w = 2 * np.pi * self.f
        # Largest scale meeting both the amplitude and the rate bound.
        self.a = a * min(amp / a.sum(), rate / (a * w).sum())
        self.w = w
        self.offset = offset

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        arg = np.outer(t, self.w) + self.phase
        s, c = np.sin(arg), np.cos(arg)
        return (self.offset + s @ self.a, c @ (self.a * self.w), -s @ (self.a * self.w**2))


class HeadTrajectory:
    """A reproducible head trajectory inside the cube: ``HeadTrajectory(seed).state(t)``."""

    def __init__(self, seed: int = 0, max_speed_mps: float = 1.0,
                 max_angular_speed_dps: float = 200.0, n_components: int = 4,
                 f_range_hz: tuple[float, float] = (0.05, 1.0),
                 center: tuple[float, float, float] = (0.0, 0.0, 0.3),
                 half_extent_m: tuple[float, float, float] = (0.7, 0.7, 0.35)):
        rng = np.random.default_rng(seed)
        v_axis = max_speed_mps / np.sqrt(3.0)  # per-axis bound keeps |v| <= max_speed
        self._pos = [_Sinusoids(rng, n_components, half_extent_m[i], v_axis, center[i],
                                f_range_hz) for i in range(3)]
        w_max = np.radians(max_angular_speed_dps)
        # |omega| <= |roll'| + |pitch'| + |yaw'|: split the budget, yaw gets most (looking around).
        self._yaw = _Sinusoids(rng, n_components, np.radians(150), 0.5 * w_max,
                               rng.uniform(-np.pi, np.pi), f_range_hz)
        self._pitch = _Sinusoids(rng, n_components, np.radians(30), 0.3 * w_max, 0.0, f_range_hz)
        self._roll = _Sinusoids(rng, n_components, np.radians(20), 0.2 * w_max, 0.0, f_range_hz)

    def state(self, t: np.ndarray | float) -> KinematicState:
        """Exact pose, velocities and accelerations at times ``t`` (seconds)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        pos = [s(t) for s in self._pos]
        (yaw, dyaw, ddyaw) = self._yaw(t)
        (pit, dpit, ddpit) = self._pitch(t)
        (rol, drol, ddrol) = self._roll(t)
        # R = Rz(yaw) Ry(pitch) Rx(roll)
        q = geo.quat_multiply(
            geo.quat_multiply(_axis_quat(2, yaw), _axis_quat(1, pit)), _axis_quat(0, rol))
        sp, cp = np.sin(pit), np.cos(pit)
        sr, cr = np.sin(rol), np.cos(rol)
        omega = np.stack([
            drol - dyaw * sp,
            dpit * cr + dyaw * cp * sr,
            -dpit * sr + dyaw * cp * cr,
        ], -1)
        alpha = np.stack([
            ddrol - ddyaw * sp - dyaw * dpit * cp,
            ddpit * cr - dpit * drol * sr + ddyaw * cp * sr - dyaw * dpit * sp * sr
            + dyaw * drol * cp * cr,
            -ddpit * sr - dpit * drol * cr + ddyaw * cp * cr - dyaw * dpit * sp * cr
            - dyaw * drol * cp * sr,
        ], -1)
        return KinematicState(
            t=t,
            position=np.stack([p[0] for p in pos], -1),
            quaternion=q,
            velocity=np.stack([p[1] for p in pos], -1),
            acceleration=np.stack([p[2] for p in pos], -1),
            omega_body=omega,
            alpha_body=alpha,
        )

    def pose(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Position (n, 3) and xyzw quaternion (n, 4) of the head in ``ivy/world``."""
        s = self.state(t)
        return s.position, s.quaternion


def _axis_quat(axis: int, angle: np.ndarray) -> np.ndarray:
    q = np.zeros((*np.shape(angle), 4))
    q[..., axis] = np.sin(0.5 * angle)
    q[..., 3] = np.cos(0.5 * angle)
    return q
