"""MARVIN's fusion filter: an error-state EKF with SCAAT updates (seed 003 ch. 6, seed 000 §4.6.2).

State (eq. 6.1) of the *head* frame: orientation ``q`` (head in world, xyzw), body angular
velocity ``omega`` and acceleration ``omega_dot`` (head axes), position ``p``, velocity
``v`` and acceleration ``alpha`` (world); then one residual bias per accelerometer (SCAAT's
autocalibration, seed 003 appendix B.3) and three optional Gauss-Markov triples: the
optical tracker's persistent position error, and the linear and angular jerk, which make
the motion model smooth at the 300 Hz step and random over a quarter second, as heads move
(``FusionConfig`` says why eq. 6.1's white jerk alone cannot be both).

Where and why the model has its own form instead of filterpy's ``ExtendedKalmanFilter``:

* The quaternion cannot take an additive correction ``x + K y``.  The filter keeps it
  outside the covariance, as SCAAT keeps its "external quaternion" (appendix B.3, eqs.
  B.30-B.32): the covariance is over the 3-vector ``dtheta`` of the world-frame (left)
  rotation error ``q_true = Exp(dtheta) q`` (geometry's convention), each update injects
  ``Exp(dtheta) q`` and zeroes ``dtheta``.
* SCAAT updates are scalar (one accelerometer, eq. 6.13): ``S`` is a number, so there is
  no matrix inverse, each reading is gated on its own and applied at its own time; the
  whole cost is a few 24-vector products (``bench/bench_fusion.py`` compares it with one
  6-D filterpy update per sample: about the same speed, both far above 3000 updates/s).
* The time update (eq. 6.2-6.5) integrates the quaternion on the manifold.

filterpy provides the white part of the process noise: ``Q_continuous_white_noise`` for
the (angle, rate, acceleration) and (position, velocity, acceleration) chains.

The static mountings (head -> accelerometer rig, head -> laser rig) are inputs
(``AccelModel.from_layout``, the ``mount`` of ``update_rig_pose``), which callers take from
the SRG's static edges; the filter has no geometry constants of its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from filterpy.common import Q_continuous_white_noise

from agent.srg import geometry as geo
from services.sim.trajectory import GRAVITY

Array = np.ndarray

TH, W, WD, P, V, A = (slice(3 * i, 3 * i + 3) for i in range(6))
CORE = 18

#: chi-square quantiles used as gates (99.9 %): a measurement further out is an outlier
CHI2_999 = {1: 10.828, 2: 13.816, 3: 16.266, 6: 22.458}


#: Default extra accelerometer noise (m/s^2, std) for what a calibration does not capture
#: (position errors of the drawing, axis residuals): 0.08 LSB, a quarter of the simulated
#: readings' own noise.  A larger floor only makes the filter conservative in simulation
#: (0.005 put the NEES of seeds 1 and 3 below its 95 % bounds); a real rig's residuals,
#: measured against a reference, may need more.
MODEL_FLOOR = 0.002


@dataclass(frozen=True)
class AccelModel:
    """The accelerometers as the filter sees them: positions and axes in the *head* frame.

    ``from_layout`` moves a rig layout (rig frame) through the head -> rig mounting, which
    comes from the SRG, so eq. 6.13 needs no rig-specific code in the filter.
    """

    positions: Array           # (N, 3) m, head frame
    axes: Array                # (N, 3) unit, head frame
    variance: Array            # (N,) per-sample reading variance (m/s^2)^2
    latency_s: float = 0.0     # a reading at t describes the motion at t - latency_s
    cross: Array = field(init=False, repr=False, compare=False)  # r_j x n_j
    n_dot_r: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        r = geo.check_vector(self.positions, "accelerometer positions")
        n = geo.check_vector(self.axes, "accelerometer axes")
        var = np.asarray(self.variance, float).reshape(-1)
        if r.ndim != 2 or n.shape != r.shape or var.shape != (r.shape[0],):
            raise ValueError(f"accel model: positions {r.shape}, axes {n.shape} and "
                             f"variance {var.shape} must be (N, 3), (N, 3), (N,)")
        if not np.all(np.isfinite(var)) or np.any(var <= 0):
            raise ValueError("accel model: reading variances must be positive and finite")
        if not (math.isfinite(self.latency_s) and self.latency_s >= 0):
            raise ValueError(f"accel model: latency_s must be >= 0, got {self.latency_s!r}")
        object.__setattr__(self, "positions", r)
        object.__setattr__(self, "axes", n / np.linalg.norm(n, axis=1, keepdims=True))
        object.__setattr__(self, "variance", var)
        object.__setattr__(self, "cross", np.cross(r, self.axes))
        object.__setattr__(self, "n_dot_r", np.einsum("ij,ij->i", r, self.axes))

    @property
    def count(self) -> int:
        return self.positions.shape[0]

    @classmethod
    def from_layout(cls, positions_rig: Array, axes_rig: Array,
                    head_to_rig: tuple[Array, Array], variance: Array | float,
                    latency_s: float = 0.0, model_floor: float = 0.0) -> AccelModel:
        """Accelerometers given in the rig frame, rig mounted at ``head_to_rig`` (p, q).

        ``model_floor`` (m/s^2, std) is added to every reading's noise for what the
        calibration does not capture (position errors of the drawing, axis residuals).
        """
        p, q = head_to_rig
        r = geo.transform_points(p, q, np.asarray(positions_rig, float))
        n = geo.quat_rotate(q, np.asarray(axes_rig, float))
        var = np.broadcast_to(np.asarray(variance, float), (r.shape[0],)) + model_floor**2
        return cls(r, n, var, latency_s)


@dataclass(frozen=True)
class FusionConfig:
    """Noise model and behaviour of the filter (SI units)."""

    #: The head's jerk, linear (m/s^3, world axes) and angular (rad/s^3, head axes), as
    #: first-order Gauss-Markov states: std and correlation time (0 std: no such states,
    #: white jerk only, as in eq. 6.1).  Head motion is smooth: over one 300 Hz step its
    #: acceleration barely changes, over a quarter second it is as good as new.  White jerk
    #: alone cannot say both -- tuned for the long scale it lets velocity and angular
    #: velocity diffuse between samples far faster than a head's do (position NEES 0.7-0.9
    #: of 3 in optical gaps), tuned for the short one it holds the acceleration so stiff that
    #: the specific force leaks into the tilt (1 s gap orientation errors up to 20 % larger).
    #: The simulated heads have jerk stds 5.3-6.6 m/s^3 and 9-12 rad/s^3 per axis, with
    #: correlation times 0.21-0.24 s.
    linear_jerk_std: float = 6.0
    linear_jerk_tau_s: float = 0.22
    angular_jerk_std: float = 11.0
    angular_jerk_tau_s: float = 0.23
    #: White jerk on top, (m/s^3)^2/Hz and (rad/s^3)^2/Hz: what the Gauss-Markov jerk misses
    #: (without those states, 2 sigma^2 / tau of the acceleration as in Singer's model: about
    #: 10 and 30 for the simulated heads).  Kept small: with accelerometers this quiet it is
    #: what spreads the position between optical frames, and 0.5 / 1.0 made the position
    #: NEES 2.8 of 3 while tracking and 1.2-2.9 in 1 s gaps (seeds 1-3).
    linear_jerk_psd: float = 0.1
    angular_jerk_psd: float = 0.2
    #: m/s^2 / sqrt(s), accelerometer bias random walk.  The residual bias after the static
    #: calibration is nearly constant (thermal drift only); a faster walk lets the bias
    #: states follow the reading noise between optical frames, and the omega_dot error they
    #: trade it for becomes angular drift in optical gaps (measured on the earlier, noisier
    #: device model, one conversion per reading, with white jerk only and the older, biased
    #: laser calibration: 1e-3 made 1 s gaps end at 1.04 deg RMS over 33 gaps of seeds 1-3,
    #: 1e-4 at 0.97 deg, where the sensor noise alone left about 0.8)
    bias_walk: float = 1e-4
    initial_bias_std: float = 0.05       # m/s^2, residual bias after calibration
    estimate_bias: bool = True
    initial_std: tuple[float, ...] = (3.0, 5.0, 1.0, 2.0, 10.0)  # omega, omega_dot, v, alpha..
    accel_gate: float = CHI2_999[1]
    pose_gate: float = CHI2_999[6]
    dot_gate: float = CHI2_999[2]
    max_rejected_poses: int = 3          # then the optical poses re-initialise the filter
    #: the filter starts from two optical poses at most this far apart (s): their difference
    #: gives the velocity and angular velocity.  From one pose alone the motion is unknown,
    #: and the first tenths of a second of dead reckoning turn a head's 1-2 rad/s into tens
    #: of degrees of tilt, so gravity leaks into the position before a slow or late optical
    #: stream (a busy host) corrects it -- and the gate then refuses every correction.
    start_max_gap_s: float = 0.5
    #: scale the optical covariance's position and rotation blocks so that each block's NIS
    #: averages 3 (see ``_adapt_pose_noise``)
    adapt_pose_noise: bool = True
    pose_noise_rate: float = 0.02        # adaptation gain per optical pose
    #: lowest scale of the optical (position, rotation) covariance: the NIS cannot tell a
    #: tracker that overstates its noise from one whose errors persist from frame to frame
    #: (both make it small), so the optics are never trusted more than twice their claim;
    #: persistent errors belong in ``optical_bias_std``
    pose_noise_min_scale: tuple[float, float] = (0.5, 0.5)
    max_step_s: float = 0.05             # longer predictions are split (integration accuracy)
    #: the optical position error's persistent part (m, per axis; 0: none), a Gauss-Markov
    #: state with correlation time ``optical_bias_tau_s``.  A tracker's calibration error
    #: (camera, screen geometry) stays while the head moves over the same part of the
    #: walls; modelled as white noise it would "average out" over frames, and the fused
    #: position would claim an accuracy the tracker never had.  The simulated laser tracker
    #: needs none (its calibration error is 0.03 mm); a real one's comes from comparing it
    #: with a reference
    optical_bias_std: float = 0.0
    optical_bias_tau_s: float = 30.0

    def __post_init__(self) -> None:
        for name in ("angular_jerk_psd", "linear_jerk_psd", "accel_gate", "pose_gate",
                     "max_step_s", "initial_bias_std", "optical_bias_tau_s",
                     "linear_jerk_tau_s", "angular_jerk_tau_s", "start_max_gap_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"fusion config: {name} must be positive, got {value!r}")
        for name in ("optical_bias_std", "linear_jerk_std", "angular_jerk_std"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"fusion config: {name} must be >= 0, got {value!r}")
        if len(self.initial_std) != 5 or not all(s > 0 for s in self.initial_std):
            raise ValueError("fusion config: initial_std needs 5 positive numbers (omega, "
                             "omega_dot, v, alpha, spare)")


@dataclass(frozen=True)
class OpticalPose:
    """A head pose from the optics, kept to start the filter from (with the next one)."""

    t: float
    p: Array
    q: Array
    cov: Array  # over [dp, dtheta]


@dataclass(frozen=True)
class FilterState:
    """A copy of everything the filter estimates, to rewind to (late measurements)."""

    t: float | None
    q: Array
    x: Array
    P: Array
    rejected_in_row: int
    last_rejected: OpticalPose | None
    last_optical_t: float | None


@dataclass
class FusionStats:
    time_updates: int = 0
    accel_updates: int = 0
    accel_rejected: int = 0
    pose_updates: int = 0
    pose_rejected: int = 0
    dot_updates: int = 0
    dot_rejected: int = 0
    reinitialised: int = 0
    last_pose_nis: float = float("nan")
    #: the adapted scale of the optical covariance's position and rotation blocks
    pose_noise_scale: tuple[float, float] = (1.0, 1.0)

    @property
    def measurement_updates(self) -> int:
        return self.accel_updates + self.pose_updates + self.dot_updates


class FusionEKF:
    """Head pose from accelerometer readings (one at a time) and absolute optical poses."""

    def __init__(self, accel: AccelModel, config: FusionConfig | None = None,
                 gravity: Array = GRAVITY):
        self.config = config or FusionConfig()
        self.accel = accel
        self.gravity = np.asarray(gravity, float)
        cfg = self.config
        self.n_bias = accel.count if cfg.estimate_bias else 0
        # after eq. 6.1's 18: the accelerometer biases, then the optional Gauss-Markov
        # states: the optical position bias, the linear jerk, the angular jerk (3 or none)
        self._ab, self._ob, self._jerk, self._ang_jerk = _consecutive(
            CORE, [self.n_bias, *(3 * (std > 0) for std in (
                cfg.optical_bias_std, cfg.linear_jerk_std, cfg.angular_jerk_std))])
        self.dim = self._ang_jerk.stop
        self.t: float | None = None
        self.q = geo.quat_identity()
        # [dtheta slot (always 0), omega, omega_dot, p, v, alpha, accelerometer biases,
        #  optical bias, linear jerk, angular jerk]
        self.x = np.zeros(self.dim)
        self.P = np.eye(self.dim)
        self.stats = FusionStats()
        self._rejected_in_row = 0
        #: the newest optical pose that was not used: the candidate to start from
        self._last_rejected: OpticalPose | None = None
        self.start_t: float | None = None  # when the filter last (re)started
        self.last_optical_t: float | None = None  # the newest optical measurement it used
        self._R = geo.quat_to_matrix(self.q)
        self._dtheta = np.zeros(3)
        self._step_cache: dict[float, tuple[Array, Array, Array]] = {}

    # ------------------------------------------------------------------ state access

    @property
    def initialised(self) -> bool:
        return self.t is not None

    @property
    def omega(self) -> Array:
        return self.x[W].copy()

    @property
    def omega_dot(self) -> Array:
        return self.x[WD].copy()

    @property
    def position(self) -> Array:
        return self.x[P].copy()

    @property
    def velocity(self) -> Array:
        return self.x[V].copy()

    @property
    def acceleration(self) -> Array:
        return self.x[A].copy()

    @property
    def bias(self) -> Array:
        """The accelerometers' residual biases (m/s^2)."""
        return self.x[self._ab].copy()

    @property
    def optical_bias(self) -> Array:
        """The optical position error the filter attributes to the tracker now (m)."""
        return self.x[self._ob].copy()

    def pose_covariance(self) -> Array:
        """6x6 covariance of the head pose in geometry's ``xi = [rho, phi]`` convention."""
        idx = np.r_[9:12, 0:3]
        return geo.decoupled_to_se3(self.x[P], self.P[np.ix_(idx, idx)])

    def pose(self, horizon_s: float = 0.0) -> tuple[Array, Array]:
        """Head pose now, or extrapolated ``horizon_s`` ahead with the estimated motion."""
        if not self.initialised:
            raise ValueError("fusion: no pose yet (waiting for the first optical pose)")
        if horizon_s == 0.0:
            return self.x[P].copy(), self.q.copy()
        h = float(horizon_s)
        p = self.x[P] + self.x[V] * h + 0.5 * self.x[A] * h * h
        q = geo.quat_multiply(self.q, geo.rotvec_to_quat(self.x[W] * h + 0.5 * self.x[WD] * h * h))
        return p, q

    def snapshot(self) -> FilterState:
        return FilterState(self.t, self.q.copy(), self.x.copy(), self.P.copy(),
                           self._rejected_in_row, self._last_rejected, self.last_optical_t)

    def restore(self, s: FilterState) -> None:
        """Go back to a snapshot (statistics keep counting)."""
        self.t, self.q, self.x, self.P = s.t, s.q.copy(), s.x.copy(), s.P.copy()
        self._rejected_in_row = s.rejected_in_row
        self._last_rejected = s.last_rejected
        self.last_optical_t = s.last_optical_t
        self._R = geo.quat_to_matrix(self.q)

    # ------------------------------------------------------------------ initialisation

    def initialise(self, t: float, p: Array, q: Array, cov_decoupled: Array) -> None:
        """Start (or restart) from an absolute pose; motion unknown (initial_std)."""
        cfg = self.config
        so, sod, sv, sa, _ = cfg.initial_std
        self.t = float(t)
        self.q = geo.check_quaternion(q, "fusion initial quaternion").reshape(4)
        ab = self._ab
        bias = self.x[ab].copy()
        self.x = np.zeros(self.dim)
        self.x[P] = geo.check_vector(p, "fusion initial position").reshape(3)
        self.x[ab] = bias
        n_ob = _size(self._ob)
        diag = np.concatenate([np.zeros(3), [so**2] * 3, [sod**2] * 3, np.zeros(3),
                               [sv**2] * 3, [sa**2] * 3, [cfg.initial_bias_std**2] * self.n_bias,
                               [cfg.optical_bias_std**2] * n_ob,
                               [cfg.linear_jerk_std**2] * _size(self._jerk),
                               [cfg.angular_jerk_std**2] * _size(self._ang_jerk)])
        P0 = np.diag(diag)
        if self.stats.reinitialised and self.n_bias:
            P0[ab, ab] = self.P[ab, ab]
        idx = np.r_[9:12, 0:3]
        P0[np.ix_(idx, idx)] = cov_decoupled
        if n_ob:  # the pose carries the tracker's bias: position error = -(bias + noise)
            var = cfg.optical_bias_std**2
            P0[self._ob, self._ob] = np.eye(3) * var
            P0[P, P] += np.eye(3) * var
            P0[P, self._ob] = P0[self._ob, P] = -np.eye(3) * var
        self.P = P0
        self._R = geo.quat_to_matrix(self.q)
        self.stats.reinitialised += 1
        self._rejected_in_row = 0
        self._last_rejected = None
        self.start_t = self.last_optical_t = self.t

    def stop(self) -> None:
        """Forget the state (keeping what was learnt of the accelerometer biases): the next
        optical poses start the filter again, as at the beginning."""
        self.t = self.start_t = self.last_optical_t = None
        self._last_rejected = None
        self._rejected_in_row = 0

    def start_from_poses(self, a: OpticalPose, b: OpticalPose) -> None:
        """Start from two poses: at their midpoint with the motion between them, then ``b``.

        A difference quotient is the rate at the interval's midpoint to second order: its
        error there is the jerk times dt^2 / 24, where at either end it is the acceleration
        times dt / 2 -- ten times more at 4 Hz, and the accelerometers' omega_dot cannot
        tell how much of that to remove.  So the filter starts at the midpoint
        (``v = (p_b - p_a) / dt``, ``w = R^T (theta_b - theta_a) / dt`` in body axes, the
        pose halfway, off by the acceleration times dt^2 / 8), and the motion model carries
        it to ``b``, whose pose is then an ordinary update.
        """
        dt = b.t - a.t
        if not dt > 0:
            raise ValueError(f"fusion: a start needs two poses in time order, got {a.t} and {b.t}")
        cfg = self.config
        _, sod, _, sa, _ = cfg.initial_std
        q_mid = geo.slerp(a.q, b.q, 0.5)
        self.initialise(a.t + 0.5 * dt, 0.5 * (a.p + b.p), q_mid, 0.25 * (a.cov + b.cov))
        R = self._R
        self.x[W] = geo.quat_to_rotvec(geo.quat_multiply(geo.quat_conjugate(a.q), b.q)) / dt
        self.x[V] = (b.p - a.p) / dt
        eye = np.eye(3)
        blocks = ((P, V, 0, eye, sa, cfg.linear_jerk_std, cfg.linear_jerk_psd),
                  (TH, W, 3, R, sod, cfg.angular_jerk_std, cfg.angular_jerk_psd))
        for pos, rate, k, rot, s_acc, s_jerk, psd in blocks:  # rot: the rate's axes
            ca, cb = a.cov[k:k + 3, k:k + 3], b.cov[k:k + 3, k:k + 3]
            jerk = s_jerk or math.sqrt(psd / dt)   # white jerk averaged over the interval
            self.P[pos, pos] += eye * (s_acc * dt * dt / 8) ** 2
            self.P[pos, rate] = (cb - ca) @ rot / (2 * dt)
            self.P[rate, pos] = self.P[pos, rate].T
            self.P[rate, rate] = rot.T @ (ca + cb) @ rot / dt**2 + eye * (jerk * dt * dt / 24) ** 2
        self.update_pose(b.t, b.p, b.q, b.cov)
        self.start_t = b.t

    # ------------------------------------------------------------------ time update

    def predict_to(self, t: float) -> None:
        """Integrate the state to time ``t`` (eqs. 6.2-6.5); earlier times are refused."""
        if self.t is None:
            raise ValueError("fusion: predict before initialisation")
        dt = float(t) - self.t
        if dt < -1e-9:
            raise ValueError(f"fusion: time {t:.6f} s is before the filter time "
                             f"{self.t:.6f} s (measurements must come in time order)")
        while dt > 1e-12:
            step = min(dt, self.config.max_step_s)
            self._predict_step(step)
            dt -= step
        self.t = max(self.t, float(t))

    def _predict_step(self, dt: float) -> None:
        F, Q, qa = self._step_matrices(dt)
        x = self.x
        # q(t+dt) = q Exp(omega dt + omega_dot dt^2 / 2 [+ jerk dt^3 / 6]): body-frame
        # increment (eq. 6.5); everything else moves linearly, by F
        turn = x[W] * dt + x[WD] * (0.5 * dt * dt)
        ang_jerk = _size(self._ang_jerk) > 0
        if ang_jerk:
            turn += x[self._ang_jerk] * (dt**3 / 6.0)
        self.q = geo.quat_multiply(self.q, geo.rotvec_to_quat(turn))
        x[3:] = F[3:, 3:] @ x[3:]
        R = geo.quat_to_matrix(self.q)
        self._R = R
        F = F.copy()
        F[TH, W] = R * dt                       # dtheta' = dtheta + R (domega dt + ...)
        F[TH, WD] = R * (0.5 * dt * dt)
        if ang_jerk:
            F[TH, self._ang_jerk] = R * (dt**3 / 6.0)
        Q = Q.copy()
        # angular chain: dtheta is world-frame, omega and omega_dot body-frame
        Q[TH, W] = qa[0, 1] * R
        Q[TH, WD] = qa[0, 2] * R
        Q[W, TH] = qa[1, 0] * R.T
        Q[WD, TH] = qa[2, 0] * R.T
        P = F @ self.P @ F.T + Q
        # the scalar updates subtract outer products; with the stiff jerk states rounding
        # would otherwise make P drift from symmetric to indefinite within seconds
        self.P = 0.5 * (P + P.T)
        self.t += dt
        self.stats.time_updates += 1

    def _step_matrices(self, dt: float) -> tuple[Array, Array, Array]:
        """The rotation-independent parts of F and Q for a step ``dt`` (cached: the
        inertial rate is nearly constant)."""
        key = round(dt, 9)
        hit = self._step_cache.get(key)
        if hit is not None:
            return hit
        cfg = self.config
        eye = np.eye(3)
        F = np.eye(self.dim)
        F[W, WD] = eye * dt
        F[P, V] = eye * dt
        F[P, A] = eye * (0.5 * dt * dt)
        F[V, A] = eye * dt
        qa = Q_continuous_white_noise(dim=3, dt=dt, spectral_density=cfg.angular_jerk_psd)
        ql = Q_continuous_white_noise(dim=3, dt=dt, spectral_density=cfg.linear_jerk_psd)
        Q = np.zeros((self.dim, self.dim))
        for i, si in enumerate((TH, W, WD)):
            for j, sj in enumerate((TH, W, WD)):
                Q[si, sj] = qa[i, j] * eye
        for i, si in enumerate((P, V, A)):
            for j, sj in enumerate((P, V, A)):
                Q[si, sj] = ql[i, j] * eye
        Q[self._ab, self._ab] = np.eye(self.n_bias) * (cfg.bias_walk**2 * dt)
        # the Gauss-Markov states: decay, stationary variance, and what they drive
        _gauss_markov(F, Q, self._ob, cfg.optical_bias_std, cfg.optical_bias_tau_s, dt)
        if _gauss_markov(F, Q, self._jerk, cfg.linear_jerk_std, cfg.linear_jerk_tau_s, dt):
            F[P, self._jerk] = eye * dt**3 / 6.0
            F[V, self._jerk] = eye * (0.5 * dt * dt)
            F[A, self._jerk] = eye * dt
        if _gauss_markov(F, Q, self._ang_jerk, cfg.angular_jerk_std, cfg.angular_jerk_tau_s,
                         dt):
            F[W, self._ang_jerk] = eye * (0.5 * dt * dt)
            F[WD, self._ang_jerk] = eye * dt
        if len(self._step_cache) > 64:
            self._step_cache.clear()
        self._step_cache[key] = (F, Q, qa)
        return F, Q, qa

    # ------------------------------------------------------------------ SCAAT: accelerometers

    def predict_reading(self, j: int) -> tuple[float, Array]:
        """Eq. 6.13 for accelerometer ``j`` and its Jacobian row over the error state.

        ``a_j = n_j . (R^T (alpha - g) + omega_dot x r_j + omega x (omega x r_j)) + b_j``,
        all in head axes (specific force: a resting head reads -g).  Written with dot
        products of precomputed vectors: this runs 1800 times a second.
        """
        x = self.x
        r, n = self.accel.positions[j], self.accel.axes[j]
        w = x[W]
        u = x[A] - self.gravity
        Rn = self._R @ n                        # R n: the axis in world coordinates
        wr = float(w @ r)
        wn = float(w @ n)
        pred = (float(Rn @ u) + float(x[WD] @ self.accel.cross[j])
                + wn * wr - float(w @ w) * self.accel.n_dot_r[j])
        H = np.zeros(self.dim)
        H[TH] = geo.cross3(Rn, u)                   # n^T R^T [u]x, the left rotation error
        H[W] = wn * r + wr * n - 2.0 * self.accel.n_dot_r[j] * w
        H[WD] = self.accel.cross[j]
        H[A] = Rn
        if self.n_bias:
            pred += x[self._ab.start + j]
            H[self._ab.start + j] = 1.0
        return pred, H

    def update_accel(self, j: int, reading: float) -> bool:
        """One SCAAT update with accelerometer ``j``'s reading (m/s^2); False if gated."""
        if not math.isfinite(reading):
            raise ValueError(f"fusion: accelerometer {j + 1} reading {reading!r} is not finite")
        pred, H = self.predict_reading(j)
        y = reading - pred
        PH = self.P @ H
        s = float(H @ PH) + self.accel.variance[j]
        if y * y / s > self.config.accel_gate:
            self.stats.accel_rejected += 1
            return False
        dx = PH * (y / s)
        # small rotation: keep R current to first order, fold into q once per sample
        self._dtheta += dx[TH]
        self._R += geo.skew3(dx[TH]) @ self._R
        self.x[3:] += dx[3:]
        self.P -= np.outer(PH, PH / s)
        self.stats.accel_updates += 1
        return True

    def update_accel_sample(self, t: float, readings: Array) -> int:
        """All accelerometers of one sample, one constraint at a time; returns accepted."""
        readings = np.asarray(readings, float).reshape(-1)
        if readings.shape != (self.accel.count,):
            raise ValueError(f"fusion: {readings.size} accelerometer readings, the model has "
                             f"{self.accel.count}")
        if not np.all(np.isfinite(readings)):
            raise ValueError(f"fusion: accelerometer readings {readings.tolist()} are not "
                             "all finite")
        self.predict_to(t - self.accel.latency_s)
        self._begin_scalar_updates()
        try:
            return sum(self.update_accel(j, float(a)) for j, a in enumerate(readings))
        finally:
            self._end_scalar_updates()

    # ------------------------------------------------------------------ optical pose

    def update_pose(self, t: float, p: Array, q: Array, cov_decoupled: Array) -> bool:
        """Absolute head pose (world) with its covariance over ``[dp, dtheta]``; False if gated.

        The first two poses close enough in time start the filter (``start_max_gap_s``).  A
        pose far outside the predicted uncertainty is rejected (Mahalanobis gate); after
        ``max_rejected_poses`` rejections in a row the filter trusts the optics again and
        restarts from the last two of them.
        """
        p = geo.check_vector(p, "optical position").reshape(3)
        q = geo.check_quaternion(q, "optical quaternion").reshape(4)
        Rm = geo.check_covariance(cov_decoupled, "optical covariance")
        if not self.initialised:
            self._start_with(OpticalPose(float(t), p, q, Rm))
            return True
        self.predict_to(t)
        H = self._pose_jacobian()
        y = np.concatenate([p - H[0:3] @ self.x, geo.quat_to_rotvec(
            geo.quat_multiply(q, geo.quat_conjugate(self.q)))])
        PHt = self.P @ H.T
        d = np.sqrt(np.repeat(self.stats.pose_noise_scale, 3))
        Rm = Rm * np.outer(d, d)
        S = H @ PHt + Rm
        nis = float(y @ np.linalg.solve(S, y))
        self.stats.last_pose_nis = nis
        self._adapt_pose_noise(nis, y, S, Rm)
        if nis > self.config.pose_gate:
            self.stats.pose_rejected += 1
            self._rejected_in_row += 1
            pose = OpticalPose(float(t), p, q, Rm)
            if self._rejected_in_row >= self.config.max_rejected_poses:
                previous = self._last_rejected
                self.stop()                      # the optics win: start again from them
                self._last_rejected = previous
                self._start_with(pose)
                return True
            self._last_rejected = pose
            return False
        self._rejected_in_row = 0
        self._last_rejected = None
        K = np.linalg.solve(S, PHt.T).T
        self._inject(K @ y)
        # Joseph form: the 6-D update is large enough for rounding to matter
        I_KH = np.eye(self.dim) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ Rm @ K.T
        self.stats.pose_updates += 1
        self.last_optical_t = self.t
        return True

    def _start_with(self, pose: OpticalPose) -> None:
        """Start from ``pose`` and the previous unused one if they are close enough in time;
        otherwise keep the newer as the candidate and stay uninitialised."""
        prev, self._last_rejected = self._last_rejected, pose
        if prev is None:
            return
        a, b = sorted((prev, pose), key=lambda e: e.t)
        if 0 < b.t - a.t <= self.config.start_max_gap_s:
            self.start_from_poses(a, b)
        else:
            self._last_rejected = b

    def update_rig_pose(self, t: float, p_rig: Array, q_rig: Array, cov_rig_se3: Array,
                        mount: tuple[Array, Array]) -> bool:
        """A tracker's pose of its rig (world -> rig), mounted at ``mount`` (head -> rig).

        ``T_world_head = T_world_rig T_head_rig^-1``; a left perturbation of the rig pose is
        the same left perturbation of the head pose, so the covariance carries over and is
        converted to the filter's position/rotation form.
        """
        pm, qm = geo.inverse(*mount)
        p, q = geo.compose(p_rig, q_rig, pm, qm)
        cov = geo.se3_to_decoupled(p, geo.check_covariance(cov_rig_se3, "rig pose covariance"))
        return self.update_pose(t, p, q, cov)

    def _pose_jacobian(self) -> Array:
        """d [position, rotation] of the optical pose / d error state (6, dim): the head
        pose plus, in position, the tracker's bias when the filter models one."""
        H = np.zeros((6, self.dim))
        H[0:3, P] = H[3:6, TH] = np.eye(3)
        if _size(self._ob):
            H[0:3, self._ob] = np.eye(3)
        return H

    def _adapt_pose_noise(self, nis: float, y: Array, S: Array, Rm: Array) -> None:
        """Covariance matching for the optical noise (Mehra's adaptive R, per block).

        A tracker's covariance is a model; if it is too large (or too small) the fused
        covariance is dishonest.  The position and the rotation block are matched
        separately, because a tracker can be right about one and wrong about the other:
        each block's NIS averages 3 when its part of ``S`` is right, and its scale moves by
        the share of that part which ``R`` makes up, bounded to [pose_noise_min_scale, 20]:
        errors that persist from frame to frame make the NIS look smaller than the error
        is, and a run of outliers must not switch the optics off.
        """
        cfg = self.config
        if not cfg.adapt_pose_noise or nis > cfg.pose_gate:
            return
        scales = []
        for block, scale, lowest in zip((slice(0, 3), slice(3, 6)),
                                        self.stats.pose_noise_scale, cfg.pose_noise_min_scale,
                                        strict=True):
            S_b = S[block, block]
            nis_b = float(y[block] @ np.linalg.solve(S_b, y[block]))
            share = float(np.trace(Rm[block, block]) / max(np.trace(S_b), 1e-300))
            step = cfg.pose_noise_rate * share * (nis_b / 3.0 - 1.0)
            scale *= 1.0 + max(-0.5, min(step, 0.5))
            scales.append(min(20.0, max(lowest, scale)))
        self.stats.pose_noise_scale = (scales[0], scales[1])

    # ------------------------------------------------------------------ SCAAT: one laser dot

    def predict_dot(self, beam_rig: Array, plane: tuple[Array, float],
                    mount: tuple[Array, Array]) -> tuple[Array, Array]:
        """Where one laser beam of the predicted pose meets a wall, and d point / d state.

        The rig sits at ``mount`` (head -> rig) on the head; its beam ``beam_rig`` (rig
        frame) leaves the rig origin; the wall is the plane ``n . x = c`` (world).  With
        ``M = I - d n^T / (n . d)`` (moving the origin or turning the beam slides the hit
        along the wall): ``dx/dp = M``, ``dx/dtheta = -M ([R p_m]x + s [d]x)``.
        """
        n, c = np.asarray(plane[0], float), float(plane[1])
        R = self._R
        arm = R @ np.asarray(mount[0], float)
        origin = self.x[P] + arm
        d = R @ geo.quat_rotate(mount[1], np.asarray(beam_rig, float))
        nd = float(n @ d)
        if nd <= 1e-6:
            raise ValueError("fusion: the predicted beam does not reach that wall")
        s = (c - float(n @ origin)) / nd
        if s <= 0:
            raise ValueError("fusion: the wall is behind the predicted beam")
        M = np.eye(3) - np.outer(d, n) / nd
        J = np.zeros((3, self.dim))
        J[:, P] = M
        J[:, TH] = -M @ (geo.skew3(arm) + s * geo.skew3(d))
        return origin + s * d, J

    def update_dot(self, t: float, point: Array, std_m: float, beam_rig: Array,
                   plane: tuple[Array, float], axes: Array,
                   mount: tuple[Array, Array]) -> bool:
        """SCAAT update with one labeled laser dot (seed 003 ch. 6: "intersect the laser beam
        with the walls of IVY"): a 2-D constraint in the wall's in-plane ``axes`` (2, 3).
        False if gated or if the predicted beam misses that wall."""
        point = geo.check_vector(point, "laser dot").reshape(3)
        if not (math.isfinite(std_m) and std_m > 0):
            raise ValueError(f"fusion: laser dot std {std_m!r} must be positive")
        if not self.initialised:
            raise ValueError("fusion: a laser dot needs an initialised filter (a pose first)")
        self.predict_to(t)
        self._R = geo.quat_to_matrix(self.q)
        try:
            pred, J = self.predict_dot(beam_rig, plane, mount)
        except ValueError:
            self.stats.dot_rejected += 1
            return False
        A2 = np.asarray(axes, float).reshape(2, 3)
        H = A2 @ J
        y = A2 @ (point - pred)
        PHt = self.P @ H.T
        S = H @ PHt + np.eye(2) * std_m**2
        if float(y @ np.linalg.solve(S, y)) > self.config.dot_gate:
            self.stats.dot_rejected += 1
            return False
        K = np.linalg.solve(S, PHt.T).T
        self._inject(K @ y)
        self.P = self.P - K @ H @ self.P
        self.P = 0.5 * (self.P + self.P.T)
        self.stats.dot_updates += 1
        self.last_optical_t = self.t
        return True

    # ------------------------------------------------------------------ internals

    def _inject(self, dx: Array) -> None:
        """Apply an error-state correction: rotation on the manifold, the rest additively."""
        self.q = geo.quat_multiply(geo.rotvec_to_quat(dx[TH]), self.q)
        self.q /= np.linalg.norm(self.q)
        self._R = geo.quat_to_matrix(self.q)
        self.x[3:] += dx[3:]

    def _begin_scalar_updates(self) -> None:
        self._R = geo.quat_to_matrix(self.q)
        self._dtheta = np.zeros(3)

    def _end_scalar_updates(self) -> None:
        """Fold the rotation corrections of one sample's scalar updates into ``q``.

        Each correction is ~1e-4 rad, so summing them differs from composing them by
        ~1e-9 rad; the quaternion is then exact again and ``R`` is rebuilt from it.
        """
        if np.any(self._dtheta):
            self.q = geo.quat_multiply(geo.rotvec_to_quat(self._dtheta), self.q)
            self.q /= np.linalg.norm(self.q)
        self._dtheta = np.zeros(3)
        self._R = geo.quat_to_matrix(self.q)


def _size(block: slice) -> int:
    return block.stop - block.start


def _consecutive(start: int, sizes: list[int]) -> list[slice]:
    """Slices of the given sizes, one after the other from ``start``."""
    out = []
    for n in sizes:
        out.append(slice(start, start + n))
        start += n
    return out


def _gauss_markov(F: Array, Q: Array, block: slice, std: float, tau_s: float,
                  dt: float) -> bool:
    """First-order Gauss-Markov states over ``dt``: decay ``exp(-dt / tau)``, driving noise
    that keeps their variance at ``std^2``.  False (and nothing set) for an empty block."""
    n = _size(block)
    if n == 0:
        return False
    decay = math.exp(-dt / tau_s)
    F[block, block] = np.eye(n) * decay
    Q[block, block] = np.eye(n) * (std**2 * (1.0 - decay**2))
    return True
