"""Velocity and angular velocity from a stream of absolute poses, for the rig's resets.

A reset gives the dead reckoner an absolute pose; the velocity and angular velocity it
restarts with must come from the absolute poses too.  They have to be good: the
six-accelerometer rig cannot tell an angular-velocity error from the centripetal terms it
removes (Hogue 2003, §4.2), an error ``e`` feeds back as ``e' ~ e^2`` and the dead reckoning
diverges within about ``1 / |e|`` seconds.  A three-point derivative multiplies the pose
noise by ``~2.5 / dt``: about 760 for 300 Hz fused head poses, so 1 mrad of orientation
noise would become 0.8 rad/s of angular-velocity error, and the reckoning would overflow
within two seconds.

Here a quadratic is fitted by least squares to the poses of the last ``FIT_WINDOW_S``
(at least three, spanning at most ``MAX_SPAN_S``) and differentiated at the newest one:
at 300 Hz the noise gain drops to ~60; at 30 Hz it is the three-point parabola.
The variance of each derivative is the fit's noise gain (sum of its squared weights) times
the per-pose noise variance, plus a floor for the truncation error of the quadratic on
head motion.  The per-pose noise is the larger of what the poses report and what the fit
residuals show, so a source without a covariance, or one that understates it, still gives
honest variances (white-noise assumption: the smooth, correlated errors of a filtered
source make this conservative).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError

Array = np.ndarray

#: Poses this close to the newest enter the fit: the noise gain falls as T^-1.5 and the
#: truncation error rises as T^2.  At 50 ms and 300 Hz the gain is ~60 (1 mrad of pose
#: noise: 0.06 rad/s) and the truncation error on the head trajectories < 0.01 rad/s (p95).
FIT_WINDOW_S = 0.05
#: Slower sources: the newest three poses, if they span at most this.
MAX_SPAN_S = 0.25
#: Truncation error of the derivative (standard deviation per axis), whatever the noise.
VELOCITY_FLOOR = 0.01  # m/s
OMEGA_FLOOR = 0.01  # rad/s
#: At most this many poses are kept (a 1 kHz source fills the window with 51).
MAX_POSES = 64


@dataclass(frozen=True)
class Rates:
    """Velocity (world) and angular velocity (body) at time ``t`` with per-axis
    variances, and the per-axis pose noise variances the fit found.  ``settled``: the
    poses kept span the whole fit window, so the residuals have seen all the poses a fast
    source gives there (a noise estimate from the first three or four is a guess)."""

    t: float
    velocity: Array
    velocity_var: float
    omega: Array
    omega_var: float
    position_var: float
    rotation_var: float
    poses: int
    settled: bool


class AbsolutePoses:
    """The recent absolute poses of one source, strictly increasing in time."""

    def __init__(self) -> None:
        # (t, position, quaternion, reported position variance, rotation variance)
        self._poses: deque[tuple[float, Array, Array, float, float]] = deque(maxlen=MAX_POSES)

    def __len__(self) -> int:
        return len(self._poses)

    def add(self, t: float, position: Array, quaternion: Array,
            covariance: Array | None) -> None:
        """Keep one pose (validated); ``ValueError`` if it is not newer than the last."""
        t = float(t)
        if not math.isfinite(t):
            raise InvalidInputError(f"absolute pose: time must be finite, got {t!r}")
        if self._poses and t <= self._poses[-1][0]:
            raise InvalidInputError(f"absolute pose at t={t:.6f} s is not after the previous one "
                                    f"(t={self._poses[-1][0]:.6f} s)")
        p = geo.check_vector(position, "absolute pose position").reshape(3)
        q = geo.check_quaternion(quaternion, "absolute pose quaternion").reshape(4)
        pos_var = rot_var = 0.0
        if covariance is not None:
            dec = geo.se3_to_decoupled(p, geo.check_covariance(covariance,
                                                               "absolute pose covariance"))
            pos_var = float(np.trace(dec[:3, :3])) / 3.0
            rot_var = float(np.trace(dec[3:, 3:])) / 3.0
        while self._poses and self._poses[0][0] < t - MAX_SPAN_S:
            self._poses.popleft()
        self._poses.append((t, p, q, pos_var, rot_var))

    def rates(self) -> Rates | None:
        """The derivatives at the newest pose, or None without three poses close enough."""
        used = self._fit_poses()
        if used is None:
            return None
        t_new = used[-1][0]
        tau = np.array([u[0] - t_new for u in used])
        span = -tau[0]
        # normalised time keeps the 3x3 normal equations well conditioned at any rate
        A = np.stack([np.ones_like(tau), tau / span, (tau / span) ** 2], axis=1)
        W = np.linalg.pinv(A)  # (3, n): coefficients from values
        d = W[1] / span  # weights of the derivative at the newest pose
        gain = float(d @ d)
        P = np.array([u[1] for u in used])
        q_new_inv = geo.quat_conjugate(used[-1][2])
        # each orientation as a rotation vector relative to the newest, in the body frame
        R = geo.quat_to_rotvec(geo.quat_multiply(q_new_inv, np.array([u[2] for u in used])))
        n = len(used)
        pos_var = max(max(u[3] for u in used), _residual_var(A, W, P))
        rot_var = max(max(u[4] for u in used), _residual_var(A, W, R))
        return Rates(t_new, d @ P, gain * pos_var + VELOCITY_FLOOR**2, d @ R,
                     gain * rot_var + OMEGA_FLOOR**2, pos_var, rot_var, n,
                     t_new - self._poses[0][0] >= FIT_WINDOW_S)

    def _fit_poses(self) -> list[tuple[float, Array, Array, float, float]] | None:
        if len(self._poses) < 3:
            return None
        t_new = self._poses[-1][0]
        used = [u for u in self._poses if u[0] >= t_new - FIT_WINDOW_S]
        if len(used) >= 3:
            return used
        used = list(self._poses)[-3:]
        return used if t_new - used[0][0] <= MAX_SPAN_S else None


def _residual_var(A: Array, W: Array, values: Array) -> float:
    """Per-axis noise variance the residuals of the quadratic fit show (0 with no
    redundancy, three poses for three coefficients)."""
    dof = A.shape[0] - A.shape[1]
    if dof <= 0:
        return 0.0
    res = values - A @ (W @ values)
    return float(np.sum(res * res)) / (dof * values.shape[1])
