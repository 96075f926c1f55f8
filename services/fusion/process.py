"""The fusion filter's time update: the motion model of Hogue, *MARVIN: a Mobile Automatic
Realtime Visual and INertial tracking system* (MSc thesis, York University 2003), eqs.
6.2-6.5, with the Gauss-Markov jerk and optical-bias states of ``StateLayout``.

The quaternion turns on the manifold by the body-frame increment; everything else moves
linearly, by ``F``.  filterpy provides the white part of the process noise:
``Q_continuous_white_noise`` for the (angle, rate, acceleration) and (position, velocity,
acceleration) chains.
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.common import Q_continuous_white_noise

from agent import geometry as geo
from services.fusion.state import TH, WD, A, Array, FusionConfig, P, StateLayout, V, W, size

#: step matrices kept at most (the inertial rate is nearly constant: a handful of dt)
CACHE_SIZE = 64


class ProcessModel:
    """``F`` and ``Q`` for a step ``dt``, and the step itself on (q, x, P)."""

    def __init__(self, config: FusionConfig, layout: StateLayout):
        self.config = config
        self.layout = layout
        self._cache: dict[float, tuple[Array, Array, Array]] = {}

    def step(self, q: Array, x: Array, P_: Array, dt: float, P_random: Array
             ) -> tuple[Array, Array, Array, Array]:
        """``(q, x, P, P_random)`` after ``dt`` seconds; ``x`` is updated in place and
        returned.  ``P_random`` (``FusionEKF.P_random``) moves as ``P`` does."""
        F, Q, qa = self.matrices(dt)
        ang_jerk = self.layout.angular_jerk
        # q(t+dt) = q Exp(omega dt + omega_dot dt^2 / 2 [+ jerk dt^3 / 6]): body-frame
        # increment (eq. 6.5); everything else moves linearly, by F
        turn = x[W] * dt + x[WD] * (0.5 * dt * dt)
        if size(ang_jerk):
            turn += x[ang_jerk] * (dt**3 / 6.0)
        q = geo.quat_multiply(q, geo.rotvec_to_quat(turn))
        x[3:] = F[3:, 3:] @ x[3:]
        R = geo.quat_to_matrix(q)
        F = F.copy()
        F[TH, W] = R * dt                       # dtheta' = dtheta + R (domega dt + ...)
        F[TH, WD] = R * (0.5 * dt * dt)
        if size(ang_jerk):
            F[TH, ang_jerk] = R * (dt**3 / 6.0)
        Q = Q.copy()
        # angular chain: dtheta is world-frame, omega and omega_dot body-frame
        Q[TH, W] = qa[0, 1] * R
        Q[TH, WD] = qa[0, 2] * R
        Q[W, TH] = qa[1, 0] * R.T
        Q[WD, TH] = qa[2, 0] * R.T
        # the scalar updates subtract outer products; with the stiff jerk states rounding
        # would otherwise make P drift from symmetric to indefinite within seconds
        P_, P_random = (0.5 * (C + C.T) for C in (F @ P_ @ F.T + Q, F @ P_random @ F.T + Q))
        return q, x, P_, P_random

    def matrices(self, dt: float) -> tuple[Array, Array, Array]:
        """The rotation-independent parts of F and Q for a step ``dt``, and the angular
        chain's white-noise block (cached: the inertial rate is nearly constant)."""
        key = round(dt, 9)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        cfg, lay = self.config, self.layout
        dim = lay.dim
        eye = np.eye(3)
        F = np.eye(dim)
        F[W, WD] = eye * dt
        F[P, V] = eye * dt
        F[P, A] = eye * (0.5 * dt * dt)
        F[V, A] = eye * dt
        qa = Q_continuous_white_noise(dim=3, dt=dt, spectral_density=cfg.angular_jerk_psd)
        ql = Q_continuous_white_noise(dim=3, dt=dt, spectral_density=cfg.linear_jerk_psd)
        Q = np.zeros((dim, dim))
        for i, si in enumerate((TH, W, WD)):
            for j, sj in enumerate((TH, W, WD)):
                Q[si, sj] = qa[i, j] * eye
        for i, si in enumerate((P, V, A)):
            for j, sj in enumerate((P, V, A)):
                Q[si, sj] = ql[i, j] * eye
        Q[lay.accel_bias, lay.accel_bias] = np.eye(lay.n_bias) * (cfg.bias_walk**2 * dt)
        # the Gauss-Markov states: decay, stationary variance, and what they drive
        _gauss_markov(F, Q, lay.optical_bias, cfg.optical_bias_std, cfg.optical_bias_tau_s, dt)
        if _gauss_markov(F, Q, lay.linear_jerk, cfg.linear_jerk_std, cfg.linear_jerk_tau_s,
                         dt):
            F[P, lay.linear_jerk] = eye * dt**3 / 6.0
            F[V, lay.linear_jerk] = eye * (0.5 * dt * dt)
            F[A, lay.linear_jerk] = eye * dt
        if _gauss_markov(F, Q, lay.angular_jerk, cfg.angular_jerk_std, cfg.angular_jerk_tau_s,
                         dt):
            F[W, lay.angular_jerk] = eye * (0.5 * dt * dt)
            F[WD, lay.angular_jerk] = eye * dt
        if len(self._cache) > CACHE_SIZE:
            self._cache.clear()
        self._cache[key] = (F, Q, qa)
        return F, Q, qa


def _gauss_markov(F: Array, Q: Array, block: slice, std: float, tau_s: float,
                  dt: float) -> bool:
    """First-order Gauss-Markov states over ``dt``: decay ``exp(-dt / tau)``, driving noise
    that keeps their variance at ``std^2``.  False (and nothing set) for an empty block."""
    n = size(block)
    if n == 0:
        return False
    decay = math.exp(-dt / tau_s)
    F[block, block] = np.eye(n) * decay
    Q[block, block] = np.eye(n) * (std**2 * (1.0 - decay**2))
    return True
