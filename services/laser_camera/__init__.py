"""MARVIN's laser-dot camera tracker (Hogue 2003, ch. 5).

The pure pipeline (no I/O) for reuse in evaluations and other services::

    from services.laser_camera.calibration import Calibration, sim_calibration
    from services.laser_camera.tracker import LaserTracker
    tracker = LaserTracker(Calibration.load("ivy.json"))
    result = tracker.process({"front": img, ...}, t)   # PoseEstimate or NoPose

    # on the simulator (calibrated once, then cached in the file):
    world = IvyWorld(seed=1)
    tracker = LaserTracker(sim_calibration(world, cache="/tmp/ivy_calibration.json"))
    result = tracker.process(world.render(t).images, t)

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.

The package imports none of them itself: its ``plugin`` (``uma service run laser-camera
--help``, ``uma eval laser-camera --help``) must stay light to import.
"""
