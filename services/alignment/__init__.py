"""alignment service."""
