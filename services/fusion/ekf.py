"""MARVIN's fusion filter: an error-state EKF with SCAAT updates (Hogue, *MARVIN: a Mobile
Automatic Realtime Visual and INertial tracking system*, MSc thesis, York University 2003,
ch. 6; Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*, JASS 2005,
§4.6.2).

The parts live in their own modules: the state layout, the accelerometer model and the
configuration in ``state``, the time update (eqs. 6.2-6.5) in ``process``, the measurement
models as pure ``h(x) -> (prediction, H)`` functions in ``measurements``.  This module is
the filter: it holds the estimate, starts and restarts it, gates and applies the updates.

Where and why the filter has its own form instead of filterpy's ``ExtendedKalmanFilter``:

* The quaternion cannot take an additive correction ``x + K y``.  The filter keeps it
  outside the covariance, as SCAAT keeps its "external quaternion" (Hogue 2003 appendix
  B.3, eqs. B.30-B.32): the covariance is over the 3-vector ``dtheta`` of the world-frame
  (left) rotation error ``q_true = Exp(dtheta) q`` (geometry's convention), each update
  injects ``Exp(dtheta) q`` and zeroes ``dtheta``.
* SCAAT updates are scalar (one accelerometer, eq. 6.13): ``S`` is a number, so there is
  no matrix inverse, each reading is gated on its own and applied at its own time; the
  whole cost is a few 24-vector products (``bench/bench_fusion.py`` compares it with one
  6-D filterpy update per sample: about the same speed, both far above 3000 updates/s).
* The time update integrates the quaternion on the manifold.

The static mountings (head -> accelerometer rig, head -> laser rig) are inputs
(``AccelModel.from_layout``, the ``mount`` of ``update_rig_pose``), which callers take from
the SRG's static edges; the filter has no geometry constants of its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.frames import GRAVITY
from services.fusion import measurements
from services.fusion.process import ProcessModel
from services.fusion.state import (
    POSE_INDEX,
    TH,
    WD,
    A,
    AccelModel,
    Array,
    FusionConfig,
    P,
    StateLayout,
    V,
    W,
    size,
)


@dataclass(frozen=True)
class OpticalPose:
    """A head pose from the optics, kept to start the filter from (with the next one)."""

    t: float
    p: Array
    q: Array
    cov: Array  # over [dp, dtheta]
    systematic: Array  # the part of ``cov`` that persists from frame to frame


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
    systematic: Array
    P_random: Array


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


@dataclass(frozen=True)
class Innovation:
    """One vector measurement against the prediction: residual ``y``, Jacobian ``H``, noise
    ``R`` and its systematic part ``R_sys``, ``P H^T``, ``S = H P H^T + R`` and the
    normalised innovation squared."""

    y: Array
    H: Array
    R: Array
    R_sys: Array
    PHt: Array
    S: Array
    nis: float


class FusionEKF:
    """Head pose from accelerometer readings (one at a time) and absolute optical poses."""

    def __init__(self, accel: AccelModel, config: FusionConfig | None = None,
                 gravity: Array = GRAVITY):
        self.config = config or FusionConfig()
        self.accel = accel
        self.gravity = np.asarray(gravity, float)
        self.layout = StateLayout.of(self.config, accel.count)
        self.process = ProcessModel(self.config, self.layout)
        self.dim = self.layout.dim
        self.n_bias = self.layout.n_bias
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
        #: the persistent part of the newest optical pose's error covariance (over [dp,
        #: dtheta]), which the fused pose carries on top of ``P_random`` (``pose_covariance``)
        self.systematic = np.zeros((6, 6))
        #: ``P`` without the share the optics' systematic parts put there, each frame's
        #: counted as if it were new (the filter weighs the optics by their whole
        #: covariance): the covariance of the error the random parts leave, propagated with
        #: ``P``'s own transitions and gains and every noise but the systematic parts; the
        #: fused covariance is it plus the systematic part whole
        #: (``pose_covariance_decoupled``)
        self.P_random = np.eye(self.dim)
        self._R = geo.quat_to_matrix(self.q)
        self._dtheta = np.zeros(3)

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
        return self.x[self.layout.accel_bias].copy()

    @property
    def optical_bias(self) -> Array:
        """The optical position error the filter attributes to the tracker now (m)."""
        return self.x[self.layout.optical_bias].copy()

    def pose_covariance_decoupled(self) -> Array:
        """6x6 covariance of the head pose over ``[dp, dtheta]``: the filter's own without
        the share the optics' systematic parts put in it (``P_random``), plus the
        systematic part of the newest optical pose's.

        The filter follows the optical poses, so an error they share from frame to frame
        (the installation's) is in the fused pose too, whole, where ``P`` has it divided by
        the frames it averaged, as if new in each (Schmidt's "consider" covariance, the
        persistent error passed through at full gain; docs/FUSION_TUNING.md says why the
        filter still weighs the poses by their whole covariance).  Counted both ways, the
        systematic part made the fused covariance claim about a quarter more than the
        errors show."""
        return self.P_random[np.ix_(POSE_INDEX, POSE_INDEX)] + self.systematic

    def pose_covariance(self) -> Array:
        """6x6 covariance of the head pose in geometry's ``xi = [rho, phi]`` convention."""
        return geo.decoupled_to_se3(self.x[P], self.pose_covariance_decoupled())

    def pose(self, horizon_s: float = 0.0) -> tuple[Array, Array]:
        """Head pose now, or extrapolated ``horizon_s`` ahead with the estimated motion."""
        if not self.initialised:
            raise InvalidInputError("fusion: no pose yet (waiting for the first optical pose)")
        if horizon_s == 0.0:
            return self.x[P].copy(), self.q.copy()
        h = float(horizon_s)
        p = self.x[P] + self.x[V] * h + 0.5 * self.x[A] * h * h
        q = geo.quat_multiply(self.q, geo.rotvec_to_quat(self.x[W] * h + 0.5 * self.x[WD] * h * h))
        return p, q

    def snapshot(self) -> FilterState:
        return FilterState(self.t, self.q.copy(), self.x.copy(), self.P.copy(),
                           self._rejected_in_row, self._last_rejected, self.last_optical_t,
                           self.systematic.copy(), self.P_random.copy())

    def restore(self, s: FilterState) -> None:
        """Go back to a snapshot (statistics keep counting)."""
        self.t, self.q, self.x, self.P = s.t, s.q.copy(), s.x.copy(), s.P.copy()
        self._rejected_in_row = s.rejected_in_row
        self._last_rejected = s.last_rejected
        self.last_optical_t = s.last_optical_t
        self.systematic = s.systematic.copy()
        self.P_random = s.P_random.copy()
        self._R = geo.quat_to_matrix(self.q)

    # ------------------------------------------------------------------ initialisation

    def initialise(self, t: float, p: Array, q: Array, cov_decoupled: Array,
                   systematic: Array | None = None) -> None:
        """Start (or restart) from an absolute pose; motion unknown (initial_std).
        ``systematic``: the part of the pose's error that persists (``update_pose``).
        ``P_random`` starts as ``P``: a start from this one pose counts its systematic part
        as if it were new until the updates replace it (``start_from_poses`` takes it out
        of ``P_random``; its ``P`` keeps it whole in the rates, where it may not cancel)."""
        cfg, lay = self.config, self.layout
        so, sod, sv, sa, _ = cfg.initial_std
        self.t = float(t)
        self.q = geo.check_quaternion(q, "fusion initial quaternion").reshape(4)
        ab, ob = lay.accel_bias, lay.optical_bias
        bias = self.x[ab].copy()
        self.x = np.zeros(self.dim)
        self.x[P] = geo.check_vector(p, "fusion initial position").reshape(3)
        self.x[ab] = bias
        n_ob = size(ob)
        diag = np.concatenate([np.zeros(3), [so**2] * 3, [sod**2] * 3, np.zeros(3),
                               [sv**2] * 3, [sa**2] * 3, [cfg.initial_bias_std**2] * self.n_bias,
                               [cfg.optical_bias_std**2] * n_ob,
                               [cfg.linear_jerk_std**2] * size(lay.linear_jerk),
                               [cfg.angular_jerk_std**2] * size(lay.angular_jerk)])
        P0 = np.diag(diag)
        if self.stats.reinitialised and self.n_bias:
            P0[ab, ab] = self.P[ab, ab]
        P0[np.ix_(POSE_INDEX, POSE_INDEX)] = cov_decoupled
        if n_ob:  # the pose carries the tracker's bias: position error = -(bias + noise)
            var = cfg.optical_bias_std**2
            P0[ob, ob] = np.eye(3) * var
            P0[P, P] += np.eye(3) * var
            P0[P, ob] = P0[ob, P] = -np.eye(3) * var
        self.P = P0
        self.P_random = P0.copy()
        self.systematic = np.zeros((6, 6)) if systematic is None else systematic
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
        """Start from two poses: at their midpoint with the motion between them, carried to
        ``b``.

        A difference quotient is the rate at the interval's midpoint to second order: its
        error there is the jerk times dt^2 / 24, where at either end it is the acceleration
        times dt / 2 -- ten times more at 4 Hz, and the accelerometers' omega_dot cannot
        tell how much of that to remove.  So the filter starts at the midpoint
        (``v = (p_b - p_a) / dt``, ``w = R^T (theta_b - theta_a) / dt`` in body axes, the
        pose halfway, off by the acceleration times dt^2 / 8), and the motion model carries
        it to ``b``.

        Those two offsets are the unknown acceleration's and jerk's, the very quantities
        the filter's acceleration and jerk states start ignorant of, so they enter the
        covariance correlated with those states; carried to ``b`` they cancel (the
        estimate there is ``b``'s pose, its error ``b``'s, and so is the covariance).
        ``b`` is not applied again as an update: the start holds all it says, and applied
        again its error would count as new, the covariance claiming less than the error
        it carries (0.88 of ``b``'s std with 1 mm per axis).

        ``P_random`` is built the same way from the poses' random parts (each covariance
        less its systematic part), so that at ``b`` it holds ``b``'s random part and the
        fused covariance, it plus ``b``'s systematic part, is ``b``'s covariance: built
        from the whole covariances it would count the systematic part twice there.
        """
        dt = b.t - a.t
        if not dt > 0:
            raise InvalidInputError(
                f"fusion: a start needs two poses in time order, got {a.t} and {b.t}")
        cfg, lay = self.config, self.layout
        _, sod, _, sa, _ = cfg.initial_std
        q_mid = geo.slerp(a.q, b.q, 0.5)
        # the persistent errors of two poses 1/15 s apart are one: the midpoint has it too
        self.initialise(a.t + 0.5 * dt, 0.5 * (a.p + b.p), q_mid, 0.25 * (a.cov + b.cov),
                        b.systematic)
        R = self._R
        self.x[W] = geo.quat_to_rotvec(geo.quat_multiply(geo.quat_conjugate(a.q), b.q)) / dt
        self.x[V] = (b.p - a.p) / dt
        eye = np.eye(3)
        self.P_random[np.ix_(POSE_INDEX, POSE_INDEX)] -= 0.25 * (a.systematic + b.systematic)
        blocks = ((P, V, A, lay.linear_jerk, 0, eye, sa, cfg.linear_jerk_std,
                   cfg.linear_jerk_psd),
                  (TH, W, WD, lay.angular_jerk, 3, R, sod, cfg.angular_jerk_std,
                   cfg.angular_jerk_psd))
        # rot: the rate's axes; acc and jerk: the states whose errors the offsets are
        for pos, rate, acc, jerk_state, k, rot, s_acc, s_jerk, psd in blocks:
            jerk = s_jerk or math.sqrt(psd / dt)   # white jerk averaged over the interval
            for M, ca6, cb6 in ((self.P, a.cov, b.cov),
                                (self.P_random, a.cov - a.systematic, b.cov - b.systematic)):
                ca, cb = ca6[k:k + 3, k:k + 3], cb6[k:k + 3, k:k + 3]
                M[pos, pos] += eye * (s_acc * dt * dt / 8) ** 2
                M[pos, rate] = (cb - ca) @ rot / (2 * dt)
                M[rate, pos] = M[pos, rate].T
                M[rate, rate] = rot.T @ (ca + cb) @ rot / dt**2 + eye * (jerk * dt * dt / 24) ** 2
                # pose offset +acc dt^2 / 8 against the state's error -acc (and rot's axes)
                M[pos, acc] = rot * (-s_acc**2 * dt * dt / 8)
                M[acc, pos] = M[pos, acc].T
                if size(jerk_state):  # rate offset +jerk dt^2 / 24 against the state's -jerk
                    M[rate, jerk_state] = eye * (-s_jerk**2 * dt * dt / 24)
                    M[jerk_state, rate] = M[rate, jerk_state].T
        self.predict_to(b.t)
        self.start_t = self.last_optical_t = b.t

    # ------------------------------------------------------------------ time update

    def predict_to(self, t: float) -> None:
        """Integrate the state to time ``t`` (eqs. 6.2-6.5); earlier times are refused."""
        if self.t is None:
            raise InvalidInputError("fusion: predict before initialisation")
        dt = float(t) - self.t
        if dt < -1e-9:
            raise InvalidInputError(f"fusion: time {t:.6f} s is before the filter time "
                                    f"{self.t:.6f} s (measurements must come in time order)")
        while dt > 1e-12:
            step = min(dt, self.config.max_step_s)
            self.q, self.x, self.P, self.P_random = self.process.step(
                self.q, self.x, self.P, step, self.P_random)
            self.t += step
            self.stats.time_updates += 1
            dt -= step
        self._R = geo.quat_to_matrix(self.q)
        self.t = max(self.t, float(t))

    # ------------------------------------------------------------------ SCAAT: accelerometers

    def predict_reading(self, j: int) -> tuple[float, Array]:
        """Eq. 6.13 for accelerometer ``j`` and its Jacobian row over the error state
        (``measurements.accel_reading`` at the current estimate)."""
        return measurements.accel_reading(self.x, self._R, self.accel, j, self.gravity,
                                          self.layout)

    def reading_spreads(self) -> Array:
        """Each accelerometer's variance of what the linearisation at the estimate leaves
        out (``measurements.accel_reading_spreads``), added to its reading's noise."""
        return measurements.accel_reading_spreads(self.x, self._R, self.P[:6, :6],
                                                  self.accel, self.gravity)

    def update_accel(self, j: int, reading: float, spread: float | None = None) -> bool:
        """One SCAAT update with accelerometer ``j``'s reading (m/s^2); False if gated.
        ``spread``: ``reading_spreads()[j]`` (computed now if None).

        Not the vector update of the optics (``_innovation`` / ``_apply``): with a scalar
        ``S`` the gain needs no solve and ``P - P H^T H P / s`` is one outer product, where
        the Joseph form would cost two dim x dim products per reading, 1800 times a
        second; the time update's symmetrisation keeps that ``P`` from drifting.
        """
        if not math.isfinite(reading):
            raise InvalidInputError(
                f"fusion: accelerometer {j + 1} reading {reading!r} is not finite")
        pred, H = self.predict_reading(j)
        y = reading - pred
        PH = self.P @ H
        s = float(H @ PH) + self.accel.variance[j] + (
            self.reading_spreads()[j] if spread is None else spread)
        if y * y / s > self.config.accel_gate:
            self.stats.accel_rejected += 1
            return False
        dx = PH * (y / s)
        self._random_scalar_update(PH / s, H, s - float(H @ PH))
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
            raise InvalidInputError(
                f"fusion: {readings.size} accelerometer readings, the model has "
                f"{self.accel.count}")
        if not np.all(np.isfinite(readings)):
            raise InvalidInputError(f"fusion: accelerometer readings {readings.tolist()} are not "
                                    "all finite")
        self.predict_to(t - self.accel.latency_s)
        self._begin_scalar_updates()
        # one sample's readings share the spreads of the covariance before them: the
        # updates between them only narrow it, so the later ones are weighed a little less
        spreads = self.reading_spreads()
        try:
            return sum(self.update_accel(j, float(a), float(spreads[j]))
                       for j, a in enumerate(readings))
        finally:
            self._end_scalar_updates()

    # ------------------------------------------------------------------ optical pose

    def update_pose(self, t: float, p: Array, q: Array, cov_decoupled: Array,
                    systematic: Array | None = None) -> bool:
        """Absolute head pose (world) with its covariance over ``[dp, dtheta]``; False if gated.

        ``systematic`` (None: nothing) is the part of ``cov_decoupled`` that persists from
        frame to frame (an installation's imperfections): it goes whole into the fused
        covariance (``pose_covariance_decoupled``), since no number of frames averages it
        away.  The pose is still weighed by all of ``cov_decoupled``: the persistent error
        changes from frame to frame too, as the dots move over the screens.

        The first two poses close enough in time start the filter (``start_max_gap_s``).  A
        pose far outside the predicted uncertainty is rejected (Mahalanobis gate); after
        ``max_rejected_poses`` rejections in a row the filter trusts the optics again and
        restarts from the last two of them.
        """
        return self._update_with(_optical_pose(t, p, q, cov_decoupled, systematic))

    def _update_with(self, pose: OpticalPose) -> bool:
        """``update_pose`` with a checked pose."""
        if not self.initialised:
            self._start_with(pose)
            return True
        self.predict_to(pose.t)
        predicted, H = measurements.optical_pose(self.x, self.q, self.layout)
        d = np.sqrt(np.repeat(self.stats.pose_noise_scale, 3))
        scale = np.outer(d, d)
        inn = self._innovation(measurements.pose_residual(pose.p, pose.q, predicted), H,
                               pose.cov * scale, pose.systematic * scale)
        self.stats.last_pose_nis = inn.nis
        self._adapt_pose_noise(inn)
        if inn.nis > self.config.pose_gate:
            self.stats.pose_rejected += 1
            self._rejected_in_row += 1
            pose = OpticalPose(pose.t, pose.p, pose.q, inn.R, inn.R_sys)
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
        self._apply(inn)
        self.systematic = pose.systematic
        self.stats.pose_updates += 1
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
                        mount: tuple[Array, Array],
                        systematic_se3: Array | None = None) -> bool:
        """A tracker's pose of its rig (world -> rig), mounted at ``mount`` (head -> rig),
        with its covariance and that covariance's systematic part (``update_pose``).

        ``T_world_head = T_world_rig T_head_rig^-1``; a left perturbation of the rig pose is
        the same left perturbation of the head pose, so the covariances carry over and are
        converted to the filter's position/rotation form.
        """
        p, q = geo.compose(p_rig, q_rig, *geo.inverse(*mount))
        cov = geo.se3_to_decoupled(p, geo.check_covariance(cov_rig_se3, "rig pose covariance"))
        sys = None if systematic_se3 is None else _head_systematic(p, systematic_se3)
        return self.update_pose(t, p, q, cov, sys)

    def carry_rig_systematic(self, p_rig: Array, q_rig: Array, systematic_se3: Array,
                             mount: tuple[Array, Array]) -> None:
        """Carry a rig pose's systematic covariance into the fused one without updating with
        the pose: in dot mode its dots are the updates, and the error they share from frame
        to frame is in the fused pose whole (``pose_covariance_decoupled``)."""
        p, _ = geo.compose(p_rig, q_rig, *geo.inverse(*mount))
        self.systematic = _head_systematic(p, systematic_se3)

    def _adapt_pose_noise(self, inn: Innovation) -> None:
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
        if not cfg.adapt_pose_noise or inn.nis > cfg.pose_gate:
            return
        scales = []
        for block, scale, lowest in zip((slice(0, 3), slice(3, 6)),
                                        self.stats.pose_noise_scale, cfg.pose_noise_min_scale,
                                        strict=True):
            S_b = inn.S[block, block]
            nis_b = float(inn.y[block] @ np.linalg.solve(S_b, inn.y[block]))
            share = float(np.trace(inn.R[block, block]) / max(np.trace(S_b), 1e-300))
            step = cfg.pose_noise_rate * share * (nis_b / 3.0 - 1.0)
            scale *= 1.0 + max(-0.5, min(step, 0.5))
            scales.append(min(20.0, max(lowest, scale)))
        self.stats.pose_noise_scale = (scales[0], scales[1])

    # ------------------------------------------------------------------ SCAAT: one laser dot

    def predict_dot(self, beam_rig: Array, plane: tuple[Array, float],
                    mount: tuple[Array, Array]) -> tuple[Array, Array]:
        """Where one laser beam of the predicted pose meets a wall, and d point / d state
        (``measurements.laser_dot`` at the current estimate)."""
        return measurements.laser_dot(self.x, self._R, self.layout, beam_rig, plane, mount)

    def update_dot(self, t: float, point: Array, std_m: float, beam_rig: Array,
                   plane: tuple[Array, float], axes: Array,
                   mount: tuple[Array, Array], systematic_std_m: float = 0.0) -> bool:
        """SCAAT update with one labeled laser dot (Hogue 2003 ch. 6: "intersect the laser
        beam with the walls of IVY"): a 2-D constraint in the wall's in-plane ``axes``
        (2, 3), weighed by its noise ``std_m`` and its installation error
        ``systematic_std_m`` (the share that persists, left out of ``P_random``).  False if
        gated or if the predicted beam misses that wall."""
        point = geo.check_vector(point, "laser dot").reshape(3)
        if not (math.isfinite(std_m) and std_m > 0):
            raise InvalidInputError(f"fusion: laser dot std {std_m!r} must be positive")
        if not (math.isfinite(systematic_std_m) and systematic_std_m >= 0):
            raise InvalidInputError(
                f"fusion: laser dot systematic std {systematic_std_m!r} must be >= 0")
        if not self.initialised:
            raise InvalidInputError(
                "fusion: a laser dot needs an initialised filter (a pose first)")
        self.predict_to(t)
        try:
            pred, J = self.predict_dot(beam_rig, plane, mount)
        except ValueError:
            self.stats.dot_rejected += 1
            return False
        A2 = np.asarray(axes, float).reshape(2, 3)
        inn = self._innovation(A2 @ (point - pred), A2 @ J,
                               np.eye(2) * (std_m**2 + systematic_std_m**2),
                               np.eye(2) * systematic_std_m**2)
        J_pose = inn.H[:, POSE_INDEX]
        if self._gate_nis(inn, J_pose @ self.systematic @ J_pose.T) > self.config.dot_gate:
            self.stats.dot_rejected += 1
            return False
        self._apply(inn)
        self.stats.dot_updates += 1
        return True

    # ------------------------------------------------------------------ internals

    def _innovation(self, y: Array, H: Array, R: Array, R_sys: Array) -> Innovation:
        """The optical measurement ``y`` (residual), ``H``, ``R`` (``R_sys`` of it
        systematic) against the prediction."""
        PHt = self.P @ H.T
        S = H @ PHt + R
        return Innovation(y, H, R, R_sys, PHt, S, float(y @ np.linalg.solve(S, y)))

    @staticmethod
    def _gate_nis(inn: Innovation, systematic: Array) -> float:
        """The NIS the dot gate judges: with the optics' systematic covariance (in the
        measurement's space) added to ``S``.  A dot comes with its random std alone, but
        the persistent error moves it too, and differently when the dots change camera or
        part of a screen: the gate must not refuse the optics for that."""
        if not np.any(systematic):
            return inn.nis
        return float(inn.y @ np.linalg.solve(inn.S + systematic, inn.y))

    def _apply(self, inn: Innovation) -> None:
        """The vector update of the optical measurements (pose and laser dot).

        Joseph form: for the 6-D pose and the 2-D dot alike the update is large enough
        (a dim x dim product of gains) for the rounding of ``P - K H P`` to matter, and the
        Joseph form keeps ``P`` symmetric positive definite whatever the gain's error.
        """
        K = np.linalg.solve(inn.S, inn.PHt.T).T
        self._inject(K @ inn.y)
        I_KH = np.eye(self.dim) - K @ inn.H
        self.P = I_KH @ self.P @ I_KH.T + K @ inn.R @ K.T
        self.P_random = I_KH @ self.P_random @ I_KH.T + K @ (inn.R - inn.R_sys) @ K.T
        self.last_optical_t = self.t

    def _random_scalar_update(self, K: Array, H: Array, r: float) -> None:
        """``P_random`` through a scalar update with gain ``K`` and noise variance ``r``
        (a reading with no systematic part): ``(I - K H) P_random (I - K H)^T + K r K^T``,
        as two outer products."""
        u = self.P_random @ H
        w = u - (0.5 * (float(H @ u) + r)) * K
        M = np.outer(K, w)
        self.P_random -= M + M.T

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


def _optical_pose(t: float, p: Array, q: Array, cov: Array,
                  systematic: Array | None) -> OpticalPose:
    """A checked optical pose with its covariance and that covariance's systematic part;
    ``ValueError`` names what is wrong (a systematic part larger than the whole)."""
    whole = geo.check_covariance(cov, "optical covariance")
    sys = np.zeros((6, 6)) if systematic is None else geo.check_covariance(
        systematic, "optical systematic covariance")
    geo.check_covariance(whole - sys, "optical covariance minus its systematic part")
    return OpticalPose(float(t), geo.check_vector(p, "optical position").reshape(3),
                       geo.check_quaternion(q, "optical quaternion").reshape(4), whole, sys)


def _head_systematic(p_head: Array, systematic_se3: Array) -> Array:
    """A rig pose's systematic covariance (SE(3) form) as the head pose's, in the filter's
    position/rotation form (``update_rig_pose`` says why it carries over)."""
    return geo.se3_to_decoupled(
        p_head, geo.check_covariance(systematic_se3, "rig pose systematic covariance"))
