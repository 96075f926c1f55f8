"""MARVIN's inertial tracker (Hogue 2003, ch. 4): the six-accelerometer rig.

The pure API (numpy only, no I/O) the fusion service and the evaluation share:

* ``rig``: ``RigLayout`` (positions, axes, the eq. 4.42 solve, the measurement model ``h``
  and its Jacobian), ``marvin_six``, ``marvin_six_table_4_1``, ``nine_accelerometer``;
* ``sensor``: appendix C.1 electronics constants and the ``Calibration`` (JSON file);
* ``simulator``: ``simulate(trajectory, seconds, rate_hz, seed, ...)`` (Hogue 2003, §4.5);
* ``calibration``: ``calibrate(layout, recordings, rate_hz)`` from static poses (§4.4.2);
* ``integrator``: ``DeadReckoner`` (§4.3), ``reset(...)`` then ``update(t, accel)``;
* ``pose_rates``: ``AbsolutePoses``, the velocities a reset restarts with, fitted to the
  recent absolute poses.

``service`` and ``evaluate`` wrap them for ``uma service run accel-rig`` and
``uma eval accel-rig``.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from services.accel_rig.calibration import (
    SIX_POSES,
    THESIS_POSES,
    StaticRecording,
    calibrate,
    calibration_errors,
)
from services.accel_rig.integrator import DeadReckoner, Estimate
from services.accel_rig.pose_rates import AbsolutePoses, Rates
from services.accel_rig.rig import (
    RigLayout,
    layout_by_name,
    marvin_six,
    marvin_six_table_4_1,
    nine_accelerometer,
)
from services.accel_rig.sensor import Calibration, NoiseModel
from services.accel_rig.simulator import (
    SensorTruth,
    SimulatedRun,
    StaticPose,
    axis_down_quaternion,
    default_device,
    simulate,
    simulate_static,
)

__all__ = [
    "SIX_POSES",
    "THESIS_POSES",
    "AbsolutePoses",
    "Calibration",
    "DeadReckoner",
    "Estimate",
    "NoiseModel",
    "Rates",
    "RigLayout",
    "SensorTruth",
    "SimulatedRun",
    "StaticPose",
    "StaticRecording",
    "axis_down_quaternion",
    "calibrate",
    "calibration_errors",
    "default_device",
    "layout_by_name",
    "marvin_six",
    "marvin_six_table_4_1",
    "nine_accelerometer",
    "simulate",
    "simulate_static",
]
