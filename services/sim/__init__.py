"""The simulator: IVY's six-sided display rendered, the head's trajectory, noise and the
ground truth, built on the installation model (``services.installation``: walls, beams,
cameras), which real-hardware code uses instead of this package.

``IvyWorld(n_cameras=6, seed=1)`` (``world``) renders the cameras' images
(``world.render(t)``), gives the true rig pose (``world.rig_pose(t)``) and the beams' wall
hits (``world.laser_hits(p, q)``); ``trajectory`` and ``mounts`` hold the head motion and
the true rig mountings; ``render`` and ``projection`` the images; ``calibrations`` the
simulated installation's calibrations, cached on disk; ``service`` publishes the ground
truth.
"""
