"""The tests' own VRPN tracker client, written from VRPN's ``Format_Of_Protocol.txt`` and
``vrpn_Connection.C`` with plain sockets and ``struct``: it shares no code with
``services.vrpn``, so a mistake there cannot hide itself.

``RawClient(host, port, "Head", udp=True)`` lobs ``"127.0.0.1 <tcp port>\\0"`` at the
server's UDP port until the server connects back, sends its cookie and a UDP description,
and collects every ``vrpn_Tracker Pos_Quat`` of the sender ``Head`` from TCP and UDP as
:class:`Report`.  ``udp=False`` connects by TCP.  ``stalled=True`` connects and then never
reads again (its receive buffer made small), as a hung application would.
"""

from __future__ import annotations

import select
import socket
import struct
import threading
import time
from dataclasses import dataclass

COOKIE = b"vrpn: ver. 07.38  0".ljust(24, b"\0")
HEADER = struct.Struct(">IIIiiI")  # length, sec, usec, sender, type, sequence


@dataclass
class Report:
    t_ns: int  # the message's timeval in ns
    sensor: int
    position: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]
    via: str  # "tcp" or "udp"
    recv_ns: int


def _pad(n: int) -> int:
    return (n + 7) // 8 * 8


class RawClient:
    def __init__(self, host: str, port: int, tracker: str, udp: bool = True,
                 stalled: bool = False, timeout: float = 20.0) -> None:
        self.tracker = tracker
        self.reports: list[Report] = []
        self.senders: dict[int, str] = {}
        self.types: dict[int, str] = {}
        self.closed_by_server = False
        self._stop = threading.Event()
        self.tcp = self._connect(host, port, udp, stalled, timeout)
        self.tcp.sendall(COOKIE)
        self.udp: socket.socket | None = None
        self._thread: threading.Thread | None = None
        if stalled:
            return
        if self.tcp.recv(24, socket.MSG_WAITALL)[:16] != COOKIE[:16]:
            raise AssertionError("server's cookie is not VRPN 07.38's")
        if udp:
            self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.udp.bind(("127.0.0.1", 0))
            body = b"127.0.0.1\0"
            self.tcp.sendall(HEADER.pack(24 + len(body), 0, 0, self.udp.getsockname()[1], -3, 0)
                             + body.ljust(_pad(len(body)), b"\0"))
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    @staticmethod
    def _connect(host: str, port: int, udp: bool, stalled: bool, timeout: float,
                 ) -> socket.socket:
        if not udp:
            s = socket.socket()
            if stalled:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            s.connect((host, port))
            return s
        with socket.socket() as listener, \
                socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as lob:
            listener.bind(("127.0.0.1", 0))
            listener.listen(1)
            listener.settimeout(0.2)
            request = b"127.0.0.1 %d\0" % listener.getsockname()[1]
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                lob.sendto(request, (host, port))
                try:
                    s, _ = listener.accept()
                    return s
                except TimeoutError:
                    continue
        raise AssertionError(f"no call back from {host}:{port} within {timeout} s")

    def _read(self) -> None:
        buf = b""
        socks = [self.tcp] + ([self.udp] if self.udp else [])
        while not self._stop.is_set():
            ready, _, _ = select.select(socks, [], [], 0.1)
            for s in ready:
                if s is self.udp:
                    self._parse(s.recv(65536), "udp")
                    continue
                data = s.recv(65536)
                if not data:
                    self.closed_by_server = True
                    return
                buf = self._parse(buf + data, "tcp")

    def _parse(self, data: bytes, via: str) -> bytes:
        """Take every whole message of ``data``; return the incomplete rest."""
        at = 0
        while len(data) - at >= 24:
            length, sec, usec, sender, mtype, _ = HEADER.unpack_from(data, at)
            end = at + 24 + _pad(length - 24)
            if len(data) < end:
                break
            payload = data[at + 24: at + length]
            if mtype in (-1, -2):
                (n,) = struct.unpack_from(">i", payload)
                name = payload[4: 4 + n - 1].decode()
                (self.senders if mtype == -1 else self.types)[sender] = name
            elif (self.types.get(mtype) == "vrpn_Tracker Pos_Quat"
                  and self.senders.get(sender) == self.tracker):
                v = struct.unpack(">ii3d4d", payload)
                self.reports.append(Report(sec * 10**9 + usec * 1000, v[0], v[2:5], v[5:9],
                                           via, time.time_ns()))
            at = end
        return data[at:]

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        self.tcp.close()
        if self.udp:
            self.udp.close()
