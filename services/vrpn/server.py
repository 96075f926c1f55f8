"""A VRPN tracker server: any number of clients, by TCP or by the UDP handshake.

Listens on one port number for both: TCP connections (``tcp://`` clients: reports go over
that TCP link) and UDP lob requests (the server connects back to the client's TCP port;
once the client sends its UDP description, reports go to it by UDP, as VRPN sends
low-latency messages).  Each tracker is one VRPN sender; every client learns the senders
and the Pos_Quat, Velocity and pong types when it connects, and gets an answer to its
pings, so VRPN's clients see a live server.  All of it runs on one asyncio loop; other
threads hand reports over with :meth:`TrackerServer.report_threadsafe`.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time

from agent.runtime import RateLimitedLog
from services.vrpn import protocol as vp
from services.vrpn.link import DEFAULT_MAX_BUFFER, Link

log = logging.getLogger("uma.vrpn")

#: our type ids (each client learns them by name)
TYPES = (vp.POS_QUAT, vp.VELOCITY, vp.PONG)
POS_QUAT_ID, VELOCITY_ID, PONG_ID = range(len(TYPES))


class _LobListener(asyncio.DatagramProtocol):
    """The UDP side of the port: 'call me back at HOST PORT' requests."""

    def __init__(self, server: TrackerServer) -> None:
        self.server = server

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            host, port = vp.parse_lob_request(data)
        except vp.ProtocolError as exc:
            self.server.bad.warning(f"VRPN request from {addr[0]}:{addr[1]}", f"refused: {exc}")
            return
        self.server.call_back(host, port)


class TrackerServer:
    """VRPN trackers named ``trackers`` (sender ids in that order) on ``host``:``port``."""

    def __init__(self, trackers: list[str], host: str = "0.0.0.0",
                 port: int = vp.DEFAULT_PORT, max_buffer: int = DEFAULT_MAX_BUFFER) -> None:
        for name in trackers:
            vp.check_name(name)
        self.trackers = list(trackers)
        self.host = host
        self.port = port
        self.max_buffer = max_buffer
        self.links: list[Link] = []
        self.loop: asyncio.AbstractEventLoop | None = None
        self._calling: set[tuple[str, int]] = set()
        self._tasks: set[asyncio.Future] = set()
        self._tcp: asyncio.Server | None = None
        self._lob: asyncio.DatagramTransport | None = None
        self._udp_out: asyncio.DatagramTransport | None = None
        #: bad requests from anyone on the network must not flood the log
        self.bad = RateLimitedLog(log)

    async def start(self) -> None:
        """Listen; ``OSError`` (port taken, bad address) is the caller's to report."""
        self.loop = asyncio.get_running_loop()
        self._tcp = await self.loop.create_server(self._new_link, self.host, self.port,
                                                  backlog=socket.SOMAXCONN)
        self.port = self._tcp.sockets[0].getsockname()[1]
        self._lob, _ = await self.loop.create_datagram_endpoint(
            lambda: _LobListener(self), local_addr=(self.host, self.port))
        self._udp_out, _ = await self.loop.create_datagram_endpoint(
            asyncio.DatagramProtocol, local_addr=(self.host, 0))

    async def close(self) -> None:
        for link in list(self.links):
            link.close()
        for t in (self._lob, self._udp_out):
            if t is not None:
                t.close()
        if self._tcp is not None:
            self._tcp.close()
            await self._tcp.wait_closed()

    # -- connections
    def _new_link(self) -> Link:
        return Link(self._ready, self._message, self._closed, self.max_buffer, self.bad)

    def call_back(self, host: str, port: int) -> None:
        """Connect to a client that lobbed a request (once while a call is under way: a
        client lobs until we call)."""
        if (host, port) in self._calling:
            return
        self._calling.add((host, port))
        task = asyncio.ensure_future(self._connect_to(host, port))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _connect_to(self, host: str, port: int) -> None:
        try:
            await self.loop.create_connection(self._new_link, host, port)
        except OSError as exc:
            log.warning("VRPN client at %s:%d asked to be called back, but: %s", host, port,
                        exc)
        finally:
            self._calling.discard((host, port))

    def _ready(self, link: Link) -> None:
        now = time.time_ns()
        out = [vp.sender_description(i, name, now) for i, name in enumerate(self.trackers)]
        out += [vp.type_description(i, name, now) for i, name in enumerate(TYPES)]
        if link.send(b"".join(out)):
            self.links.append(link)
            log.info("VRPN client %s connected (%d now)", link.peer, len(self.links))

    def _message(self, link: Link, msg: vp.Message) -> None:
        if link.types.get(msg.type) == vp.PING:
            name = link.senders.get(msg.sender)
            if name in self.trackers:
                link.send(vp.encode_message(PONG_ID, self.trackers.index(name), time.time_ns()))

    def _closed(self, link: Link) -> None:
        if link in self.links:
            self.links.remove(link)
            log.info("VRPN client %s gone (%d left)", link.peer, len(self.links))

    # -- reports
    def report(self, tracker: int, t_ns: int, position: object, quaternion: object,
               sensor: int = 0) -> None:
        """Send a Pos_Quat of ``self.trackers[tracker]`` to every client (on the loop)."""
        payload = vp.encode_pos_quat(sensor, position, quaternion)
        self._broadcast(vp.encode_message(POS_QUAT_ID, tracker, t_ns, payload))

    def report_threadsafe(self, tracker: int, t_ns: int, position: object,
                          quaternion: object) -> None:
        """:meth:`report` from another thread."""
        self.loop.call_soon_threadsafe(self.report, tracker, t_ns, position, quaternion)

    def _broadcast(self, data: bytes) -> None:
        for link in list(self.links):
            if link.udp_peer is not None and self._udp_out is not None:
                self._udp_out.sendto(data, link.udp_peer)
            else:
                link.send(data)  # drops a client that stopped reading
