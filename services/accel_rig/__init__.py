"""accel_rig service."""
