"""laser_camera service."""
