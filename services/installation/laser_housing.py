"""MARVIN's laser-diode housing (Hogue 2003, fig. 5.4, appendix C.2) in the ``marvin/laser_rig``
frame.

Four diodes whose beams all pass through one point P0, the frame's origin.  Beams 1 and 2
point in opposite directions along a line (here +y and -y), beam 3 is orthogonal to that
line (here -x: behind the user) and beam 4 is orthogonal to both (here +z), so that
``P3P0 . P1P2 = P4P0 . P1P2 = P3P0 . P4P0 = 0`` and the normal ``n = P0P1 x P0P3`` points
along beam 4.  The rig frame is recovered from four wall hits as origin P0, x = -(unit
P0P3), z = unit n, y = z x x (``services.laser_camera.pose``).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import numpy as np

#: diode label -> unit beam direction in the rig frame
BEAM_DIRECTIONS = {
    1: np.array([0.0, 1.0, 0.0]),
    2: np.array([0.0, -1.0, 0.0]),
    3: np.array([-1.0, 0.0, 0.0]),
    4: np.array([0.0, 0.0, 1.0]),
}
LABELS = (1, 2, 3, 4)

