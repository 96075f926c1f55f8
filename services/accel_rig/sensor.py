"""The accelerometer electronics (Hogue 2003, appendix C.1) and the calibration that inverts
them.

Signal chain per accelerometer (Kyowa AS-5GA, RHC amplifier, VIPS 10 A/D):

    volts = bias + gain * (n_true . specific force at r_j) + noise     (eq. 4.2, §4.4.1)
    amplifier clips at +/-2.0 V (1 g = 400 mV, so +/-5 g)
    frequency response 0-110 Hz: a 2nd-order Butterworth low-pass at 110 Hz
    12-bit A/D, bipolar +/-2.048 V, 1 LSB = 1 mV, with its own noise per conversion
    each reading averages 8 conversions spread over its sample period

A ``Calibration`` holds what Hogue 2003, §4.4.2 estimates for each accelerometer (bias B_j,
scale, sensing axis n_j) together with the layout positions, the noise model and the
filter latency, so a reading in volts becomes an acceleration along n_j and the dead
reckoner knows how much to trust it.  It is serialised as JSON (the calibration file of
``uma service run accel-rig --calibrate``) and copied into the ``accel_raw`` ability's
attributes for the fusion service.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from agent.errors import InvalidInputError
from services.accel_rig.rig import RigLayout
from services.frames import GRAVITY

Array = np.ndarray

G = float(np.linalg.norm(GRAVITY))
VOLTS_PER_G = 0.400  # appendix C.1: "1G = 400mV"
NOMINAL_GAIN = VOLTS_PER_G / G  # V per m/s^2
AMP_RAIL_V = 2.0  # the amplifier regulates its output to +/-2.0 V
ADC_BITS = 12
ADC_REF_V = 4.096  # +/-2.048 V bipolar, table C.2
LSB_V = ADC_REF_V / 2**ADC_BITS  # 1 mV
ADC_MIN_COUNT = -(2 ** (ADC_BITS - 1))
ADC_MAX_COUNT = 2 ** (ADC_BITS - 1) - 1
BANDWIDTH_HZ = 110.0  # table C.1 frequency response 0-110 Hz
#: White noise density at the amplifier output.  Appendix C gives no noise figure; the
#: signal chain's own is 6-19 uV/sqrt(Hz) (0.64 mV/g from the AS-5GA bridge at 5 V, amplified
#: 625 times; 9-30 nV/sqrt(Hz) of instrumentation amplifier noise), rounded up.
NOISE_DENSITY_V = 20e-6
#: A/D conversions averaged into each reading.  The VIPS 10 converts a channel in 20 us
#: (table C.2), so scanning the six channels takes 120 us of each 3.3 ms period at 300 Hz;
#: the driver scans eight times per period, evenly spaced, and averages.  Alone, 20 uV/sqrt(Hz)
#: (0.2 LSB rms) would not dither the 1 mV steps: a still rig's quantisation error would
#: persist, bias the static calibration by up to 0.1 LSB and make the dead reckoner
#: overconfident; one conversion per reading with the noise raised to half an LSB (50
#: uV/sqrt(Hz)) would dither, at 2.3 times the noise.
ADC_CONVERSIONS = 8
#: rms noise of one conversion (LSB), white from conversion to conversion.  Table C.2 gives
#: no figure; 0.5 LSB is within its +/-1 LSB relative accuracy and dithers every conversion:
#: what quantisation leaves in a static average falls to 0.001 LSB.
CONVERTER_NOISE_LSB = 0.5
#: Readings this close to the amplifier rail are clipped and carry no information.
SATURATION_MARGIN_V = 0.5 * LSB_V

CALIBRATION_FORMAT = "uma.accel_rig.calibration/1"


def counts_to_volts(counts: Array) -> Array:
    """A/D counts to volts (1 LSB = 1 mV)."""
    return np.asarray(counts, float) * LSB_V


#: Every voltage strictly below this in magnitude is finite, inside the A/D range and off
#: the amplifier rail: one comparison accepts a good sample (NaN compares False), and only a
#: refused one pays for finding which check it fails.
_SAFE_V = AMP_RAIL_V - SATURATION_MARGIN_V
assert _SAFE_V < -ADC_MIN_COUNT * LSB_V and _SAFE_V < ADC_MAX_COUNT * LSB_V


def check_volts(volts: Array, name: str = "accelerometer voltages") -> Array:
    """Refuse NaN, infinite, out-of-range and saturated voltages with a clear message.

    A reading outside the A/D range cannot come from the hardware (wrong units or a
    corrupt line); one at the amplifier rail is clipped, so its acceleration is unknown.
    """
    v = np.asarray(volts, dtype=float)
    if not (np.abs(v) < _SAFE_V).all():
        _refuse_volts(v, name)
    return v


def _refuse_volts(v: Array, name: str) -> None:
    """Raise the ``ValueError`` that names the first bad voltage of ``v`` and what is wrong
    with it; called when a value is not strictly below ``_SAFE_V``, which fails one of the
    three checks."""
    if not np.all(np.isfinite(v)):
        idx = tuple(int(i) for i in np.argwhere(~np.isfinite(v))[0])
        raise InvalidInputError(f"{name}: non-finite value {float(v[idx])} at index {idx} "
                                "(NaN samples are refused, not interpolated)")
    lo, hi = ADC_MIN_COUNT * LSB_V, ADC_MAX_COUNT * LSB_V
    out = np.abs(v) > max(-lo, hi) + 1e-9
    if np.any(out):
        idx = tuple(int(i) for i in np.argwhere(out)[0])
        raise InvalidInputError(f"{name}: {v[idx]:.4g} V at index {idx} is outside the A/D range "
                                f"[{lo:.3f}, {hi:.3f}] V (are these volts?)")
    sat = np.abs(v) >= AMP_RAIL_V - SATURATION_MARGIN_V
    if np.any(sat):
        idx = tuple(int(i) for i in np.argwhere(sat)[0])
        raise InvalidInputError(f"{name}: {v[idx]:.4g} V at index {idx} is at the amplifier rail "
                                f"(+/-{AMP_RAIL_V} V = +/-5 g): the accelerometer saturated")


@dataclass(frozen=True)
class NoiseModel:
    """What the estimator assumes about a reading's random error (volts).

    A reading averages ``conversions`` A/D conversions spread evenly over its sample period;
    each conversion sees the analog noise (``density_v`` through the 0-110 Hz response) and
    the converter's own white noise (``converter_noise_lsb``), and is quantised.

    ``per_sample_var_v2(rate)`` is the variance of a white sequence at that rate with the
    same low-frequency power as the readings' noise (including what the 0-110 Hz response
    and the averaging let alias down from above the Nyquist frequency) plus the
    quantisation error: what matters once readings are integrated twice.
    """

    density_v: float = NOISE_DENSITY_V
    lsb_v: float = LSB_V
    quantised: bool = True
    bandwidth_hz: float | None = BANDWIDTH_HZ
    conversions: int = ADC_CONVERSIONS
    converter_noise_lsb: float = CONVERTER_NOISE_LSB

    def __post_init__(self) -> None:
        if not (isinstance(self.conversions, int) and self.conversions >= 1):
            raise InvalidInputError(f"noise model: conversions must be a whole number >= 1, got "
                                    f"{self.conversions!r}")
        for name in ("density_v", "converter_noise_lsb"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"noise model: {name} must be >= 0, got {value!r}")

    def per_sample_var_v2(self, rate_hz: float) -> float:
        q = self.lsb_v**2 / 12.0 if self.quantised else 0.0
        converter = (self.converter_noise_lsb * self.lsb_v) ** 2
        alias = 0.0
        if self.bandwidth_hz is not None:
            # averaging N conversions spread over the period cancels every alias of the
            # rate except those of N * rate (2nd-order Butterworth |H(f)|^2 there)
            f = np.arange(1, 64) * self.conversions * rate_hz
            alias = float(np.sum(2.0 / (1.0 + (f / self.bandwidth_hz) ** 4)))
        return (self.density_v**2 * rate_hz / 2.0 * (1.0 + alias)
                + (q + converter) / self.conversions)

    def static_mean_bias_var_v2(self, rate_hz: float) -> float:
        """Variance of the error quantisation leaves in the *mean* of a static recording.

        Averaging removes quantisation error only as far as the noise dithers it: a
        constant input x read through steps of one LSB with Gaussian noise of rms sigma
        (analog and converter, per conversion) averages to x plus a periodic error whose
        first harmonic has amplitude (LSB / pi) exp(-2 pi^2 sigma^2 / LSB^2).  Over the
        unknown position of x within a step its mean square is half the amplitude squared,
        and no number of samples or conversions reduces it.  Negligible with the default
        device (0.5 LSB of converter noise), it dominated a quieter one without it.
        """
        if not self.quantised:
            return 0.0
        bw = (math.pi / (2.0 * math.sqrt(2.0)) * self.bandwidth_hz
              if self.bandwidth_hz is not None else rate_hz / 2.0)  # noise bandwidth
        sigma2 = self.density_v**2 * bw + (self.converter_noise_lsb * self.lsb_v) ** 2
        amp = self.lsb_v / math.pi * math.exp(-2.0 * math.pi**2 * sigma2 / self.lsb_v**2)
        return 0.5 * amp**2


@dataclass(frozen=True)
class Calibration:
    """Per-accelerometer bias (V), gain (V per m/s^2) and sensing axis, plus the model.

    ``param_cov`` (N, 4, 4) is the covariance of each accelerometer's ``[bias, gain * axis]``
    estimate (§4.4.2 least squares); ``latency_s`` is the group delay of the 0-110 Hz
    response, so a reading taken at t describes the motion at ``t - latency_s``.
    """

    layout: RigLayout
    bias_v: Array
    gain_v_per_mps2: Array
    param_cov: Array | None = None
    noise: NoiseModel = NoiseModel()
    latency_s: float = 0.0

    def __post_init__(self) -> None:
        n = self.layout.count
        b = np.asarray(self.bias_v, float)
        k = np.asarray(self.gain_v_per_mps2, float)
        if b.shape != (n,) or k.shape != (n,):
            raise InvalidInputError(
                f"calibration: bias {b.shape} and gain {k.shape} must be ({n},) "
                f"for {n} accelerometers")
        if not (np.all(np.isfinite(b)) and np.all(np.isfinite(k))):
            raise InvalidInputError("calibration: bias and gain must be finite")
        if np.any(k <= 0):
            raise InvalidInputError(
                f"calibration: gain of accelerometer {int(np.argmin(k)) + 1} is "
                f"{k.min():.4g} V/(m/s^2); gains are positive (sign goes in the axis)")
        object.__setattr__(self, "bias_v", b)
        object.__setattr__(self, "gain_v_per_mps2", k)
        if self.param_cov is not None:
            c = np.asarray(self.param_cov, float)
            if c.shape != (n, 4, 4) or not np.all(np.isfinite(c)):
                raise InvalidInputError(f"calibration: param_cov must be finite ({n}, 4, 4)")
            object.__setattr__(self, "param_cov", c)
        if not math.isfinite(self.latency_s) or self.latency_s < 0:
            raise InvalidInputError(f"calibration: latency_s must be >= 0, got {self.latency_s!r}")

    @property
    def axes(self) -> Array:
        return self.layout.axes

    def to_accel(self, volts: Array) -> Array:
        """Voltages (..., N) to accelerations along each sensing axis (m/s^2), validated."""
        v = check_volts(volts)
        if v.shape[-1] != self.layout.count:
            raise InvalidInputError(
                f"accelerometer voltages: {v.shape[-1]} channels, the calibration "
                f"has {self.layout.count}")
        return (v - self.bias_v) / self.gain_v_per_mps2

    def to_accel_floats(self, volts: Array) -> list[float]:
        """``to_accel`` of one sample (N,) as plain floats, validated the same way.

        The dead reckoner's per-sample path: on six values each numpy call costs more than
        its arithmetic, so a good sample is checked and converted in Python floats and only
        a refused one goes through ``check_volts``'s checks for its message.
        """
        v = np.asarray(volts, dtype=float)
        if v.shape != (self.layout.count,):
            raise InvalidInputError(f"accelerometer voltages: expected {self.layout.count} values, "
                                    f"got shape {v.shape}")
        vals = v.tolist()
        if not all(map(_SAFE_V.__gt__, map(abs, vals))):
            _refuse_volts(v, "accelerometer voltages")
        bias, gain = self._bias_gain_floats
        return [(x - b) / k for x, b, k in zip(vals, bias, gain, strict=True)]

    @cached_property
    def _bias_gain_floats(self) -> tuple[list[float], list[float]]:
        """Bias and gain as plain floats for ``to_accel_floats`` (the calibration is frozen)."""
        return self.bias_v.tolist(), self.gain_v_per_mps2.tolist()

    def to_volts(self, accel: Array) -> Array:
        """Accelerations along the axes back to ideal (unquantised) voltages."""
        return np.asarray(accel, float) * self.gain_v_per_mps2 + self.bias_v

    def accel_var(self, rate_hz: float) -> Array:
        """Per-sample variance (m/s^2)^2 of each accelerometer's reading at ``rate_hz``."""
        return self.noise.per_sample_var_v2(rate_hz) / self.gain_v_per_mps2**2

    # ------------------------------------------------------------------ JSON

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable description (also the ``accel_raw`` ability's attributes, which
        is why absent optional values are left out rather than null)."""
        d = {
            "format": CALIBRATION_FORMAT,
            "layout": self.layout.name,
            "positions_m": self.layout.positions.tolist(),
            "axes": self.layout.axes.tolist(),
            "bias_v": self.bias_v.tolist(),
            "gain_v_per_mps2": self.gain_v_per_mps2.tolist(),
            "param_cov": None if self.param_cov is None else self.param_cov.tolist(),
            "noise_density_v_per_rthz": self.noise.density_v,
            "lsb_v": self.noise.lsb_v,
            "quantised": self.noise.quantised,
            "bandwidth_hz": self.noise.bandwidth_hz,
            "adc_conversions": self.noise.conversions,
            "converter_noise_lsb": self.noise.converter_noise_lsb,
            "latency_s": self.latency_s,
        }
        return {k: v for k, v in d.items() if v is not None}

    @classmethod
    def from_dict(cls, d: Any) -> Calibration:
        """Rebuild from ``to_dict``'s output; ``ValueError`` naming a missing/bad field."""
        if not isinstance(d, dict):
            raise InvalidInputError("calibration: expected a JSON object")
        if d.get("format") != CALIBRATION_FORMAT:
            raise InvalidInputError(f"calibration: format {d.get('format')!r} is not "
                                    f"{CALIBRATION_FORMAT!r}")
        try:
            layout = RigLayout(np.asarray(d["positions_m"], float), np.asarray(d["axes"], float),
                               name=str(d.get("layout", "custom")))
            bw = d.get("bandwidth_hz")
            # a file without the A/D's fields describes one conversion per reading
            noise = NoiseModel(float(d["noise_density_v_per_rthz"]), float(d["lsb_v"]),
                               bool(d["quantised"]), None if bw is None else float(bw),
                               int(d.get("adc_conversions", 1)),
                               float(d.get("converter_noise_lsb", 0.0)))
            cov = d.get("param_cov")
            return cls(layout, np.asarray(d["bias_v"], float),
                       np.asarray(d["gain_v_per_mps2"], float),
                       None if cov is None else np.asarray(cov, float), noise,
                       float(d["latency_s"]))
        except KeyError as exc:
            raise InvalidInputError(f"calibration: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"calibration: bad value ({exc})") from None

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise InvalidInputError(f"calibration file {str(path)!r}: {exc.strerror}") from None
        try:
            return cls.from_dict(json.loads(text))
        except json.JSONDecodeError as exc:
            raise InvalidInputError(f"calibration file {str(path)!r}: not JSON ({exc})") from None
        except ValueError as exc:
            raise InvalidInputError(f"calibration file {str(path)!r}: {exc}") from None
