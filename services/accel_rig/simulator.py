"""The inertial simulator of Hogue 2003, §4.5: what each accelerometer outputs for a motion.

Instead of the thesis' finite differences (eqs. 4.66-4.69) it takes the exact kinematics of
the rig frame (``KinematicState.rigid_offset`` of the ground-truth head trajectory), applies
eq. 4.72 with gravity, then the device of appendix C.1: per-accelerometer bias, scale error
and misaligned axis (table 4.1 by default), white noise, the 0-110 Hz response (2nd-order
Butterworth, run at 8x the output rate so the analog filter is faithful), the +/-2 V
amplifier rail and the 12-bit A/D converter, which converts each channel eight times per
sample period, with its own noise, and averages.  Everything is deterministic from a seed.

``SensorTruth`` is the device (fixed errors); ``seed`` draws the noise of one run.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.accel_rig import sensor as sn
from services.accel_rig.rig import RigLayout, marvin_six_table_4_1
from services.frames import GRAVITY
from services.kinematics import KinematicState
from services.sim.mounts import HEAD_TO_ACCEL_RIG

Array = np.ndarray

DEFAULT_RATE_HZ = 300.0
#: Seed of the default simulated device (its biases and scale errors), fixed so that the
#: calibration and every simulated run describe the same hardware.
DEVICE_SEED = 2003
#: The amplifier zero offset is unknown before calibration; +/-50 mV is 1/8 g.
BIAS_RANGE_V = 0.05
SCALE_ERROR_RANGE = 0.02  # +/-2 % gain error before calibration
_FILTER_WARMUP_S = 0.02  # ten time constants of the 110 Hz filter


class Trajectory(Protocol):
    def state(self, t: Array | float) -> KinematicState: ...


@dataclass(frozen=True)
class SensorTruth:
    """The simulated device: true layout (positions, misaligned axes), biases, gain errors,
    and which of the appendix C.1 effects are switched on."""

    layout: RigLayout
    bias_v: Array
    scale_error: Array
    noise_density_v: float = sn.NOISE_DENSITY_V
    bandwidth_hz: float | None = sn.BANDWIDTH_HZ
    #: the A/D: quantisation and its own noise per conversion (False: an ideal converter)
    quantise: bool = True
    #: steps of the analog simulation per sample period (the 0-110 Hz filter's fidelity)
    oversample: int = 8
    #: A/D conversions averaged into each reading, spread evenly over the sample period
    conversions: int = sn.ADC_CONVERSIONS
    converter_noise_lsb: float = sn.CONVERTER_NOISE_LSB

    def __post_init__(self) -> None:
        if not (isinstance(self.conversions, int) and self.conversions >= 1
                and self.oversample % self.conversions == 0):
            raise InvalidInputError(
                f"simulated device: conversions ({self.conversions!r}) must divide "
                f"the analog steps per sample ({self.oversample})")

    @classmethod
    def draw(cls, seed: int = DEVICE_SEED, layout: RigLayout | None = None) -> SensorTruth:
        """A device with random bias and scale errors; table 4.1 axes by default."""
        layout = marvin_six_table_4_1() if layout is None else layout
        rng = np.random.default_rng(seed)
        n = layout.count
        return cls(layout, rng.uniform(-BIAS_RANGE_V, BIAS_RANGE_V, n),
                   rng.uniform(-SCALE_ERROR_RANGE, SCALE_ERROR_RANGE, n))

    @classmethod
    def ideal(cls, layout: RigLayout) -> SensorTruth:
        """Perfect accelerometers on ``layout``: no bias, gain error, noise, filter or A/D."""
        n = layout.count
        return cls(layout, np.zeros(n), np.zeros(n), noise_density_v=0.0, bandwidth_hz=None,
                   quantise=False)

    def noise_free(self) -> SensorTruth:
        """The same device (bias, gain, axes) without noise, filter and quantisation."""
        return replace(self, noise_density_v=0.0, bandwidth_hz=None, quantise=False)

    @property
    def conversions_per_reading(self) -> int:
        """Conversions averaged per reading (one without the analog filter's finer steps)."""
        return self.conversions if self.bandwidth_hz is not None else 1

    @property
    def gain_v_per_mps2(self) -> Array:
        return sn.NOMINAL_GAIN * (1.0 + np.asarray(self.scale_error, float))

    def latency_s(self, rate_hz: float = DEFAULT_RATE_HZ) -> float:
        """Low-frequency group delay of the 0-110 Hz response and of the averaging of the
        conversions (0 without the filter)."""
        if self.bandwidth_hz is None:
            return 0.0
        fs = self.oversample * rate_hz
        spread = (self.conversions - 1) * (self.oversample // self.conversions)
        return _group_delay_s(self.bandwidth_hz, fs) + 0.5 * spread / fs

    def noise_model(self) -> sn.NoiseModel:
        return sn.NoiseModel(self.noise_density_v, sn.LSB_V, self.quantise, self.bandwidth_hz,
                             self.conversions_per_reading,
                             self.converter_noise_lsb if self.quantise else 0.0)

    def calibration(self, rate_hz: float = DEFAULT_RATE_HZ) -> sn.Calibration:
        """The exact calibration of this device (what a perfect §4.4.2 run would give)."""
        return sn.Calibration(self.layout, self.bias_v, self.gain_v_per_mps2,
                              noise=self.noise_model(), latency_s=self.latency_s(rate_hz))


@dataclass(frozen=True)
class SimulatedRun:
    """One simulated recording.

    ``t`` are sample times; ``truth`` is the rig's exact kinematics at the motion times
    ``t - latency_s`` that the samples describe.  ``accel`` converts ``volts`` with the
    calibration given to ``simulate`` (the device's exact one by default).
    """

    t: Array  # (n,) s
    counts: Array | None  # (n, N) A/D counts averaged over the conversions, None: ideal A/D
    volts: Array  # (n, N)
    accel: Array  # (n, N) m/s^2 along each calibrated axis
    truth: KinematicState
    latency_s: float
    rate_hz: float


def simulate(trajectory: Trajectory, seconds: float, rate_hz: float = DEFAULT_RATE_HZ,
             seed: int | np.random.SeedSequence = 0, *, t0: float = 0.0,
             sensor: SensorTruth | None = None,
             mount: tuple[Array, Array] | None = HEAD_TO_ACCEL_RIG,
             calibration: sn.Calibration | None = None) -> SimulatedRun:
    """Simulate ``seconds`` of accelerometer output at ``rate_hz`` starting at ``t0``.

    ``trajectory.state(t)`` gives the head (or, with ``mount=None``, the rig itself);
    ``mount`` is the rig's pose in that frame (default: the simulated head mounting).
    ``seed`` (an integer or a ``numpy.random.SeedSequence``) draws the noise.
    """
    if not (math.isfinite(seconds) and seconds > 0):
        raise InvalidInputError(f"simulate: seconds must be positive, got {seconds!r}")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise InvalidInputError(f"simulate: rate_hz must be positive, got {rate_hz!r}")
    sensor = default_device() if sensor is None else sensor
    n = round(seconds * rate_hz)
    t = t0 + np.arange(n) / rate_hz
    rng = np.random.default_rng(seed)
    volts = np.clip(_analog_volts(trajectory, mount, sensor, t, rate_hz, rng),
                    -sn.AMP_RAIL_V, sn.AMP_RAIL_V)  # (n, conversions, N)
    counts = None
    if sensor.quantise:
        noise = sensor.converter_noise_lsb * rng.standard_normal(volts.shape)
        counts = np.clip(np.round(volts / sn.LSB_V + noise), sn.ADC_MIN_COUNT,
                         sn.ADC_MAX_COUNT).mean(axis=1)
        volts = sn.counts_to_volts(counts)
    else:
        volts = volts.mean(axis=1)
    cal = sensor.calibration(rate_hz) if calibration is None else calibration
    accel = (volts - cal.bias_v) / cal.gain_v_per_mps2
    latency = sensor.latency_s(rate_hz)
    truth = _rig_state(trajectory, mount, t - latency)
    return SimulatedRun(t, counts, volts, accel, truth, latency, rate_hz)


def default_device() -> SensorTruth:
    """MARVIN's simulated device: table 4.1 axes, fixed random bias and gain errors."""
    return SensorTruth.draw(DEVICE_SEED)


def specific_force_readings(layout: RigLayout, state: KinematicState,
                            gravity: Array = GRAVITY) -> Array:
    """Eq. 4.72 with gravity (eq. 4.71): ideal readings (n, N) for the rig's kinematics."""
    f = geo.quat_rotate(geo.quat_conjugate(state.quaternion), state.acceleration - gravity)
    return layout.readings(f, state.omega_body, state.alpha_body)


# ---------------------------------------------------------------------- static poses


@dataclass(frozen=True)
class StaticPose:
    """A rig held still at orientation ``quaternion`` (rig in world): a calibration pose."""

    quaternion: Array
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def state(self, t: Array | float) -> KinematicState:
        t = np.atleast_1d(np.asarray(t, float))
        z = np.zeros((t.size, 3))
        q = np.broadcast_to(geo.check_quaternion(self.quaternion, "static pose"), (t.size, 4))
        return KinematicState(t, np.broadcast_to(self.position, (t.size, 3)).copy(), q.copy(),
                              z, z, z, z)


def axis_down_quaternion(label: str) -> Array:
    """Orientation (rig in world) with the rig axis ``label`` ('+x', '-z', ...) pointing
    along gravity, the calibration poses of Hogue 2003, §4.4.2."""
    axes = {"x": 0, "y": 1, "z": 2}
    if len(label) != 2 or label[0] not in "+-" or label[1] not in axes:
        raise InvalidInputError(f"calibration pose {label!r}: expected one of +x -x +y -y +z -z")
    d = np.zeros(3)
    d[axes[label[1]]] = 1.0 if label[0] == "+" else -1.0
    down = np.array([0.0, 0.0, -1.0])
    c = np.cross(d, down)
    s, cos = np.linalg.norm(c), float(d @ down)
    if s < 1e-12:  # parallel or antiparallel: no rotation or a half turn about x
        return geo.quat_identity() if cos > 0 else geo.rotvec_to_quat([np.pi, 0.0, 0.0])
    return geo.rotvec_to_quat(c / s * math.atan2(s, cos))


def simulate_static(quaternion: Array, seconds: float, rate_hz: float = DEFAULT_RATE_HZ,
                    seed: int = 0, sensor: SensorTruth | None = None) -> Array:
    """Voltages (n, N) of the rig held still at ``quaternion`` for ``seconds``."""
    return simulate(StaticPose(quaternion), seconds, rate_hz, seed, sensor=sensor,
                    mount=None).volts


# ---------------------------------------------------------------------- internals


def _rig_state(trajectory: Trajectory, mount: tuple[Array, Array] | None,
               t: Array) -> KinematicState:
    s = trajectory.state(t)
    return s if mount is None else s.rigid_offset(*mount)


def _analog_volts(trajectory: Trajectory, mount: tuple[Array, Array] | None,
                  sensor: SensorTruth, t: Array, rate_hz: float,
                  rng: np.random.Generator) -> Array:
    """Amplifier output (n, conversions, N) at each sample's conversion instants, the last
    at the sample time: signal + noise through the 0-110 Hz response."""
    gain, bias = sensor.gain_v_per_mps2, np.asarray(sensor.bias_v, float)
    if sensor.bandwidth_hz is None:
        ideal = specific_force_readings(sensor.layout, _rig_state(trajectory, mount, t))
        std = sensor.noise_density_v * math.sqrt(rate_hz / 2.0)
        return (bias + gain * ideal + std * rng.standard_normal(ideal.shape))[:, None, :]
    fs = sensor.oversample * rate_hz
    warm = max(math.ceil(_FILTER_WARMUP_S * fs), sensor.oversample)  # + one period's conversions
    ti = t[0] + (np.arange(warm + len(t) * sensor.oversample) - warm) / fs
    ideal = specific_force_readings(sensor.layout, _rig_state(trajectory, mount, ti))
    x = bias + gain * ideal
    x = x + sensor.noise_density_v * math.sqrt(fs / 2.0) * rng.standard_normal(x.shape)
    y = _butterworth2(x, sensor.bandwidth_hz, fs)
    step = sensor.oversample // sensor.conversions
    ends = warm + sensor.oversample * np.arange(len(t))
    return y[ends[:, None] - step * np.arange(sensor.conversions - 1, -1, -1)[None, :]]


def _biquad(fc: float, fs: float) -> tuple[Array, Array]:
    """2nd-order Butterworth low-pass by the bilinear transform, prewarped at ``fc``."""
    k = math.tan(math.pi * fc / fs)
    norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    b0 = k * k * norm
    b = np.array([b0, 2 * b0, b0])
    a = np.array([1.0, 2.0 * (k * k - 1.0) * norm, (1.0 - math.sqrt(2.0) * k + k * k) * norm])
    return b, a


def _group_delay_s(fc: float, fs: float) -> float:
    """Low-frequency group delay of the digital biquad (s): sum k c_k / sum c_k."""
    b, a = _biquad(fc, fs)
    k = np.arange(3)
    return float((k @ b) / b.sum() - (k @ a) / a.sum()) / fs


def _butterworth2(x: Array, fc: float, fs: float) -> Array:
    """Filter the columns of ``x`` (n, N), starting in steady state (the sensor was on)."""
    b, a = _biquad(fc, fs)
    y = np.empty_like(x)
    z1 = x[0] * (1.0 - b[0])
    z2 = x[0] * (b[2] - a[2])
    for i in range(x.shape[0]):  # transposed direct form II
        xi = x[i]
        yi = b[0] * xi + z1
        z1 = b[1] * xi - a[1] * yi + z2
        z2 = b[2] * xi - a[2] * yi
        y[i] = yi
    return y
