"""What-if flags for the simulated accelerometer electronics, shared by the evaluations.

Appendix C of Hogue 2003 names the parts but gives no noise figures, so the simulated device's
noise is an assumption (``sensor``'s constants say which).  These flags let an evaluation
run another device of the same design, e.g. the earlier model of this project, one
conversion per reading with the noise raised to dither it:

    uma eval fusion --accel-noise-uv 50 --adc-conversions 1 --converter-noise-lsb 0

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from typing import Any

from agent.errors import InvalidInputError
from services.accel_rig import sensor as sn
from services.accel_rig.simulator import SensorTruth


def add_device_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--accel-noise-uv", type=float, default=None, metavar="UV",
                        help="what-if: the accelerometers' analog noise density in "
                             f"uV/sqrt(Hz) (default {1e6 * sn.NOISE_DENSITY_V:g}: the signal "
                             "chain's own 6-19, rounded up; appendix C gives none)")
    parser.add_argument("--adc-conversions", type=int, default=None, metavar="N",
                        help="what-if: A/D conversions averaged into each reading, spread "
                             f"over the sample period (default {sn.ADC_CONVERSIONS}; "
                             "1, 2, 4 or 8)")
    parser.add_argument("--converter-noise-lsb", type=float, default=None, metavar="LSB",
                        help="what-if: rms noise of one A/D conversion in LSB (default "
                             f"{sn.CONVERTER_NOISE_LSB:g}; it dithers the 1 mV steps)")


def device_from_args(device: SensorTruth, args: argparse.Namespace) -> SensorTruth:
    """``device`` with the what-if flags applied; ``ValueError`` naming a bad flag."""
    changes: dict[str, Any] = {}
    uv = getattr(args, "accel_noise_uv", None)
    if uv is not None:
        if not (math.isfinite(uv) and 0 <= uv <= 1000):
            raise InvalidInputError(f"--accel-noise-uv must be within 0..1000, got {uv!r}")
        changes["noise_density_v"] = uv / 1e6
    n = getattr(args, "adc_conversions", None)
    if n is not None:
        if n < 1 or device.oversample % n:
            raise InvalidInputError(
                f"--adc-conversions must divide {device.oversample} (the analog "
                f"steps per sample), got {n!r}")
        changes["conversions"] = n
    lsb = getattr(args, "converter_noise_lsb", None)
    if lsb is not None:
        if not (math.isfinite(lsb) and 0 <= lsb <= 100):
            raise InvalidInputError(f"--converter-noise-lsb must be within 0..100, got {lsb!r}")
        changes["converter_noise_lsb"] = lsb
    return replace(device, **changes) if changes else device


def device_figures(device: SensorTruth) -> dict[str, float]:
    """The simulated electronics an evaluation ran with (to put beside its figures): what
    the device's noise model says, so an ideal A/D reports no converter noise."""
    noise = device.noise_model()
    return {"accel_noise_uv_per_sqrt_hz": 1e6 * noise.density_v,
            "adc_conversions": noise.conversions,
            "converter_noise_lsb": noise.converter_noise_lsb}
