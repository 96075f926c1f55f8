"""The simulated world: IVY six-sided display, head trajectory and ground truth.

``IvyWorld(n_cameras=6, seed=1)`` (``world``) renders the cameras' images
(``world.render(t)``), gives the true rig pose (``world.rig_pose(t)``) and the beams' wall
hits (``world.laser_hits(p, q)``); ``trajectory`` and ``mounts`` hold the head motion and
the frames shared by all services; ``service`` publishes the ground truth.
"""
