"""The parts of ``uma view`` that need no browser: the event log's diff, placing frames in
a root frame, the page's text, stream states and the command's refusals."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from agent import geometry as geo
from agent.view import events, panels
from agent.view.space import EdgeView, Space, Trails, ellipsoid
from agent.view.taps import StreamFacts, stream_state
from agent.view.watch import Look, measured_edges


def _realm(services: dict[str, list[dict]], agents: tuple[str, ...] = ("lab",)) -> dict:
    return {"realm": "r", "problems": [], "agents": [
        {"agent_id": a, "endpoints": [f"tcp/127.0.0.1:{7000 + i}"],
         "services": services.get(a, [])} for i, a in enumerate(agents)]}


def _svc(sid: str, needs: list[dict] = (), abilities: list[dict] = ()) -> dict:
    return {"service_id": sid, "abilities": list(abilities), "needs": list(needs)}


def _need(name: str, *matches: tuple[str, str, str], excluded: dict | None = None) -> dict:
    return {"name": name, "type": "pose6d", "edge": ["w", "*/head"], "satisfied": bool(matches),
            "excluded": excluded or {},
            "matches": [{"agent_id": a, "service_id": s, "ability": ab, "key": f"k/{a}/{s}/{ab}",
                         "measured": {"measured_frequency_hz": 99.5,
                                      "measured_latency_s": 0.002}} for a, s, ab in matches]}


def test_events_name_arrivals_departures_and_rematches_with_the_reason():
    before = _realm({"lab": [_svc("sim"), _svc("cam"), _svc("fusion", [
        _need("optical", ("lab", "cam", "pose"))])]})
    after = _realm({"lab": [_svc("sim"), _svc("fusion", [_need("optical", ("b", "cam2", "p"))])],
                    "b": [_svc("cam2")]}, ("lab", "b"))
    lines = events.changes(events.digest(before), events.digest(after))
    assert lines == ["agent b joined the realm", "service cam2 came on agent b",
                     "service cam left agent lab",
                     "need lab/fusion.optical re-matched to b/cam2/p (was lab/cam/pose; "
                     "lab/cam/pose: its service left)"]
    excluded = _realm({"lab": [_svc("cam"), _svc("fusion", [_need(
        "optical", excluded={"uma/r/data/lab/cam/pose": "rate 3 Hz < 30"})])]})
    lines = events.changes(events.digest(before), events.digest(excluded))
    assert lines[-1] == ("need lab/fusion.optical lost its match (lab/cam/pose: excluded, "
                         "rate 3 Hz < 30): no route")
    gone = events.changes(events.digest(after), events.digest(_realm({}, ("lab",))))
    assert "agent b left the realm" in gone and "service sim left agent lab" in gone
    assert not any("cam2" in line for line in gone)  # its agent's departure says it


def test_frames_are_placed_by_composing_edges_either_way():
    q90 = geo.rotvec_to_quat(np.array([0.0, 0.0, np.pi / 2]))
    edges = {e.name: e for e in (
        EdgeView("w", "head", "a", False, "sim/head", "k1"),
        EdgeView("head", "rig", "a", True, "config"),
        EdgeView("cam", "w", "b", True, "config"),          # traversed backwards
        EdgeView("x", "y", "b", False, "s/x", "k2"))}        # not connected to w
    names = {e.parent + e.child: e.name for e in edges.values()}
    values = {names["whead"]: (np.array([1.0, 0.0, 0.0]), q90),
              names["headrig"]: (np.array([0.0, 2.0, 0.0]), geo.quat_identity()),
              names["camw"]: (np.array([0.0, 0.0, 3.0]), geo.quat_identity()),
              names["xy"]: (np.zeros(3), geo.quat_identity())}
    placed = Space().place("w", edges, values)
    at = placed.index()
    assert set(placed.frames) == {"w", "head", "rig", "cam"}
    np.testing.assert_allclose(placed.positions[at["rig"]], [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(placed.positions[at["cam"]], [0.0, 0.0, -3.0], atol=1e-12)
    assert placed.via["rig"] == names["headrig"]
    # an edge without a value places nothing beyond it
    del values[names["whead"]]
    assert set(Space().place("w", edges, values).frames) == {"w", "cam"}


def test_a_thousand_frames_are_placed_in_a_few_levels_of_numpy():
    edges = {f"e{i}": EdgeView("w", f"f{i}", "a", False, f"s/{i}", f"k{i}") for i in range(1000)}
    values = {f"e{i}": (np.array([i, 0.0, 0.0]), geo.quat_identity()) for i in range(1000)}
    placed = Space().place("w", edges, values)
    assert len(placed.frames) == 1001
    assert placed.positions[placed.index()["f999"]][0] == 999.0


def test_trails_keep_moving_frames_only_and_forget_old_points():
    space, trails = Space(), Trails(seconds=1.0)
    edges = {"e": EdgeView("w", "h", "a", False, "s/h", "k"),
             "s": EdgeView("w", "still", "a", True, "config")}
    for t in range(5):
        placed = space.place("w", edges, {"e": (np.array([0.1 * t, 0, 0]), geo.quat_identity()),
                                          "s": (np.ones(3), geo.quat_identity())})
        trails.add(0.4 * t, placed)
    segs = trails.segments()
    assert segs.shape == (2, 2, 3)  # h's points of the last second; still never moved
    np.testing.assert_allclose(segs[-1, 1], [0.4, 0, 0])


def test_ellipsoid_axes_follow_the_covariance():
    cov = np.diag([4.0, 1.0, 0.25])
    radii, q = ellipsoid(cov, geo.quat_identity())
    axes = geo.quat_to_matrix(q)
    for r, axis in zip(radii, axes.T, strict=True):
        np.testing.assert_allclose(cov @ axis, r * r * axis, atol=1e-9)


def test_stream_states():
    fresh, old = StreamFacts(100.0, 0.01, 500), StreamFacts(None, 2.0, 500)
    assert stream_state(False, fresh, 100.0, 100.0) == "no route"
    assert stream_state(True, fresh, 100.0, 100.0) == "streaming"
    assert stream_state(True, old, 100.0, 100.0) == "stalled"
    assert stream_state(True, old, 1.0, 1.0) == "streaming"   # 10 periods of 1 Hz: 10 s
    assert stream_state(True, None, None, 0.0) == "stalled"
    assert stream_state(True, None, None, 30.0) == "streaming"


def test_the_page_text():
    empty = Look(_realm({}, ()))
    assert "No agents in realm `r` yet" in panels.realm_md(empty)
    realm = _realm({"lab": [_svc("fusion", [_need("optical", ("lab", "cam", "pose")),
                                            _need("accel")], [
        {"name": "head", "type": "pose6d", "edge": ["w", "a/head"],
         "attributes": {"frequency_hz": 100.0, "latency_s": 0.004}}])]})
    look = Look(realm, {"lab": (0.05, 0.4)}, measured_edges(realm), ((0.0, "agent lab came"),))
    assert "| lab | tcp/127.0.0.1:7000 | yes | 0.05 ms | 0.40 ms | 1 |" in panels.realm_md(look)
    m = panels.matches_md(look, lambda key: None)
    assert "| lab/cam/pose → lab/fusion.optical | 99.5 Hz | 2.00 ms | streaming |" in m
    assert "| nothing → lab/fusion.accel | - | - | no route |" in m
    s = panels.services_md(look)
    assert "ability `head` pose6d w -> a/head frequency_hz=100, latency_s=0.004" in s
    assert "need `accel`" in s and "(unsatisfied)" in s
    name = next(iter(look.edges))
    assert look.edges[name].key == "uma/r/data/lab/fusion/head"
    detail = panels.edge_md(name, look, lambda key: StreamFacts(99.0, 0.012, 7))
    assert "rate: 99.0 Hz" in detail and "12 ms ago" in detail and "owner agent: lab" in detail
    assert "agent lab came" in panels.events_md(look)


def _uma(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "agent.cli", *args], capture_output=True,
                          text=True, timeout=60)


@pytest.mark.parametrize(("args", "says"), [
    (["--port", "70000"], "--port must be in 0..65535"),
    (["--hz", "100"], "--hz must be in (0, 30]"),
    (["--trail", "-1"], "--trail must be in [0, 60]"),
    (["--realm", "a/b"], "realm 'a/b'"),
])
def test_bad_arguments_are_refused_with_a_message(args, says):
    r = _uma("view", "--port", "0", *args, "--seconds", "1")
    assert r.returncode == 1 and says in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_a_port_in_use_is_refused():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        r = _uma("view", "--port", str(s.getsockname()[1]), "--seconds", "1")
    assert r.returncode == 1 and "choose another --port" in r.stderr, r.stderr


def test_without_the_extra_it_says_what_to_install():
    code = ("import sys; sys.modules['viser'] = None\n"
            "from agent.cli.main import main\n"
            "sys.exit(main(['view', '--seconds', '1']))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, r.stderr
    assert "pip install 'uma-tracking[view]'" in r.stderr and "Traceback" not in r.stderr


def test_taps_pull_the_newest_sample_and_measure_the_rate_from_sequence_numbers():
    """A pose stream is read from its agent's digest (the newest sample of each of its
    streams), the others from their own key."""
    import logging
    import time

    import zenoh

    from agent.protocol.digest import digest_message
    from agent.view.taps import Taps
    from schemas.codec import encode_pose

    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    session = zenoh.open(config)
    pose, digest = "uma/r/data/a/s/pose", "uma/r/agent/a/digest"
    try:
        taps = Taps(session, logging.getLogger("test"), "r")
        taps.follow([(pose, "pose6d")])
        assert taps.latest(pose) is None
        t0 = time.time_ns()
        for k in range(51):   # 100 Hz in the samples' own time, sent in one burst
            sample = encode_pose(t0 + k * 10_000_000, [0.01 * k, 0.0, 0.0], [0, 0, 0, 1], seq=k)
            session.put(digest, digest_message("a", {("s", "pose"): sample}))
            if k in (0, 25, 50):
                time.sleep(0.2)
                m = taps.latest(pose)
                assert m is not None and m.seq == k
        facts = taps.facts(pose)
        assert facts.seq == 50 and facts.rate_hz == pytest.approx(100.0)
        assert facts.age_s is not None and facts.age_s < 5.0
        session.put(digest, digest_message("a", {("s", "pose"): b"\x00not msgpack"}))
        time.sleep(0.2)
        assert taps.latest(pose).seq == 50  # the malformed sample is skipped
        session.put(digest, digest_message("b", {("s", "pose"): sample}))  # not a's
        time.sleep(0.2)
        assert taps.latest(pose).seq == 50
        taps.follow([])
        assert taps.facts(pose) is None
    finally:
        session.close()


def test_the_watch_hides_services_whose_token_went_and_keeps_agents_alive_by_token():
    """The watch's bookkeeping, without a realm: a service whose token went is hidden from
    every look until its agent drops it or its token comes back; an agent whose snapshot came
    too late keeps its last one while its token is there."""
    import threading
    from types import SimpleNamespace

    from agent.view.watch import Watch

    w = Watch.__new__(Watch)
    w._dead, w._dead_lock = {("lab", "cam")}, threading.Lock()
    alive = {"lab", "slow"}
    w.client = SimpleNamespace(tracker=SimpleNamespace(is_alive=lambda a: a in alive))
    both = _realm({"lab": [_svc("cam"), _svc("sim")], "slow": [_svc("x")]}, ("lab", "slow"))
    w.look = Look(both)
    hidden = w._without_dead(both)
    assert [s["service_id"] for s in hidden["agents"][0]["services"]] == ["sim"]
    assert w._without_dead(hidden) is hidden
    # "slow" did not answer this time: it keeps its last snapshot while its token is there
    late = w._carry_over(_realm({"lab": [_svc("cam"), _svc("sim")]}, ("lab",)))
    assert [a["agent_id"] for a in late["agents"]] == ["lab", "slow"]
    alive.discard("slow")
    assert [a["agent_id"] for a in w._carry_over(_realm({}, ("lab",)))["agents"]] == ["lab"]
    # still listed by its agent: still hidden; once the agent drops it, forgotten
    w._forget_dropped(both)
    assert w._dead == {("lab", "cam")}
    w._forget_dropped(_realm({"lab": [_svc("sim")]}))
    assert w._dead == set()


def test_the_agents_digest_is_put_only_while_someone_listens_and_holds_the_newest_samples():
    import time

    import zenoh

    from agent.daemon.digest import StreamDigest
    from agent.protocol import keys, read_digest

    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    session = zenoh.open(config)
    got: list = []
    newest: dict = {}
    seen = [0]

    def note(local, data):  # what the graph store does per sample
        newest[local] = data
        seen[0] += 1
    try:
        digest = StreamDigest(session, "r", "a", lambda: newest, lambda: seen[0])
        note(("s", "pose"), b"first")
        digest.publish()  # nobody listens: nothing put, the change kept for later
        sub = session.declare_subscriber(keys.agent_digest("r", "a"),
                                         lambda s: got.append(s.payload.to_bytes()))
        note(("s", "pose"), b"second")
        note(("t", "pose"), b"other")
        deadline = time.monotonic() + 5
        while not got and time.monotonic() < deadline:
            digest.publish()
            time.sleep(0.05)
        assert read_digest(got[0], "r", "a") == {"uma/r/data/a/s/pose": b"second",
                                                 "uma/r/data/a/t/pose": b"other"}
        count = len(got)
        digest.publish()  # nothing new since: nothing put
        del newest[("t", "pose")]  # the stream went
        note(("s", "pose"), b"third")
        digest.publish()
        time.sleep(0.2)
        assert len(got) == count + 1
        assert read_digest(got[-1], "r", "a") == {"uma/r/data/a/s/pose": b"third"}
        with pytest.raises(ValueError, match="not the agent of its key"):
            read_digest(got[-1], "r", "b")
        sub.undeclare()
        digest.close()
    finally:
        session.close()
