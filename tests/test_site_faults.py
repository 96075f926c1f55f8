"""Faults on a site of real hosts (network namespaces, :mod:`agent_helpers.site`), each
with its figures (printed as a ``FAULT`` line; ``pytest -s`` shows them): time to detect,
time to recover, samples lost, and whether anything came twice or out of order.

A producer ``cam`` publishes a pose at 100 Hz with sequence numbers on one host, a
consumer ``app`` on another host has a need matched to it and reports every sample
(``agent_helpers.svc --each-sample``).  Nothing is restarted by hand: each fault heals by
itself or not at all.  This kernel has no ``sch_netem``: delays and stalls come from a
userspace TCP proxy on the slow link (:mod:`agent_helpers.tcp_proxy`).  Hosts share the
machine's clock, so a host 200 ms ahead is its agent and tracker told so
(``UMA_CLOCK_SKEW_NS``, ``--skew-ns``), as ``tests/test_client_stream.py`` does on loopback.
"""

from __future__ import annotations

import json
import os
import signal
import statistics
import threading
import time

import pytest
from agent_helpers.faults import figures
from agent_helpers.harness import START_WAIT_S, Proc, freeze
from agent_helpers.site import Host, Site

CUT_S = 5.0
RECOVER_LIMIT_S = 20.0  # generous: a loaded 2-core machine; the figures say how long it took


def start_stream(s: Site, realm: str, cam_host: Host, cam_connect: str, app_host: Host,
                 app_connect: str, cam_agent: str, app_agent: str) -> tuple[Proc, Proc]:
    common = ["-m", "tests.agent_helpers.svc", "--realm", realm]
    cam = s.spawn(cam_host, [*common, "--id", "cam", "--agent", cam_agent, "--connect",
                             cam_connect, "--ability", "pose", "--rate", "100"])
    app = s.spawn(app_host, [*common, "--id", "app", "--agent", app_agent, "--connect",
                             app_connect, "--need", "head", "--each-sample"])
    app.wait_for(lambda ev: ev.get("event") == "sample", 60)
    return cam, app


def router_on(s: Site, host: Host) -> Proc:
    """``uma router`` listening on ``host``'s address; returns once it listens."""
    router = s.spawn(host, ["-m", "agent.cli", "router", "--listen", host.endpoint(),
                            "--insecure"])
    router.wait_line("listening on", START_WAIT_S)
    return router


def client_agents(s: Site, realm: str, hosts: list[tuple[Host, str]]) -> list[Proc]:
    """An agent in client mode on each host, of the router at the endpoint paired with it."""
    agents = [s.spawn(h, ["-m", "agent.cli", "agent", "--realm", realm, "--id", h.name,
                          "--mode", "client", "--connect", ep]) for h, ep in hosts]
    for a in agents:
        a.wait_line("listening on", START_WAIT_S)
    return agents


def wait_after(app: Proc, t: float, timeout: float = RECOVER_LIMIT_S) -> None:
    app.wait_for(lambda ev: ev.get("event") == "sample" and ev["_mono"] > t, timeout)


def services_on(s: Site, host: Host, realm: str, connect: str) -> tuple[int, list[str], float]:
    """``uma services`` on ``host``: exit code, agents listed, seconds it took."""
    t0 = time.monotonic()
    out = s.run(host, ["-m", "agent.cli", "services", "--realm", realm, "--connect", connect,
                       "--json", "--timeout", "2"], 60)
    took = time.monotonic() - t0
    if out.returncode != 0:
        return out.returncode, [], took
    realm_view = json.loads(out.stdout.strip().splitlines()[-1])
    return 0, [a["agent_id"] for a in realm_view["agents"]], took


def first_unmatch(app: Proc, after: float) -> float | None:
    for ev in app.events:
        if ev.get("event") == "match" and ev["_mono"] > after and not ev["keys"]:
            return ev["_mono"] - after
    return None


def test_a_link_down_for_5_s_heals_without_a_restart(site, realm: str) -> None:
    s = site(2)
    h0, h1 = s.hosts
    s.start_agents(realm)
    _, app = start_stream(s, realm, h0, h0.endpoint(), h1, h1.endpoint(), "h0", "h1")

    t_cut = time.monotonic()
    s.cut(h0)
    time.sleep(1.5)
    during: list[tuple[int, list[str], float]] = []
    asking = threading.Thread(target=lambda: during.append(
        services_on(s, h1, realm, h1.endpoint())))
    asking.start()  # a thread: the command's start-up must not lengthen the cut
    time.sleep(max(0.0, t_cut + CUT_S - time.monotonic()))
    s.heal(h0)
    t_heal = time.monotonic()
    asking.join(90)
    wait_after(app, t_heal)
    time.sleep(1.0)
    fig = figures("link down 5 s", app.events, "cam", t_cut, t_heal,
                  time.monotonic())
    fig.detect_s = first_unmatch(app, t_cut)
    code, seen, took = during[0]
    print(fig.line(), f"; uma services started during the cut: exit {code}, agents {seen}, "
          f"{took:.2f} s (the whole command)")
    assert fig.duplicates == 0 and fig.reordered == 0
    assert code == 0 and "h1" in seen, during
    code, agents, _ = services_on(s, h1, realm, h1.endpoint())
    assert code == 0 and agents == ["h0", "h1"]


# slow (CI's second step): the default run heals a site after its router's SIGKILL and a
# restart 3 s later in tests/test_site_security.py (over TLS, the agents back in the listing)
@pytest.mark.slow
def test_the_router_killed_and_restarted_after_3_s(site, realm: str) -> None:
    s = site(3)
    r, h1, h2 = s.hosts
    router_ep = r.endpoint()
    router = router_on(s, r)
    client_agents(s, realm, [(h1, router_ep), (h2, router_ep)])
    _, app = start_stream(s, realm, h1, router_ep, h2, router_ep, "h1", "h2")

    t_kill = time.monotonic()
    os.kill(router.popen.pid, signal.SIGKILL)
    router.popen.wait(10)
    time.sleep(3.0)
    router = router_on(s, r)
    t_back = time.monotonic()
    wait_after(app, t_back)
    time.sleep(1.0)
    fig = figures("router SIGKILL, back after 3 s", app.events, "cam", t_kill,
                  t_back, time.monotonic())
    fig.detect_s = first_unmatch(app, t_kill)
    print(fig.line())
    assert fig.duplicates == 0 and fig.reordered == 0


# slow (CI's second step): the default run drops a frozen producer after its lease and takes
# it back (tests/test_agent_multiprocess.py), moves a stream off a frozen agent and back
# (tests/test_reliability_stream.py) and names a frozen agent that does not answer a query
# (tests/test_registration_trust.py), each on loopback
@pytest.mark.slow
def test_a_frozen_agent_is_detected_within_its_lease_and_recovers(site, realm: str) -> None:
    s = site(2)
    h0, h1 = s.hosts
    agents = s.start_agents(realm)
    _, app = start_stream(s, realm, h0, h0.endpoint(), h1, h1.endpoint(), "h0", "h1")

    t_stop = time.monotonic()
    freeze(agents[0])
    detected = None
    for _ in range(100):  # bounded: 10 s at most
        code, seen, _ = services_on(s, h1, realm, h1.endpoint())
        if code == 0 and "h0" not in seen:
            detected = time.monotonic() - t_stop
            break
        if time.monotonic() - t_stop > CUT_S:
            break
    time.sleep(max(0.0, t_stop + CUT_S - time.monotonic()))
    os.kill(agents[0].popen.pid, signal.SIGCONT)
    t_cont = time.monotonic()
    wait_after(app, t_cont)
    time.sleep(1.0)
    fig = figures("agent SIGSTOP 5 s", app.events, "cam", t_stop, t_cont,
                  time.monotonic())
    fig.detect_s = detected
    print(fig.line())
    assert detected is not None, "the frozen agent was still listed after 5 s"
    assert fig.duplicates == 0 and fig.reordered == 0


def test_a_frozen_agent_does_not_stop_a_stream_that_does_not_cross_it(site, realm: str
                                                                       ) -> None:
    s = site(3)
    r, h1, h2 = s.hosts
    router_ep = r.endpoint()
    router_on(s, r)
    agents = client_agents(s, realm, [(h1, router_ep), (h2, router_ep)])
    # both services are clients of the router: cam's samples never cross its agent
    _, app = start_stream(s, realm, h1, router_ep, h2, router_ep, "h1", "h2")

    t_stop = time.monotonic()
    freeze(agents[0])
    time.sleep(CUT_S)
    os.kill(agents[0].popen.pid, signal.SIGCONT)
    t_cont = time.monotonic()
    wait_after(app, t_cont)
    time.sleep(1.0)
    fig = figures("producer's agent SIGSTOP 5 s, data via the router", app.events, "cam",
                  t_stop, t_cont, time.monotonic())
    fig.detect_s = first_unmatch(app, t_stop)
    print(fig.line())
    assert fig.duplicates == 0 and fig.reordered == 0
    # the stream kept flowing: its agent's absence may stop new plans, not a working stream
    # (before the realm view kept such services: the match dropped one lease after the
    # freeze, a 3.6 s gap, 352 samples lost; now at most a re-match when the agent resumes)
    assert fig.lost < 50, fig.line()


def test_a_slow_link_50_ms_delay_and_a_stall_keep_streams_and_queries(site, realm: str
                                                                       ) -> None:
    s = site(3)
    r, h1, h2 = s.hosts
    router_ep = r.endpoint()
    router_on(s, r)
    # h2 reaches the router only through a userspace proxy on its own loopback
    proxy = s.spawn(h2, ["-m", "tests.agent_helpers.tcp_proxy", "--listen", "127.0.0.1:7447",
                         "--target", f"{r.addr}:7447"])
    proxy.wait_for(lambda ev: ev.get("event") == "ready", 30)
    via_proxy = "tcp/127.0.0.1:7447"
    client_agents(s, realm, [(h1, router_ep), (h2, via_proxy)])
    _, app = start_stream(s, realm, h1, router_ep, h2, via_proxy, "h1", "h2")

    def window(seconds: float) -> tuple[float, float, float, float]:
        """(rate Hz, median latency ms, p99 latency ms, query s) over the next seconds."""
        mark, t0 = app.mark, time.monotonic()
        q0 = time.monotonic()
        query = s.run(h2, ["-m", "agent.cli", "query", "ivy/world", "alice/head", "--realm",
                           realm, "--connect", via_proxy, "--timeout", "2", "--json"], 60)
        took = time.monotonic() - q0
        assert query.returncode == 0, query.stderr
        time.sleep(max(0.0, seconds - (time.monotonic() - t0)))
        got = [ev for ev in app.events[mark:] if ev.get("event") == "sample"]
        lat = sorted((ev["recv_ns"] - ev["t_ns"]) / 1e6 for ev in got)
        return (len(got) / (time.monotonic() - t0), statistics.median(lat),
                lat[int(0.99 * (len(lat) - 1))], took)

    plain = window(3.0)
    proxy.send("delay 50")
    proxy.wait_for(lambda ev: ev.get("command") == "delay", 10)
    time.sleep(0.5)
    delayed = window(3.0)
    # a bandwidth cap of 256 kB/s each way (the stream needs ~30 kB/s with its overhead)
    proxy.send("rate 256")
    proxy.wait_for(lambda ev: ev.get("command") == "rate", 10)
    capped = window(3.0)
    proxy.send("rate 0")
    t_stall = time.monotonic()
    proxy.send("stall")
    time.sleep(0.5)  # shorter than the 1 s lease: a stall, not a lost link
    proxy.send("resume")
    t_resume = time.monotonic()
    wait_after(app, t_resume)
    time.sleep(1.0)
    fig = figures("link stalled 0.5 s (with 50 ms delay)", app.events, "cam", t_stall,
                  t_resume, time.monotonic())
    print(f"FAULT slow link: without delay {plain[0]:.0f} Hz, latency median "
          f"{plain[1]:.1f} ms p99 {plain[2]:.1f} ms, uma query {plain[3]:.2f} s (the whole "
          f"command); with 50 ms delay {delayed[0]:.0f} Hz, latency median "
          f"{delayed[1]:.1f} ms p99 {delayed[2]:.1f} ms, uma query {delayed[3]:.2f} s; "
          f"and capped at 256 kB/s {capped[0]:.0f} Hz, latency median {capped[1]:.1f} ms "
          f"p99 {capped[2]:.1f} ms, uma query {capped[3]:.2f} s")
    print(fig.line())
    assert delayed[1] >= plain[1] + 40  # the proxy really delayed what it carried
    assert delayed[0] > 0.7 * plain[0]  # the stream kept its rate
    assert capped[0] > 0.7 * plain[0]
    assert fig.lost == 0 and fig.duplicates == 0 and fig.reordered == 0


SKEW_NS = 200_000_000
POSE_NOW = """
import json, sys, time
from agent import Client
with Client(realm=sys.argv[1], connect=[sys.argv[2]], timeout=5.0) as c:
    deadline = time.monotonic() + 60
    while True:
        try:
            c.pose("ivy/world", "alice/head")
            break
        except LookupError:
            assert time.monotonic() < deadline, "no pose within 60 s"
            time.sleep(0.2)
    for _ in range(20):
        t0 = time.time_ns(); r = c.pose("ivy/world", "alice/head"); t1 = time.time_ns()
        print(json.dumps({"t0": t0, "t_ns": r.t_ns, "t1": t1, "offset": c.clock.offset(
            sys.argv[3])}), flush=True)
"""


def test_a_host_200_ms_ahead_is_taken_out_of_composed_poses(site, realm: str) -> None:
    """Host h2's clock is 200 ms ahead (its agent and its tracker's stamps): a client on h1
    gets the tracker's latest pose stamped on h1's clock, not 200 ms in its future."""
    s = site(3)
    r, h1, h2 = s.hosts
    router_ep = r.endpoint()
    router_on(s, r)
    client_agents(s, realm, [(h1, router_ep)])
    ahead = s.spawn(h2, ["-m", "agent.cli", "agent", "--realm", realm, "--id", h2.name,
                         "--mode", "client", "--connect", router_ep],
                    env={"UMA_CLOCK_SKEW_NS": str(SKEW_NS)})
    ahead.wait_line("listening on", START_WAIT_S)
    s.spawn(h2, ["-m", "tests.agent_helpers.svc", "--realm", realm, "--id", "cam", "--agent",
                 h2.name, "--connect", router_ep, "--ability", "pose", "--rate", "100",
                 "--skew-ns", str(SKEW_NS)])
    out = s.run(h1, ["-c", POSE_NOW, realm, router_ep, h2.name], 120)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [json.loads(line) for line in out.stdout.splitlines()]
    ahead_ms = [(row["t_ns"] - row["t1"]) / 1e6 for row in rows]
    behind_ms = [(row["t0"] - row["t_ns"]) / 1e6 for row in rows]
    print(f"FAULT clock skew 200 ms: offset estimate {rows[-1]['offset'] / 1e6:.1f} ms; "
          f"pose time minus the query's end: median {statistics.median(ahead_ms):.1f} ms "
          f"(uncorrected it would be about +190 ms); age at the query's start: median "
          f"{statistics.median(behind_ms):.1f} ms")
    assert abs(rows[-1]["offset"] - SKEW_NS) < 50_000_000
    # the latest sample is at most a period and a transit old, and never in the future
    assert statistics.median(ahead_ms) < 50 and max(ahead_ms) < 100, ahead_ms
