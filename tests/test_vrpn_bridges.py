"""The VRPN bridges in real processes on loopback.

* ``vrpn-out`` serving the simulator's head: the tests' own VRPN client
  (:mod:`agent_helpers.vrpn_peer`, written from VRPN's protocol documentation) receives
  exactly the poses a ``Client`` subscription gives, with the same timestamps up to the
  two clients' estimates of the agent's clock offset (so ``Client.pose(at=VRPN time)``
  would interpolate up to a few milliseconds of head motion away), by TCP and by the UDP
  handshake.
* ``vrpn-in`` connected to a ``vrpn-out`` of another realm: the pose comes round the loop
  unchanged, the ability is listed by ``uma services``; when the server is stopped
  (SIGSTOP: its connection stays open) the client says it answers no ping, drops it and is
  back once the server runs again; after the server is killed and started again the client
  is back within 1 s of its return.
* Two VRPN clients, one stalled: the other keeps its rate and the stalled one is dropped.

Malformed peers are tested without Zenoh in ``test_vrpn_links.py``.
"""

from __future__ import annotations

import bisect
import datetime
import math
import os
import signal
import socket
import threading
import time

import numpy as np
from agent_helpers.harness import Proc, agent, freeze, poll, services_json, spawn
from agent_helpers.vrpn_peer import RawClient
from conftest import endpoint, free_port

from agent import Client, Service


def _free_vrpn_port() -> int:
    """A port free for TCP and UDP alike (the VRPN server takes both)."""
    for _ in range(50):
        port = free_port()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
                return port
            except OSError:
                continue
    raise AssertionError("no port free for both TCP and UDP")


def vrpn_out(processes, realm: str, ep: str, port: int, *serve: str, extra=()) -> Proc:
    args = ["-m", "agent.cli", "service", "run", "vrpn-out", "--realm", realm,
            "--agent", "host", "--connect", ep, "--port", str(port), "--bind", "127.0.0.1"]
    for s in serve:
        args += ["--serve", s]
    return spawn(processes, [*args, *extra])


def _count(proc: Proc, text: str) -> int:
    return sum(text in line for line in list(proc.log))


def _log_time(line: str) -> float:
    """The time of a log line (logging's ``asctime``, local time, milliseconds)."""
    stamp = datetime.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f")
    return stamp.timestamp()


def test_vrpn_out_streams_the_simulators_head_by_tcp_and_udp(processes, realm) -> None:
    ep = endpoint(free_port())
    agent(processes, realm, "host", ep)
    spawn(processes, ["-m", "agent.cli", "service", "run", "sim", "--realm", realm,
                      "--agent", "host", "--connect", ep, "--mountings", "none"])
    port = _free_vrpn_port()
    out = vrpn_out(processes, realm, ep, port, "Head=ivy/world:alice/head")
    out.wait_log("tracker Head streams")
    client = Client(realm=realm, connect=[ep])
    mine: list = []
    sub = client.subscribe("ivy/world", "alice/head", mine.append)
    tcp = RawClient("127.0.0.1", port, "Head", udp=False)
    udp = RawClient("127.0.0.1", port, "Head", udp=True)
    try:
        poll(lambda: len(tcp.reports) >= 30, what="30 reports over TCP")
        # as in VRPN, reports go over TCP until the client's UDP description arrives
        poll(lambda: [r.via for r in udp.reports].count("udp") >= 30, what="30 over UDP")
        assert {r.via for r in tcp.reports} == {"tcp"}
        vias = [r.via for r in udp.reports]
        assert set(vias[vias.index("udp"):]) == {"udp"}, vias
        for reports in (tcp.reports, [r for r in udp.reports if r.via == "udp"]):
            for r in reports[5:25:4]:
                same = [m for m in list(mine) if np.allclose(m.position, r.position, 0, 1e-9)
                        and np.allclose(m.quaternion, r.quaternion, 0, 1e-9)]
                assert len(same) == 1, f"{r} is not exactly one of the client's poses"
                # its time on two clients' clocks: each estimates the agent's clock offset
                # (well under a millisecond apart on one idle host, 5 ms and more on a
                # loaded 2-core one), and VRPN keeps microseconds; the pose itself has
                # already named the sample, so the times need only agree within a period
                assert abs(same[0].t_ns - r.t_ns) < 10_000_000
                assert r.sensor == 0
    finally:
        tcp.close()
        udp.close()
        sub.close()
        client.close()


class LoopSource:
    """Publishes a known pose at whole microseconds, so VRPN carries its time exactly."""

    def __init__(self, realm: str, ep: str) -> None:
        self.svc = Service("wand", realm=realm, agent="host", connect=[ep])
        self.handle = self.svc.ability("pose", type="pose6d", edge=("lab/world", "lab/wand"),
                                       frequency_hz=100)
        self.stop = threading.Event()
        self.published: list[int] = []
        self.thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def pose(t_ns: int) -> tuple[list[float], list[float]]:
        s = t_ns * 1e-9 % 1000
        half = 0.5 * math.sin(s)
        return ([math.cos(s), 0.5 * math.sin(2 * s), 1.5 + 1e-3 * s],
                [0.0, math.sin(half), 0.0, math.cos(half)])

    def _run(self) -> None:
        while not self.stop.wait(0.01):
            t = time.time_ns() // 1000 * 1000
            self.handle.publish(t, *self.pose(t))
            self.published.append(t)

    def check_published(self, r) -> None:
        """AssertionError unless pose ``r`` is one published (to 1e-9) within 50 ms of its
        time: its time differs only by the clients' clock offset estimates (the loop passes
        two agents; each estimate errs by up to half the round trip it was measured over,
        tens of milliseconds on a loaded 2-core host) and VRPN's microseconds.  The pose
        itself names the sample: no other time within the window has it."""
        published = list(self.published)
        lo = bisect.bisect_left(published, r.t_ns - 50_000_000)
        hi = bisect.bisect_right(published, r.t_ns + 50_000_000)
        for t in published[lo:hi]:
            p, q = self.pose(t)
            if np.allclose(p, r.position, 0, 1e-9) and np.allclose(q, r.quaternion, 0, 1e-9):
                return
        raise AssertionError(f"{r} was not published within 50 ms of its time")

    def __enter__(self) -> LoopSource:
        self.svc.start()
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(2)
        self.svc.close()


def test_vrpn_in_from_vrpn_out_round_trip_and_reconnect(processes, realm) -> None:
    realm_b = realm + "b"
    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    agent(processes, realm, "host", ep_a)
    agent(processes, realm_b, "host", ep_b)
    port = _free_vrpn_port()
    serve = "Wand=lab/world:lab/wand@hops"
    with LoopSource(realm, ep_a) as source:
        out = vrpn_out(processes, realm, ep_a, port, serve)
        vin = spawn(processes, ["-m", "agent.cli", "service", "run", "vrpn-in",
                                "--realm", realm_b, "--agent", "host", "--connect", ep_b,
                                "--tracker", f"Wand@127.0.0.1:{port}",
                                "--edge", "site/world:site/wand", "--pos-std-m", "0.001"])
        vin.wait_log("connected (UDP handshake)")
        with Client(realm=realm_b, connect=[ep_b]) as client:
            got: list = []
            sub = poll(lambda: client.subscribe("site/world", "site/wand", got.append),
                       what="a route to site/wand in realm B")

            checked = [0]

            def round_trip(after: int = 0) -> int:
                """Every pose realm B received is one realm A published, unchanged."""
                now = list(got)
                for r in now[checked[0]:]:
                    source.check_published(r)
                checked[0] = len(now)
                assert len(now) > after + 20
                return len(now)
            seen = poll(round_trip, what="the pose round the loop")
            listed = services_json(realm_b, ep_b)
            ability = [a for ag in listed["agents"] for s in ag["services"]
                       if s["service_id"] == "vrpn-in" for a in s["abilities"]]
            assert [(a["name"], a["edge"]) for a in ability] == [
                ("sensor0", ["site/world", "site/wand"])]

            freeze(out)  # hung: the connection stays open, nothing more comes
            try:
                vin.wait_log("no pong within 3 s of our ping")
            finally:
                os.kill(out.popen.pid, signal.SIGCONT)
            poll(lambda: _count(vin, "connected (UDP handshake)") == 2, what="rejoined")
            seen = poll(lambda: round_trip(seen), what="poses after SIGCONT")

            out.popen.kill()
            out.popen.wait(10)
            time.sleep(1.0)  # the client retries meanwhile
            assert _count(vin, "connected (UDP handshake)") == 2
            out = vrpn_out(processes, realm, ep_a, port, serve)
            back = out.wait_log("VRPN server on")
            poll(lambda: _count(vin, "connected (UDP handshake)") == 3, what="reconnected")
            again = [line for line in list(vin.log) if "connected (UDP handshake)" in line][2]
            assert 0 <= _log_time(again) - _log_time(back) < 1.0, (back, again)
            poll(lambda: round_trip(seen), what="poses after the restart")
            sub.close()


def test_a_stalled_client_is_dropped_and_the_other_keeps_its_rate(processes, realm) -> None:
    ep = endpoint(free_port())
    agent(processes, realm, "host", ep)
    spawn(processes, ["-m", "agent.cli", "service", "run", "sim", "--realm", realm,
                      "--agent", "host", "--connect", ep, "--mountings", "none",
                      "--rate-hz", "300"])
    port = _free_vrpn_port()
    out = vrpn_out(processes, realm, ep, port, "Head=ivy/world:alice/head",
                   extra=["--max-buffer-kb", "8"])
    out.wait_log("tracker Head streams")
    client = Client(realm=realm, connect=[ep])
    mine: list = []
    sub = client.subscribe("ivy/world", "alice/head", mine.append)
    stalled = RawClient("127.0.0.1", port, "Head", udp=False, stalled=True)
    good = RawClient("127.0.0.1", port, "Head", udp=False)
    try:
        poll(lambda: len(good.reports) > 0, what="the first report")
        t0 = good.reports[-1].t_ns
        out.wait_log("stopped reading")
        time.sleep(1.0)
        # the reading client got (nearly) every pose while the other was stuck and after it
        # was dropped: as many as the test's own subscription over the same samples' times,
        # whatever the sim's real rate (counted once the reader has read up to the cut: on a
        # loaded host its thread lags the subscription by a few hundred samples)
        cut = mine[-1].t_ns - 50_000_000
        poll(lambda: good.reports[-1].t_ns >= cut, what="the reader up to the cut")
        got = sum(t0 < r.t_ns <= cut for r in list(good.reports))
        pushed = sum(t0 < m.t_ns <= cut for m in list(mine))
        assert got >= 0.8 * pushed > 0, (got, pushed)
        assert _count(out, "gone (1 left)") == 1
    finally:
        stalled.close()
        good.close()
        sub.close()
        client.close()
