"""What the fusion filter estimates and how it is set up: the error-state layout, the
accelerometer model and the noise configuration.

The state of the *head* frame follows Hogue, *MARVIN: a Mobile Automatic Realtime Visual
and INertial tracking system* (MSc thesis, York University 2003), eq. 6.1: orientation
(kept outside the vector as a quaternion, see ``services.fusion.ekf``), body angular
velocity and acceleration (head axes), position, velocity and acceleration (world).  After
those 18 come the optional blocks of ``StateLayout``.  Why the defaults of ``FusionConfig``
are what they are, with the runs that chose them, is in ``docs/FUSION_TUNING.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError

Array = np.ndarray

#: the error state's eq. 6.1 blocks: rotation error (world, left), angular velocity and
#: acceleration (head axes), position, velocity, acceleration (world)
TH, W, WD, P, V, A = (slice(3 * i, 3 * i + 3) for i in range(6))
CORE = 18
#: the head pose's rows in the error state, position first (the optics' order)
POSE_INDEX = np.r_[9:12, 0:3]

#: chi-square quantiles used as gates (99.9 %): a measurement further out is an outlier
CHI2_999 = {1: 10.828, 2: 13.816, 3: 16.266, 6: 22.458}

#: Default extra accelerometer noise (m/s^2, std) for what a calibration does not capture
#: (position errors of the drawing, axis residuals): 0.08 LSB, a quarter of the simulated
#: readings' own noise (docs/FUSION_TUNING.md says why not more).
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
    #: (N, 3, 3) the centripetal term's quadratic form: n . w x (w x r) = w^T M w
    centripetal: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        r = geo.check_vector(self.positions, "accelerometer positions")
        n = geo.check_vector(self.axes, "accelerometer axes")
        var = np.asarray(self.variance, float).reshape(-1)
        if r.ndim != 2 or n.shape != r.shape or var.shape != (r.shape[0],):
            raise InvalidInputError(f"accel model: positions {r.shape}, axes {n.shape} and "
                                    f"variance {var.shape} must be (N, 3), (N, 3), (N,)")
        if not np.all(np.isfinite(var)) or np.any(var <= 0):
            raise InvalidInputError("accel model: reading variances must be positive and finite")
        if not (math.isfinite(self.latency_s) and self.latency_s >= 0):
            raise InvalidInputError(f"accel model: latency_s must be >= 0, got {self.latency_s!r}")
        object.__setattr__(self, "positions", r)
        object.__setattr__(self, "axes", n / np.linalg.norm(n, axis=1, keepdims=True))
        object.__setattr__(self, "variance", var)
        object.__setattr__(self, "cross", np.cross(r, self.axes))
        object.__setattr__(self, "n_dot_r", np.einsum("ij,ij->i", r, self.axes))
        object.__setattr__(self, "centripetal", _symmetric_outer(self.axes, r)
                           - self.n_dot_r[:, None, None] * np.eye(3))

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


def _symmetric_outer(a: Array, b: Array) -> Array:
    """``(a b^T + b a^T) / 2`` for each row of ``a`` and ``b`` (N, 3)."""
    ab = np.einsum("ni,nj->nij", a, b)
    return 0.5 * (ab + ab.transpose(0, 2, 1))


def check_config(config: object, what: str, positive: tuple[str, ...],
                 non_negative: tuple[str, ...], initial_std: str) -> None:
    """The checks every filter configuration needs: finite positive and non-negative
    settings, and one positive initial standard deviation per state block (``initial_std``
    names the blocks); ``ValueError`` names the setting."""
    for name in positive:
        value = getattr(config, name)
        if not (math.isfinite(value) and value > 0):
            raise InvalidInputError(f"{what}: {name} must be a positive number, got {value!r}")
    for name in non_negative:
        value = getattr(config, name)
        if not (math.isfinite(value) and value >= 0):
            raise InvalidInputError(f"{what}: {name} must be >= 0, got {value!r}")
    blocks = initial_std.split(", ")
    stds = config.initial_std  # type: ignore[attr-defined]
    if len(stds) != len(blocks) or not all(x > 0 for x in stds):
        raise InvalidInputError(f"{what}: initial_std needs {len(blocks)} positive numbers "
                                f"({initial_std}), got {stds!r}")


@dataclass(frozen=True)
class FusionConfig:
    """Noise model and behaviour of the filter (SI units); docs/FUSION_TUNING.md has the
    runs behind each default."""

    #: The head's jerk, linear (m/s^3, world axes) and angular (rad/s^3, head axes), as
    #: first-order Gauss-Markov states: std and correlation time (0 std: no such states,
    #: white jerk only, as in eq. 6.1).  Head motion is smooth over one 300 Hz step and
    #: as good as new over a quarter second; white jerk alone cannot say both.
    linear_jerk_std: float = 6.0
    linear_jerk_tau_s: float = 0.22
    angular_jerk_std: float = 11.0
    angular_jerk_tau_s: float = 0.23
    #: White jerk on top, (m/s^3)^2/Hz and (rad/s^3)^2/Hz: what the Gauss-Markov jerk
    #: misses.  Kept small: with quiet accelerometers it is what spreads the position
    #: between optical frames.
    linear_jerk_psd: float = 0.1
    angular_jerk_psd: float = 0.2
    #: m/s^2 / sqrt(s), accelerometer bias random walk.  The residual bias after the static
    #: calibration is nearly constant (thermal drift only); a faster walk lets the bias
    #: states follow the reading noise between optical frames.
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
    #: averages 3 (see ``FusionEKF._adapt_pose_noise``)
    adapt_pose_noise: bool = True
    pose_noise_rate: float = 0.02        # adaptation gain per optical pose
    #: lowest scale of the optical (position, rotation) covariance: the NIS cannot tell a
    #: tracker that overstates its noise from one whose errors persist from frame to frame
    #: (both make it small), so the optics are never trusted more than twice their claim;
    #: persistent errors belong in the systematic part of the optical covariance
    #: (``FusionEKF.update_pose``) or in ``optical_bias_std``
    pose_noise_min_scale: tuple[float, float] = (0.5, 0.5)
    max_step_s: float = 0.05             # longer predictions are split (integration accuracy)
    #: the optical position error's persistent part (m, per axis; 0: none), a Gauss-Markov
    #: state with correlation time ``optical_bias_tau_s``.  A tracker's calibration error
    #: (camera, screen geometry) stays while the head moves over the same part of the
    #: walls; modelled as white noise it would "average out" over frames, and the fused
    #: position would claim an accuracy the tracker never had.  For a tracker that does not
    #: publish the systematic part of its covariance (the laser tracker does, and needs
    #: none); a real one's comes from comparing it with a reference
    optical_bias_std: float = 0.0
    optical_bias_tau_s: float = 30.0

    def __post_init__(self) -> None:
        check_config(self, "fusion config",
                     positive=("angular_jerk_psd", "linear_jerk_psd", "accel_gate", "pose_gate",
                               "max_step_s", "initial_bias_std", "optical_bias_tau_s",
                               "linear_jerk_tau_s", "angular_jerk_tau_s", "start_max_gap_s"),
                     non_negative=("optical_bias_std", "linear_jerk_std", "angular_jerk_std"),
                     initial_std="omega, omega_dot, v, alpha, spare")


@dataclass(frozen=True)
class StateLayout:
    """Where the blocks after eq. 6.1's 18 sit: one residual bias per accelerometer
    (SCAAT's autocalibration, Hogue 2003 appendix B.3), then three optional Gauss-Markov
    triples: the optical tracker's persistent position error, the linear and the angular
    jerk.  A block the configuration switches off is an empty slice."""

    accel_bias: slice
    optical_bias: slice
    linear_jerk: slice
    angular_jerk: slice

    @classmethod
    def of(cls, config: FusionConfig, n_accel: int) -> StateLayout:
        sizes = [n_accel if config.estimate_bias else 0,
                 *(3 * (std > 0) for std in (config.optical_bias_std, config.linear_jerk_std,
                                             config.angular_jerk_std))]
        return cls(*consecutive(CORE, sizes))

    @property
    def dim(self) -> int:
        return self.angular_jerk.stop

    @property
    def n_bias(self) -> int:
        return size(self.accel_bias)


def size(block: slice) -> int:
    """How many states a block of the layout holds."""
    return block.stop - block.start


def consecutive(start: int, sizes: list[int]) -> list[slice]:
    """Slices of the given sizes, one after the other from ``start``."""
    out = []
    for n in sizes:
        out.append(slice(start, start + n))
        start += n
    return out
