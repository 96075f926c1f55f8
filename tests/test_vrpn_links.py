"""The VRPN server and client on loopback without Zenoh: both connection kinds, reconnects,
pings, and peers that misbehave (garbage, a wrong version, an oversized length, a bad
description, silence instead of a cookie, leaving mid-message, bad call-back requests),
which are logged and dropped while the others are served.  Servers that go silent with the
connection open (a hung fake, a real uma server in a process stopped with SIGSTOP) are
pinged, dropped and rejoined; one that answers the pings but has nothing to report is kept.
The raw peers here write bytes by hand, as VRPN's documentation lays them out."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import socket
import struct
import time

import numpy as np
import pytest
from agent_helpers.harness import freeze, spawn
from conftest import free_port

from agent.cli.main import main as uma
from services.vrpn import link
from services.vrpn import protocol as vp
from services.vrpn.bridge_in import Publisher, sensor_frames
from services.vrpn.client import TrackerClient
from services.vrpn.server import TrackerServer

COOKIE = b"vrpn: ver. 07.38  0".ljust(24, b"\0")
LIMIT_S = 10.0  # every wait below is bounded by this (a loaded machine)


async def until(cond, what: str, limit_s: float = LIMIT_S) -> None:
    deadline = time.monotonic() + limit_s
    for _ in range(100_000):
        if cond():
            return
        if time.monotonic() > deadline:
            break
        await asyncio.sleep(0.01)
    raise AssertionError(f"{what} not within {limit_s} s")


async def streaming(server: TrackerServer, stop: asyncio.Event) -> None:
    """Reports of tracker 0 at ~200 Hz: pose k is (k, 2k, 3k)."""
    k = 0
    while not stop.is_set():
        k += 1
        server.report(0, time.time_ns(), [k, 2 * k, 3 * k], [0, 0, 0, 1])
        await asyncio.sleep(0.005)


async def _serve_and_receive(tcp: bool, restart: bool) -> TrackerClient:
    port = free_port()
    server = TrackerServer(["Head", "Other"], "127.0.0.1", port)
    await server.start()
    got: list = []
    client = TrackerClient(vp.DeviceAddress("Head", "127.0.0.1", port, tcp),
                           lambda *r: got.append(r))
    stop, stop_stream = asyncio.Event(), asyncio.Event()
    tasks = [asyncio.ensure_future(client.run(stop)),
             asyncio.ensure_future(streaming(server, stop_stream))]
    await until(lambda: len(got) > 20, "reports")
    sensor, t_ns, p, _ = got[-1]
    assert sensor == 0 and t_ns % 1000 == 0
    np.testing.assert_array_equal(p, [p[0], 2 * p[0], 3 * p[0]])
    if not tcp:  # a bad datagram at our UDP port is logged and dropped; reports go on
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
            u.sendto(b"\0\0\0\x10garbage", client._udp.get_extra_info("sockname"))
        n = len(got)
        await until(lambda: len(got) > n + 5, "reports after a bad datagram")
    if restart:
        stop_stream.set()
        await tasks[1]
        await server.close()
        await until(lambda: not client.connected.is_set(), "the client noticing")
        server = TrackerServer(["Head"], "127.0.0.1", port)
        await server.start()
        back = time.monotonic()
        stop_stream.clear()
        tasks[1] = asyncio.ensure_future(streaming(server, stop_stream))
        await until(lambda: client.connections == 2, "a reconnection")
        assert time.monotonic() - back < 1.0
        n = len(got)
        await until(lambda: len(got) > n + 20, "reports after the reconnection")
    stop.set()
    stop_stream.set()
    await asyncio.gather(*tasks)
    await server.close()
    return client


@pytest.mark.parametrize("tcp", [True, False], ids=["tcp", "udp-handshake"])
def test_client_receives_and_reconnects(tcp: bool, caplog) -> None:
    client = asyncio.run(_serve_and_receive(tcp, restart=True))
    assert ("dropped: datagram of 11 bytes ends inside a message" in caplog.text) is not tcp
    assert client.connections == 2 and client.silent_drops == 0
    if tcp:
        assert client.udp_reports == 0
    else:
        assert client.udp_reports > 0


def _raw(port: int, data: bytes) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port))
    s.sendall(data)
    return s


def _closed(s: socket.socket) -> bool:
    """True once the server closed ``s`` (reading what it sent before)."""
    s.settimeout(0.05)
    try:
        while data := s.recv(65536):
            del data
    except TimeoutError:
        return False
    except OSError:
        return True
    return True


BAD_PEERS = {
    "garbage": (b"GET / HTTP/1.1\r\nHost: x\r\n\r\n", "not a VRPN 07.xx peer"),
    "old version": (b"vrpn: ver. 06.00  0".ljust(24, b"\0"), "not a VRPN 07.xx peer"),
    "oversized": (COOKIE + struct.pack(">IIIiiI", 10**6, 0, 0, 0, 0, 0),
                  "exceeds VRPN's limit"),
    "bad name": (COOKIE + struct.pack(">IIIiiI", 24 + 8, 0, 0, 3, -1, 0)
                 + struct.pack(">i", 90) + b"abc\0", "description says its name"),
    "silent": (b"", "sent no VRPN cookie within"),
    "mid-message": (COOKIE + struct.pack(">IIIiiI", 24 + 64, 0, 0, 0, 0, 0) + b"\0" * 10,
                    "left mid-message"),
}


async def _bad_peers(caplog) -> None:
    port = free_port()
    server = TrackerServer(["Head"], "127.0.0.1", port)
    await server.start()
    got: list = []
    good = TrackerClient(vp.DeviceAddress("Head", "127.0.0.1", port, True),
                         lambda *r: got.append(r))
    stop = asyncio.Event()
    tasks = [asyncio.ensure_future(good.run(stop)),
             asyncio.ensure_future(streaming(server, stop))]
    await until(lambda: len(got) > 5, "first reports")
    loop = asyncio.get_running_loop()
    for name, (data, reason) in BAD_PEERS.items():
        s = await loop.run_in_executor(None, _raw, port, data)
        if name == "mid-message":
            s.close()
        await until(lambda reason=reason: reason in caplog.text, f"the log line for {name}")
        if name != "mid-message":
            await until(lambda s=s: _closed(s), f"{name} closed")
            s.close()
        n = len(got)
        await until(lambda n=n: len(got) > n + 5, f"the good client served after {name}")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
        u.sendto(b"127.0.0.1 80\0", ("127.0.0.1", port))
        u.sendto(b"\x00\x01garbage", ("127.0.0.1", port))
    await until(lambda: "must be 1024..65535" in caplog.text and "malformed connection "
                "request" in caplog.text, "lob refusals logged")
    assert len(server.links) == 1
    stop.set()
    await asyncio.gather(*tasks)
    await server.close()


def test_bad_peers_are_logged_and_dropped_and_the_others_served(caplog, monkeypatch) -> None:
    monkeypatch.setattr(link, "COOKIE_TIMEOUT_S", 0.3)
    caplog.set_level(logging.INFO, "uma.vrpn")
    asyncio.run(_bad_peers(caplog))


async def _repeated_bad_peer(caplog) -> TrackerServer:
    port = free_port()
    server = TrackerServer(["Head"], "127.0.0.1", port)
    await server.start()
    loop = asyncio.get_running_loop()
    for _ in range(5):
        s = await loop.run_in_executor(None, _raw, port, BAD_PEERS["garbage"][0])
        await until(lambda s=s: _closed(s), "the bad peer closed")
        s.close()
    await until(lambda: server.bad.seen == 5, "five refusals counted")
    await server.close()
    return server


def test_a_peer_that_misbehaves_in_a_loop_gets_one_log_line_not_one_per_connection(
        caplog) -> None:
    caplog.set_level(logging.INFO, "uma.vrpn")
    server = asyncio.run(_repeated_bad_peer(caplog))
    lines = [r for r in caplog.records if "not a VRPN 07.xx peer" in r.getMessage()]
    assert len(lines) == 1 and "VRPN host 127.0.0.1: peer 127.0.0.1:" in lines[0].getMessage()
    assert server.bad.seen == 5 and server.bad.logged == 1


async def _ping() -> bytes:
    port = free_port()
    server = TrackerServer(["Head"], "127.0.0.1", port)
    await server.start()
    loop = asyncio.get_running_loop()
    hello = (COOKIE + vp.sender_description(7, "Head", 0) + vp.type_description(3, vp.PING, 0)
             + vp.encode_message(3, 7, time.time_ns()))

    def talk() -> bytes:
        with _raw(port, hello) as s:
            s.settimeout(LIMIT_S)
            data = b""
            deadline = time.monotonic() + LIMIT_S
            while not _pongs(data) and time.monotonic() < deadline:
                data += s.recv(65536)
            return data
    data = await loop.run_in_executor(None, talk)
    await server.close()
    return data


def _pongs(data: bytes) -> list[vp.Message]:
    """The pong messages of what the server sent (its cookie first)."""
    msgs = vp.StreamDecoder().feed(data[24:])
    types = {m.sender: vp.decode_name(m.payload) for m in msgs if m.type == vp.TYPE_DESCRIPTION}
    return [m for m in msgs if types.get(m.type) == vp.PONG]


def test_the_server_answers_pings() -> None:
    pong = _pongs(asyncio.run(_ping()))
    assert len(pong) == 1 and pong[0].sender == 0  # from tracker "Head", our sender 0


# ---------------------------------------------------------------------------- silent servers

def _hello(t_ns: int) -> bytes:
    """What a VRPN server says first: its cookie, tracker Head, the Pos_Quat type, a report."""
    return (COOKIE + vp.sender_description(0, "Head", t_ns)
            + vp.type_description(0, vp.POS_QUAT, t_ns)
            + vp.encode_message(0, 0, t_ns, vp.encode_pos_quat(0, [1, 2, 3], [0, 0, 0, 1])))


class _Hung(asyncio.Protocol):
    """A server that says hello, then neither reads nor writes, its socket left open: a
    hung process, or a network path that died without a FIN or RST."""

    def __init__(self, hung: list[tuple[float, asyncio.Transport]]) -> None:
        self.hung = hung

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        transport.write(_hello(time.time_ns()))
        transport.pause_reading()
        self.hung.append((time.monotonic(), transport))


async def _hung_server(caplog) -> None:
    port = free_port()
    hung: list[tuple[float, asyncio.Transport]] = []
    server = await asyncio.get_running_loop().create_server(lambda: _Hung(hung), "127.0.0.1",
                                                            port)
    got: list = []
    client = TrackerClient(vp.DeviceAddress("Head", "127.0.0.1", port, True),
                           lambda *r: got.append(r), ping_s=0.2, pong_timeout_s=0.5)
    stop = asyncio.Event()
    task = asyncio.ensure_future(client.run(stop))
    try:
        await until(lambda: client.silent_drops == 1, "the first silent drop")
        dropped = time.monotonic()
        assert dropped - hung[0][0] >= 0.2 + 0.5  # pinged after 0.2 s, waited 0.5 s more
        assert client.pings == 1 and len(got) == 1
        assert f"VRPN server Head@tcp://127.0.0.1:{port} silent for " in caplog.text
        assert " s: no pong within 0.5 s of our ping" in caplog.text
        await until(lambda: client.connections == 2 and len(got) == 2,
                    "a reconnection to the same server")
        await until(lambda: client.silent_drops == 2, "the second silent drop")
    finally:
        stop.set()
        await task
        for _, t in hung:
            t.abort()
        server.close()
        await server.wait_closed()


def test_a_hung_server_is_pinged_dropped_and_reconnected(caplog) -> None:
    asyncio.run(_hung_server(caplog))


async def _quiet_server(tcp: bool) -> None:
    port = free_port()
    server = TrackerServer(["Head"], "127.0.0.1", port)
    await server.start()
    client = TrackerClient(vp.DeviceAddress("Head", "127.0.0.1", port, tcp), lambda *r: None,
                           ping_s=0.1, pong_timeout_s=2.0)
    stop = asyncio.Event()
    task = asyncio.ensure_future(client.run(stop))
    # the next ping goes 0.1 s after a pong; without the pongs there would be one ping,
    # then a drop 2 s later (a loaded machine may hold a pong up for a while)
    await until(lambda: client.pings >= 10, "ten pings")
    assert client.pongs >= 9 and client.silent_drops == 0 and client.connections == 1
    assert client.connected.is_set()
    stop.set()
    await task
    await server.close()


@pytest.mark.parametrize("tcp", [True, False], ids=["tcp", "udp-handshake"])
def test_a_server_that_answers_pings_but_sends_no_reports_is_kept(tcp: bool) -> None:
    asyncio.run(_quiet_server(tcp))


#: a real uma VRPN server in a process of its own, streaming Head at ~100 Hz (bounded)
SERVER = """
import asyncio, sys, time
from services.vrpn.server import TrackerServer

async def main():
    server = TrackerServer(["Head"], "127.0.0.1", int(sys.argv[1]))
    await server.start()
    print("serving", flush=True)
    for k in range(12_000):
        server.report(0, time.time_ns(), [k, 0, 0], [0, 0, 0, 1])
        await asyncio.sleep(0.01)

asyncio.run(main())
"""


async def _stopped_server(processes, tcp: bool, caplog) -> None:
    port = free_port()
    proc = spawn(processes, ["-c", SERVER, str(port)])
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, proc.wait_line, "serving")
    got: list = []
    client = TrackerClient(vp.DeviceAddress("Head", "127.0.0.1", port, tcp),
                           lambda *r: got.append(r))  # the default timings
    stop = asyncio.Event()
    task = asyncio.ensure_future(client.run(stop))
    try:
        await until(lambda: len(got) > 20, "reports")
        await loop.run_in_executor(None, freeze, proc)
        await until(lambda: client.silent_drops == 1, "the stopped server noticed", 30.0)
        assert "no pong within 3 s of our ping" in caplog.text
        assert not client.connected.is_set() and client.connections == 1
        n = len(got)
    finally:
        os.kill(proc.popen.pid, signal.SIGCONT)
    await until(lambda: client.connections == 2, "the reconnection after SIGCONT", 30.0)
    await until(lambda: len(got) > n + 20, "reports again")
    stop.set()
    await task
    assert client.silent_drops == 1


@pytest.mark.parametrize("tcp", [True, False], ids=["tcp", "udp-handshake"])
def test_a_stopped_uma_server_is_noticed_and_rejoined_after_sigcont(processes, tcp,
                                                                     caplog) -> None:
    asyncio.run(_stopped_server(processes, tcp, caplog))


class _Handle:
    def __init__(self) -> None:
        self.samples: list = []

    def publish(self, t, p, q) -> None:
        self.samples.append((t, p, q))


def test_vrpn_in_publisher_maps_sensors_and_says_what_it_ignores(caplog) -> None:
    h0, h2 = _Handle(), _Handle()
    pub = Publisher({0: h0, 2: h2}, 5_000, vp.parse_device("T@h"))
    now = time.time_ns() // 1000 * 1000
    for sensor in (0, 1, 2, 1):
        pub(sensor, now, [1, 2, 3], [0, 0, 0, 1])
    assert [s[0] for s in h0.samples] == [now + 5_000] and len(h2.samples) == 1
    assert caplog.text.count("sensor 1 of T@h:3883 reports but has no --sensor") == 1
    pub(0, now - 10**10, [1, 2, 3], [0, 0, 0, 1])
    assert "10.0 s behind our clock: set --clock-offset-s" in caplog.text


def test_vrpn_in_drops_a_report_uma_refuses_with_a_reason(caplog) -> None:
    from schemas.codec import encode_pose

    class Strict:  # checks a pose as AbilityHandle.publish does: with the wire codec
        def publish(self, t, p, q) -> None:
            encode_pose(t, p, q)
    pub = Publisher({0: Strict()}, 0, vp.parse_device("T@h"))
    pub(0, time.time_ns(), [1, 2, 3], [0, 0, 0, 0])  # a lost body, as some servers send it
    assert pub.published == 0
    assert "sensor 0 of T@h:3883: report dropped: quaternion: norm 0 is not 1" in caplog.text


def test_vrpn_in_sensor_frames() -> None:
    args = argparse.Namespace(edge=("w/world", "w/a"), sensor=[(1, "w/b"), (3, "w/c")])
    assert sensor_frames(args) == {0: "w/a", 1: "w/b", 3: "w/c"}
    for bad, why in (([(0, "w/b")], "sensor 0 is already w/a"),
                     ([(1, "w/a")], "frame w/a is already used")):
        with pytest.raises(ValueError, match=why):
            sensor_frames(argparse.Namespace(edge=("w/world", "w/a"), sensor=bad))


@pytest.mark.parametrize(("argv", "why"), [
    (["vrpn-in", "--tracker", "Tracker0", "--edge", "a/w:a/b"], "NAME@HOST"),
    (["vrpn-in", "--tracker", "T@h", "--edge", "a/w"], "WORLD:FRAME"),
    (["vrpn-in", "--tracker", "T@h", "--edge", "a/w:a/b", "--sensor", "x=a/c"], "N=FRAME"),
    (["vrpn-in", "--tracker", "T@h", "--edge", "a/w:a/b", "--ping-s", "0"],
     "'0' is not a positive number of seconds"),
    (["vrpn-in", "--tracker", "T@h", "--edge", "a/w:a/b", "--pong-timeout-s", "nan"],
     "'nan' is not a positive number of seconds"),
    (["vrpn-out", "--serve", "Head"], "NAME=SOURCE:TARGET"),
    (["vrpn-out"], "--serve"),
])
def test_bad_command_lines_say_what_is_wrong(argv, why, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        uma(["service", "run", *argv])
    assert exc.value.code == 2
    assert why in capsys.readouterr().err
