"""The VRPN encoder and decoder against bytes VRPN itself wrote.

Every hex string below was captured on loopback from VRPN 07.38 (the vrpn/vrpn repository,
built from its own sources): a ``vrpn_Tracker_Server`` named ``Tracker0`` with two sensors
reporting ``report_pose`` and ``report_pose_velocity``, and a ``vrpn_Tracker_Remote``
client.  Their layout is the one ``Format_Of_Protocol.txt`` documents; our encoder must
reproduce them byte for byte and our decoder must read them.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.vrpn import protocol as vp

# the server's and the client's cookie (write_vrpn_cookie, log mode 0)
COOKIE = b"vrpn: ver. 07.38  0\x00\x00\x00\x00\x00"
# sender description: id 1 is "Tracker0" (sequence number 1)
SENDER_TRACKER0 = ("000000256b0714d8000efcfe00000001ffffffff00000001"
                   "00000009547261636b65723000000000")
# type description: id 4 is "vrpn_Tracker Pos_Quat" (sequence number 7), zero padding
TYPE_POS_QUAT = ("000000326b0714d8000efcff00000004fffffffe00000007"
                 "000000167672706e5f547261636b657220506f735f5175617400000000000000")
# the same description from the client: VRPN leaves stale bytes in the padding
TYPE_POS_QUAT_DIRTY_PADDING = ("000000326b0714e4000dc92c00000004fffffffe00000007"
                               "000000167672706e5f547261636b657220506f735f517561740000416b0714e4")
# Pos_Quat, sender 1, type 4, sensor 0: (0.25, -1.5, 2.033), quat (0, 0, sin 22.5°, cos 22.5°)
POS_QUAT_S0 = ("000000586b0714d8000f09970000000100000004000000140000000000000000"
               "3fd0000000000000bff800000000000040004395810624dd"
               "000000000000000000000000000000003fd87de2a6aea9633fed906bcf328d46")
# Pos_Quat of sensor 1: the padding word repeats the sensor (encode_to)
POS_QUAT_S1 = ("000000586b0714d8000f09970000000100000004000000150000000100000001"
               "3ff000000000000040000000000000004008000000000000"
               "3fe00000000000003fe00000000000003fe00000000000003fe0000000000000")
# Velocity, type 5: vel (0.5, 0, -0.25), vel_quat (0, 0, sin 0.01, cos 0.01), dt 0.02
VELOCITY_S0 = ("000000606b0714d8000f09970000000100000005000000160000000000000000"
               "3fe00000000000000000000000000000bfd0000000000000"
               "000000000000000000000000000000003f847acae915e8073fefff9724ad97aa"
               "3f947ae147ae147b")
# the server's UDP description: "send to 127.0.0.1 port 57526"
UDP_DESCRIPTION = ("000000226b0714e00009fcdb0000e0b6fffffffd00000000"
                   "3132372e302e302e3100000000000000")
# the client's lob datagram: "call me back at 127.0.0.1 port 54127"
LOB = bytes.fromhex("3132372e302e302e3120353431323700")
# the client's ping (sender 1, type 16, no payload)
PING = "000000186b0714e4000dc94f000000010000001000000015"
T_NS = 1795626200 * 10**9 + 985495 * 1000  # the reports' timeval


def _without_seq(hexed: str) -> bytes:
    """A captured message without its sequence number (header word 6, which VRPN counts
    per connection and never reads)."""
    raw = bytes.fromhex(hexed)
    return raw[:20] + raw[24:]


def test_cookie_is_vrpns_and_checks_versions() -> None:
    assert vp.cookie() == COOKIE
    assert vp.check_cookie(COOKIE) is None
    assert "minor version" in vp.check_cookie(b"vrpn: ver. 07.35  0".ljust(24, b"\0"))
    with pytest.raises(vp.ProtocolError, match="not a VRPN 07"):
        vp.check_cookie(b"vrpn: ver. 06.00  0".ljust(24, b"\0"))
    with pytest.raises(vp.ProtocolError, match="not a VRPN 07"):
        vp.check_cookie(b"GET / HTTP/1.1\r\nHost: x\r\n"[:24])
    with pytest.raises(vp.ProtocolError, match="log mode"):
        vp.check_cookie(b"vrpn: ver. 07.38  7".ljust(24, b"\0"))
    with pytest.raises(vp.ProtocolError, match="24 bytes"):
        vp.check_cookie(COOKIE[:20])


def test_sender_and_type_descriptions_byte_for_byte() -> None:
    (msg,) = vp.StreamDecoder().feed(bytes.fromhex(SENDER_TRACKER0))
    assert (msg.sender, msg.type, vp.decode_name(msg.payload)) == (1, -1, "Tracker0")
    sec, usec = vp.ns_to_timeval(msg.t_ns)
    assert (sec, usec) == (0x6B0714D8, 0x000EFCFE)
    built = vp.sender_description(1, "Tracker0", msg.t_ns)
    assert built[:20] + built[24:] == _without_seq(SENDER_TRACKER0)

    (t,) = vp.StreamDecoder().feed(bytes.fromhex(TYPE_POS_QUAT))
    assert (t.sender, t.type, vp.decode_name(t.payload)) == (4, -2, vp.POS_QUAT)
    built = vp.type_description(4, vp.POS_QUAT, t.t_ns)
    assert built[:20] + built[24:] == _without_seq(TYPE_POS_QUAT)
    (dirty,) = vp.StreamDecoder().feed(bytes.fromhex(TYPE_POS_QUAT_DIRTY_PADDING))
    assert vp.decode_name(dirty.payload) == vp.POS_QUAT


def test_pos_quat_byte_for_byte() -> None:
    msgs = vp.StreamDecoder().feed(bytes.fromhex(POS_QUAT_S0 + POS_QUAT_S1))
    assert [(m.sender, m.type, m.t_ns) for m in msgs] == [(1, 4, T_NS), (1, 4, T_NS)]
    r0, r1 = (vp.decode_pos_quat(m.payload) for m in msgs)
    assert r0.sensor == 0 and r1.sensor == 1
    np.testing.assert_array_equal(r0.position, [0.25, -1.5, 2.033])
    np.testing.assert_array_equal(r0.quaternion, [0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)])
    np.testing.assert_array_equal(r1.quaternion, [0.5, 0.5, 0.5, 0.5])
    for hexed, r, seq in ((POS_QUAT_S0, r0, 0x14), (POS_QUAT_S1, r1, 0x15)):
        payload = vp.encode_pos_quat(r.sensor, r.position, r.quaternion)
        assert vp.encode_message(4, 1, T_NS, payload, seq=seq).hex() == hexed


def test_velocity_byte_for_byte() -> None:
    (m,) = vp.StreamDecoder().feed(bytes.fromhex(VELOCITY_S0))
    v = vp.decode_velocity(m.payload)
    assert (m.type, v.sensor, v.dt_s) == (5, 0, 0.02)
    np.testing.assert_array_equal(v.velocity, [0.5, 0.0, -0.25])
    np.testing.assert_allclose(v.vel_quat, [0, 0, np.sin(0.01), np.cos(0.01)], rtol=1e-15)
    payload = vp.encode_velocity(0, v.velocity, v.vel_quat, v.dt_s)
    assert vp.encode_message(5, 1, T_NS, payload, seq=0x16).hex() == VELOCITY_S0


def test_udp_description_and_lob_byte_for_byte() -> None:
    (m,) = vp.StreamDecoder().feed(bytes.fromhex(UDP_DESCRIPTION))
    assert vp.decode_udp_description(m) == ("127.0.0.1", 57526)
    built = vp.udp_description("127.0.0.1", 57526, m.t_ns)
    assert built[:20] + built[24:] == _without_seq(UDP_DESCRIPTION)
    assert vp.parse_lob_request(LOB) == ("127.0.0.1", 54127)
    assert vp.lob_request("127.0.0.1", 54127) == LOB


def test_a_ping_has_no_payload() -> None:
    (m,) = vp.StreamDecoder().feed(bytes.fromhex(PING))
    assert (m.sender, m.type, m.payload) == (1, 16, b"")
    assert vp.encode_message(16, 1, m.t_ns, seq=0x15).hex() == PING


def test_a_datagram_holds_several_messages() -> None:
    data = bytes.fromhex(POS_QUAT_S0 + POS_QUAT_S1 + VELOCITY_S0)
    assert [m.type for m in vp.decode_datagram(data)] == [4, 4, 5]
    with pytest.raises(vp.ProtocolError, match="ends inside a message starting at byte 88"):
        vp.decode_datagram(data[:100])


@given(st.lists(st.integers(1, 97), min_size=1, max_size=60))
def test_stream_decoder_takes_any_split(cuts: list[int]) -> None:
    stream = bytes.fromhex(SENDER_TRACKER0 + TYPE_POS_QUAT + POS_QUAT_S0 + PING + VELOCITY_S0)
    whole = vp.StreamDecoder().feed(stream)
    dec, got, at = vp.StreamDecoder(), [], 0
    for n in cuts:
        got += dec.feed(stream[at: at + n])
        at += n
    got += dec.feed(stream[at:])
    assert got == whole and len(whole) == 5 and dec.pending == 0


def test_malformed_messages_say_what_is_wrong() -> None:
    short = struct.pack(">IIIiiI", 20, 0, 0, 0, 4, 0)
    with pytest.raises(vp.ProtocolError, match="shorter than the 24-byte header"):
        vp.StreamDecoder().feed(short)
    huge = struct.pack(">IIIiiI", 24 + vp.MAX_PAYLOAD + 1, 0, 0, 0, 4, 0)
    with pytest.raises(vp.ProtocolError, match="exceeds VRPN's limit"):
        vp.StreamDecoder().feed(huge)
    dec = vp.StreamDecoder()
    assert dec.feed(bytes.fromhex(POS_QUAT_S0)[:50]) == [] and dec.pending == 50
    with pytest.raises(vp.ProtocolError, match="Pos_Quat payload is 56 bytes"):
        vp.decode_pos_quat(b"\0" * 56)
    with pytest.raises(vp.ProtocolError, match="Velocity payload"):
        vp.decode_velocity(b"\0" * 64)
    with pytest.raises(vp.ProtocolError, match="negative"):
        vp.decode_pos_quat(struct.pack(">ii7d", -1, 0, *[0.0] * 7))
    with pytest.raises(vp.ProtocolError, match="payload holds"):
        vp.decode_name(struct.pack(">i", 40) + b"abc\0")
    with pytest.raises(vp.ProtocolError, match=r"5\.\.100"):
        vp.decode_name(b"\0" * 101)
    with pytest.raises(vp.ProtocolError, match="UDP description"):
        vp.decode_udp_description(vp.Message(0, -3, 0, b"\0"))


@pytest.mark.parametrize(("data", "why"), [
    (b"127.0.0.1 80\0", "port 80"),
    (b"127.0.0.1;rm 5000\0", "malformed"),
    (b"\xff\xfe", "malformed"),
    (b"127.0.0.1\0", "malformed"),
])
def test_bad_lob_requests_are_refused(data: bytes, why: str) -> None:
    with pytest.raises(vp.ProtocolError, match=why):
        vp.parse_lob_request(data)


def test_time_is_a_timeval() -> None:
    assert vp.ns_to_timeval(1_700_000_000_123_456_789) == (1_700_000_000, 123_456)
    assert vp.timeval_to_ns(1_700_000_000, 123_456) == 1_700_000_000_123_456_000
    with pytest.raises(vp.ProtocolError, match="before 1970"):
        vp.ns_to_timeval(-1)
    with pytest.raises(vp.ProtocolError, match="32-bit seconds"):
        vp.ns_to_timeval(2**32 * 10**9)


def test_device_names() -> None:
    assert vp.parse_device("Tracker0@localhost") == vp.DeviceAddress(
        "Tracker0", "localhost", 3883, False)
    assert vp.parse_device("DTrack@tcp://10.0.0.2:3884") == vp.DeviceAddress(
        "DTrack", "10.0.0.2", 3884, True)
    assert str(vp.parse_device("T@h:5")) == "T@h:5"
    for bad in ("Tracker0", "@host", "T@", "T@udp://h", "T@h:0", "T@h:x", "T@:5", "Tête@h",
                "x" * 96 + "@h"):
        with pytest.raises(ValueError, match="VRPN device"):
            vp.parse_device(bad)
