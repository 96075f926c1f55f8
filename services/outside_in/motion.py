"""The filter that smooths and predicts a tracked body: Dorfmüller-Ulhaas's motion model.

The state is the body's pose (``p``, ``R``), its velocity ``v``, angular velocity
``omega`` and acceleration ``a`` (world frame): the paper's kinematic vector (eq. 9).
Over ``dt`` the body turns by ``W`` of Theorem 1 (``services.fusion.predictor``'s
``motion_matrices``, the exponential map, eqs. 4-6), ``R' = W R``, and moves as eq. 12
says, ``v' = v + a dt``, ``omega`` and ``a`` constant; its origin follows
``p' = p + v dt + a dt^2 / 2``.  (Theorem 1's ``V v + A a`` couples the translation to
the rotation of the points it moves; for the body's own origin, over a marker camera's
8 ms, that coupling is below a micrometre, and keeping it out keeps ``F`` linear in
``v`` and ``a``.)  Process noise drives the acceleration with white jerk and ``omega``
with white angular acceleration: the acceleration state is what lets the filter average
several frames without lagging behind a hand's motion.  How much noise is right depends
on the motion: ``ImmFilter`` runs a smooth model and a manoeuvring one and mixes them by
how well each explains the poses.

The covariance is an error state ``[dp, dtheta, dv, domega, da]`` with the world-frame
(left) rotation error, as the fusion filter keeps it (the quaternion outside the vector).
A pose measurement farther than the gate from the prediction is refused; several in a row
restart the filter at the measurement (the body was lost and found).  A model's
prediction, innovation and correction run in the compiled twin (``_fit.filter_innovation``,
``_fit.filter_correct``), and ``ImmFilter``'s whole update in one call of it
(``_fit.imm_update``), where it was built (numpy otherwise; they agree to rounding).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from filterpy.common import Q_continuous_white_noise

from agent import geometry as geo
from agent.errors import InvalidInputError
from agent.runtime import compiled_twin

Array = np.ndarray

#: process noise matrices kept (by time step)
MAX_CACHED_DT = 64
#: chi-square(6) at 99.9 %: a pose measurement further out is an outlier
GATE_6 = 22.458
N = 15
P_, TH, V_, W_, A_ = (slice(3 * i, 3 * i + 3) for i in range(5))
_EYE3, _EYE_N, _H = np.eye(3), np.eye(N), np.eye(6, N)
#: the compiled filter step in use (tests set it to None to run numpy's)
FILTER: Any = compiled_twin("services.outside_in._fit", "UMA_FIT_PURE_PYTHON")


def _turn(omega: Array, dt: float) -> Array:
    """``W`` of ``motion_matrices`` alone, the body's turn over ``dt``: ``exp(omega dt)``,
    the same rotation by ``geometry.rodrigues`` (equal to rounding; its one-vector path
    takes a third of the time of the coefficients' series, and a filter predicts several
    times a frame set)."""
    return geo.rodrigues(omega * dt)


@dataclass(frozen=True)
class MotionConfig:
    """Process noise (white jerk, white angular acceleration) of smooth motion and of a
    manoeuvre (``ImmFilter``'s two models; a ``MotionFilter`` uses the first), and
    start-up uncertainty.

    The smooth model's densities are near those of a body swaying at a fraction of a
    hertz (the simulator's paths: sinusoids of 0.15-0.6 Hz, at the filter's bandwidth
    about 0.1 (m/s^3)^2/Hz of jerk and 0.06 (rad/s^2)^2/Hz of angular acceleration), not
    a rougher motion's: a white-noise model whose body moves more smoothly than it says
    reports more variance than its error has, by nearly the same share at any density
    (its position 7-13 % at 120 Hz), since the lag its process noise allows for never
    comes; only near the motion's own density does the lag fill it.  A hand's quicker
    moves are the manoeuvre model's."""

    jerk_psd: float = 1.0                     # (m/s^3)^2 / Hz
    angular_accel_psd: float = 0.06           # (rad/s^2)^2 / Hz
    manoeuvre_jerk_psd: float = 200.0         # (m/s^3)^2 / Hz
    manoeuvre_angular_accel_psd: float = 5.0  # (rad/s^2)^2 / Hz
    switch_rate_hz: float = 2.0               # expected switches between them per second
    initial_velocity_std: float = 2.0    # m/s
    initial_omega_std: float = 6.0       # rad/s
    initial_accel_std: float = 10.0      # m/s^2
    gate: float = GATE_6
    restart_after: int = 3               # refused measurements in a row
    max_gap_s: float = 0.5               # a longer silence restarts the filter


class MotionFilter:
    """One body's pose and motion, updated with pose measurements."""

    def __init__(self, config: MotionConfig | None = None):
        self.config = config or MotionConfig()
        self.t: float | None = None
        self.p = np.zeros(3)
        self.R = np.eye(3)
        self.v = np.zeros(3)
        self.omega = np.zeros(3)
        self.a = np.zeros(3)
        self.P = np.eye(N)
        self.refused_in_row = 0
        self.last_nis = float("nan")
        self._q: dict[float, Array] = {}
        #: predicted poses of the current state, by time
        self._poses: dict[float, tuple[Array, Array, Array]] = {}

    @property
    def ready(self) -> bool:
        return self.t is not None

    @property
    def pose_covariance(self) -> Array:
        """6x6 over ``[dp, phi]`` (decoupled, world-frame rotation error)."""
        return self.P[:6, :6].copy()

    @property
    def motion_covariance(self) -> Array:
        """9x9 over ``[v, omega, a]``."""
        return self.P[V_.start:, V_.start:].copy()

    def reset(self) -> None:
        """Forget the body: the next measurement starts the filter again."""
        self.t = None
        self._poses.clear()

    @property
    def start_motion_covariance(self) -> Array:
        """9x9 over ``[v, omega, a]``: what a start knows of the motion (none: zero)."""
        cfg = self.config
        return np.diag([cfg.initial_velocity_std ** 2] * 3 + [cfg.initial_omega_std ** 2] * 3
                       + [cfg.initial_accel_std ** 2] * 3)

    def start(self, t: float, p: Array, R: Array, cov: Array,
              sensitivity: Array | None = None) -> None:
        """Start at a pose, at rest with the configured uncertainty.  A pose fitted to
        cameras exposed at different times, taking the body at rest, is off by ``S du``
        for the true motion ``du`` (``sensitivity`` ``S``, 6 x 9 by ``[v, omega, a]``;
        ``cov`` holds ``S P_u S^T``): its error and the motion's are then correlated by
        ``S P_u``, which the start keeps, so that the next poses correct both."""
        cfg = self.config
        self._poses.clear()
        self.t, self.p, self.R = t, np.asarray(p, float).copy(), np.asarray(R, float).copy()
        self.v, self.omega, self.a = np.zeros(3), np.zeros(3), np.zeros(3)
        self.P = np.zeros((N, N))
        self.P[:6, :6] = cov
        self.P[V_, V_] = np.eye(3) * cfg.initial_velocity_std ** 2
        self.P[W_, W_] = np.eye(3) * cfg.initial_omega_std ** 2
        self.P[A_, A_] = np.eye(3) * cfg.initial_accel_std ** 2
        if sensitivity is not None:
            cross = sensitivity @ self.P[V_.start:, V_.start:]
            self.P[:6, V_.start:] = cross
            self.P[V_.start:, :6] = cross.T
        self.refused_in_row = 0

    def predicted_pose(self, t: float) -> tuple[Array, Array]:
        """Pose ``(p, R)`` at ``t`` without its covariance (cheap: a marker's window; kept
        per ``t`` until the state changes, as a frame set asks it at one time several
        times).  The arrays are the filter's: read them, do not change them."""
        if self.t is None:
            raise InvalidInputError("motion filter: not started")
        got = self._poses.get(t)
        if got is None:
            dt = t - self.t
            W = _turn(self.omega, dt)
            if len(self._poses) >= MAX_CACHED_DT:
                self._poses.clear()
            got = self._poses[t] = (self.p + self.v * dt + 0.5 * dt * dt * self.a,
                                    W @ self.R, W)
        return got[0], got[1]

    def predicted(self, t: float) -> tuple[Array, Array, Array]:
        """Pose ``(p, R)`` and its 6x6 covariance at ``t`` (the state is not changed)."""
        p, R = self.predicted_pose(t)
        return p, R, self._covariance_at(t)[:6, :6]

    def advance(self, t: float) -> None:
        """Move the state to time ``t``."""
        p, R = self.predicted_pose(t)     # first: its turn serves the covariance too
        P = self._covariance_at(t)
        dt = t - self.t
        self.p, self.R = p, R
        self.v = self.v + self.a * dt
        self.P = P
        self.t = t
        self._poses.clear()

    def _covariance_at(self, t: float) -> Array:
        if self.t is None:
            raise InvalidInputError("motion filter: not started")
        dt = t - self.t
        if dt == 0.0:
            return self.P.copy()
        got = self._poses.get(t)
        W = got[2] if got is not None else _turn(self.omega, dt)
        eye = _EYE3
        F = _EYE_N.copy()
        F[P_, V_] = dt * eye
        F[P_, A_] = 0.5 * dt * dt * eye
        F[V_, A_] = dt * eye
        F[TH, TH] = W
        F[TH, W_] = dt * eye
        P = F @ self.P @ F.T + self._noise(abs(dt))
        return 0.5 * (P + P.T)

    def _noise(self, dt: float) -> Array:
        """filterpy's continuous white noise: jerk on (p, v, a), angular acceleration on
        (theta, omega); kept per ``dt`` (a camera's frame period comes again and again, and
        building it costs more than the rest of a prediction)."""
        Q = self._q.get(dt)
        if Q is None:
            if len(self._q) >= MAX_CACHED_DT:
                self._q.clear()
            Q = self._q[dt] = self._build_noise(dt)
        return Q

    def _build_noise(self, dt: float) -> Array:
        Q = np.zeros((N, N))
        eye = np.eye(3)
        lin = Q_continuous_white_noise(dim=3, dt=dt, spectral_density=self.config.jerk_psd)
        for i, si in enumerate((P_, V_, A_)):
            for j, sj in enumerate((P_, V_, A_)):
                Q[si, sj] = lin[i, j] * eye
        ang = Q_continuous_white_noise(dim=2, dt=dt,
                                       spectral_density=self.config.angular_accel_psd)
        for i, si in enumerate((TH, W_)):
            for j, sj in enumerate((TH, W_)):
                Q[si, sj] = ang[i, j] * eye
        return Q

    def update(self, t: float, p: Array, R: Array, cov: Array,
               sensitivity: Array | None = None, noise_cov: Array | None = None) -> bool:
        """A pose measurement with its 6x6 covariance over ``[dp, phi]``; False when it
        was refused (beyond the gate) -- the filter then holds its prediction, and restarts
        at the measurement after ``restart_after`` refusals in a row or a long gap.

        A pose fitted with this filter's own motion at ``t`` (cameras exposed at other
        times moved by it, ``pose.refine_pose``) carries that motion's error: it measures
        ``pose - S du + e``, ``S`` its ``sensitivity`` (6 x 9 by ``[v, omega, a]``) and
        ``e`` of ``noise_cov``.  Given both the update measures that (``H = [I, -S]``):
        the error the prediction and the fit share is counted once, and the fit corrects
        the motion through it; taken as independent of the prediction (``cov`` with
        ``S P S^T`` in it), the filter and the fit fed each other's velocity errors,
        which grew to a 0.6 mm oscillation on a body every 60 ms."""
        if self.t is None or t - self.t > self.config.max_gap_s:
            self.start(t, p, R, cov)
            return True
        inn = self.innovation(t, p, R, cov, sensitivity, noise_cov)
        self.last_nis = inn.nis
        if inn.nis > self.config.gate:
            self.refused_in_row += 1
            if self.refused_in_row >= self.config.restart_after:
                self.start(t, p, R, cov)
                return True
            return False
        self.refused_in_row = 0
        self.correct(inn)
        return True

    def innovation(self, t: float, p: Array, R: Array, cov: Array,
                   sensitivity: Array | None = None, noise_cov: Array | None = None,
                   motion: Array | None = None) -> Innovation:
        """The state moved to ``t`` and what the measurement says of it (``update``), not
        yet applied.  ``motion`` (9: ``[v, omega, a]`` at ``t``) is the motion the fit
        was given when it was not this filter's own (``ImmFilter``: the models' mixture):
        the fit then expects the pose moved by ``S`` times the difference."""
        H = _H.copy()
        noise = cov
        with_s = sensitivity is not None and noise_cov is not None
        if with_s:
            H[:, V_.start:] = -sensitivity
            noise = noise_cov
        if FILTER is not None:
            got = self._innovation_compiled(t, p, R, H, noise, motion if with_s else None)
            if got is not None:
                return got
        if t > self.t:
            self.advance(t)
        y = np.concatenate([np.asarray(p, float) - self.p,
                            geo.rodrigues_inverse(np.asarray(R, float) @ self.R.T)])
        if with_s and motion is not None:
            y = y - sensitivity @ (np.asarray(motion, float) - self.motion)
        PHt = self.P @ H.T
        S = H @ PHt + noise
        return Innovation(y, H, S, noise, PHt, float(y @ np.linalg.solve(S, y)))

    def _innovation_compiled(self, t: float, p: Array, R: Array, H: Array, noise: Array,
                             motion: Array | None) -> Innovation | None:
        """:meth:`innovation` in the compiled twin (``_fit.filter_innovation``: one call
        where numpy takes some twenty-five, each costing more than its arithmetic); None
        when its covariance is singular (numpy's then says so)."""
        dt, W, Q = 0.0, _EYE3, _EYE_N
        p_pred, R_pred = self.p, self.R
        if t > self.t:
            p_pred, R_pred = self.predicted_pose(t)
            dt = t - self.t
            W, Q = self._poses[t][2], self._noise(abs(dt))
        c = np.ascontiguousarray
        got = FILTER.filter_innovation(
            c(p_pred), c(R_pred), c(self.v), c(self.omega), c(self.a), c(self.P), c(W), dt,
            c(Q), c(p, float), c(R, float), H, c(noise, float),
            None if motion is None else c(motion, float))
        if got is None:
            return None
        self._set(np.frombuffer(got[0]).copy())
        if dt:
            self.t = t
        return Innovation(np.frombuffer(got[1]), H, np.frombuffer(got[2]).reshape(6, 6),
                          noise, np.frombuffer(got[3]).reshape(N, 6), got[4])

    def _block(self) -> Array:
        """The state as the compiled twin's block ``[p, R, v, omega, a, P]``."""
        return np.concatenate((self.p, self.R.ravel(), self.v, self.omega, self.a,
                               self.P.ravel()))

    def _set(self, x: Array) -> None:
        """The state from the compiled twin's block ``[p, R, v, omega, a, P]``."""
        self._poses.clear()
        self.p, self.R, self.v = x[0:3], x[3:12].reshape(3, 3), x[12:15]
        self.omega, self.a, self.P = x[15:18], x[18:21], x[21:].reshape(N, N)

    @property
    def motion(self) -> Array:
        """``[v, omega, a]`` now."""
        return np.concatenate([self.v, self.omega, self.a])

    def correct(self, inn: Innovation) -> None:
        """Apply an innovation of the state's present time (``innovation``)."""
        if FILTER is not None:
            c = np.ascontiguousarray
            x = FILTER.filter_correct(c(self.p), c(self.R), c(self.v), c(self.omega),
                                      c(self.a), c(self.P), c(inn.y), c(inn.H), c(inn.S),
                                      c(inn.PHt), c(inn.noise, float))
            if x is not None:
                self._set(np.frombuffer(x).copy())
                return
        K = np.linalg.solve(inn.S, inn.PHt.T).T       # P H^T S^-1
        self.set_state(self.t, K @ inn.y)
        I_KH = _EYE_N - K @ inn.H
        P = I_KH @ self.P @ I_KH.T + K @ inn.noise @ K.T
        self.P = 0.5 * (P + P.T)

    def set_state(self, t: float, dx: Array, P: Array | None = None) -> None:
        """Move the state by the error-state step ``dx`` (15) at ``t``; ``P`` replaces
        the covariance when given."""
        self._poses.clear()
        self.t = t
        self.p = self.p + dx[P_]
        self.R = geo.rodrigues(dx[TH]) @ self.R
        self.v = self.v + dx[V_]
        self.omega = self.omega + dx[W_]
        self.a = self.a + dx[A_]
        if P is not None:
            self.P = 0.5 * (P + P.T)

    def mix(self, ref: MotionFilter, other: MotionFilter, w_ref: float,
            w_other: float) -> None:
        """Become the mixture of ``ref`` and ``other`` (weights summing to 1) about
        ``ref``: its state moved by the weighted mean of ``other``'s difference from it,
        with the covariance of both about that mean (``ImmFilter``'s interaction and
        output; in the compiled twin ``_fit.filter_mix`` where it was built)."""
        if FILTER is not None:
            c = np.ascontiguousarray
            x = FILTER.filter_mix(c(ref.p), c(ref.R), c(ref.v), c(ref.omega), c(ref.a),
                                  c(ref.P), c(other.p), c(other.R), c(other.v),
                                  c(other.omega), c(other.a), c(other.P), float(w_ref),
                                  float(w_other))
            self._set(np.frombuffer(x).copy())
            self.t = ref.t
            return
        d = other.minus(ref)
        mean = w_other * d
        spread = d - mean
        P = w_ref * (ref.P + np.outer(mean, mean)) + w_other * (other.P + np.outer(spread,
                                                                                 spread))
        self.p, self.R, self.v, self.omega, self.a = ref.p, ref.R, ref.v, ref.omega, ref.a
        self.set_state(ref.t, mean, P)

    def minus(self, other: MotionFilter) -> Array:
        """This state less ``other``'s, as an error state (15) of ``other``'s."""
        return np.concatenate([self.p - other.p, geo.rodrigues_inverse(self.R @ other.R.T),
                               self.v - other.v, self.omega - other.omega, self.a - other.a])


@dataclass(frozen=True)
class Innovation:
    """A measurement's innovation against a filter's prediction (``MotionFilter``)."""

    y: Array       # (6,)
    H: Array       # (6, 15)
    S: Array       # (6, 6) its covariance
    noise: Array   # (6, 6) the measurement's own
    PHt: Array     # (15, 6)
    nis: float


class ImmFilter:
    """Two motion models of one body mixed by how well each explains the poses: the
    interacting multiple model filter (Blom and Bar-Shalom).

    A single white-jerk model has to choose: process noise for a hand's quick turns
    (``manoeuvre_*``) lets it average few frames, while the noise of smooth motion
    averages many but refuses and restarts on a quick turn (at three times the
    simulator's speed, 3 m/s, a jerk density of 20 alone refused 42 of 360 poses and
    its NEES left its band).  Here both models run; before each update each starts from a
    mixture of the two (weighted by the chance of switching, ``switch_rate_hz``), each
    is updated, and their probabilities follow the measurement's likelihood under
    each.  The state reported (pose, motion, covariance with the models' spread) is the
    mixture; a measurement is refused only when both models refuse it."""

    def __init__(self, config: MotionConfig | None = None):
        self.config = config or MotionConfig()
        cfg = self.config
        self.models = [MotionFilter(cfg), MotionFilter(replace(
            cfg, jerk_psd=cfg.manoeuvre_jerk_psd,
            angular_accel_psd=cfg.manoeuvre_angular_accel_psd))]
        self.mu = np.array([0.5, 0.5])
        self.mixed = MotionFilter(cfg)
        self.refused_in_row = 0
        self.last_nis = float("nan")

    def __getattr__(self, name: str) -> Any:
        # the mixture's state and predictions: t, p, R, v, omega, a, P, ready,
        # pose_covariance, motion_covariance, start_motion_covariance, predicted_pose,
        # predicted
        if name in _MIXTURE:
            return getattr(self.mixed, name)
        raise AttributeError(name)

    def reset(self) -> None:
        """Forget the body (``MotionFilter.reset``)."""
        for m in (*self.models, self.mixed):
            m.reset()
        self.refused_in_row = 0

    def start(self, t: float, p: Array, R: Array, cov: Array,
              sensitivity: Array | None = None) -> None:
        """Both models start at the pose (``MotionFilter.start``), equally likely."""
        for m in (*self.models, self.mixed):
            m.start(t, p, R, cov, sensitivity)
        self.mu = np.array([0.5, 0.5])
        self.refused_in_row = 0

    def update(self, t: float, p: Array, R: Array, cov: Array,
               sensitivity: Array | None = None, noise_cov: Array | None = None,
               motion: Array | None = None) -> bool:
        """``MotionFilter.update`` for the mixture; ``motion`` (9) is the motion the fit
        was given (the mixture's at ``t``), which each model's own differs from."""
        if self.mixed.t is None or t - self.mixed.t > self.config.max_gap_s:
            self.start(t, p, R, cov)
            return True
        if FILTER is not None:
            accepted = self._update_compiled(t, p, R, cov, sensitivity, noise_cov, motion)
            if accepted is not None:
                return accepted
        prior = self._interact(t)
        inns = [m.innovation(t, p, R, cov, sensitivity, noise_cov, motion)
                for m in self.models]
        nis = np.array([i.nis for i in inns])
        self.last_nis = float(nis.min())
        if self.last_nis > self.config.gate:
            self.refused_in_row += 1
            if self.refused_in_row >= self.config.restart_after:
                self.reset()
                return False
            self.mu = prior
            self._mix_output()
            return False
        self.refused_in_row = 0
        log_like = np.array([-0.5 * (i.nis + np.linalg.slogdet(i.S)[1]) for i in inns])
        w = prior * np.exp(log_like - log_like.max())
        self.mu = w / w.sum()
        for m, inn in zip(self.models, inns, strict=True):
            m.correct(inn)
        self._mix_output()
        return True

    def _update_compiled(self, t: float, p: Array, R: Array, cov: Array,
                         sensitivity: Array | None, noise_cov: Array | None,
                         motion: Array | None) -> bool | None:
        """:meth:`update` in one call of the compiled twin (``_fit.imm_update``: the
        interaction, both models' innovations and corrections, their probabilities and
        the mixture, where they took six calls and the numpy between them); None when a
        covariance is singular (numpy's path then says so), nothing changed."""
        H, noise = _H, cov
        if sensitivity is not None and noise_cov is not None:
            H = _H.copy()
            H[:, V_.start:] = -sensitivity
            noise = noise_cov
        else:
            motion = None
        smooth, quick = self.models
        c = np.ascontiguousarray
        got = FILTER.imm_update(
            smooth._block(), quick._block(),
            *(m._noise(abs(t - m.t)) if t > m.t else _EYE_N for m in self.models),
            smooth.t, quick.t, self.mixed.t, t, self.mu, self.config.switch_rate_hz,
            c(p, float), c(R, float), H, c(noise, float),
            None if motion is None else c(motion, float), self.config.gate)
        if got is None:
            return None
        x_smooth, x_quick, x_mixed, mu, self.last_nis, accepted = got
        for m, x in ((smooth, x_smooth), (quick, x_quick)):
            m._set(np.frombuffer(x).copy())
            m.t = max(m.t, t)
        if not accepted:
            self.refused_in_row += 1
            if self.refused_in_row >= self.config.restart_after:
                self.reset()
                return False
        else:
            self.refused_in_row = 0
        self.mu = np.array(mu)
        self.mixed._set(np.frombuffer(x_mixed).copy())
        self.mixed.t = self.models[int(mu[1] > mu[0])].t
        return bool(accepted)

    def _interact(self, t: float) -> Array:
        """Start each model from the mixture the switching chances make of both (at
        their common time); the models' probabilities before the measurement."""
        dt = max(t - self.mixed.t, 0.0)
        s = -np.expm1(-self.config.switch_rate_hz * dt)
        switch = np.array([[1.0 - s, s], [s, 1.0 - s]])    # [from, to]
        prior = self.mu @ switch
        given = self.mu[:, None] * switch / np.maximum(prior, 1e-300)[None, :]
        smooth, quick = self.models
        smooth.mix(smooth, quick, given[0, 0], given[1, 0])
        return prior

    def _mix_output(self) -> None:
        """The mixture's state: the models' weighted mean about the likelier one, and
        its covariance with their spread."""
        k = int(np.argmax(self.mu))
        self.mixed.mix(self.models[k], self.models[1 - k], self.mu[k], self.mu[1 - k])


#: what an ``ImmFilter`` reads from its mixture
_MIXTURE = frozenset({"t", "p", "R", "v", "omega", "a", "P", "ready", "pose_covariance",
                      "motion_covariance", "start_motion_covariance", "predicted_pose",
                      "predicted", "motion"})
