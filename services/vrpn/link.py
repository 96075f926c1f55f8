"""One TCP connection to a VRPN peer, either side: cookies, name tables, bounded sending.

A :class:`Link` is an asyncio protocol.  It writes our cookie, checks the peer's, then
decodes messages: sender and type descriptions fill the peer's name tables, a UDP
description records where the peer takes low-latency messages, everything else goes to
``on_message``.  Anything malformed (a wrong cookie, a length beyond VRPN's limit, a bad
description) is logged with the peer's address and the reason, and the connection is
closed; a peer that leaves mid-message is logged as such.

Sending is bounded: the socket's kernel buffer is set to ``max_buffer`` and once more than
``max_buffer`` bytes wait in the transport besides for a peer that does not read, the peer
is dropped, so one stalled client never holds up the others
nor grows our memory.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import Callable
from typing import Any

from agent.runtime import RateLimitedLog
from services.vrpn import protocol as vp

log = logging.getLogger("uma.vrpn")

#: VRPN's own TCP output buffer (vrpn_CONNECTION_TCP_BUFLEN)
DEFAULT_MAX_BUFFER = 64000
#: a peer that has not sent its cookie by then is not a VRPN peer
COOKIE_TIMEOUT_S = 5.0


class Link(asyncio.Protocol):
    """A VRPN TCP link; ``on_ready(link)`` once the cookies are exchanged,
    ``on_message(link, msg)`` for each non-system message, ``on_closed(link)`` once.
    ``bad`` is the owner's limiter for what peers do wrong: a peer that reconnects and
    misbehaves in a loop gets one line per kind every 10 s, not one per connection."""

    def __init__(self, on_ready: Callable[[Link], Any],
                 on_message: Callable[[Link, vp.Message], Any],
                 on_closed: Callable[[Link], Any], max_buffer: int = DEFAULT_MAX_BUFFER,
                 bad: RateLimitedLog | None = None) -> None:
        self.bad = bad if bad is not None else RateLimitedLog(log)
        self.on_ready = on_ready
        self.on_message = on_message
        self.on_closed = on_closed
        self.max_buffer = max_buffer
        self.transport: asyncio.Transport | None = None
        self.peer = self.peer_host = "?"
        self.ready = False
        self.closed = False
        #: closed by us (``fail``), not by the peer
        self.failed = False
        #: the peer's ids -> names
        self.senders: dict[int, str] = {}
        self.types: dict[int, str] = {}
        #: where the peer takes UDP messages, once it said so
        self.udp_peer: tuple[str, int] | None = None
        #: when the peer last sent anything (``time.monotonic()``): a hung peer closes
        #: nothing, so silence is how a client tells it from a live one
        self.heard = time.monotonic()
        self._cookie = bytearray()
        self._decoder = vp.StreamDecoder()

    # -- asyncio
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        name = transport.get_extra_info("peername")
        self.peer = f"{name[0]}:{name[1]}" if name else "?"
        self.peer_host = str(name[0]) if name else "?"
        sock = transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            # the kernel's buffer is bounded too (Linux grows it to megabytes otherwise,
            # minutes of reports for a client that stopped reading)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.max_buffer)
        self.transport.write(vp.cookie())
        asyncio.get_running_loop().call_later(COOKIE_TIMEOUT_S, self._cookie_due)

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        self.heard = time.monotonic()
        try:
            if not self.ready:
                data = self._take_cookie(data)
            for msg in self._decoder.feed(data) if data else ():
                self._dispatch(msg)
        except vp.ProtocolError as exc:
            self.fail(str(exc))

    def connection_lost(self, exc: Exception | None) -> None:
        if self.closed:
            return
        self.closed = True
        if self.failed:
            pass  # ``fail`` said why: the peer did not leave, we closed it
        elif self._decoder.pending:
            self._warn(f" left mid-message ({self._decoder.pending} bytes of it received)")
        elif not self.ready:
            self._warn(f" left before its cookie ({exc or 'connection closed'})")
        else:
            log.info("VRPN peer %s disconnected%s", self.peer, f" ({exc})" if exc else "")
        self.on_closed(self)

    # -- receiving
    def _cookie_due(self) -> None:
        if not self.ready:
            self.fail(f"sent no VRPN cookie within {COOKIE_TIMEOUT_S:g} s")

    def _take_cookie(self, data: bytes) -> bytes:
        need = vp.COOKIE_SIZE - len(self._cookie)
        self._cookie += data[:need]
        if len(self._cookie) < vp.COOKIE_SIZE:
            return b""
        note = vp.check_cookie(bytes(self._cookie))
        if note:
            log.info("VRPN peer %s: %s", self.peer, note)
        self.ready = True
        self.on_ready(self)
        return data[need:]

    def _dispatch(self, msg: vp.Message) -> None:
        if msg.type == vp.SENDER_DESCRIPTION:
            self.senders[msg.sender] = vp.decode_name(msg.payload)
        elif msg.type == vp.TYPE_DESCRIPTION:
            self.types[msg.sender] = vp.decode_name(msg.payload)
        elif msg.type == vp.UDP_DESCRIPTION:
            self.udp_peer = vp.decode_udp_description(msg)
        elif msg.type == vp.LOG_DESCRIPTION:
            log.info("VRPN peer %s asks for remote logging; not supported, ignored", self.peer)
        elif msg.type >= 0:
            self.on_message(self, msg)
        else:
            raise vp.ProtocolError(f"unknown system message type {msg.type}")

    # -- sending
    def send(self, data: bytes) -> bool:
        """Queue ``data``; False (and the peer dropped) if it has stopped reading."""
        if self.closed or self.transport is None:
            return False
        self.transport.write(data)
        waiting = self.transport.get_write_buffer_size()
        if waiting > self.max_buffer:
            self.fail(f"stopped reading ({waiting} bytes waiting, limit {self.max_buffer}); "
                      "dropped so the others are not held up")
            return False
        return True

    def fail(self, reason: str) -> None:
        """Log why and close the connection now."""
        if self.closed or self.failed:
            return
        self.failed = True
        self._warn(f": {reason}; closing the connection")
        if self.transport is not None:
            self.transport.abort()

    def _warn(self, what: str) -> None:
        self.bad.warning(f"VRPN host {self.peer_host}", f"peer {self.peer}{what}")

    def close(self) -> None:
        if self.transport is not None and not self.closed:
            self.transport.close()
