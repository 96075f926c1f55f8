"""The accelerometer rig: where each single-axis accelerometer sits and what it senses.

Seed 003 §4.2: accelerometer j at position ``r_j`` (rig frame) sensing along the unit axis
``n_j`` reads the specific force at its position projected on its axis (eq. 4.36/4.72):

    a_j = n_j . (f + omega_dot x r_j + omega x (omega x r_j))

with ``f`` the specific force at the rig origin in rig axes (kinematic acceleration minus
gravity: a rig at rest with z up reads f = [0, 0, +9.81]).  Moving the centripetal term to
the left gives the general linear system of eq. 4.42,

    a_j - Omega_j(omega) = [n_j^T, (r_j x n_j)^T] [f; omega_dot],

which handles misaligned axes and any layout whose N x 6 matrix has rank 6.  The
centripetal term is linear in the six entries of ``W = omega omega^T``; with nine or more
accelerometers placed like Padgaonkar's 3-2-2-2 rig (Hogue 2003, §4.2, its ref. [50]) the
off-diagonal entries of W can be solved for together with ``f`` and ``omega_dot``, so the
angular acceleration no longer needs an angular-velocity estimate (``RigLayout.omega_free``).

This module is pure computation (numpy only): the measurement model ``h`` and its Jacobian
are what the fusion EKF's SCAAT update uses one accelerometer at a time.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass, field

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.frames import GRAVITY

Array = np.ndarray

#: Half-distance between the accelerometers of a pair (m).  The thesis leaves delta
#: unspecified; 5 cm matches the palm-sized aluminium housing of its figure 4.8.
DEFAULT_DELTA_M = 0.05

#: Table 4.1: sensing axes of the real device, as calibrated (rig frame, accelerometers 1-6).
TABLE_4_1_AXES = np.array([
    [0.004454, -0.025742, -0.999659],
    [0.012620, 0.000073, -0.999920],
    [-0.016351, -0.999858, 0.004054],
    [0.000157, -0.999978, -0.006581],
    [-0.999843, 0.009090, -0.015183],
    [-0.999651, -0.013739, -0.022575],
])

#: A layout whose solve matrix has a condition number above this is refused: its
#: accelerometers do not observe all six rigid-body accelerations usefully.
MAX_CONDITION = 1e6

# Index pairs of the six entries of the symmetric W = omega omega^T: xx yy zz xy yz xz.
_W_ROWS = np.array([0, 1, 2, 0, 1, 0])
_W_COLS = np.array([0, 1, 2, 1, 2, 2])
_W_OFFDIAG = np.array([3, 4, 5])
_W_DIAG = np.array([0, 1, 2])


@dataclass(frozen=True)
class RigLayout:
    """N single-axis accelerometers: positions (N, 3) in m and unit axes (N, 3), rig frame.

    Construction validates the layout and refuses one whose system (eq. 4.42) is singular
    or badly conditioned, naming what is missing.  Axes are normalised (refused if their
    norm is off by more than 1 %, which is a typo, not a misalignment).
    """

    positions: Array
    axes: Array
    name: str = "custom"
    _cent: Array = field(init=False, repr=False, compare=False)
    _pred: Array = field(init=False, repr=False, compare=False)
    _proj: Array = field(init=False, repr=False, compare=False)
    _corr: Array = field(init=False, repr=False, compare=False)
    _proj_rows: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)
    _corr_rows: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        r = geo.check_vector(self.positions, "accelerometer positions")
        n = geo.check_vector(self.axes, "accelerometer axes")
        if r.ndim != 2 or n.shape != r.shape:
            raise InvalidInputError(f"accelerometer layout: positions {r.shape} and axes {n.shape} "
                                    "must both be (N, 3)")
        if r.shape[0] < 6:
            raise InvalidInputError(f"accelerometer layout: {r.shape[0]} accelerometers cannot "
                                    "observe the 6 rigid-body accelerations (need at least 6)")
        norms = np.linalg.norm(n, axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > 0.01)
        if bad.size:
            raise InvalidInputError(f"accelerometer layout: axis {int(bad[0]) + 1} has norm "
                                    f"{norms[bad[0]]:.4g}, expected a unit vector")
        n = n / norms[:, None]
        object.__setattr__(self, "positions", r)
        object.__setattr__(self, "axes", n)
        self._build_solver()

    # ------------------------------------------------------------------ structure

    @property
    def count(self) -> int:
        """Number of accelerometers N."""
        return self.positions.shape[0]

    @property
    def system_matrix(self) -> Array:
        """The N x 6 matrix of eq. 4.42: rows ``[n_j^T, (r_j x n_j)^T]``."""
        return np.hstack([self.axes, np.cross(self.positions, self.axes)])

    @property
    def omega_free(self) -> bool:
        """True if the angular acceleration is solved without an angular-velocity estimate."""
        return self._pred.size < 6

    def _centripetal(self) -> Array:
        r, n = self.positions, self.axes
        M = 0.5 * (n[:, :, None] * r[:, None, :] + r[:, :, None] * n[:, None, :])
        M -= np.einsum("ij,ij->i", n, r)[:, None, None] * np.eye(3)
        C = M[:, _W_ROWS, _W_COLS]
        C[:, 3:] *= 2.0  # off-diagonal entries appear twice in omega^T M omega
        return C

    def _build_solver(self) -> None:
        """Choose the unknowns and precompute the pseudo-inverse of the linear system.

        Caches ``_proj`` (6 x N: readings to [f; omega_dot]) and ``_corr`` (6 x 6: the
        correction per entry xx yy zz xy yz xz of omega omega^T, zero for the entries the
        layout solves for), and both as rows of plain floats for the per-sample path.
        """
        H = self.system_matrix
        rank = np.linalg.matrix_rank(H, tol=1e-9 * max(1.0, np.abs(H).max()))
        if rank < 6:
            raise InvalidInputError(f"singular accelerometer layout {self.name!r}: the system of "
                                    f"eq. 4.42 has rank {rank} < 6 ({self._unobserved(H)}); "
                                    "move or turn accelerometers so every axis and every rotation "
                                    "is sensed")
        cond = np.linalg.cond(H)
        if cond > MAX_CONDITION:
            raise InvalidInputError(f"near-singular accelerometer layout {self.name!r}: condition "
                                    f"number {cond:.3g} > {MAX_CONDITION:g}")
        C = self._centripetal()
        solved, A = np.array([], dtype=int), H
        if self.count >= 9:
            A9 = np.hstack([H, C[:, _W_OFFDIAG]])
            if np.linalg.cond(A9) < MAX_CONDITION:
                solved, A = _W_OFFDIAG, A9
        pred = np.setdiff1d(np.arange(6), solved)
        proj = np.linalg.pinv(A)[:6]
        corr = np.zeros((6, 6))  # (output, entry of omega omega^T)
        corr[:, pred] = -proj @ C[:, pred]
        cache = {"_cent": C, "_pred": pred, "_proj": proj, "_corr": corr,
                 "_proj_rows": tuple(map(tuple, proj.tolist())),
                 "_corr_rows": tuple(map(tuple, corr.tolist()))}
        for name, value in cache.items():
            object.__setattr__(self, name, value)

    @staticmethod
    def _unobserved(H: Array) -> str:
        """Name the rigid-body acceleration direction the layout cannot see."""
        _, _, vt = np.linalg.svd(H)
        v = vt[-1]
        lin, ang = v[:3], v[3:]
        part = "linear acceleration" if np.linalg.norm(lin) >= np.linalg.norm(ang) \
            else "angular acceleration"
        d = lin if part == "linear acceleration" else ang
        d = d / np.linalg.norm(d)
        return f"unobserved {part} along [{d[0]:.2f}, {d[1]:.2f}, {d[2]:.2f}]"

    # ------------------------------------------------------------------ measurement model

    def readings(self, specific_force: Array, omega: Array, omega_dot: Array) -> Array:
        """Eq. 4.36: the N readings (m/s^2) for rig-frame specific force, omega, omega_dot.

        Inputs broadcast over leading axes: (..., 3) each gives (..., N).
        """
        f = np.asarray(specific_force, float)
        w = np.asarray(omega, float)
        wd = np.asarray(omega_dot, float)
        r = self.positions
        # a(r_j) = f + wd x r_j + w x (w x r_j) = f + wd x r_j + w (w.r_j) - r_j |w|^2
        at = (f[..., None, :] + np.cross(wd[..., None, :], r)
              + w[..., None, :] * (w @ r.T)[..., None]
              - r * np.sum(w * w, axis=-1)[..., None, None])
        return np.einsum("...ji,ji->...j", at, self.axes)

    def h(self, accel_world: Array, quaternion: Array, omega: Array, omega_dot: Array,
          gravity: Array = GRAVITY) -> Array:
        """The N readings for a rig with world acceleration, orientation (rig in world, xyzw),
        body angular velocity and body angular acceleration: the EKF measurement model."""
        f = geo.quat_rotate(geo.quat_conjugate(quaternion),
                            np.asarray(accel_world, float) - gravity)
        return self.readings(f, omega, omega_dot)

    def h_jacobian(self, accel_world: Array, quaternion: Array, omega: Array,
                   omega_dot: Array, gravity: Array = GRAVITY) -> Array:
        """N x 12 Jacobian of ``h`` w.r.t. ``[accel_world, dtheta, omega, omega_dot]``.

        ``dtheta`` is the world-frame (left) rotation error of geometry's covariance
        convention: ``q_true = Exp(dtheta) * q``.  One row is one accelerometer, so a SCAAT
        update takes row j alone.
        """
        R = geo.quat_to_matrix(quaternion)
        Rt = R.T
        g_free = np.asarray(accel_world, float) - gravity
        w = np.asarray(omega, float)
        r, n = self.positions, self.axes
        J = np.empty((self.count, 12))
        J[:, 0:3] = n @ Rt
        J[:, 3:6] = n @ (Rt @ geo.skew(g_free))
        # d/dw [w (w.r) - r |w|^2] = w r^T + (w.r) I - 2 r w^T
        wr = r @ w
        J[:, 6:9] = (n @ w)[:, None] * r + wr[:, None] * n \
            - 2.0 * (np.einsum("ji,ji->j", n, r))[:, None] * w[None, :]
        # n . (wd x r) = (r x n) . wd
        J[:, 9:12] = np.cross(r, n)
        return J

    # ------------------------------------------------------------------ the inverse (eq. 4.42)

    def centripetal(self, omega: Array) -> Array:
        """Omega_j = n_j . (omega x (omega x r_j)) for each accelerometer, (..., N)."""
        w = np.asarray(omega, float)
        return (w[..., _W_ROWS] * w[..., _W_COLS]) @ self._cent.T

    def project(self, readings: Array) -> Array:
        """The omega-independent part of ``solve``: ``[f; omega_dot]`` (..., 6) before the
        centripetal correction.  Linear in the readings, so it can be computed per sample."""
        return np.asarray(readings, float) @ self._proj.T

    def correction(self, omega: Array) -> Array:
        """What the centripetal terms predicted from ``omega`` add to ``project``, (..., 6)."""
        w = np.asarray(omega, float)
        return (w[..., _W_ROWS] * w[..., _W_COLS]) @ self._corr.T

    def solve(self, readings: Array, omega: Array) -> tuple[Array, Array]:
        """Eq. 4.42: rig-frame specific force and angular acceleration from N readings.

        ``omega`` (the current angular-velocity estimate) removes the centripetal terms;
        for an ``omega_free`` layout only the diagonal of ``omega omega^T`` is taken from it
        (zero weight for an ideal nine-accelerometer rig).  Least squares when N exceeds the
        number of unknowns.
        """
        x = self.project(readings) + self.correction(omega)
        return x[..., :3], x[..., 3:6]

    @property
    def correction_matrix(self) -> Array:
        """The 6 x 6 matrix of ``correction``: rows per output ``[f; omega_dot]``, columns per
        entry xx yy zz xy yz xz of omega omega^T (the dead reckoner's compiled step takes it
        as numbers, not as a method)."""
        return self._corr

    @property
    def readings_jacobian(self) -> Array:
        """d(f, omega_dot)/d(readings) of ``solve``, 6 x N (a constant of the layout)."""
        return self._proj

    # ------------------------------------------------------------------ one sample, plain floats
    # The dead reckoner solves one sample of six values at a time, 300 times a second; a numpy
    # call on such small vectors costs more than its arithmetic, so its per-sample path works on
    # Python floats.  These equal ``project``, ``solve`` and the omega derivative of ``solve``
    # to float rounding (tests/test_accel_fast_path.py checks them against numpy).

    def project_floats(self, readings: list[float]) -> list[float]:
        """``project`` of one sample of N readings: ``[f; omega_dot]`` before the correction."""
        return [sum(map(operator.mul, row, readings)) for row in self._proj_rows]

    def solve_floats(self, projected: list[float], omega: list[float]) -> list[float]:
        """``solve`` of one sample from its ``project_floats``: ``projected`` plus the
        ``correction`` for ``omega`` ``[x, y, z]``, 6 floats ``[f, omega_dot]``."""
        x, y, z = omega
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        return [p + a * xx + b * yy + c * zz + d * xy + e * yz + f * xz
                for p, (a, b, c, d, e, f) in zip(projected, self._corr_rows, strict=True)]

    def omega_jacobian_floats(self, omega: list[float]) -> list[tuple[float, float, float]]:
        """d(f, omega_dot)/d(omega) of ``solve`` at ``omega``: 6 rows of 3.  The correction is
        a quadratic form in omega, so its derivative is linear in it: d(xy)/dx = y, ..."""
        x, y, z = omega
        x2, y2, z2 = 2.0 * x, 2.0 * y, 2.0 * z
        return [(a * x2 + d * y + f * z, b * y2 + d * x + e * z, c * z2 + e * y + f * x)
                for a, b, c, d, e, f in self._corr_rows]


# ---------------------------------------------------------------------- standard layouts


def marvin_six(delta: float = DEFAULT_DELTA_M, axes: Array | None = None) -> RigLayout:
    """MARVIN's rig (Hogue 2003, §4.1, figure 4.7): three orthogonal pairs at distance delta.

    A1, A2 at -/+delta on y sense z; A3, A4 at +/-delta on x sense y; A5, A6 at -/+delta on
    z sense x (eqs. 4.20-4.25).  ``axes`` replaces the ideal sensing axes, e.g. with
    ``TABLE_4_1_AXES``.
    """
    _check_delta(delta)
    d = float(delta)
    positions = np.array([[0, -d, 0], [0, d, 0], [d, 0, 0], [-d, 0, 0], [0, 0, -d], [0, 0, d]])
    ideal = np.array([[0, 0, 1], [0, 0, 1], [0, 1, 0], [0, 1, 0], [1, 0, 0], [1, 0, 0]], float)
    return RigLayout(positions, ideal if axes is None else axes,
                     name="marvin-six" if axes is None else "marvin-six-custom-axes")


def marvin_six_table_4_1(delta: float = DEFAULT_DELTA_M) -> RigLayout:
    """MARVIN's rig with the sensing axes calibrated on the real device (table 4.1)."""
    layout = marvin_six(delta, TABLE_4_1_AXES)
    object.__setattr__(layout, "name", "marvin-six-table-4.1")
    return layout


def nine_accelerometer(delta: float = DEFAULT_DELTA_M) -> RigLayout:
    """Padgaonkar's 3-2-2-2 rig: a triad at the origin and two on each axis at delta.

    The accelerometer at ``delta e_a`` senses the two axes other than a, so pairwise
    differences cancel the centripetal terms and omega_dot needs no omega estimate.
    """
    _check_delta(delta)
    d = float(delta)
    e = np.eye(3)
    positions = [np.zeros(3)] * 3
    axes = list(e)
    for a in range(3):
        for b in range(3):
            if b != a:
                positions.append(d * e[a])
                axes.append(e[b])
    return RigLayout(np.array(positions), np.array(axes), name="nine")


LAYOUTS = {"marvin-six": marvin_six, "marvin-six-table-4.1": marvin_six_table_4_1,
           "nine": nine_accelerometer}


def layout_by_name(name: str, delta: float = DEFAULT_DELTA_M) -> RigLayout:
    """One of the standard layouts by name; ``ValueError`` listing the known ones."""
    try:
        return LAYOUTS[name](delta)
    except KeyError:
        raise InvalidInputError(f"unknown accelerometer layout {name!r} "
                                f"(known: {', '.join(LAYOUTS)})") from None


def _check_delta(delta: float) -> None:
    if not np.isfinite(delta) or delta <= 0:
        raise InvalidInputError(f"accelerometer spacing delta must be a positive length in m, "
                                f"got {delta!r}")
