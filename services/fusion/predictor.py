"""Dorfmüller-Ulhaas's motion predictor: an EKF over (omega, v, a) on the exponential map.

The filter does not hold the pose.  It holds the *relative* motion of a rigid body:
angular velocity ``omega``, translational velocity ``v`` and constant translational
acceleration ``a`` (eq. 9).  Each pose of the input stream becomes three points on the
body (eq. 11, ``P_i = R e_i + t``); between two poses the points move by Theorem 1,
``P'_i = W P_i + V v + A a`` (eqs. 3-6), and the filter minimises the residual of eq. 13.
Because only motion is estimated, the filter works on any pose6d stream (optical or
not) and predicts the pose any horizon ahead by applying Theorem 1 to the last pose.

Choices the paper leaves open, and why:

* Points are taken relative to the body's previous origin ``C`` (fig. 7), so ``v`` is the
  velocity of the body, not of the world origin dragged along by the rotation.
* The implicit measurement ``f(x, s) = 0`` (eq. 13) is used in its equivalent explicit
  form: the current points are the measurement and the previous points a parameter of
  ``h``; the noise of both enters as ``R = R_cur + W R_prev W^T`` (the paper's
  ``df/dx R df/dx^T`` with ``df/dx`` of eq. 14).  That is filterpy's
  ``ExtendedKalmanFilter`` exactly, and the time update (eq. 12) is its linear ``F``.
* The printed eq. 16 term ``(omega^T P) I`` of d(omega~^2 P)/d(omega) should read
  ``omega P^T``; the Jacobian below is the corrected one, checked against finite
  differences in the tests (the printed one fails that check).
* Near ``theta dt -> 0`` every coefficient is evaluated from its Taylor series, not only
  at ``omega = 0`` (the paper's limits), so there is no cancellation for small but
  non-zero rotations either.
* An abrupt change of motion (figs. 12-14) shows as an innovation far outside its
  covariance.  The filter then re-opens its covariance to the initial one (a manoeuvre
  detector), so it re-converges in a few frames instead of trusting the old motion.

Dorfmüller-Ulhaas: Dorfmüller-Ulhaas, *Robust Optical User Motion Tracking Using a Kalman
Filter*.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.fusion.state import check_config

#: below this rotation per step (rad) the coefficient functions use their Taylor series
_SERIES_BELOW = 0.2
#: Taylor coefficients in x^0, x^2, x^4, x^6 of c1..c4, d1..d4 as functions of x = theta dt
#: (the scale dt^k is applied separately); truncation error < 1e-11 relative below 0.2.
_SERIES = np.array([
    [1.0, -1 / 6, 1 / 120, -1 / 5040],
    [1 / 2, -1 / 24, 1 / 720, -1 / 40320],
    [1 / 6, -1 / 120, 1 / 5040, -1 / 362880],
    [1 / 24, -1 / 720, 1 / 40320, -1 / 3628800],
    [-1 / 3, 1 / 30, -1 / 840, 1 / 45360],
    [-1 / 12, 1 / 180, -1 / 6720, 1 / 453600],
    [-1 / 60, 1 / 1260, -1 / 60480, 1 / 4989600],
    [-1 / 360, 1 / 10080, -1 / 604800, 1 / 59875200],
])
_DT_EXPONENTS = np.array([1, 2, 3, 4, 3, 4, 5, 6])
_MAX_ITERATIONS = 5
_ITERATION_TOL = 1e-12


def _dt_powers(dt: float) -> np.ndarray:
    return dt ** _DT_EXPONENTS


@dataclass(frozen=True)
class PredictorConfig:
    """Noise model and behaviour of the predictor.

    Process noise is a random walk of each motion parameter with the given intensity per
    second (``std**2 * dt`` per step), so streams with irregular timing are handled.
    """

    point_std_m: float = 1e-3          # noise of each measured rigid-body point
    lever_m: float = 1.0               # length of the basis vectors e_i (eq. 11)
    omega_walk: float = 1.0            # rad/s per sqrt(s)
    velocity_walk: float = 1.0         # m/s per sqrt(s)
    accel_walk: float = 1.0            # m/s^2 per sqrt(s)
    initial_std: tuple[float, float, float] = (10.0, 10.0, 10.0)  # omega, v, a
    manoeuvre_nis: float = 33.7        # chi-square(9) at 99.99 %: re-open the covariance
    max_gap_s: float = 0.5             # a longer silence restarts the filter

    def __post_init__(self) -> None:
        check_config(self, "predictor config",
                     positive=("point_std_m", "lever_m", "max_gap_s", "manoeuvre_nis"),
                     non_negative=("omega_walk", "velocity_walk", "accel_walk"),
                     initial_std="omega, v, a")


@dataclass(frozen=True)
class MotionCoefficients:
    """Scalar coefficients of W, V, A (eqs. 4-6) and of their derivatives (eq. 16).

    ``c[k]`` multiplies ``omega~`` or ``omega~^2``; ``d[k] = (dc[k]/d theta) / theta``
    so that ``d(c(theta) M) / d omega = M (d[k] omega^T) + c ...``.
    """

    c1: float  # sin(x)/theta                      W, omega~
    c2: float  # (1-cos x)/theta^2                 W omega~^2, V omega~
    c3: float  # (x - sin x)/theta^3               V omega~^2, A omega~
    c4: float  # (x^2 - 2(1-cos x))/(2 theta^4)    A omega~^2
    d1: float
    d2: float
    d3: float
    d4: float


def coefficients(theta: float, dt: float) -> MotionCoefficients:
    """The coefficient functions at ``theta = |omega|`` and step ``dt``, stable near 0."""
    x = theta * dt
    if x < _SERIES_BELOW:
        x2 = x * x
        powers = np.array([1.0, x2, x2 * x2, x2 * x2 * x2])
        c = _SERIES @ powers * _dt_powers(dt)
        return MotionCoefficients(*c)
    s, c = np.sin(x), np.cos(x)
    t = theta
    return MotionCoefficients(
        c1=s / t,
        c2=(1 - c) / t**2,
        c3=(x - s) / t**3,
        c4=(x * x - 2 * (1 - c)) / (2 * t**4),
        d1=(x * c - s) / t**3,
        d2=(x * s - 2 * (1 - c)) / t**4,
        d3=(3 * s - x * (2 + c)) / t**5,
        d4=(4 * (1 - c) - x * x - x * s) / t**6,
    )


def motion_matrices(omega: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``W, V, A`` of Theorem 1 (eqs. 4-6) for angular velocity ``omega`` over ``dt``."""
    k = coefficients(float(np.linalg.norm(omega)), dt)
    Om = geo.skew(omega)
    Om2 = Om @ Om
    eye = np.eye(3)
    W = eye + k.c1 * Om + k.c2 * Om2
    V = dt * eye + k.c2 * Om + k.c3 * Om2
    A = 0.5 * dt * dt * eye + k.c3 * Om + k.c4 * Om2
    return W, V, A


def _d_term(omega: np.ndarray, u: np.ndarray, c_lin: float, c_sq: float, d_lin: float,
            d_sq: float) -> np.ndarray:
    """d/d omega of ``(c_lin omega~ + c_sq omega~^2) u`` (3x3)."""
    Om = geo.skew(omega)
    wu = Om @ u
    wwu = Om @ wu
    # d(omega~ u) = -u~ ;  d(omega~^2 u) = -omega~ u~ - (omega x u)~   (product rule)
    d_om_u = -geo.skew(u)
    d_om2_u = -Om @ geo.skew(u) - geo.skew(wu)
    return (np.outer(wu, omega) * d_lin + np.outer(wwu, omega) * d_sq
            + c_lin * d_om_u + c_sq * d_om2_u)


def point_motion_jacobian(omega: np.ndarray, point: np.ndarray, v: np.ndarray, a: np.ndarray,
                          dt: float) -> np.ndarray:
    """Eq. 16: d(W P + V v + A a)/d omega, a 3x3 matrix, valid down to omega = 0."""
    k = coefficients(float(np.linalg.norm(omega)), dt)
    return (_d_term(omega, point, k.c1, k.c2, k.d1, k.d2)
            + _d_term(omega, v, k.c2, k.c3, k.d2, k.d3)
            + _d_term(omega, a, k.c3, k.c4, k.d3, k.d4))


def moved_points(state: np.ndarray, points: np.ndarray, dt: float) -> np.ndarray:
    """Theorem 1 applied to each row of ``points`` (n, 3): ``W P + V v + A a``."""
    W, V, A = motion_matrices(state[:3], dt)
    return points @ W.T + V @ state[3:6] + A @ state[6:9]


def measurement_jacobian(state: np.ndarray, points: np.ndarray, dt: float) -> np.ndarray:
    """Eq. 15: d f / d s for the stacked points, shape (3 n, 9)."""
    _, V, A = motion_matrices(state[:3], dt)
    rows = []
    for P in points:
        rows.append(np.hstack([point_motion_jacobian(state[:3], P, state[3:6], state[6:9], dt),
                               V, A]))
    return np.vstack(rows)


def transition(dt: float) -> np.ndarray:
    """Eq. 12: omega and a constant, v grows by a dt."""
    F = np.eye(9)
    F[3:6, 6:9] = dt * np.eye(3)
    return F


@dataclass
class _Last:
    t_s: float
    p: np.ndarray
    q: np.ndarray


@dataclass
class PredictorStats:
    updates: int = 0
    restarts: int = 0
    manoeuvres: int = 0
    last_nis: float = float("nan")


class DorfmullerPredictor:
    """Smooths and predicts a pose stream: ``update(t, p, q)`` then ``predict(horizon)``."""

    def __init__(self, config: PredictorConfig | None = None):
        self.config = config or PredictorConfig()
        L = self.config.lever_m
        self._basis = L * np.eye(3)             # e_1, e_2, e_3 as rows (eq. 11)
        self._ekf = ExtendedKalmanFilter(dim_x=9, dim_z=9)
        self._ekf.x = np.zeros(9)
        self._last: _Last | None = None
        self._since_restart = 0
        self.stats = PredictorStats()
        self._reset_covariance()

    # ------------------------------------------------------------------ state

    @property
    def omega(self) -> np.ndarray:
        """Estimated angular velocity (rad/s, world axes)."""
        return self._ekf.x[0:3].copy()

    @property
    def velocity(self) -> np.ndarray:
        """Estimated translational velocity of the body origin (m/s)."""
        return self._ekf.x[3:6].copy()

    @property
    def acceleration(self) -> np.ndarray:
        """Estimated translational acceleration (m/s^2)."""
        return self._ekf.x[6:9].copy()

    @property
    def covariance(self) -> np.ndarray:
        return self._ekf.P.copy()

    @property
    def ready(self) -> bool:
        """True once two poses have been seen since the (re)start: motion is estimated."""
        return self._since_restart > 0

    def _reset_covariance(self) -> None:
        so, sv, sa = self.config.initial_std
        self._ekf.P = np.diag([so**2] * 3 + [sv**2] * 3 + [sa**2] * 3)

    def restart(self) -> None:
        """Forget the motion (after a long gap or on request)."""
        self._ekf.x = np.zeros(9)
        self._reset_covariance()
        self._last = None
        self._since_restart = 0
        self.stats.restarts += 1

    # ------------------------------------------------------------------ filtering

    def _points(self, q: np.ndarray) -> np.ndarray:
        """Eq. 11 relative to the body origin: ``R e_i`` (rows)."""
        return geo.quat_rotate(q, self._basis)

    def update(self, t_s: float, p: np.ndarray, q: np.ndarray) -> float:
        """Feed one pose; returns the normalised innovation squared (NaN on the first pose).

        Raises ``ValueError`` for non-finite input, non-unit quaternions or time that does
        not increase.
        """
        p = geo.check_vector(p, "predictor position").reshape(3)
        q = geo.check_quaternion(q, "predictor quaternion").reshape(4)
        if not np.isfinite(t_s):
            raise InvalidInputError(f"predictor: timestamp {t_s!r} is not finite")
        last = self._last
        if last is not None and t_s <= last.t_s:
            raise InvalidInputError(f"predictor: timestamp {t_s:.6f} s does not increase "
                                    f"(last {last.t_s:.6f} s)")
        if last is not None and t_s - last.t_s > self.config.max_gap_s:
            self.restart()
            last = None
        if last is None:
            self._last = _Last(t_s, p, q)
            return float("nan")
        dt = t_s - last.t_s
        nis = self._step(dt, self._points(last.q), self._points(q) + (p - last.p))
        self._last = _Last(t_s, p, q)
        return nis

    def _step(self, dt: float, prev_pts: np.ndarray, cur_pts: np.ndarray) -> float:
        cfg = self.config
        ekf = self._ekf
        ekf.F = transition(dt)
        ekf.Q = np.diag([cfg.omega_walk**2] * 3 + [cfg.velocity_walk**2] * 3
                        + [cfg.accel_walk**2] * 3) * dt
        ekf.predict()
        z = cur_pts.reshape(9)
        R = 2.0 * cfg.point_std_m**2 * np.eye(9)   # R_cur + W R_prev W^T, W orthonormal
        nis = self._nis(z, prev_pts, dt, R)
        if nis > cfg.manoeuvre_nis:
            self._reset_covariance()
            self.stats.manoeuvres += 1
        self._iterated_update(z, prev_pts, dt, R)
        self.stats.updates += 1
        self._since_restart += 1
        self.stats.last_nis = nis
        return nis

    def _iterated_update(self, z: np.ndarray, prev_pts: np.ndarray, dt: float,
                         R: np.ndarray) -> None:
        """Iterated EKF update (Gauss-Newton on eq. 13 with the prior as regulariser).

        filterpy's single-linearisation update is not enough here: linearised at a far-off
        prior (the first frame, or right after a manoeuvre) it leaves a bias in omega that
        the small process noise then carries for many frames; re-linearising at the new
        estimate removes it in two or three passes.  filterpy has no iterated EKF.
        """
        ekf = self._ekf
        x0, P = ekf.x.copy(), ekf.P
        x = x0.copy()
        for _ in range(_MAX_ITERATIONS):
            H = measurement_jacobian(x, prev_pts, dt)
            PHt = P @ H.T
            K = np.linalg.solve(H @ PHt + R, PHt.T).T
            x_next = x0 + K @ (z - moved_points(x, prev_pts, dt).reshape(9) - H @ (x0 - x))
            converged = np.max(np.abs(x_next - x)) < _ITERATION_TOL
            x = x_next
            if converged:
                break
        I_KH = np.eye(9) - K @ H
        P = I_KH @ P @ I_KH.T + K @ R @ K.T          # Joseph form keeps P positive
        ekf.x = x
        ekf.P = 0.5 * (P + P.T)

    def _nis(self, z: np.ndarray, prev_pts: np.ndarray, dt: float, R: np.ndarray) -> float:
        """Normalised innovation squared of the predicted points: the manoeuvre test."""
        x = self._ekf.x
        H = measurement_jacobian(x, prev_pts, dt)
        y = z - moved_points(x, prev_pts, dt).reshape(9)
        S = H @ self._ekf.P @ H.T + R
        return float(y @ np.linalg.solve(S, y))

    # ------------------------------------------------------------------ prediction

    def predict(self, horizon_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The pose ``horizon_s`` after the last measurement (F_4 of the paper).

        Theorem 1 moves the last measured pose by the estimated motion: rotation
        ``W R`` and translation ``t + V v' + A a`` with ``v' = v + a horizon`` (eq. 12).
        """
        if self._last is None:
            raise InvalidInputError("predictor: no pose received yet")
        if not (np.isfinite(horizon_s) and horizon_s >= 0):
            raise InvalidInputError(f"predictor: horizon must be a finite number >= 0 s, "
                                    f"got {horizon_s!r}")
        if horizon_s == 0:
            return self._last.p.copy(), self._last.q.copy()
        x = self._ekf.x.copy()
        x[3:6] = x[3:6] + x[6:9] * horizon_s
        W, V, A = motion_matrices(x[:3], horizon_s)
        q = geo.quat_multiply(geo.matrix_to_quat(W), self._last.q)
        p = self._last.p + V @ x[3:6] + A @ x[6:9]
        return p, q / np.linalg.norm(q)
