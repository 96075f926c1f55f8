"""Telling a supervisor that a daemon is ready: systemd's ``sd_notify`` protocol.

A unit with ``Type=notify`` (``deploy/systemd/``) starts the units ordered after it only
once the daemon has sent ``READY=1``, and shows its ``STATUS=``; a daemon that exits
before is restarted (``Restart=on-failure``).  The protocol is one datagram of
``NAME=VALUE`` lines to the Unix socket named by ``$NOTIFY_SOCKET`` (a leading ``@`` is an
abstract socket), as the sd_notify(3) manual describes; a dozen lines here rather than a
dependency on libsystemd.  Without ``$NOTIFY_SOCKET`` (not under systemd) it does nothing.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger("uma.ready")


def notify(**fields: str) -> bool:
    """Send ``fields`` (``READY="1"``, ``STATUS="..."``, ``STOPPING="1"``) to the
    supervisor; True if one listens.  A failure is logged, never raised: the daemon works
    the same without its supervisor's notice."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    message = "\n".join(f"{k}={v}" for k, v in fields.items()).encode()
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(address)
            s.sendall(message)
    except OSError as exc:
        log.warning("cannot notify the supervisor at NOTIFY_SOCKET=%s: %s",
                    os.environ.get("NOTIFY_SOCKET"), exc)
        return False
    return True
