"""The installation model: what a real site describes of itself, in a file or a
calibration, and what the trackers need to know of it.

``ivy`` holds the IVY cube's walls and screens (where a laser spot on a screen is in the
world, eq. 5.40; the active area; a beam's hit), ``laser_housing`` the laser rig's four
beams, ``camera`` the cameras behind the screens (mount, intrinsics, OpenCV distortion).
Real-hardware code (the laser tracker and its calibration, the fusion's dots, the dead
reckoner) imports this, never the simulator (``services.sim``), which builds its world
from it.
"""
