"""Stopping child processes: the one way uma's commands, tests and benchmarks end them."""

from __future__ import annotations

import signal
import subprocess
import time
from collections.abc import Iterable


def stop_processes(procs: Iterable[subprocess.Popen], timeout: float = 5.0) -> None:
    """SIGTERM every child still running, give them ``timeout`` seconds in all to exit
    cleanly (tokens undeclared, sessions closed), then SIGKILL the rest.

    Only ``Popen`` objects the caller started are touched, by their PID: never by name.
    """
    procs = list(procs)
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=timeout)
