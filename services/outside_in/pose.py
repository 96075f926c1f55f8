"""A body's pose from its markers: absolute orientation, then refinement on the images.

The first estimate aligns the body's markers to their triangulated points (Kabsch /
Umeyama without scale: scipy's ``Rotation.align_vectors``).  The refinement then fits the
pose to every camera's 2D observation of every identified marker
(``scipy.optimize.least_squares``, residuals in pixels divided by each centroid's std),
which weighs each ray by what it measured instead of trusting triangulated points
equally, and gives the covariance ``(J^T J)^-1`` of the pose.

Observations of cameras exposed at other times than the pose's time ``t`` are moved to it
with the filter's velocities (``Motion``): the marker a camera saw ``tau`` seconds after
``t`` stood at ``Exp(omega tau) R m + p + v tau + a tau^2 / 2``.  Unsynchronised cameras
then refine one pose instead of several poses blurred together.

The pose is ``world -> body``: ``x_world = R x_body + p``; the covariance is over
``[dp, phi]`` with ``R_true = Exp(phi) R`` (geometry's decoupled form).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from agent import geometry as geo
from agent.runtime import compiled_twin
from services.outside_in.rig import RigCamera

Array = np.ndarray


def absolute_orientation(body_points: Array, world_points: Array) -> tuple[Array, Array]:
    """``(R, p)`` minimising ``sum |R b_i + p - w_i|^2`` (needs 3 or more points)."""
    b = np.asarray(body_points, float)
    w = np.asarray(world_points, float)
    cb, cw = b.mean(axis=0), w.mean(axis=0)
    rot, _ = Rotation.align_vectors(w - cw, b - cb)
    R = rot.as_matrix()
    return R, cw - R @ cb


@dataclass(frozen=True)
class Observation:
    """Markers of one body seen by one camera: which markers, where (normalised), how
    well (std in pixels), and when relative to the pose's time."""

    camera: RigCamera
    markers: Array   # (k,) marker indices
    xy: Array        # (k, 2) undistorted normalised coordinates
    std_px: Array    # (k,)
    dt_s: float = 0.0
    index: int = -1  # the camera's index in its rig (for the caller's bookkeeping)


@dataclass(frozen=True)
class Rows:
    """A fit's observations as one row per marker image, each camera's fields repeated
    for its markers, in the order the fit sums them (one camera's rows together): the
    tracker gathers them once per body and frame set and drops an outlier by its row,
    where a list of ``Observation`` was built again for every fit."""

    camera: Array   # (k,) int: which camera (its rows together)
    stack: Array    # (k, 13) the camera's ``RigCamera.stack_row``
    markers: Array  # (k,) marker indices
    xy: Array       # (k, 2) undistorted normalised coordinates
    std_px: Array   # (k,)
    dt_s: Array     # (k,) the camera's exposure time less the pose's time

    def __len__(self) -> int:
        return len(self.markers)

    @staticmethod
    def of(observations: list[Observation]) -> Rows:
        """The rows of ``observations``, in their order (cameras told apart by name)."""
        counts = [len(o.markers) for o in observations]
        names: dict[str, int] = {}
        ids = [names.setdefault(o.camera.name, len(names)) for o in observations]
        return Rows(np.repeat(np.array(ids, int), counts),
                    np.repeat(np.array([o.camera.stack_row for o in observations]).reshape(
                        -1, 13), counts, axis=0),
                    np.concatenate([o.markers for o in observations]).astype(int),
                    np.concatenate([o.xy for o in observations]).astype(float).reshape(-1, 2),
                    np.concatenate([o.std_px for o in observations]).astype(float).reshape(-1),
                    np.repeat(np.array([o.dt_s for o in observations], float), counts))

    def take(self, rows: Array) -> Rows:
        """The rows selected by ``rows`` (a mask or indices, in order)."""
        return Rows(self.camera[rows], self.stack[rows], self.markers[rows], self.xy[rows],
                    self.std_px[rows], self.dt_s[rows])


@dataclass(frozen=True)
class Motion:
    """Velocities that move observations to the pose's time (world frame), and their
    covariance (6 x 6 over ``[velocity, omega]``, or 9 x 9 over ``[velocity, omega,
    accel]``; None: taken as exact)."""

    velocity: Array   # m/s
    omega: Array      # rad/s
    cov: Array | None = None
    accel: Array | None = None   # m/s^2: a camera exposed dt away saw the body moved by
                                 # v dt + a dt^2 / 2 (0.1 mm at 3 m/s^2 over 8 ms)


@dataclass(frozen=True)
class PoseFit:
    p: Array
    R: Array
    cov: Array        # (6, 6) over [dp, phi]
    rms_px: float
    n_observations: int
    n_cameras: int
    errors_px: Array  # (n_observations,) each marker image's distance from the fit, in the
                      # order of the observations and their markers
    sensitivity: Array | None = None   # (6, 9) d pose / d [v, omega, accel] of the motion
                                       # the fit was given (None: no camera moved)
    noise_cov: Array | None = None     # (6, 6) the centroids' part of cov: cov less what the
                                       # given motion's error adds

    @property
    def q(self) -> Array:
        return geo.matrix_to_quat(self.R)


def refine_pose(markers: Array, observations: list[Observation], p0: Array, R0: Array,
                motion: Motion | None = None) -> PoseFit | None:
    """The pose that best explains the observations; None with fewer than 3 markers seen
    or fewer than 2 cameras (no depth), or when the fit fails."""
    obs = [o for o in observations if len(o.markers)]
    if not obs:
        return None
    return refine_rows(markers, Rows.of(obs), p0, R0, motion)


def refine_rows(markers: Array, rows: Rows, p0: Array, R0: Array,
                motion: Motion | None = None) -> PoseFit | None:
    """``refine_pose`` of observations given as ``Rows``."""
    cams = len(set(rows.camera.tolist()))
    if cams < 2 or len(set(rows.markers.tolist())) < 3:
        return None
    m = np.asarray(markers, float)
    stack = _Stack.of(rows, m, motion)
    p0 = np.asarray(p0, float)
    R0 = np.asarray(R0, float)
    zero = np.zeros(6)
    solved = _gauss_newton(stack, p0, R0)
    if solved is None:
        try:
            sol = least_squares(lambda x: stack.residual(x, p0, R0), zero,
                                jac=lambda x: stack.jacobian(x, p0, R0), method="lm",
                                xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=50)
        except (ValueError, np.linalg.LinAlgError):
            return None
        p, R = p0 + sol.x[:3], geo.rodrigues(sol.x[3:]) @ R0
        J = stack.jacobian(zero, p, R)   # at the solution itself: the perturbation zero
    else:
        p, R, J = solved
    info = J.T @ J
    if not np.all(np.isfinite(info)):
        return None
    # its condition number (eigenvalues, not np.linalg.cond's SVD: the same for a
    # symmetric matrix, at a third of the cost)
    low, high = np.linalg.eigvalsh(info)[[0, -1]]
    if not low > high * 1e-14:
        return None
    noise = np.linalg.inv(info)
    noise = 0.5 * (noise + noise.T)
    cov = noise
    S = _sensitivity(stack, p, R, J, noise) if motion is not None else None
    if S is not None and motion.cov is not None:
        Sm = S[:, :len(motion.cov)]
        cov = noise + Sm @ motion.cov @ Sm.T
        cov = 0.5 * (cov + cov.T)
    pix = stack.pixels(zero, p, R)
    return PoseFit(p, R, cov, float(np.sqrt(np.mean(pix ** 2))), len(pix), cams, pix, S,
                   noise)


#: Gauss-Newton steps at most, and the step (m, rad) below which the fit has converged
GN_STEPS = 8
GN_TOLERANCE = 1e-10


def _gauss_newton(stack: _Stack, p: Array, R: Array) -> tuple[Array, Array, Array] | None:
    """The fit by Gauss-Newton steps on the pose itself (each step a left perturbation,
    relinearised where it lands), with the Jacobian at the solution; None when a step
    does not lower the cost or it has not converged (``least_squares``' Levenberg-
    Marquardt then takes over).  From a tracked body's prediction two or three steps
    converge; ``least_squares`` costs about a millisecond per call before its first
    step, more than the whole fit, three bodies a frame set at 120 Hz.  The compiled
    twin (``_fit.c``) takes the same steps."""
    if FIT is not None:
        c = np.ascontiguousarray
        got = FIT.gauss_newton(c(stack.R_cw), c(stack.t_cw), c(stack.xy), c(stack.scale),
                               c(stack.turn), c(stack.shift), c(stack.body), c(p, float),
                               c(R, float), GN_STEPS, GN_TOLERANCE)
        if got is None:
            return None
        return (np.frombuffer(got[0]).copy(), np.frombuffer(got[1]).reshape(3, 3).copy(),
                np.frombuffer(got[2]).reshape(-1, 6).copy())
    zero = np.zeros(6)
    r = stack.residual(zero, p, R)
    cost = r @ r
    for _ in range(GN_STEPS):
        J = stack.jacobian(zero, p, R)
        try:
            dx = -np.linalg.solve(J.T @ J, J.T @ r)
        except np.linalg.LinAlgError:
            return None
        p_new, R_new = p + dx[:3], geo.rodrigues(dx[3:]) @ R
        r = stack.residual(zero, p_new, R_new)
        new_cost = r @ r
        if not new_cost <= cost * (1 + 1e-9):
            return None
        p, R, cost = p_new, R_new, new_cost
        if np.max(np.abs(dx)) < GN_TOLERANCE:
            return p, R, stack.jacobian(zero, p, R)
    return None


#: the compiled fit in use (tests set it to None to run the pure-Python one)
FIT: Any = compiled_twin("services.outside_in._fit", "UMA_FIT_PURE_PYTHON")


def _sensitivity(stack: _Stack, p: Array, R: Array, J: Array, cov: Array) -> Array | None:
    """How the fitted pose moves with the motion it was given: 6 x 9 by ``[v, omega,
    accel]``, None when every camera exposed at the pose's time.  A velocity error dv
    moves every observation of a camera exposed ``dt`` from the pose's time by the same
    ``dv dt`` (an acceleration error by ``da dt^2 / 2``, a turn rate error turns them by
    ``dw dt``): one error shared by all of that camera's markers, which the
    observations' own stds, taken as independent, cannot carry.  With ``B`` the
    residuals' derivative by the motion, the fit moves by ``S = -cov J^T B`` per unit of
    its error: ``S P S^T`` is what a motion of covariance ``P`` adds to the pose's
    covariance, and a filter whose own motion it was takes the fit as a measurement of
    its pose less ``S`` times its motion's error (``motion.MotionFilter.update``)."""
    dt = stack.dt
    if not np.any(dt):
        return None
    by = stack.by_shift_and_turn(np.zeros(6), p, R) * stack.scale[:, None, None]
    B = np.concatenate([by * dt[:, None, None], by[:, :, :3] * (0.5 * dt * dt)[:, None, None]],
                       axis=2).reshape(-1, 9)
    return -cov @ (J.T @ B)


_EYE3 = np.eye(3)


def _moved(motion: Motion | None, dt_s: float) -> tuple[Array, Array]:
    """``Exp(omega dt)`` and ``v dt + a dt^2 / 2``: how far the body moved between two
    exposures."""
    if motion is None or dt_s == 0.0:
        return np.eye(3), np.zeros(3)
    shift = np.asarray(motion.velocity, float) * dt_s
    if motion.accel is not None:
        shift = shift + 0.5 * dt_s * dt_s * np.asarray(motion.accel, float)
    return geo.rodrigues(np.asarray(motion.omega, float) * dt_s), shift


@dataclass(frozen=True)
class _Stack:
    """Every observed marker image of a fit, stacked, with residuals in units of its std."""

    R_cw: Array      # (k, 3, 3)
    t_cw: Array      # (k, 3)
    focal: Array     # (k,)
    body: Array      # (k, 3) marker positions in the body frame
    xy: Array        # (k, 2)
    scale: Array     # (k,) focal / std: normalised units -> standard deviations
    turn: Array      # (k, 3, 3) Exp(omega dt)
    shift: Array     # (k, 3) v dt
    dt: Array        # (k,) exposure time minus the pose's time
    moving: bool     # whether any observation is moved (else turn is I, shift 0)
    last: dict       # the last pose's camera points (``_camera_points``)

    @staticmethod
    def of(rows: Rows, markers: Array, motion: Motion | None) -> _Stack:
        k = len(rows)
        focal = rows.stack[:, 12]
        dt = rows.dt_s
        moving = motion is not None and bool(np.any(dt != 0.0))
        if moving:   # each camera's motion once, for its rows
            times, at = np.unique(dt, return_inverse=True)
            moved = [_moved(motion, float(t)) for t in times]
            turn = np.array([turn for turn, _ in moved])[at]
            shift = np.array([shift for _, shift in moved])[at]
        else:   # every camera at the pose's time: nothing moves
            turn = np.broadcast_to(_EYE3, (k, 3, 3))
            shift = np.zeros((k, 3))
        return _Stack(rows.stack[:, :9].reshape(k, 3, 3), rows.stack[:, 9:12], focal,
                      markers[rows.markers], rows.xy, focal / rows.std_px, turn, shift, dt,
                      moving, {})

    def _camera_points(self, x: Array, p0: Array, R0: Array) -> tuple[Array, Array]:
        """The markers in each observing camera's frame, and their arms ``Exp(omega dt) R
        m`` (kept for the last pose ``p0, R0`` itself, unperturbed: a Gauss-Newton step
        asks residuals and then the Jacobian there)."""
        at = self.last.get("at")
        still = not x.any()
        if still and at is not None and at[0] is p0 and at[1] is R0:
            return self.last["points"]
        R = R0 if still else geo.rodrigues(x[3:]) @ R0
        arm = self.body @ R.T
        if self.moving:
            arm = np.einsum("kij,kj->ki", self.turn, arm)   # Exp(omega dt) R m
        world = arm + p0 + x[:3] + self.shift
        got = np.einsum("kij,kj->ki", self.R_cw, world) + self.t_cw, arm
        if still:
            self.last["at"], self.last["points"] = (p0, R0), got
        return got

    def pixels(self, x: Array, p0: Array, R0: Array) -> Array:
        xc, _ = self._camera_points(x, p0, R0)
        d = (xc[:, :2] / xc[:, 2:3] - self.xy) * self.focal[:, None]
        return np.hypot(d[:, 0], d[:, 1])

    def residual(self, x: Array, p0: Array, R0: Array) -> Array:
        xc, _ = self._camera_points(x, p0, R0)
        return ((xc[:, :2] / xc[:, 2:3] - self.xy) * self.scale[:, None]).reshape(-1)

    def jacobian(self, x: Array, p0: Array, R0: Array) -> Array:
        """Residuals by ``[dp, phi]`` (a world-frame shift and left turn of the body)."""
        J = self.by_shift_and_turn(x, p0, R0)
        return (J * self.scale[:, None, None]).reshape(-1, 6)

    def by_shift_and_turn(self, x: Array, p0: Array, R0: Array) -> Array:
        """Each marker image's derivative (k, 2, 6), normalised units, by a shift of its
        marker in the world and a left turn of its arm about the body's origin."""
        xc, arm = self._camera_points(x, p0, R0)
        z = xc[:, 2]
        proj = xc[:, :2] / z[:, None]
        # d proj / d world (k, 2, 3)
        dpw = (self.R_cw[:, :2, :] - proj[:, :, None] * self.R_cw[:, 2:3, :]) / z[:, None, None]
        # d world / d phi = -Exp(omega dt) [R m]x ~ -[arm]x  (left perturbation; omega dt
        # is a fraction of a degree between two cameras' exposures)
        dphi = np.einsum("kij,kjl->kil", dpw, -geo.skew(arm))
        return np.concatenate([dpw, dphi], axis=2)
