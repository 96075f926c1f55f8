"""Pose from accelerations, Hogue 2003, §4.3: dead reckoning with an honest covariance.

Each sample's N accelerations give the rig-frame specific force and angular acceleration
by the linear system of eq. 4.42 (``RigLayout.solve``); the angular acceleration is
integrated to angular velocity (eq. 4.44), the rate quaternion (eq. 4.45) to orientation,
gravity is added back in the world frame (eq. 4.46) and the acceleration is integrated
twice (eqs. 4.47-4.48).  All four are one coupled ODE, integrated by classical RK4 between
consecutive samples, with the readings inside a step interpolated by the parabola through
the last three samples (third-order accurate, no extra latency).

The covariance is the linearised error propagation of that ODE, error state
``[phi, rho, dv, domega]``: ``(rho, phi)`` the pose error in geometry's SE(3) convention
(left perturbation, so the reported covariance needs no conversion), ``dv`` the world
velocity error and ``domega`` the rig-frame angular-velocity error; driven by the reading
noise of the calibration's noise model, plus the calibration's own uncertainty (bias, gain
and axis of each accelerometer act as constant reading errors, carried as a sensitivity
matrix).  It includes the instability of the six-accelerometer rig: an angular-velocity
error feeds back through the centripetal terms of eq. 4.42.

To second order the orientation error also changes the acceleration (a tilt error shortens
the specific force's component along itself by |u| |tilt|^2 / 2 whatever its sign), which
the linear propagation leaves out (``_second_order``).  The estimate is left as it is; the
term enters the covariance as one draw that lasts as long as the orientation error does, so
it is carried like a constant error (``_State.D``, integrated into velocity and position by
the same propagation, ``D D^T`` added to the covariance), not as fresh noise at every step,
which would shrink it by the number of steps.

The step and the estimate's arrays have a compiled twin (``_step.c``, built when a C
compiler is there) doing the same operations on the same data: :data:`NATIVE` is it unless
it was not built or ``UMA_ACCEL_PURE_PYTHON=1`` is set.  Both are tested to agree
(``tests/test_accel_native.py``).

Times: a reading taken at sample time t describes the motion at ``t - latency_s`` (the
0-110 Hz response), so the state and the reported pose carry that motion time.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from functools import cached_property
from typing import Any, NamedTuple

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from agent.runtime import compiled_twin
from services.accel_rig.sensor import Calibration
from services.frames import GRAVITY
from services.kinematics import KinematicState

Array = np.ndarray

#: Seconds of samples kept to replay after a late reset; a reset further ahead of the newest
#: sample than this is refused too (the clocks of pose and samples disagree).
HISTORY_S = 1.0
#: A head turns at a few rad/s; at 50 rad/s the centripetal terms alone would saturate
#: MARVIN's +/-5 g accelerometers 5 cm from the centre.  An angular velocity beyond it is
#: not a motion the rig can have measured: a reset carrying one is refused, and a state
#: that reaches it has diverged (the six-accelerometer rig's omega feedback, Hogue 2003, §4.2).
MAX_OMEGA_RAD_S = 50.0
#: Beyond 1000 m, m/s, rad or rad/s of standard deviation the linearised covariance
#: describes nothing: the dead reckoning has diverged (and would overflow soon after).
MAX_VARIANCE = 1e6
#: What the readings' noise from before a start weighs in the dead reckoning that starts
#: there, in one sample's variance.  The steps integrate the parabola through the last three
#: samples (the line through two at a first start): each later sample's noise ends up as one
#: velocity impulse at its own time, the noise each step adds, but the first steps also use
#: samples from the start's time and before.  From a start at a sample's time with two
#: earlier ones those weigh -1/12 and 7/12 of a sample; from a first start the start's
#: sample weighs 5/12 and the next one 13/12 instead of 1.  Either way (1 + 49) / 144 =
#: (25 + 25) / 144 more than the steps add (0.33-0.37 from a start between samples), an
#: impulse at the start: 1.5 % of the pose's variance after 0.25 s at 300 Hz.
START_NOISE_WEIGHT = 50.0 / 144.0
_I12 = np.eye(12)
#: rows and columns of the 12x12 state covariance that make the pose's 6x6 in geometry's
#: order [rho, phi] (the state holds [phi, rho, ...])
_POSE_ORDER = np.array([3, 4, 5, 0, 1, 2])
_POSE_FLAT = (12 * _POSE_ORDER[:, None] + _POSE_ORDER[None, :]).ravel()  # for one take


def _error_dynamics_layout(gk: Array) -> tuple[Array, Array]:
    """The matrix ``[A | Bk]`` of ``DeadReckoner._propagate`` (12 x (12 + N)): the error
    dynamics A and the reading sensitivity over the gains Bk, as a template holding what
    is constant (the identity of rho' = dv + ..., and Bk's rows 9:12, ``gk[3:]``) and the
    flat indices where each step puts the rest, in the order R, [v]x, [p]x R, -[R f]x,
    R df/domega, domega_dot/domega (3x3 blocks of A; of the cross-product matrices only the
    off-diagonal entries), then R gk[:3] (Bk's rows 6:9): one ``put`` fills the matrix."""
    n = gk.shape[1]
    width = 12 + n
    template = np.zeros((12, width))
    template[3:6, 6:9] = np.eye(3)
    template[9:12, 12:] = gk[3:]
    full = [(i, j) for i in range(3) for j in range(3)]
    off = [(i, j) for i, j in full if i != j]
    blocks = [(0, 9, full), (3, 0, off), (3, 9, full), (6, 0, off), (6, 9, full), (9, 9, full),
              (6, 12, [(i, j) for i in range(3) for j in range(n)])]
    index = [width * (r + i) + c + j for r, c, cells in blocks for i, j in cells]
    return template, np.array(index)


@dataclass(frozen=True)
class Estimate:
    """The dead-reckoned state at motion time ``t``.

    ``velocity`` is world-frame, ``omega`` rig-frame.  ``covariance`` is the 6x6 pose
    covariance in geometry's SE(3) convention (left perturbation, ``[rho, phi]``);
    ``decoupled_covariance`` the same over ``[position error, world-frame rotation error]``,
    computed on first use.  ``calibration_sensitivity`` (6 x 4N, rows ``[rho, phi]``) is
    the part of the pose error that is the calibration's, per unit error of each
    accelerometer's ``[bias, gain * axis]`` (None without a calibration covariance): every
    estimate made with one calibration shares that error, which a consumer combining
    several of them (``uma eval accel-rig``'s NEES band) must count once.
    """

    t: float
    position: Array
    quaternion: Array
    velocity: Array
    omega: Array
    covariance: Array
    calibration_sensitivity: Array | None = None

    @classmethod
    def _of(cls, t: float, position: Array, quaternion: Array, velocity: Array, omega: Array,
            covariance: Array, calibration_sensitivity: Array | None) -> Estimate:
        """``Estimate(...)`` for the dead reckoner's per-sample path: a frozen dataclass's
        ``__init__`` sets each field through ``object.__setattr__``, which costs a tenth of
        a compiled update; this fills the same fields at once."""
        e = object.__new__(cls)
        e.__dict__.update(t=t, position=position, quaternion=quaternion, velocity=velocity,
                          omega=omega, covariance=covariance,
                          calibration_sensitivity=calibration_sensitivity)
        return e

    @cached_property
    def decoupled_covariance(self) -> Array:
        return geo.se3_to_decoupled(self.position, self.covariance)


class _DivergedError(ValueError):
    """A step whose result is no longer a dead-reckoned state (see ``_divergence``)."""


class _State(NamedTuple):
    """One committed integrator state.  Never mutated, so keeping a reference is a snapshot:
    a late reset restarts from the state at its own time, a refused one changes nothing."""

    t: float  # motion time, s
    p: list[float]  # plain floats: the step's arithmetic is on them (see ``_step``)
    q: list[float]  # xyzw
    v: list[float]  # world frame
    w: list[float]  # rig frame
    P: Array  # (12, 12) covariance of [phi, rho, dv, domega] from the reading noise
    S: Array  # (12, 4N) sensitivity of that error to the calibration parameters
    D: Array  # (12,) the tilt's second-order error, one persistent draw (``_second_order``)


_Sample = tuple[float, list[float]]  # (motion time, projected readings)


class DeadReckoner:
    """Step-by-step inertial integrator: ``reset(...)`` with an absolute pose, then
    ``update(t, accel)`` for every sample.

    ``rate_hz`` is the nominal sample rate; it scales the per-sample noise variance.

    Every call either succeeds or raises ``ValueError`` naming the input and the reason,
    and the state stays usable: a refused reset leaves it as it was; a sample whose step
    diverges (non-finite, beyond ``MAX_OMEGA_RAD_S`` or ``MAX_VARIANCE``) is kept for
    replay, but the pose is dropped (``initialised`` turns False) until the next reset,
    which then starts like the first one.
    """

    def __init__(self, calibration: Calibration, rate_hz: float = 300.0,
                 gravity: Array = GRAVITY):
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise InvalidInputError(f"dead reckoner: rate_hz must be positive, got {rate_hz!r}")
        self.calibration = calibration
        self.layout = calibration.layout
        self.rate_hz = float(rate_hz)
        self.gravity = np.asarray(gravity, float)
        self._gravity = self.gravity.tolist()
        n = self.layout.count
        self._cal_cov = calibration_covariance(calibration)  # (4N, 4N) or None
        # d(f, wd)/d(readings) per unit calibration error: G / k (a bias error dB_j and a
        # gain*axis error dm_j make the reading error ([1, f] / k_j) . [dB_j, dm_j])
        gk = self.layout.readings_jacobian / calibration.gain_v_per_mps2
        self._gk_cols = list(zip(*gk[:3].tolist(), strict=True))  # rows 0:3, by reading
        self._AB, self._AB_INDEX = _error_dynamics_layout(gk)
        self._gk = gk
        # the reading noise in units of G / k: B diag(std^2) B^T = Bk diag((k std)^2) Bk^T
        self._noise_var_k = calibration.accel_var(rate_hz) * calibration.gain_v_per_mps2**2
        self._consts = _native_constants(self.layout.correction_matrix, gk, self._noise_var_k,
                                         self.rate_hz, self.gravity, calibration.param_cov)
        self._samples: list[_Sample] = []  # the last 3, for the next step's parabola
        keep = max(4, math.ceil(HISTORY_S * rate_hz))
        # recent samples and the states after them, so that a reset arriving late is applied
        # at its own time (with the velocities of that time) and the samples since replayed
        self._history: deque[_Sample] = deque(maxlen=keep)
        self._states: deque[_State] = deque(maxlen=2 * keep)  # resets add states too
        self._x: _State | None = None
        self._rest = _State(0.0, [0.0] * 3, [0.0, 0.0, 0.0, 1.0], [0.0] * 3, [0.0] * 3,
                            np.zeros((12, 12)), np.zeros((12, 4 * n)), np.zeros(12))

    # ------------------------------------------------------------------ state

    @property
    def initialised(self) -> bool:
        """True while there is a pose: after a reset, until the dead reckoning diverges."""
        return self._x is not None

    def reset(self, t: float, position: Array, quaternion: Array,
              covariance: Array | None = None, velocity: Array | None = None,
              velocity_cov: Array | None = None, omega: Array | None = None,
              omega_cov: Array | None = None) -> None:
        """Restart from an absolute pose at motion time ``t`` (seconds).

        ``covariance`` is the pose's 6x6 covariance in geometry's convention (None: exact).
        Velocity (world) and angular velocity (rig frame) keep the estimate the integrator
        had at time ``t`` when not given (with their covariance and calibration
        sensitivity); at the first reset they start at zero (a rig at rest, as in §4.3.1).
        A pose older than the newest sample (it travelled through the network) is applied
        at its own time and the samples since are integrated again; one older than the
        kept ``HISTORY_S`` of samples, or more than that ahead of the newest, is refused,
        and so is one whose replay diverges (then nothing changes).
        """
        t = float(t)
        if not math.isfinite(t):
            raise InvalidInputError(f"reset: time must be finite, got {t!r}")
        self._check_reset_time(t)
        p = geo.check_vector(position, "reset position").reshape(3).tolist()
        q = geo.check_quaternion(quaternion, "reset quaternion").reshape(4).tolist()
        C = np.zeros((6, 6)) if covariance is None else \
            geo.check_covariance(covariance, "reset covariance")
        rates = {name: _checked_rate(name, value, cov) for name, value, cov in
                 (("velocity", velocity, velocity_cov), ("omega", omega, omega_cov))}
        kept = len(self._states)  # the states up to t stay, the later ones are replaced
        while kept and self._states[kept - 1].t > t:
            kept -= 1
        upto = [s for s in self._history if s[0] <= t][-3:]
        after = [s for s in self._history if s[0] > t]
        try:
            base = self._base_at(t, kept, upto, after, rates)
            x = _reset_state(base, t, p, q, C, rates, self._start_noise(q))
            states, window = [x], upto
            for sample in after:
                window = [*window[-2:], sample]
                x = self._step(x, window, sample[0])
                states.append(x)
        except _DivergedError as exc:
            raise InvalidInputError(f"reset at t={t:.3f} s refused: replaying the {len(after)} "
                                    f"samples since it diverged {exc}") from None
        while len(self._states) > kept:
            self._states.pop()
        self._states.extend(states)
        self._x, self._samples = x, window

    def _check_reset_time(self, t: float) -> None:
        if not self._history:
            return
        first, last = self._history[0][0], self._history[-1][0]
        if t < first and len(self._history) == self._history.maxlen:
            raise InvalidInputError(f"reset: pose time {t:.3f} s is older than the kept samples "
                                    f"(from {first:.3f} s); it cannot be replayed")
        if t > last + HISTORY_S:
            raise InvalidInputError(
                f"reset: pose time {t:.3f} s is {t - last:.3f} s after the newest "
                f"sample ({last:.3f} s); the clocks of poses and samples disagree")

    def _base_at(self, t: float, kept: int, upto: list[_Sample], after: list[_Sample],
                 rates: dict[str, tuple[Array, Array] | None]) -> _State:
        """The state whose velocities a reset at ``t`` keeps: the newest one not after
        ``t``, stepped on to ``t`` when a sample after ``t`` allows it (a late reset); the
        oldest kept one if all are newer; the rig at rest when there is no pose."""
        if self._x is None:
            return self._rest
        if not kept:
            return self._states[0] if self._states else self._x
        base = self._states[kept - 1]
        if base.t < t and after and any(r is None for r in rates.values()):
            base = self._step(base, [*upto[-2:], after[0]], t)
        return base

    def _start_noise(self, q: list[float]) -> Array:
        """The 6x6 covariance of ``[dv, domega]`` that the readings at and before a reset's
        time leave in the dead reckoning that starts there (world-frame dv at orientation
        ``q``): ``START_NOISE_WEIGHT`` of one sample's noise (see there)."""
        B = np.vstack([geo.quat_to_matrix(np.asarray(q)) @ self._gk[:3], self._gk[3:]])
        return (START_NOISE_WEIGHT / self.rate_hz**2) * (B * self._noise_var_k) @ B.T

    def estimate(self) -> Estimate:
        """The current state and its pose covariance (geometry convention)."""
        x = self._x
        if x is None:
            raise InvalidInputError("dead reckoner: no pose; reset it with an absolute pose first")
        native = NATIVE
        if native is None:
            C, S = self._pose_covariance(x)
            return Estimate._of(x.t, np.array(x.p), np.array(x.q), np.array(x.v),
                                np.array(x.w), C, S)
        # one buffer for the four vectors: a fresh array and four views of it cost half of
        # four arrays made from lists
        vec, C = np.empty(13), np.empty((6, 6))
        S = None if self._cal_cov is None else np.empty((6, x.S.shape[1]))
        native.estimate(self._consts, x, vec, C, S)
        return Estimate._of(x.t, vec[0:3], vec[3:7], vec[7:10], vec[10:13], C, S)

    def _pose_covariance(self, x: _State) -> tuple[Array, Array | None]:
        """The pose's 6x6 covariance (symmetrised) and the pose rows of ``S`` (None
        without a calibration covariance); the compiled step's ``estimate`` computes the same."""
        C = x.P.take(_POSE_FLAT).reshape(6, 6)  # [phi, rho] -> [rho, phi]
        S = None
        if self._cal_cov is not None:  # the pose rows of _full_covariance only
            S = x.S[_POSE_ORDER]
            C = S @ self._cal_cov @ S.T + C
        d = x.D[_POSE_ORDER]
        C = C + np.multiply.outer(d, d)
        return (C + C.T) * 0.5, S

    def state_covariance(self) -> Array:
        """Full 12x12 covariance of ``[phi, rho, dv, domega]`` (noise + calibration)."""
        if self._x is None:
            raise InvalidInputError("dead reckoner: no pose; reset it with an absolute pose first")
        return self._full_covariance(self._x).copy()

    def _full_covariance(self, x: _State) -> Array:
        P = x.P + np.multiply.outer(x.D, x.D)
        if self._cal_cov is None:
            return P
        return P + x.S @ self._cal_cov @ x.S.T

    # ------------------------------------------------------------------ integration

    def update_volts(self, t: float, volts: Array) -> Estimate | None:
        """``update`` for raw voltages, converted (and validated) by the calibration."""
        return self._update(t, self.calibration.to_accel_floats(volts))

    def update(self, t: float, accel: Array) -> Estimate | None:
        """Integrate up to the sample taken at time ``t`` with accelerations ``accel`` (N,).

        Returns the estimate at motion time ``t - latency_s``, or None without a pose.
        NaN or wrongly sized samples and non-increasing times are refused without touching
        the state.  A step that diverges drops the pose (the sample is kept for replay) and
        raises ``ValueError`` saying so.
        """
        a = np.asarray(accel, dtype=float)
        if a.shape != (self.layout.count,):
            raise InvalidInputError(f"accelerometer sample: expected {self.layout.count} values, "
                                    f"got shape {a.shape}")
        vals = a.tolist()
        if not all(map(math.isfinite, vals)):
            j = next(j for j, x in enumerate(vals) if not math.isfinite(x))
            raise InvalidInputError(f"accelerometer sample at t={t!r}: accelerometer {j + 1} is "
                                    f"{vals[j]} (NaN samples are refused)")
        return self._update(t, vals)

    def _update(self, t: float, accel: list[float]) -> Estimate | None:
        """``update`` of a sample its caller has validated (N finite floats)."""
        tm = float(t) - self.calibration.latency_s
        if not math.isfinite(tm):
            raise InvalidInputError(f"accelerometer sample: time must be finite, got {t!r}")
        if self._samples and tm <= self._samples[-1][0]:
            raise InvalidInputError(
                f"accelerometer sample at t={t!r} is not after the previous "
                f"one (t={self._samples[-1][0] + self.calibration.latency_s!r})")
        sample = (tm, self.layout.project_floats(accel))
        self._samples = [*self._samples[-2:], sample]
        self._history.append(sample)
        if self._x is None:
            return None
        if tm > self._x.t:
            try:
                x = self._step(self._x, self._samples, tm)
            except _DivergedError as exc:
                self._x = None
                self._states.clear()
                raise InvalidInputError(f"accelerometer sample at t={t!r}: the dead reckoning "
                                        f"diverged {exc}; no pose until the next reset") from None
            self._x = x
            self._states.append(x)
        return self.estimate()

    def _step(self, x: _State, samples: list[_Sample], t1: float) -> _State:
        """One RK4 step of the coupled (q, omega, v, p) ODE from ``x`` to ``t1`` and its
        error propagation, the readings interpolated over ``samples``; ``_DivergedError`` if
        the result is no dead-reckoned state any more.  Compiled (``NATIVE.step``) or in
        Python (``_step_python``): the same operations, the same result to float rounding."""
        native = NATIVE
        if native is None:
            p, q, v, w, norm, P, S, D = self._step_python(x, samples, t1)
            variances = P.diagonal().tolist()
            reason = _divergence(norm, w, sum(variances), max(variances))
        else:
            P, D = np.empty((12, 12)), np.empty(12)
            S = x.S if self._cal_cov is None else np.empty_like(x.S)
            p, q, v, w, norm, total, largest, fine = native.step(self._consts, x, samples, t1,
                                                                 P, S, D)
            reason = "" if fine else _divergence(norm, w, total, largest)
        if reason:
            raise _DivergedError(f"at t={t1:.3f} s: {reason}")
        return _State(t1, p, q, v, w, P, S, D)

    def _step_python(self, x: _State, samples: list[_Sample], t1: float) -> \
            tuple[list[float], list[float], list[float], list[float], float, Array, Array, Array]:
        """``_step`` before its divergence check: the new p, q (normalised unless its norm
        is 0), v, omega, the norm of q before normalising, and the new P, S and D.

        The 3- and 4-vectors are Python floats: a numpy call on them costs more than the
        arithmetic (see "small-vector arithmetic" below); the matrices stay numpy."""
        t0 = x.t
        h = t1 - t0
        hh = 0.5 * h
        x0, xm, x1 = _interpolate(samples, (t0, t0 + hh, t1))
        solve = self.layout.solve_floats  # [f, omega_dot] of a sample's readings at omega
        # omega stages (omega_dot depends on omega through the centripetal terms only)
        w0 = x.w
        s1 = solve(x0, w0)
        w2 = [w0[0] + hh * s1[3], w0[1] + hh * s1[4], w0[2] + hh * s1[5]]
        s2 = solve(xm, w2)
        w3 = [w0[0] + hh * s2[3], w0[1] + hh * s2[4], w0[2] + hh * s2[5]]
        s3 = solve(xm, w3)
        w4 = [w0[0] + h * s3[3], w0[1] + h * s3[4], w0[2] + h * s3[5]]
        s4 = solve(x1, w4)
        q1, q2, q3, q4 = _quaternion_rk4(x.q, (w0, w2, w3, w4), h)
        # velocity / position stages: v' = R(q) f + g, p' = v
        R2 = _rotation(q2)
        g = self._gravity
        a1, a2 = _rotate(x.q, s1), _mat_vec(R2, s2)
        a3, a4 = _rotate(q3, s3), _rotate(q4, s4)
        spread = _second_order(self._tilt_covariance(x), a2)
        h6, hh6 = h / 6.0, h * h / 6.0
        p0, v0 = x.p, x.v
        p1, v1, w1 = [], [], []
        for i in range(3):
            gi = g[i]
            p1.append(p0[i] + h * v0[i] + hh6 * ((a1[i] + gi) + (a2[i] + gi) + (a3[i] + gi)))
            v1.append(v0[i] + h6 * ((a1[i] + gi) + 2.0 * (a2[i] + gi) + 2.0 * (a3[i] + gi)
                                    + (a4[i] + gi)))
            w1.append(w0[i] + h6 * (s1[3 + i] + 2.0 * s2[3 + i] + 2.0 * s3[3 + i] + s4[3 + i]))
        P, S, D = self._propagate(x, h, R2, s2, w2,
                                  [0.5 * (p1[0] + p0[0]), 0.5 * (p1[1] + p0[1]),
                                   0.5 * (p1[2] + p0[2])],
                                  [0.5 * (v1[0] + v0[0]), 0.5 * (v1[1] + v0[1]),
                                   0.5 * (v1[2] + v0[2])], spread)
        a, b, c, d = q1
        norm = math.sqrt(a * a + b * b + c * c + d * d)
        if norm:  # else the divergence check refuses the state
            q1 = [a / norm, b / norm, c / norm, d / norm]
        return p1, q1, v1, w1, norm, P, S, D

    def _tilt_covariance(self, x: _State) -> Array:
        """The 3x3 covariance of the orientation error phi (reading noise and
        calibration; the block of ``_full_covariance``)."""
        C = x.P[0:3, 0:3]
        if self._cal_cov is None:
            return C
        S = x.S[0:3]
        return S @ self._cal_cov @ S.T + C

    def _propagate(self, x: _State, h: float, R: list[float], f: list[float],
                   w: list[float], p: list[float], v: list[float],
                   spread: list[float]) -> tuple[Array, Array, Array]:
        """Error-state propagation of ``x.P``, ``x.S`` and ``x.D`` over one step,
        linearised at the step's midpoint (``R`` row-major, 9 floats).

        phi' = R domega;  rho' = dv + [p]x R domega + [v]x phi  (rho = dp - phi x p);
        dv' = -[R f]x phi + R df (+ ``spread`` in D, see ``_second_order``);
        domega' = d(omega_dot).
        """
        P, S = x.P, x.S
        J = self.layout.omega_jacobian_floats(w)  # d(f, wd)/d(omega)
        r0, r1, r2 = R[0:3], R[3:6], R[6:9]
        # A and the rows 6:9 of Bk = d(state error)/d(readings) / k (R G[:3] / k) as floats,
        # in the order of _error_dynamics_layout; one put fills the numpy matrix [A | Bk]
        AB = self._AB.copy()
        cols = self._gk_cols
        AB.put(self._AB_INDEX, _dynamics_entries(R, f, w=J, p=p, v=v)
               + [a * r0[0] + b * r0[1] + c * r0[2] for a, b, c in cols]
               + [a * r1[0] + b * r1[1] + c * r1[2] for a, b, c in cols]
               + [a * r2[0] + b * r2[1] + c * r2[2] for a, b, c in cols])
        Ah = AB[:, :12] * h
        Bk = AB[:, 12:]
        F = _I12 + Ah + 0.5 * (Ah @ Ah)
        P = F @ P @ F.T + (Bk * (self._noise_var_k * (h / self.rate_hz))) @ Bk.T
        if self._cal_cov is not None:  # a calibration error is a reading error ([1, f]/k)
            S = F @ S + np.multiply.outer(Bk, [h, h * f[0], h * f[1], h * f[2]]).reshape(12, -1)
        D = F @ x.D
        D[6:9] += [h * spread[0], h * spread[1], h * spread[2]]
        return P, S, D


def _second_order(C: Array, u: list[float]) -> list[float]:
    """The orientation error's second-order effect on the acceleration over a step, as
    what drives ``_State.D``: ``u``'s direction times the root mean square of the effect
    along it, from the covariance ``C`` of the orientation error phi and the estimate's
    world-frame specific force ``u`` (the step's midpoint).

    The linear propagation takes the truth's specific force as u + phi x u, linearised at
    the estimate's own u.  Rotating u by phi changes its component along u by
    -|u| (1 - cos|phi|) |phi_perp|^2 / |phi|^2, about -|u| |phi_perp|^2 / 2 (phi_perp the
    tilt across u): a rig at rest whose estimate is tilted sinks by g (1 - cos|tilt|)
    whatever the tilt's sign.  The linear part cannot hold that, and worse, linearised at
    the tilted u it expects, given the horizontal error, a sink of g |tilt|^2, twice the
    real one.  So the covariance carries the term about zero (its mean squared plus its
    variance): honest for the height given the other five components, where the gap
    lies, without moving the estimate, which moving by the mean would put further from
    the truth after a start with a large orientation uncertainty.

    Along u, a tilt about each principal axis i of C_perp (eigenvalue l_i) contributes
    1 - cos(phi_i), of mean 1 - exp(-l_i / 2) and variance (1 - exp(-l_i))^2 / 2; the two
    added as independent give the second moment (sum of means)^2 + sum of variances,
    times |u|^2: exact to fourth order in phi (there it is (tr C_p)^2 / 4 + tr(C_p^2) / 2,
    a Gaussian quadratic form's), and bounded (by sqrt(5) |u|) however large C.  Across u the
    second-order terms, (phi . u) phi_perp / 2, sit beside first-order ones larger by
    1 / |phi|: left out."""
    u_ = np.asarray(u, float)
    uu = float(u_ @ u_)
    if uu == 0.0:  # no specific force: no second-order term
        return [0.0, 0.0, 0.0]
    perp = np.eye(3) - np.multiply.outer(u_, u_) / uu
    M = perp @ C @ perp
    return (_along_rms(float(np.trace(M)), float((M * M).sum())) * u_).tolist()


def _along_rms(t: float, q: float) -> float:
    """``_second_order``'s root mean square per unit |u|, from the trace ``t`` and the
    sum of squares ``q`` of C_perp (its two eigenvalues t / 2 +- sqrt(q / 2 - t^2 / 4))."""
    d = math.sqrt(max(0.5 * q - 0.25 * t * t, 0.0))
    lam = (max(0.5 * t + d, 0.0), max(0.5 * t - d, 0.0))
    mean = sum(-math.expm1(-0.5 * x) for x in lam)
    var = sum(0.5 * math.expm1(-x) ** 2 for x in lam)
    return math.sqrt(mean * mean + var)


def _native_constants(corr: Array, gk: Array, noise_var_k: Array, rate_hz: float,
                      gravity: Array, param_cov: Array | None) -> Array:
    """The constants of a dead reckoner as the compiled step reads them, in one float64
    array: ``[N, rate_hz, MAX_OMEGA_RAD_S^2, MAX_VARIANCE, gravity, corr, gk, noise_var_k]``
    and, with a calibration covariance, its N 4x4 blocks (the layout is described in
    ``_step.c``)."""
    parts = [[gk.shape[1], rate_hz, MAX_OMEGA_RAD_S**2, MAX_VARIANCE], gravity, corr, gk,
             noise_var_k]
    if param_cov is not None:
        parts.append(param_cov)
    return np.concatenate([np.asarray(part, float).ravel() for part in parts])


#: the compiled step in use (tests set it to None to run the pure-Python one)
NATIVE: Any = compiled_twin("services.accel_rig._step", "UMA_ACCEL_PURE_PYTHON")


def _checked_rate(name: str, value: Array | None, cov: Array | None) -> \
        tuple[list[float], Array] | None:
    """A reset's velocity or angular velocity and its 3x3 covariance (zero when not
    given), or None when the reset does not set it."""
    if value is None:
        if cov is not None:
            raise InvalidInputError(f"reset: {name} covariance given without a {name}")
        return None
    v = geo.check_vector(value, f"reset {name}").reshape(3)
    if name == "omega" and float(v @ v) > MAX_OMEGA_RAD_S**2:
        raise InvalidInputError(f"reset omega: {math.sqrt(v @ v):.4g} rad/s is beyond the "
                                f"{MAX_OMEGA_RAD_S:g} rad/s a head-mounted rig can measure")
    C = np.zeros((3, 3)) if cov is None else \
        geo.check_covariance(cov, f"reset {name} covariance", dim=3)
    if float(C.max(initial=0.0)) > MAX_VARIANCE:
        raise InvalidInputError(f"reset {name} covariance: variance {C.max():.3g} is beyond "
                                f"{MAX_VARIANCE:g} (no information)")
    return v.tolist(), C


def _reset_state(base: _State, t: float, p: list[float], q: list[float], C: Array,
                 rates: dict[str, tuple[list[float], Array] | None],
                 start_noise: Array) -> _State:
    """The state right after a reset: the absolute pose with its covariance; each rate
    given with its own covariance plus its block of ``start_noise`` (the readings' noise
    the first steps integrate from before the reset; ``DeadReckoner._start_noise``), or
    kept from ``base`` with its covariance, cross-covariance with the other kept rate and
    calibration sensitivity (the new pose is independent of the old estimate)."""
    P = np.zeros_like(base.P)
    S = np.zeros_like(base.S)
    D = np.zeros_like(base.D)
    P[3:6, 3:6], P[0:3, 0:3] = C[:3, :3], C[3:, 3:]
    P[0:3, 3:6], P[3:6, 0:3] = C[3:, :3], C[:3, 3:]
    values, kept, fresh = {}, [], []
    for name, sl, current in (("velocity", slice(6, 9), base.v), ("omega", slice(9, 12), base.w)):
        given = rates[name]
        if given is None:
            values[name] = current
            kept.append(sl)
        else:
            values[name], P[sl, sl] = given
            fresh.append(sl)
    for a in fresh:
        for b in fresh:
            P[a, b] += start_noise[a.start - 6:a.stop - 6, b.start - 6:b.stop - 6]
    for a in kept:
        for b in kept:
            P[a, b] = base.P[a, b]
        S[a] = base.S[a]
        D[a] = base.D[a]
    return _State(t, p, q, values["velocity"], values["omega"], P, S, D)


def _divergence(q_norm: float, w: list[float], var_sum: float, var: float) -> str:
    """Why a stepped state is no dead-reckoned state any more ('' when it still is), from
    the norm of its quaternion, its omega and the sum and largest of its variances (the
    diagonal of ``P``).  The compiled step makes the same tests, and calls this only to
    word a divergence it found.

    A NaN or an overflow anywhere in the step reaches the diagonal of ``P``: the stage
    rotations and specific force and the midpoint position and velocity all enter F."""
    x, y, z = w
    ww = x * x + y * y + z * z
    if not math.isfinite(var_sum + ww + q_norm):
        return "to non-finite values"
    if q_norm < 1e-6:
        return "to a zero quaternion"
    if ww > MAX_OMEGA_RAD_S**2:
        return (f"to an angular velocity of {math.sqrt(ww):.4g} rad/s (beyond "
                f"{MAX_OMEGA_RAD_S:g} rad/s)")
    if var > MAX_VARIANCE:
        return f"to a variance of {var:.3g} (beyond {MAX_VARIANCE:g})"
    return ""


def _interpolate(samples: list[_Sample], taus: tuple[float, ...]) -> list[list[float]]:
    """Projected readings (``layout.project``) at motion times ``taus``, one list of 6 per
    tau, by Lagrange interpolation over ``samples``: the parabola through the last three
    (written out), the line or the constant through fewer (the first two samples).  At a
    sample's own time (where a step starts and ends) the weights are exactly 0, 1, 0, so
    that sample's readings are returned as they are: the floats the products would give."""
    if len(samples) < 3:
        return [_lagrange_few(samples, tau) for tau in taus]
    (ta, xa), (tb, xb), (tc, xc) = samples
    dab, dac, dbc = ta - tb, ta - tc, tb - tc
    out = []
    for tau in taus:
        if tau in (tb, tc):
            out.append(xb if tau == tb else xc)
            continue
        ua, ub, uc = tau - ta, tau - tb, tau - tc
        wa, wb, wc = ub * uc / (dab * dac), -ua * uc / (dab * dbc), ua * ub / (dac * dbc)
        out.append([wa * a + wb * b + wc * c for a, b, c in zip(xa, xb, xc, strict=True)])
    return out


def _lagrange_few(samples: list[_Sample], tau: float) -> list[float]:
    """``_interpolate`` at ``tau`` over one sample (its readings) or two (their line)."""
    if len(samples) == 1:
        return list(samples[0][1])
    (ta, xa), (tb, xb) = samples
    wa, wb = (tau - tb) / (ta - tb), (tau - ta) / (tb - ta)
    return [wa * a + wb * b for a, b in zip(xa, xb, strict=True)]


# ---------------------------------------------------------------------- small-vector arithmetic
# On Python floats, written out: at 3 and 4 values a numpy call costs more than the
# arithmetic, and so do Python's generators and helper calls (the step runs 300 times a
# second).  Rotations are row-major 9-lists, quaternions xyzw.


def _quaternion_rk4(q0: list[float], ws: tuple[list[float], ...], h: float) -> \
        tuple[list[float], ...]:
    """RK4 of eq. 4.45, q' = q (x) [omega, 0] / 2 (geometry's Hamilton product, xyzw), with
    the omega of each stage: the end quaternion (not normalised) and those of stages 2-4."""
    x0, y0, z0, s0 = q0
    x, y, z, s = q0
    stages, k = [], []
    for i, (a, b, c) in enumerate(ws):
        kx, ky, kz = 0.5 * (s * a + y * c - z * b), 0.5 * (s * b + z * a - x * c), \
            0.5 * (s * c + x * b - y * a)
        ks = -0.5 * (x * a + y * b + z * c)
        k.append((kx, ky, kz, ks))
        if i < 3:
            d = h if i == 2 else 0.5 * h
            x, y, z, s = x0 + d * kx, y0 + d * ky, z0 + d * kz, s0 + d * ks
            stages.append([x, y, z, s])
    h6 = h / 6.0
    (a1, b1, c1, d1), (a2, b2, c2, d2), (a3, b3, c3, d3), (a4, b4, c4, d4) = k
    end = [x0 + h6 * (a1 + 2.0 * a2 + 2.0 * a3 + a4), y0 + h6 * (b1 + 2.0 * b2 + 2.0 * b3 + b4),
           z0 + h6 * (c1 + 2.0 * c2 + 2.0 * c3 + c4), s0 + h6 * (d1 + 2.0 * d2 + 2.0 * d3 + d4)]
    return (end, *stages)


def _rotation(q: list[float]) -> list[float]:
    """R(q / |q|), row-major, for a quaternion an RK4 stage has moved off the unit sphere."""
    x, y, z, s = q
    xx, yy, zz, ss = x * x, y * y, z * z, s * s
    n = 1.0 / (xx + yy + zz + ss)
    xy, xz, yz, xs, ys, zs = 2 * x * y, 2 * x * z, 2 * y * z, 2 * x * s, 2 * y * s, 2 * z * s
    return [n * (ss + xx - yy - zz), n * (xy - zs), n * (xz + ys),
            n * (xy + zs), n * (ss - xx + yy - zz), n * (yz - xs),
            n * (xz - ys), n * (yz + xs), n * (ss - xx - yy + zz)]


def _rotate(q: list[float], v: list[float]) -> list[float]:
    """R(q / |q|) v (the first 3 of ``v``) without forming R:
    q v q* = (s^2 - |u|^2) v + 2 (u.v) u + 2 s (u x v), divided by |q|^2."""
    x, y, z, s = q
    a, b, c = v[0], v[1], v[2]
    uu = x * x + y * y + z * z
    n = 1.0 / (uu + s * s)
    k = s * s - uu
    d = 2.0 * (x * a + y * b + z * c)
    s2 = 2.0 * s
    return [n * (k * a + d * x + s2 * (y * c - z * b)),
            n * (k * b + d * y + s2 * (z * a - x * c)),
            n * (k * c + d * z + s2 * (x * b - y * a))]


def _mat_vec(R: list[float], v: list[float]) -> list[float]:
    """R v for a row-major 3x3 ``R`` and the first 3 of ``v``."""
    a, b, c = v[0], v[1], v[2]
    return [R[0] * a + R[1] * b + R[2] * c, R[3] * a + R[4] * b + R[5] * c,
            R[6] * a + R[7] * b + R[8] * c]


def _dynamics_entries(R: list[float], f: list[float], w: list[tuple[float, float, float]],
                      p: list[float], v: list[float]) -> list[float]:
    """The step-dependent entries of the error dynamics A (``_propagate``) in the order of
    ``_error_dynamics_layout``: R; [v]x; [p]x R; -[R f]x; R J[:3]; J[3:], where J (``w``)
    is d(f, omega_dot)/d(omega).  Written out: at 3x3, Python's loops would cost more than
    the products."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
    px, py, pz = p
    vx, vy, vz = v
    ux, uy, uz = _mat_vec(R, f)
    (j00, j01, j02), (j10, j11, j12), (j20, j21, j22) = w[0], w[1], w[2]
    return [r00, r01, r02, r10, r11, r12, r20, r21, r22,
            -vz, vy, vz, -vx, -vy, vx,
            py * r20 - pz * r10, py * r21 - pz * r11, py * r22 - pz * r12,
            pz * r00 - px * r20, pz * r01 - px * r21, pz * r02 - px * r22,
            px * r10 - py * r00, px * r11 - py * r01, px * r12 - py * r02,
            uz, -uy, -uz, ux, uy, -ux,
            r00 * j00 + r01 * j10 + r02 * j20, r00 * j01 + r01 * j11 + r02 * j21,
            r00 * j02 + r01 * j12 + r02 * j22,
            r10 * j00 + r11 * j10 + r12 * j20, r10 * j01 + r11 * j11 + r12 * j21,
            r10 * j02 + r11 * j12 + r12 * j22,
            r20 * j00 + r21 * j10 + r22 * j20, r20 * j01 + r21 * j11 + r22 * j21,
            r20 * j02 + r21 * j12 + r22 * j22,
            *w[3], *w[4], *w[5]]


def calibration_covariance(cal: Calibration) -> Array | None:
    """Block-diagonal (4N, 4N) covariance of the calibration parameters ``[bias,
    gain * axis]`` per accelerometer (the ``c`` of ``Estimate.calibration_sensitivity``),
    or None."""
    if cal.param_cov is None:
        return None
    n = cal.layout.count
    out = np.zeros((4 * n, 4 * n))
    for j in range(n):
        out[4 * j:4 * j + 4, 4 * j:4 * j + 4] = cal.param_cov[j]
    return out


def dead_reckon_from_truth(calibration: Calibration, t: Array, accel: Array,
                           truth: KinematicState, rate_hz: float) -> list[Estimate]:
    """Reset to the exact state of the first sample, then integrate every later sample.

    ``truth`` holds the rig's kinematics at the samples' motion times (as
    ``SimulatedRun.truth``); returns one estimate per sample, the first being the reset.
    This is how the tests and ``uma eval accel-rig`` measure the drift of §4.3 alone.
    """
    dr = DeadReckoner(calibration, rate_hz)
    dr.reset(truth.t[0], truth.position[0], truth.quaternion[0],
             velocity=truth.velocity[0], omega=truth.omega_body[0])
    dr.update(t[0], accel[0])
    out = [dr.estimate()]
    out.extend(dr.update(t[k], accel[k]) for k in range(1, len(t)))
    return out
