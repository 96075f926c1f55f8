"""The conventions every tracker service shares with the simulator: frame names and the
world's gravity.

They live here, not in ``services.sim``, because the production services (the
accelerometer rig, the fusion, the laser camera) need them without the simulated world:
a service built for real hardware must not import the simulator to learn what "up" is.
The simulator imports them from here too, so simulation and production cannot disagree.

Frames (the SRG's node names; every service takes them as command-line defaults):

* ``ivy/world``         the IVY cube, origin at its centre, z up
* ``alice/head``        the user's head (x forward, y left, z up); the trajectory's frame
* ``marvin/laser_rig``  the laser-diode housing of the optical tracker (Hogue, *MARVIN: a
  Mobile Automatic Realtime Visual and INertial tracking system*, MSc thesis, York
  University 2003, ch. 5)
* ``marvin/accel_rig``  the six-accelerometer rig (Hogue 2003 ch. 4)
"""

from __future__ import annotations

import numpy as np

WORLD = "ivy/world"
HEAD = "alice/head"
LASER_RIG = "marvin/laser_rig"
ACCEL_RIG = "marvin/accel_rig"

#: m/s^2, standard gravity (ISO 80000-3)
STANDARD_GRAVITY = 9.80665
#: gravity in ``ivy/world`` (z up): what a resting accelerometer reads is its negative
GRAVITY = np.array([0.0, 0.0, -STANDARD_GRAVITY])
