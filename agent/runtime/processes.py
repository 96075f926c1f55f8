"""Processes: the one way uma's commands, tests and benchmarks end their children, how a
long-running command learns it must stop (SIGINT, SIGTERM), and how many network links a
process holds (the measure of the realm's topology)."""

from __future__ import annotations

import signal
import subprocess
import threading
import time
from collections.abc import Iterable
from pathlib import Path


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


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT/SIGTERM, so long-running commands stop cleanly."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def established_tcp(pid: int) -> int:
    """How many ESTABLISHED TCP connections process ``pid`` holds (IPv4 and IPv6), read from
    ``/proc``: its socket inodes, looked up in its network namespace's connection tables."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = fd.readlink().name if fd.is_symlink() else ""
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    count = 0
    for table in ("tcp", "tcp6"):
        try:
            lines = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 9 and fields[3] == "01" and fields[9] in inodes:  # 01: ESTABLISHED
                count += 1
    return count
