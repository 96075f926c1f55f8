"""Where the trackers sit on the simulated user: the ground truth of the rig mountings.

The frames they join are ``services.frames``'s.  Each mounting is the pose of the rig in
the head frame (the SRG edge ``alice/head -> marvin/<rig>``).  They are deliberately not
axis-aligned, so alignment and fusion cannot succeed by assuming identity.  Real systems
get them from tracker alignment (AX = XB).
"""

from __future__ import annotations

import numpy as np

from agent import geometry as geo

#: laser housing on top of the head, pitched 5 degrees forward
HEAD_TO_LASER_RIG = (np.array([0.02, 0.0, 0.12]),
                     geo.rotvec_to_quat(np.radians([0.0, 5.0, 0.0])))
#: accelerometer rig at the back of the head, turned 12 degrees about z and tilted 4 about x
HEAD_TO_ACCEL_RIG = (np.array([-0.08, 0.01, 0.06]),
                     geo.rotvec_to_quat(np.radians([4.0, 0.0, 12.0])))
