"""The thesis' test motions (Hogue 2003, §4.6) with exact derivatives, for the simulator.

Figure 4.12/4.13: the rig oscillates sinusoidally along one axis without turning.
Figures 4.15-4.20: the rig turns +/-90 degrees about one of its axes (yaw, pitch, roll)
without moving.  Both have the ``state(t) -> KinematicState`` shape of
``services.sim.trajectory.HeadTrajectory``, so ``simulate(..., mount=None)`` takes them as
the rig's own motion.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.kinematics import KinematicState

Array = np.ndarray


def _axis_index(axis: str) -> int:
    try:
        return "xyz".index(axis)
    except ValueError:
        raise InvalidInputError(f"axis must be 'x', 'y' or 'z', got {axis!r}") from None


@dataclass(frozen=True)
class SinusoidalTranslation:
    """Position ``center + A sin(2 pi f t) e_axis``, orientation fixed (figure 4.12)."""

    axis: str = "x"
    amplitude_m: float = 0.5
    frequency_hz: float = 0.5
    center: tuple[float, float, float] = (0.0, 0.0, 0.3)

    def state(self, t: Array | float) -> KinematicState:
        t = np.atleast_1d(np.asarray(t, float))
        e = np.eye(3)[_axis_index(self.axis)]
        w = 2 * np.pi * self.frequency_hz
        s, c = np.sin(w * t)[:, None], np.cos(w * t)[:, None]
        z = np.zeros((t.size, 3))
        return KinematicState(t, np.asarray(self.center) + self.amplitude_m * s * e,
                              geo.quat_identity((t.size,)), self.amplitude_m * w * c * e,
                              -self.amplitude_m * w * w * s * e, z, z.copy())


@dataclass(frozen=True)
class AxisRotation:
    """Angle ``A sin(2 pi f t)`` about one rig axis, position fixed (figures 4.15-4.17).

    ``axis`` 'z' is yaw, 'y' pitch and 'x' roll for a rig with z up.
    """

    axis: str = "z"
    amplitude_rad: float = np.pi / 2
    frequency_hz: float = 0.25
    center: tuple[float, float, float] = (0.0, 0.0, 0.3)

    def angle(self, t: Array | float) -> Array:
        return self.amplitude_rad * np.sin(2 * np.pi * self.frequency_hz * np.asarray(t, float))

    def state(self, t: Array | float) -> KinematicState:
        t = np.atleast_1d(np.asarray(t, float))
        e = np.eye(3)[_axis_index(self.axis)]
        w = 2 * np.pi * self.frequency_hz
        theta = self.amplitude_rad * np.sin(w * t)[:, None]
        rate = self.amplitude_rad * w * np.cos(w * t)[:, None]
        accel = -self.amplitude_rad * w * w * np.sin(w * t)[:, None]
        z = np.zeros((t.size, 3))
        return KinematicState(t, np.broadcast_to(np.asarray(self.center, float), z.shape).copy(),
                              geo.rotvec_to_quat(theta * e), z, z.copy(), rate * e, accel * e)
