"""Tracker services (MARVIN): ``sim`` (the simulated IVY world), ``laser_camera``,
``accel_rig``, ``fusion`` and ``alignment``.  Each registers as a plug-in (see
``agent.runtime.plugins`` and the entry points in pyproject.toml).
"""
