"""Loopback plumbing the multi-process benchmarks share: a free port, and waiting until
the processes a benchmark started listen.  Import it as ``from loopback import ...``."""

from __future__ import annotations

import socket
import time


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_listening(ports: list[int], limit_s: float = 60.0) -> None:
    """Return once every port accepts a connection; ``SystemExit`` naming the first that
    does not within ``limit_s`` (processes take seconds to start on a loaded machine)."""
    deadline = time.monotonic() + limit_s
    for port in ports:
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise SystemExit(f"setup failed: nothing listens on port {port} after "
                                     f"{limit_s:g} s") from None
                time.sleep(0.1)
