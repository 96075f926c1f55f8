"""VRPN's wire format for trackers: the one place that knows its bytes (no I/O here).

A VRPN connection is a TCP stream (and optionally UDP datagrams) of messages.  Both peers
first write a 24-byte **cookie** (``"vrpn: ver. 07.38  L"``, L the remote log mode, NUL
padded); peers whose major version differs refuse each other, a minor difference is only
noted.  Every message is then a 24-byte **header** of six big-endian 32-bit words — total
length (header + *unpadded* payload), time seconds, time microseconds, sender id, type id,
a sequence number nobody reads — followed by the payload padded with any bytes to a
multiple of 8.  Ids are per connection and per direction: a peer names its ids with
**sender** (-1) and **type** (-2) **description** messages, whose sender field is the id
and whose payload is ``int32 strlen(name) + 1``, the name and its NUL.  A **UDP
description** (-3) carries, in its sender field, the UDP port on which the peer takes
low-latency messages and, as payload, its IP address as a NUL-terminated string.

| type (name)              | payload                                                    |
|--------------------------|------------------------------------------------------------|
| ``vrpn_Tracker Pos_Quat`` | int32 sensor, int32 padding, float64 pos[3], quat[4] xyzw |
| ``vrpn_Tracker Velocity`` | int32 sensor, int32 padding, float64 vel[3], vel_quat[4],  |
|                          | float64 vel_quat_dt                                        |
| ``vrpn_Base ping_message`` | empty: a client asks whether the server is alive         |
| ``vrpn_Base pong_message`` | empty: the server's answer                               |

Connecting: with a ``tcp://`` name the client connects to the server's TCP port (default
3883) and the link is TCP only.  Otherwise the client listens on a TCP port of its own and
**lobs** UDP datagrams ``"<its IP> <that port>\\0"`` at the server's UDP port (the same
number) until the server connects back; then both may send UDP descriptions and the
tracker reports flow over UDP.  Doubles are big-endian IEEE 754; time is a ``timeval``
(seconds, microseconds since the epoch), so a nanosecond timestamp loses its last three
digits on the way through VRPN.

Sources (VRPN 07.38, the vrpn/vrpn repository): ``Format_Of_Protocol.txt`` (header, cookie,
descriptions); ``vrpn_Connection.C`` (``marshall_message``, ``write_vrpn_cookie``,
``check_vrpn_cookie``, ``pack_sender_description``, ``pack_udp_description``,
``vrpn_udp_request_lob_packet``, ``server_check_for_incoming_connections``: its checks of a
lob request); ``vrpn_Tracker.C`` (``encode_to``, ``encode_vel_to`` and the payload length
checks of ``vrpn_Tracker_Remote``); ``vrpn_Shared.C`` (``vrpn_htond``: big-endian doubles).
``Format_Of_Protocol.txt`` says the payload is padded by ``len % 8``; the code (which the
tests follow, with bytes captured from VRPN itself) pads to the next multiple of 8.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

import numpy as np

from agent.errors import InvalidInputError

MAGIC = b"vrpn: ver. 07.38"
#: what must match for two peers to talk: everything through the last '.' of MAGIC
MAGIC_MAJOR = MAGIC[: MAGIC.rindex(b".") + 1]
COOKIE_SIZE = 24
HEADER_SIZE = 24
ALIGN = 8
DEFAULT_PORT = 3883
#: VRPN's TCP input buffer (vrpn_CONNECTION_TCP_BUFLEN): a longer message is refused
MAX_PAYLOAD = 64000
#: VRPN's longest sender or type name buffer (vrpn_CNAME_LENGTH), NUL included
MAX_NAME = 100

SENDER_DESCRIPTION = -1
TYPE_DESCRIPTION = -2
UDP_DESCRIPTION = -3
LOG_DESCRIPTION = -4

POS_QUAT = "vrpn_Tracker Pos_Quat"
VELOCITY = "vrpn_Tracker Velocity"
PING = "vrpn_Base ping_message"
PONG = "vrpn_Base pong_message"

_HEADER = struct.Struct(">IIIiiI")
_POS_QUAT = struct.Struct(">ii3d4d")
_VELOCITY = struct.Struct(">ii3d4dd")
_LOB_RE = re.compile(rb"^([A-Za-z0-9.]{1,199}) (\d{1,5})\x00?$")


class ProtocolError(InvalidInputError):
    """Bytes that are not what VRPN sends; the message says what was wrong."""


@dataclass(frozen=True, slots=True)
class Message:
    """One VRPN message: ids are the sending peer's, ``t_ns`` its timeval in ns."""

    sender: int
    type: int
    t_ns: int
    payload: bytes


@dataclass(frozen=True, slots=True)
class PosQuat:
    """A tracker report: ``position`` in metres, ``quaternion`` x, y, z, w."""

    sensor: int
    position: np.ndarray
    quaternion: np.ndarray


@dataclass(frozen=True, slots=True)
class Velocity:
    """A velocity report: linear m/s, and the rotation ``vel_quat`` made in ``dt_s`` s."""

    sensor: int
    velocity: np.ndarray
    vel_quat: np.ndarray
    dt_s: float


# ---------------------------------------------------------------------------- time

def ns_to_timeval(t_ns: int) -> tuple[int, int]:
    """Seconds and microseconds of ``t_ns`` (floored: VRPN has no finer time)."""
    if t_ns < 0:
        raise ProtocolError(f"time {t_ns} ns is before 1970: a timeval cannot hold it")
    sec, rest = divmod(int(t_ns), 1_000_000_000)
    if sec > 0xFFFFFFFF:
        raise ProtocolError(f"time {t_ns} ns does not fit VRPN's 32-bit seconds")
    return sec, rest // 1000


def timeval_to_ns(sec: int, usec: int) -> int:
    return sec * 1_000_000_000 + usec * 1000


# ---------------------------------------------------------------------------- cookie

def cookie(log_mode: int = 0) -> bytes:
    """Our cookie, as ``write_vrpn_cookie`` writes it (24 bytes, NUL padded)."""
    text = MAGIC + b"  " + str(int(log_mode)).encode()
    return text.ljust(COOKIE_SIZE, b"\0")


def check_cookie(data: bytes) -> str | None:
    """Raise ``ProtocolError`` unless ``data`` is a compatible cookie; a note (minor
    version differs) or None."""
    if len(data) != COOKIE_SIZE:
        raise ProtocolError(f"cookie must be {COOKIE_SIZE} bytes, got {len(data)}")
    if not data.startswith(MAGIC_MAJOR):
        raise ProtocolError(f"not a VRPN 07.xx peer: cookie starts {bytes(data[:16])!r}, "
                            f"expected {MAGIC.decode()!r}")
    if data[18:19] not in (b"0", b"1", b"2", b"3"):
        raise ProtocolError(f"cookie's remote log mode {bytes(data[18:19])!r} is not 0..3")
    if data[:16] != MAGIC:
        return f"minor version differs: peer {bytes(data[:16]).decode('ascii', 'replace')}"
    return None


# ---------------------------------------------------------------------------- messages

def padded(n: int) -> int:
    """``n`` rounded up to VRPN's 8-byte alignment."""
    return (n + ALIGN - 1) // ALIGN * ALIGN


def encode_message(type_id: int, sender: int, t_ns: int, payload: bytes = b"",
                   seq: int = 0) -> bytes:
    """Header, payload and zero padding, as ``marshall_message`` lays them out."""
    if len(payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(payload)} bytes exceeds VRPN's {MAX_PAYLOAD}")
    sec, usec = ns_to_timeval(t_ns)
    header = _HEADER.pack(HEADER_SIZE + len(payload), sec, usec, sender, type_id,
                          seq & 0xFFFFFFFF)
    return header + payload + b"\0" * (padded(len(payload)) - len(payload))


def _message_at(data: bytes | memoryview, at: int) -> tuple[Message, int] | None:
    """The message starting at ``at`` and where the next begins; None if incomplete."""
    if len(data) - at < HEADER_SIZE:
        return None
    length, sec, usec, sender, type_id, _ = _HEADER.unpack_from(data, at)
    if length < HEADER_SIZE:
        raise ProtocolError(f"message length {length} is shorter than the 24-byte header")
    payload_len = length - HEADER_SIZE
    if payload_len > MAX_PAYLOAD:
        raise ProtocolError(f"message length {length} exceeds VRPN's limit of "
                            f"{HEADER_SIZE + MAX_PAYLOAD} bytes")
    end = at + HEADER_SIZE + padded(payload_len)
    if len(data) < end:
        return None
    payload = bytes(data[at + HEADER_SIZE: at + HEADER_SIZE + payload_len])
    return Message(sender, type_id, timeval_to_ns(sec, usec), payload), end


class StreamDecoder:
    """Messages out of a TCP byte stream, fed in pieces of any size."""

    def __init__(self) -> None:
        self._buf = bytearray()

    @property
    def pending(self) -> int:
        """Bytes of an incomplete message held (non-zero when a peer leaves mid-message)."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Message]:
        """Every message completed by ``data``; ``ProtocolError`` on a malformed header."""
        self._buf += data
        out: list[Message] = []
        at = 0
        while (found := _message_at(self._buf, at)) is not None:
            msg, at = found
            out.append(msg)
        del self._buf[:at]
        return out


def decode_datagram(data: bytes) -> list[Message]:
    """Every message of one UDP datagram (VRPN packs several into one)."""
    out: list[Message] = []
    at = 0
    while at < len(data):
        found = _message_at(data, at)
        if found is None:
            raise ProtocolError(f"datagram of {len(data)} bytes ends inside a message "
                                f"starting at byte {at}")
        msg, at = found
        out.append(msg)
    return out


# ---------------------------------------------------------------------------- descriptions

def check_name(name: str) -> bytes:
    """``name`` as VRPN sends it (``ProtocolError`` unless it is 1..95 ASCII characters,
    what a description's 100-byte buffer holds with its length and NUL)."""
    try:
        raw = name.encode("ascii")
    except UnicodeEncodeError:
        raw = b""
    if not 0 < len(raw) < MAX_NAME - 4 or b"\0" in raw:
        raise ProtocolError(f"VRPN name {name!r} must be 1..{MAX_NAME - 5} ASCII characters")
    return raw


def _encode_name(name: str) -> bytes:
    raw = check_name(name)
    return struct.pack(">i", len(raw) + 1) + raw + b"\0"


def decode_name(payload: bytes) -> str:
    """The name of a sender or type description (``handle_sender_message``'s checks)."""
    if not 4 < len(payload) <= MAX_NAME:
        raise ProtocolError(f"description payload of {len(payload)} bytes: a name needs "
                            f"5..{MAX_NAME}")
    (n,) = struct.unpack_from(">i", payload)
    if not 1 < n <= len(payload) - 4:
        raise ProtocolError(f"description says its name has {n} bytes; the payload holds "
                            f"{len(payload) - 4}")
    try:
        return payload[4: 4 + n - 1].decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError("description name is not ASCII") from None


def sender_description(sender: int, name: str, t_ns: int) -> bytes:
    return encode_message(SENDER_DESCRIPTION, sender, t_ns, _encode_name(name))


def type_description(type_id: int, name: str, t_ns: int) -> bytes:
    return encode_message(TYPE_DESCRIPTION, type_id, t_ns, _encode_name(name))


def udp_description(host: str, port: int, t_ns: int) -> bytes:
    """'Send your low-latency messages to ``host``:``port`` by UDP'."""
    return encode_message(UDP_DESCRIPTION, port, t_ns, host.encode("ascii") + b"\0")


def decode_udp_description(msg: Message) -> tuple[str, int]:
    host = msg.payload.split(b"\0", 1)[0]
    if not host or not 0 < msg.sender < 65536:
        raise ProtocolError(f"UDP description names host {host!r} port {msg.sender}")
    try:
        return host.decode("ascii"), msg.sender
    except UnicodeDecodeError:
        raise ProtocolError("UDP description host is not ASCII") from None


# ---------------------------------------------------------------------------- tracker

def encode_pos_quat(sensor: int, position: object, quaternion: object) -> bytes:
    """A Pos_Quat payload (the padding word repeats the sensor, as ``encode_to`` does)."""
    p = np.asarray(position, dtype=float).reshape(3)
    q = np.asarray(quaternion, dtype=float).reshape(4)
    return _POS_QUAT.pack(sensor, sensor, *p, *q)


def _report(kind: str, layout: struct.Struct, payload: bytes) -> tuple:
    """A tracker report's fields, with ``vrpn_Tracker_Remote``'s checks (exact length, a
    sensor number that is not negative)."""
    if len(payload) != layout.size:
        raise ProtocolError(f"{kind} payload is {len(payload)} bytes, expected {layout.size}")
    v = layout.unpack(payload)
    if v[0] < 0:
        raise ProtocolError(f"{kind} sensor {v[0]} is negative")
    return v


def decode_pos_quat(payload: bytes) -> PosQuat:
    v = _report("Pos_Quat", _POS_QUAT, payload)
    return PosQuat(v[0], np.array(v[2:5]), np.array(v[5:9]))


def encode_velocity(sensor: int, velocity: object, vel_quat: object, dt_s: float) -> bytes:
    v = np.asarray(velocity, dtype=float).reshape(3)
    q = np.asarray(vel_quat, dtype=float).reshape(4)
    return _VELOCITY.pack(sensor, sensor, *v, *q, float(dt_s))


def decode_velocity(payload: bytes) -> Velocity:
    v = _report("Velocity", _VELOCITY, payload)
    return Velocity(v[0], np.array(v[2:5]), np.array(v[5:9]), v[9])


# ---------------------------------------------------------------------------- UDP "call me back"

def lob_request(host: str, port: int) -> bytes:
    """The datagram asking a server to connect back to ``host``:``port`` by TCP."""
    return f"{host} {int(port)}".encode("ascii") + b"\0"


def parse_lob_request(data: bytes) -> tuple[str, int]:
    """Host and port of a lob request, checked as VRPN's server checks it (host of letters,
    digits and dots; port at least 1024)."""
    m = _LOB_RE.match(data)
    if m is None:
        raise ProtocolError(f"malformed connection request {data[:60]!r} (expected "
                            "'<host> <port>\\0')")
    port = int(m.group(2))
    if not 1024 <= port < 65536:
        raise ProtocolError(f"connection request names port {port} (must be 1024..65535)")
    return m.group(1).decode("ascii"), port


# ---------------------------------------------------------------------------- device names

@dataclass(frozen=True, slots=True)
class DeviceAddress:
    """``Tracker0@host:3883`` (UDP handshake) or ``Tracker0@tcp://host:3883`` (TCP only)."""

    name: str
    host: str
    port: int
    tcp: bool

    def __str__(self) -> str:
        return f"{self.name}@{'tcp://' if self.tcp else ''}{self.host}:{self.port}"


def parse_device(text: str) -> DeviceAddress:
    """A VRPN device name as VRPN's clients take it; ``ValueError`` names what is wrong."""
    name, at, location = text.partition("@")
    if not at or not name or not location:
        raise InvalidInputError(f"VRPN device {text!r} must be NAME@HOST[:PORT] or "
                                "NAME@tcp://HOST[:PORT]")
    try:
        check_name(name)
    except ProtocolError as exc:
        raise InvalidInputError(f"VRPN device {text!r}: {exc}") from None
    tcp = location.startswith("tcp://")
    if tcp:
        location = location[len("tcp://"):]
    elif "://" in location:
        raise InvalidInputError(f"VRPN device {text!r}: only tcp:// or no scheme (UDP handshake) "
                                "is supported")
    host, colon, port_text = location.rpartition(":")
    if not colon:
        host, port_text = location, str(DEFAULT_PORT)
    if not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise InvalidInputError(f"VRPN device {text!r}: bad host or port in {location!r}")
    return DeviceAddress(name, host, int(port_text), tcp)
