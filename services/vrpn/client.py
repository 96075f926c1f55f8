"""A VRPN tracker client that stays connected: TCP or the UDP "call me back" handshake.

``NAME@tcp://HOST:PORT`` connects to the server's TCP port.  ``NAME@HOST:PORT`` listens on
a TCP port of its own, lobs ``"<our IP> <that port>"`` datagrams at the server's UDP port
until the server connects back, then opens a UDP port and tells the server (a UDP
description), so the reports arrive by UDP as VRPN sends them.  Pos_Quat reports of the
tracker ``NAME`` go to ``on_pose(sensor, t_ns, position, quaternion)`` with the server's
timestamp.

When the server goes away the client tries again every ``retry_s`` (0.25 s: VRPN's own
clients wait 1 to 2 s between attempts), so it is back within a fraction of a second of the
server's return.

A server that goes silent without closing the connection (its process hung or stopped, the
network path gone without a FIN or RST) is noticed with VRPN's ping: when nothing has come
from the server for ``ping_s``, the client sends ``vrpn_Base ping_message`` on the
tracker's sender, which VRPN's servers (and uma's) answer with ``vrpn_Base pong_message``.
If neither the pong nor anything else arrives within ``pong_timeout_s``, the client logs
how long the server has been silent, drops the connection (counted in ``silent_drops``)
and reconnects as for a lost server.  A server that sends nothing because its device does
not move still answers the pings, so it is kept.

VRPN's clients (VRPN, vrpn_BaseClass.C: ``client_mainloop``, ``initiate_ping_cycle``) ping
only when they connect or lose the connection, repeat the ping every second while it is
unanswered, warn "No response from server for >= 3 seconds" and call the server flatlined
after 10 s, but never drop it; a server that hangs after its first pong goes unnoticed
(``vrpn_print_devices`` just stops printing).  uma takes the same second and three seconds
(``ping_s`` 1, ``pong_timeout_s`` 3: a silent server is dropped after about 4 s of silence)
but pings whenever the server is silent and drops the connection instead of only warning:
neither a stopped process nor a dead path ever closes it (a client that only receives
gives TCP nothing to time out), while reconnecting finds the server again once it runs (or
is back at its address).  Over TCP one ping is enough: a repeat cannot overtake the first.
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
from services.vrpn.link import Link
from services.vrpn.loop import wait_for_event

log = logging.getLogger("uma.vrpn")

OnPose = Callable[[int, int, Any, Any], Any]

#: silence (s) after which the server is pinged: VRPN's clients ping once a second
DEFAULT_PING_S = 1.0
#: a ping unanswered this long (s), with nothing else received, drops the connection:
#: VRPN's clients warn "No response from server" after 3 s
DEFAULT_PONG_TIMEOUT_S = 3.0
#: our ids on the link (per connection and direction): the tracker's sender, the ping type
SENDER_ID = 0
PING_ID = 0


class _Datagrams(asyncio.DatagramProtocol):
    """Our UDP port: messages from the server, named by the TCP link's tables."""

    def __init__(self, client: TrackerClient, link: Link) -> None:
        self.client = client
        self.link = link

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            msgs = vp.decode_datagram(data)
        except vp.ProtocolError as exc:
            self.client.bad(f"datagram from {addr[0]}:{addr[1]} dropped: {exc}")
            return
        self.link.heard = time.monotonic()  # the server is alive: no ping needed
        for msg in msgs:
            self.client.udp_reports += self.client.handle(self.link, msg)


class TrackerClient:
    """Receives one VRPN tracker; :meth:`run` connects and reconnects until stopped
    (``ping_s`` and ``pong_timeout_s``: the module docstring)."""

    def __init__(self, address: vp.DeviceAddress, on_pose: OnPose,
                 retry_s: float = 0.25, ping_s: float = DEFAULT_PING_S,
                 pong_timeout_s: float = DEFAULT_PONG_TIMEOUT_S) -> None:
        self.address = address
        self.on_pose = on_pose
        self.retry_s = retry_s
        self.ping_s = ping_s
        self.pong_timeout_s = pong_timeout_s
        self.connected = asyncio.Event()
        self.connections = 0
        #: pings sent, pongs received, connections dropped because the server went silent
        self.pings = 0
        self.pongs = 0
        self.silent_drops = 0
        #: set by a pong, so the next ping is timed from it (not from the ping's timeout)
        self._ponged = asyncio.Event()
        self.reports = 0
        self.velocity_reports = 0
        self._warned: set[str] = set()
        self._log = RateLimitedLog(log)
        self._udp: asyncio.DatagramTransport | None = None
        self._udp_task: asyncio.Future | None = None
        #: reports that came by UDP (the rest came by TCP)
        self.udp_reports = 0

    # -- messages
    def handle(self, link: Link, msg: vp.Message) -> bool:
        """Take one message of the server; True if it was a pose report of our tracker."""
        if link.senders.get(msg.sender) != self.address.name:
            return False  # another device of the same server
        kind = link.types.get(msg.type)
        try:
            if kind == vp.POS_QUAT:
                r = vp.decode_pos_quat(msg.payload)
                self.reports += 1
                self.on_pose(r.sensor, msg.t_ns, r.position, r.quaternion)
                return True
            elif kind == vp.VELOCITY:
                vp.decode_velocity(msg.payload)
                self.velocity_reports += 1
                self.note("velocity", "velocity reports arrive; uma has no velocity type, "
                          "so only poses are published")
            elif kind == vp.PONG:
                self.pongs += 1
                self._ponged.set()
        except vp.ProtocolError as exc:
            self.bad(f"{kind} report dropped: {exc}")
        return False

    def bad(self, text: str) -> None:
        """A bad datagram or report: logged (rate-limited: UDP can come from anyone)."""
        self._log.warning(f"VRPN server {self.address}", text)

    def note(self, key: str, text: str) -> None:
        """Log ``text`` once per run."""
        if key not in self._warned:
            self._warned.add(key)
            log.info("VRPN server %s: %s", self.address, text)

    # -- connecting
    async def run(self, stop: asyncio.Event) -> None:
        """Connect, serve until the link closes, try again; until ``stop`` is set."""
        while not stop.is_set():
            closed = asyncio.get_running_loop().create_future()
            try:
                link = await self._connect(closed, stop)
            except OSError as exc:
                self.note(f"unreachable {exc}", f"not reachable yet ({exc}); trying again "
                          f"every {self.retry_s} s")
                link = None
            if link is not None:
                await self._watch(link, closed, stop)
                self.connected.clear()
                link.close()
                self._close_udp()
            if not stop.is_set():
                await wait_for_event(stop, self.retry_s)

    async def _watch(self, link: Link, closed: asyncio.Future, stop: asyncio.Event) -> None:
        """Until the link closes or ``stop`` is set: ping a server silent for ``ping_s``,
        drop it if nothing comes within ``pong_timeout_s`` of the ping (a hung server or a
        dead path closes nothing; TCP alone would wait for ever)."""
        await _until(closed, stop, self.connected)  # until then, Link's cookie timeout
        pinged: float | None = None  # when we pinged, while nothing came since
        while not (closed.done() or stop.is_set()):
            now = time.monotonic()
            if pinged is not None and link.heard > pinged:
                pinged = None
            if pinged is None and now - link.heard >= self.ping_s:
                self._ping(link)
                pinged = now
            if pinged is not None and now - pinged >= self.pong_timeout_s:
                self._drop_silent(link, now - link.heard)
                return
            due = link.heard + self.ping_s if pinged is None else pinged + self.pong_timeout_s
            self._ponged.clear()
            await _until(closed, stop, self._ponged, timeout=due - now)

    def _ping(self, link: Link) -> None:
        """``vrpn_Base ping_message`` on the tracker's sender, as VRPN's clients send it."""
        self.pings += 1
        link.send(vp.encode_message(PING_ID, SENDER_ID, time.time_ns()))

    def _drop_silent(self, link: Link, silent_s: float) -> None:
        """Say why and close: :meth:`run` then reconnects as for a lost server."""
        self.silent_drops += 1
        link.fail(f"VRPN server {self.address} silent for {silent_s:.1f} s: no pong within "
                  f"{self.pong_timeout_s:g} s of our ping (the server hangs or is stopped, "
                  "the network path to it is gone, or it has no device "
                  f"{self.address.name!r})")

    def _link(self, closed: asyncio.Future) -> Link:
        def on_closed(link: Link) -> None:
            if not closed.done():
                closed.set_result(None)
        return Link(self._ready, self.handle, on_closed, bad=self._log)

    async def _connect(self, closed: asyncio.Future, stop: asyncio.Event) -> Link | None:
        loop = asyncio.get_running_loop()
        a = self.address
        if a.tcp:
            _, link = await loop.create_connection(lambda: self._link(closed), a.host, a.port)
            return link
        accepted: asyncio.Future = loop.create_future()

        def factory() -> Link:
            link = self._link(closed)
            if not accepted.done():
                accepted.set_result(link)
            return link
        my_ip = _local_ip_towards(a.host, a.port)
        listener = await loop.create_server(factory, my_ip, 0, backlog=1)
        try:
            request = vp.lob_request(my_ip, listener.sockets[0].getsockname()[1])
            lob, _ = await loop.create_datagram_endpoint(asyncio.DatagramProtocol,
                                                         remote_addr=(a.host, a.port))
            try:
                while not accepted.done() and not stop.is_set():
                    lob.sendto(request)
                    await asyncio.wait([accepted], timeout=self.retry_s)
            finally:
                lob.close()
        finally:
            listener.close()
        return accepted.result() if accepted.done() else None

    def _ready(self, link: Link) -> None:
        """Cookies exchanged: name our sender and the ping type (so we can ping), connected;
        over the UDP handshake, open our UDP port and say where."""
        now = time.time_ns()
        link.send(vp.sender_description(SENDER_ID, self.address.name, now)
                  + vp.type_description(PING_ID, vp.PING, now))
        self.connections += 1
        self.connected.set()
        log.info("VRPN server %s: connected (%s)", self.address,
                 "TCP" if self.address.tcp else "UDP handshake")
        if not self.address.tcp:
            self._udp_task = asyncio.ensure_future(self._open_udp(link))

    async def _open_udp(self, link: Link) -> None:
        loop = asyncio.get_running_loop()
        my_ip = link.transport.get_extra_info("sockname")[0]
        try:
            udp, _ = await loop.create_datagram_endpoint(lambda: _Datagrams(self, link),
                                                         local_addr=(my_ip, 0))
        except OSError as exc:
            link.fail(f"cannot open a UDP port for its reports ({exc})")
            return
        if link.closed:  # gone meanwhile
            udp.close()
            return
        self._udp = udp
        port = udp.get_extra_info("sockname")[1]
        link.send(vp.udp_description(my_ip, port, time.time_ns()))

    def _close_udp(self) -> None:
        if self._udp is not None:
            self._udp.close()
            self._udp = None


def _local_ip_towards(host: str, port: int) -> str:
    """The address of our interface that reaches ``host`` (what VRPN's vrpn_getmyIP
    finds from a socket connected to the server), so the server can call us back."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.connect((socket.gethostbyname(host), port))
        return s.getsockname()[0]


async def _until(closed: asyncio.Future, *events: asyncio.Event,
                 timeout: float | None = None) -> None:
    """Until ``closed`` is done, one of ``events`` is set or ``timeout`` s have passed."""
    waits = [asyncio.ensure_future(e.wait()) for e in events]
    try:
        await asyncio.wait([closed, *waits], timeout=timeout,
                           return_when=asyncio.FIRST_COMPLETED)
    finally:
        for w in waits:
            w.cancel()
