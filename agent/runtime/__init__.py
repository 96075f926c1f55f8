"""What every uma process uses, whatever its role: its Zenoh session, plug-in lookup,
rate-limited logs and the stopping of child processes."""
