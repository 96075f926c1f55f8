"""Loopback plumbing the multi-process benchmarks share: a free port, a bare Zenoh session's
configuration, and waiting until the processes a benchmark started listen.  Import it as
``from loopback import ...``."""

from __future__ import annotations

import json
import socket
import time
from typing import Any


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


def zenoh_config(mode: str = "peer", listen: str | None = None,
                 connect: str | None = None) -> Any:
    """A bare Zenoh session's configuration (no uma code): no multicast scouting, listening
    only on ``listen`` (none: nowhere, rather than Zenoh's default of every interface) and
    connecting to ``connect``."""
    import zenoh
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([listen] if listen else []))
    if connect:
        c.insert_json5("connect/endpoints", json.dumps([connect]))
    return c
