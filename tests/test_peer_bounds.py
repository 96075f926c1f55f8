"""Bounds against buggy and hostile peers: what a peer
sends cannot grow a log, a cache or a queue without bound, and every refusal is counted."""

from __future__ import annotations

import logging

from agent.runtime.logs import RateLimitedLog, kind_of


def test_log_keys_on_the_kind_of_error_not_its_values(caplog) -> None:
    """11,600 bad messages gave 497 warnings: the limiter keyed on byte values and
    positions.  One sender's malformed messages of one kind now give one line."""
    rl = RateLimitedLog(logging.getLogger("uma.test.kind"), interval=60)
    with caplog.at_level(logging.WARNING, logger="uma.test.kind"):
        for i in range(2000):
            rl.warning("data uma/r/data/a/s/p",
                       f"not valid msgpack: unpack(b) received extra data at {i} "
                       f"(byte 0x{i % 256:02x}) in 'x{i}'")
            rl.warning("data uma/r/data/a/s/p", f"expected a pose6d measurement, got {i}")
    assert len(caplog.records) == 2
    assert rl.seen == 4000 and rl.logged == 2
    assert kind_of("byte 0xc1 at 17 in 'abc'") == kind_of("byte 0x92 at 3 in 'zz'")
    assert kind_of("field 'k' missing") != kind_of("field 'k': not a string")


def test_log_bounds_a_flood_of_distinct_senders_and_reports_the_count(caplog) -> None:
    rl = RateLimitedLog(logging.getLogger("uma.test.flood"), interval=60, burst=5,
                        max_keys=100)
    with caplog.at_level(logging.WARNING, logger="uma.test.flood"):
        for i in range(3000):
            rl.warning(f"supernode uma/r/agent/forged{i}/supernode", "malformed summary")
    assert len(caplog.records) == 5 and len(rl._last) <= 100
    rl.interval = 0  # the next window: the swallowed ones are reported by count
    with caplog.at_level(logging.WARNING, logger="uma.test.flood"):
        rl.warning("supernode uma/r/agent/late/supernode", "malformed summary")
    assert "2995 more warnings" in caplog.records[-2].getMessage()
    assert caplog.records[-1].getMessage().startswith("supernode uma/r/agent/late")


# --------------------------------------------------------------------------- finding 5


def _static_node():
    from unittest import mock

    from agent.daemon.srg_node import SrgNode
    edges = [{"parent": "w", "child": "cam", "position": [1.0, 0.0, 2.0],
              "quaternion": [0.0, 0.0, 0.0, 1.0], "pos_std_m": 0.01},
             {"parent": "cam", "child": "rig", "position": [0.0, 0.5, 0.0],
              "quaternion": [0.0, 0.0, 0.0, 1.0]}]
    return SrgNode(mock.MagicMock(), "lab", "A", edges)


def _rss_kib() -> int:
    from pathlib import Path
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS in /proc/self/status")


def test_queries_with_distinct_error_expressions_keep_bounded_caches(monkeypatch,
                                                                     caplog) -> None:
    """20,000 queries with distinct error texts kept 133 MB (plans and answers never
    evicted).  Both caches are least-recently-used with a count limit now; the test uses
    limits of 50 to stay fast, and checks memory does not grow with more queries."""
    from agent.daemon import query_server
    monkeypatch.setattr(query_server, "MAX_ANSWERS", 50)
    n = _static_node()
    n.graph.max_plans = 50
    n.handle({"op": "segment", "source": "rig", "target": "w", "error": "hops"})

    def flood(start: int, count: int) -> None:
        for i in range(start, start + count):
            r = n.handle({"op": "segment", "source": "rig", "target": "w", "t": None,
                          "error": f"latency_s + {i} * pos_std_m"})
            assert "result" in r, r
    flood(0, 100)
    rss = _rss_kib()
    flood(100, 500)
    assert len(n.graph._plans) == 50 and len(n.queries.answers) == 50
    assert n.graph.plans_evicted == 601 - 50 and n.answers_evicted == 601 - 50
    plans_indexed = set().union(*n.graph._plans_by_frame.values())
    assert plans_indexed == set(n.graph._plans), "the frame index holds exactly the cache"
    assert set().union(*n.graph._plans_by_edge.values()) == set(n.graph._plans)
    assert _rss_kib() - rss < 8 * 1024, "500 more queries must not grow the process"
    said = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("query plans: 50 plans cached") for m in said), said
    assert any(m.startswith("query cache: 50 answers cached") for m in said), said


def test_the_most_recently_used_plan_survives_eviction() -> None:
    from agent.srg import Graph
    g = Graph(max_plans=2)
    g.add_static("a", "b", [0, 0, 0], [0, 0, 0, 1])
    g.add_static("b", "c", [0, 0, 0], [0, 0, 0, 1])
    g.pose("a", "c")
    g.pose("a", "b")
    g.pose("a", "c")  # used again: now b is the oldest
    g.pose("c", "a")
    assert g.has_plan("a", "c") and g.has_plan("c", "a") and not g.has_plan("a", "b")
    g.remove_edge("b", "c")  # the index stays consistent through eviction and removal
    assert not g.has_plan("a", "c") and g._plans_by_edge.keys() <= {("a", "b", "static")}


def test_summaries_from_too_many_agents_are_refused_and_counted(monkeypatch) -> None:
    from types import SimpleNamespace

    import zenoh

    from agent.daemon import peer_frames
    from schemas.codec import encode_message
    monkeypatch.setattr(peer_frames, "MAX_REMOTE_AGENTS", 50)
    n = _static_node()
    n.peers.learn("uma/lab/agent/ghost/supernode",  # its agent never had a token
                  encode_message({"agent": "ghost", "frames": ["g0"]}))
    assert n.peers.frames == {} and n.summaries_refused == 1
    for i in range(300):  # the first 50 tokens are remembered
        n.peers.on_agent_token(SimpleNamespace(key_expr=f"uma/lab/agent/x{i}",
                                               kind=zenoh.SampleKind.PUT))
        n.peers.learn(f"uma/lab/agent/x{i}/supernode",
                 encode_message({"agent": f"x{i}", "frames": [f"f{i}"]}))
    n.peers.learn("uma/lab/agent/big/supernode",
             encode_message({"agent": "x1", "frames": [f"f{i}" for i in range(5000)]}))
    assert len(n.peers.frames) == 50 and n.summaries_refused == 252
    assert n.peers.frames["x1"] == {"f1"}
    n.peers.learn("uma/lab/agent/x1/supernode", encode_message({"agent": "x1", "frames": ["g"]}))
    assert n.peers.frames["x1"] == {"g"}, "a known agent's summary still replaces its own"
    assert "g" in n.peers.known_elsewhere() and "f1" not in n.peers.known_elsewhere()
    for bad in (["a b"], ["x" * 201], [7]):  # frames are checked by name
        n.peers.learn("uma/lab/agent/x2/supernode", encode_message({"agent": "x2",
                                                                    "frames": bad}))
    assert n.peers.frames["x2"] == {"f2"} and n.summaries_refused == 255
    monkeypatch.setattr(peer_frames, "MAX_AGENT_FRAME_BYTES", 100)
    n.peers.learn("uma/lab/agent/x3/supernode", encode_message(
        {"agent": "x3", "frames": [f"frame{i:03d}" for i in range(20)]}))
    assert n.peers.frames["x3"] == {"f3"} and n.summaries_refused == 256


def test_a_flooded_worker_refuses_and_counts_instead_of_growing(caplog) -> None:
    """The agent's and the service's worker queue: calls come from peers' messages."""
    from agent.runtime.worker import MAX_QUEUED, Worker
    w = Worker("t", "agent T", logging.getLogger("uma.test.worker"), lambda: None, 1.0)
    with caplog.at_level(logging.WARNING, logger="uma.test.worker"):
        for _ in range(MAX_QUEUED + 500):
            w.put(print, "never run")
    assert w._q.qsize() == MAX_QUEUED and w.refused == 500
    assert len(caplog.records) == 1 and "refused" in caplog.records[0].getMessage()


def test_need_patterns_keep_a_bounded_number_of_candidates() -> None:
    """3,000 forged abilities fitting one need pattern: the index keeps 1,024, counts the
    refusals, tells its owner, and a removal lets a refused one in."""
    from agent.daemon.matching import MAX_CANDIDATES, MAX_PATTERNS, Offer, OfferIndex
    from schemas.models import Ability, Need

    def offer(i: int) -> Offer:
        ab = Ability(name="pose", type="pose6d", edge=("lab/world", f"x{i}/head"))
        return Offer.of(f"uma/lab/data/evil/s{i}/pose", "evil", f"s{i}", ab)
    told = []
    idx = OfferIndex(on_refused=lambda *a: told.append(a))
    need = Need(name="head", type="pose6d", edge=("lab/world", "*/head"))
    assert list(idx.candidates(need)) == []
    for i in range(3000):
        idx.add(offer(i))
    assert len(list(idx.candidates(need))) == MAX_CANDIDATES
    assert idx.refused == 3000 - MAX_CANDIDATES and len(told) == idx.refused
    assert told[-1] == (("pose6d", "lab/world", "*/head"), "uma/lab/data/evil/s2999/pose",
                        3000 - MAX_CANDIDATES)
    idx.remove("uma/lab/data/evil/s0/pose")
    keys = {o.key for o in idx.candidates(need)}
    assert len(keys) == MAX_CANDIDATES and "uma/lab/data/evil/s1024/pose" in keys
    few = OfferIndex([offer(i) for i in range(3)])
    for i in range(2000):  # distinct patterns: at most MAX_PATTERNS remembered
        few.candidates(Need(name="n", type="pose6d", edge=("lab/world", f"y{i}/*")))
    assert len(few._candidates) == MAX_PATTERNS


# --------------------------------------------------------------------------- finding 6


def _wait_for(cond, timeout: float = 5.0) -> bool:
    import time
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def test_zenoh_refuses_a_message_above_umas_receive_limit() -> None:
    """Zenoh reassembled messages up to 1 GiB for uma to copy and refuse; a uma session
    now takes at most MAX_RECEIVE_BYTES (the largest uma message, an image, + 1 MiB)."""
    import zenoh

    from agent.runtime.session import (
        MAX_RECEIVE_BYTES,
        close_session,
        listening_endpoints,
        open_session,
    )
    uma = open_session("peer", None, [])
    hostile = zenoh.open(_plain_peer(listening_endpoints(uma)))
    try:
        got: list[int] = []
        sub = uma.declare_subscriber("uma/r/data/A/s/x", lambda smp: got.append(len(smp.payload)))
        # BLOCK: with DROP, Zenoh may drop a big message's fragments itself
        pub = hostile.declare_publisher("uma/r/data/A/s/x",
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        assert _wait_for(lambda: (pub.put(b"ok"), got)[1] != [])
        got.clear()
        pub.put(b"\x00" * (MAX_RECEIVE_BYTES + (4 << 20)))
        pub.put(b"\x01" * (2 << 20))  # under the limit: still delivered, after the big one
        assert _wait_for(lambda: 2 << 20 in got, 10.0), got
        assert max(got) == 2 << 20, "the oversized message reached the subscriber"
        sub.undeclare()
    finally:
        hostile.close()
        close_session(uma)


def _plain_peer(connect: list[str]):
    """A plain Zenoh peer (Zenoh's defaults: admin space on, 1 GiB messages), as a hostile
    program would open it, on loopback without multicast scouting."""
    import json

    import zenoh
    c = zenoh.Config()
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([]))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    return c


def test_another_peer_cannot_read_a_uma_sessions_admin_space() -> None:
    import zenoh

    from agent.runtime.session import close_session, listening_endpoints, open_session, query
    uma = open_session("peer", None, [])
    hostile = zenoh.open(_plain_peer(listening_endpoints(uma)))
    try:
        assert _wait_for(lambda: str(uma.zid()) in {str(z) for z in hostile.info.peers_zid()})
        replies = query(hostile, f"@/{uma.zid()}/**", 1.0)
        assert replies == [], [str(r.ok.key_expr) for r in replies if r.ok]
        assert listening_endpoints(uma)[0].startswith("tcp/127.0.0.1:"), "port still known"
        assert not listening_endpoints(uma)[0].endswith(":0")
    finally:
        hostile.close()
        close_session(uma)


def test_an_oversized_summary_is_refused_before_it_is_copied(caplog) -> None:
    """uma copied a payload (``to_bytes``) before its 1 MiB check: the size is checked on
    the Zenoh buffer now (tracemalloc sees no copy of the 8 MiB)."""
    import tracemalloc
    from types import SimpleNamespace

    import zenoh
    n = _static_node()
    big = zenoh.ZBytes(b"\x80" * (8 << 20))
    sample = SimpleNamespace(key_expr="uma/lab/agent/B/supernode", payload=big)
    n.peers.on_agent_token(SimpleNamespace(key_expr="uma/lab/agent/B",
                                           kind=zenoh.SampleKind.PUT))
    tracemalloc.start()
    try:
        with caplog.at_level(logging.WARNING, logger="uma.srg"):
            n.peers.on_summary(sample)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, f"{peak} bytes allocated for a refused 8 MiB summary"
    assert "exceeds the limit" in caplog.records[-1].getMessage()
    assert n.peers.frames == {}


def test_a_summary_of_an_agent_without_a_token_is_refused_before_it_is_decoded() -> None:
    """Decoding and checking a stranger's 20,000 frame ids cost the flood's CPU and memory;
    the key names the agent, whose token was never seen: nothing is decoded."""
    import tracemalloc

    from schemas.codec import encode_message
    n = _static_node()
    data = encode_message({"agent": "ghost", "frames": [f"ghost/f{i:05d}" for i in range(20_000)]})
    tracemalloc.start()
    try:
        n.peers.learn("uma/lab/agent/ghost/supernode", data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < len(data) // 4, f"{peak} bytes allocated for a {len(data)}-byte summary"
    assert n.peers.frames == {} and n.summaries_refused == 1


def _summary(agent: str, frames: list[str], links: list[tuple[str, str]]):
    from agent.protocol.query import Summary
    attrs = {"hops": {"hops": 1, "latency_s": 0.01, "cost": 0.0, "confidence": 1.0,
                      "accuracy": 0.0, "pos_std_m": 0.0, "rot_std_rad": 0.0, "static": True}}
    return Summary(agent, 1, set(frames), [set(frames)], [(a, b, attrs) for a, b in links])


def test_planning_over_forged_summaries_considers_a_bounded_number_of_links(caplog) -> None:
    """Forged summaries with 801 links each made one plan take 0.5-0.8 s: a plan now
    considers at most MAX_LINKS_PER_AGENT links of one agent and MAX_PLAN_LINKS in all,
    nearest agents first, so the honest route is still found, and says what it left out."""
    import itertools

    from agent.sdk import planner
    from agent.srg.errorfn import error_function
    frames = [f"f{i}" for i in range(41)]
    clique = list(itertools.combinations(frames, 2))[:801]
    summaries = {"h1": _summary("h1", ["src", "f0"], [("src", "f0")]),
                 "h2": _summary("h2", ["f40", "dst"], [("f40", "dst")]),
                 "h3": _summary("h3", ["f0", "f40"], [("f0", "f40")])}
    for i in range(20):
        summaries[f"evil{i}"] = _summary(f"evil{i}", frames, clique)
    with caplog.at_level(logging.WARNING, logger="uma.client"):
        links = planner.considered_links(summaries, "src", "dst")
        routes = planner.plan_routes(summaries, "src", "dst", error_function("hops"))
    assert len(links) == planner.MAX_PLAN_LINKS
    per_agent = {}
    for (agent, _, _), _ in links:
        per_agent[agent] = per_agent.get(agent, 0) + 1
    assert max(per_agent.values()) == planner.MAX_LINKS_PER_AGENT
    assert per_agent["h1"] == per_agent["h2"] == per_agent["h3"] == 1, "nearest, fewest first"
    assert [str(s) for s in routes[0].segments] == ["src -> f0 of agent 'h1'",
                                                    "f0 -> f40 of agent 'h3'",
                                                    "f40 -> dst of agent 'h2'"]
    assert f"{20 * 801 - 509} links" in caplog.records[-1].getMessage()


# --------------------------------------------------------------------------- finding 11


def test_recalibration_only_on_the_exact_key_and_not_too_often(caplog) -> None:
    """A wildcard ``recalibrate`` reached every alignment service and each request emptied
    its buffers; now only the service's own key counts, once per RECALIBRATE_MIN_S."""
    import argparse
    import json
    from types import SimpleNamespace

    from services.alignment import service as alignment
    from services.alignment.plugin import add_arguments
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--a", "w/a", "--b", "w/b"])
    live = alignment.LiveAlignment(args, alignment.options_from(args))
    key = alignment.recalibrate_key("lab", "A", "alignment")
    replies: list[dict] = []

    def ask(asked: str) -> dict:
        query = SimpleNamespace(key_expr=asked, reply=lambda k, data: replies.append(
            {"key": k, **json.loads(data)}))
        live.a.samples.append((1, None, None))  # a buffered motion: a request clears it
        alignment._answer_request(query, live, key)
        return replies[-1]
    with caplog.at_level(logging.WARNING, logger="uma.alignment"):
        wild = ask("uma/lab/svc/*/*/recalibrate")
        assert not wild["ok"] and "wildcards are refused" in wild["status"]
        assert not live.requested.is_set() and len(live.a.samples) == 1
        assert ask(key)["ok"] and live.requested.is_set() and len(live.a.samples) == 0
        again = ask(key)
        assert not again["ok"] and "at most one per" in again["status"]
    assert live.refused == 2 and {r["key"] for r in replies} == {key}
    assert "2 refused so far" in caplog.records[-1].getMessage()


def test_fusion_refuses_optical_poses_stamped_far_ahead() -> None:
    """A pose stamped a day ahead stayed pending in the fusion filter forever; it is refused
    now, against the filter's time and against this host's clock, and counted."""
    import time
    from types import SimpleNamespace

    import numpy as np
    from test_fusion import HEAD_TO_LASER_RIG, MODEL_FLOOR, _still_rig

    from services.fusion.service import LiveFusion
    tracker, p, q, cov, rest = _still_rig()
    for i in range(1, 30):
        tracker.add_accel(i / 300, rest)
    assert not tracker.add_rig_pose(86400.0, p, q, cov, HEAD_TO_LASER_RIG)
    assert tracker.stats.optical_too_far_ahead == 1 and tracker._pending == []
    assert tracker.add_rig_pose(0.2, p, q, cov, HEAD_TO_LASER_RIG)  # honest, a bit ahead
    live = LiveFusion(0.02, MODEL_FLOOR)
    live.on_optical(SimpleNamespace(t_ns=time.time_ns() + 86_400 * 10**9, position=np.zeros(3),
                                    quaternion=np.array([0, 0, 0, 1.0]), covariance=None))
    assert list(live.dropped) == ["optical pose stamped more than 10 s ahead of this host's clock"]


def test_the_codec_refuses_a_covariance_that_is_not_positive_semi_definite() -> None:
    """Symmetric with a non-negative diagonal was all the codec checked; a correlation above
    1 (here 2) passed.  Both the diagonal fast path and the Cholesky fall-back hold."""
    import numpy as np
    import pytest

    from schemas.codec import DecodeError, decode_measurement, encode_pose
    bad = np.eye(6) * 1e-4
    bad[0, 1] = bad[1, 0] = 2e-4  # |corr| = 2: eigenvalue -1e-4
    with pytest.raises(DecodeError, match=r"not positive semi-definite \(smallest eigenvalue"):
        decode_measurement(encode_pose(1, [0, 0, 0], [0, 0, 0, 1], bad), "pose6d")
    rng = np.random.default_rng(3)
    a = rng.normal(size=(6, 6))
    for good in (np.diag([1e-4] * 3 + [1e-6] * 3), a @ a.T, np.zeros((6, 6)),
                 np.outer(a[0], a[0])):  # rank one: semi-definite, not definite
        m = decode_measurement(encode_pose(1, [0, 0, 0], [0, 0, 0, 1], good), "pose6d")
        assert np.allclose(m.covariance, good)


def test_a_calibration_cache_of_the_wrong_structure_is_made_again(tmp_path, monkeypatch,
                                                                   caplog) -> None:
    """A cache file holding JSON of another structure crashed with AttributeError; an
    interrupted write left its ``*.tmp`` behind.  Both are handled now."""
    import json

    import pytest

    import services.laser_camera
    from services.laser_camera.calibration import FORMAT_VERSION, Calibration
    from services.sim import calibrations
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    made = []

    def make(path):
        made.append(path)
        path.write_text(json.dumps({"made": True}))

    def load(path):
        if json.loads(path.read_text()) != {"made": True}:
            Calibration.load(path)  # the real loader meets the wrong structure
    pkgs = (services.laser_camera,)
    target = calibrations.cached_file("t", pkgs, load, make)
    for cameras in ([1], 1):  # AttributeError, TypeError from the loader before
        target.write_text(json.dumps({"format": "uma-laser-camera-calibration",
                                      "version": FORMAT_VERSION, "cameras": cameras}))
        with caplog.at_level(logging.WARNING, logger="uma.eval"):
            assert calibrations.cached_file("t", pkgs, load, make) == target
        assert "'cameras' must be a list of maps" in caplog.records[-1].getMessage()
    assert len(made) == 3
    target.unlink()

    def interrupted(path):
        path.write_text("half")
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        calibrations.cached_file("t", pkgs, load, interrupted)
    orphan = target.with_suffix(".999999999.tmp")  # a writer killed mid-write
    orphan.write_text("half")
    calibrations.cached_file("t", pkgs, load, make)
    assert sorted(p.name for p in target.parent.iterdir()) == [target.name]


def _make_slowly(path) -> None:
    """A calibration that takes a while and counts how often it was made."""
    import time
    with open(path.parent / "made.log", "a") as log:
        log.write("x")
    time.sleep(0.5)
    path.write_text("{}")


def _cache_in_child(cache_home: str) -> str:
    import os

    import services.laser_camera
    from services.sim import calibrations
    os.environ["XDG_CACHE_HOME"] = cache_home
    return str(calibrations.cached_file("slow", (services.laser_camera,), lambda p: None,
                                        _make_slowly))


def test_processes_missing_the_cache_at_once_make_the_file_once(tmp_path) -> None:
    """Four test workers or two demos missing the cache together wait for the first one's
    calibration instead of each making their own."""
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(2) as pool:
        paths = pool.map(_cache_in_child, [str(tmp_path)] * 2, chunksize=1)
    assert len(set(paths)) == 1
    assert (tmp_path / "uma" / "made.log").read_text() == "x"


def test_an_exception_in_a_zenoh_callback_is_logged_rate_limited(capfd, caplog) -> None:
    """zenoh-python prints a traceback ("callback error") per exception a callback raises;
    uma's callbacks are guarded: 200 failing samples give one log line, no traceback."""
    from agent.runtime.callbacks import guarded
    from agent.runtime.session import close_session, open_session
    session = open_session("peer", [], [])
    seen: list[int] = []

    def on_sample(sample) -> None:
        seen.append(1)
        raise KeyError(f"forged id {len(seen)}")
    bad = RateLimitedLog(logging.getLogger("uma.test.callback"), interval=60)
    try:
        with caplog.at_level(logging.WARNING, logger="uma.test.callback"):
            sub = session.declare_subscriber("uma/r/data/A/s/x",
                                             guarded(on_sample, "data uma/r/data/A/s/x", bad))
            for i in range(200):
                session.put("uma/r/data/A/s/x", str(i))
            # the guard counts a failure after the callback raised: wait for its count
            assert _wait_for(lambda: bad.seen == 200)
            sub.undeclare()
    finally:
        close_session(session)
    assert "callback error" not in capfd.readouterr().err
    assert len(caplog.records) == 1 and bad.seen == 200
    line = caplog.records[0].getMessage()
    assert "on_sample failed: KeyError: 'forged id 1' (at test_peer_bounds.py:" in line


def test_a_listener_whose_chosen_port_was_taken_is_opened_on_another(monkeypatch) -> None:
    """With the admin space off, uma picks a ``:0`` listener's port itself; another process
    may take it before Zenoh binds it: the session is opened again on a fresh port."""
    import socket

    from agent.runtime import session as sessions
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    real, calls = sessions._free_port, []

    def first_taken(ep: str) -> str:
        calls.append(ep)
        return f"tcp/127.0.0.1:{port}" if len(calls) == 1 else real(ep)
    monkeypatch.setattr(sessions, "_free_port", first_taken)
    try:
        s = sessions.open_session("peer", None, [])
        try:
            (ep,) = sessions.listening_endpoints(s)
            assert len(calls) == 2 and ep.startswith("tcp/127.0.0.1:")
            assert ep != f"tcp/127.0.0.1:{port}"
        finally:
            sessions.close_session(s)
    finally:
        taken.close()


def test_a_client_keeps_summaries_of_agents_with_tokens_within_a_byte_bound(monkeypatch,
                                                                            realm) -> None:
    """Invented agents on a plain realm may declare tokens too: what their summaries make a
    client hold stays within ``MAX_SUMMARY_BYTES``; a summary of an agent whose token it
    never saw is not kept at all."""
    from types import SimpleNamespace

    import msgpack
    import zenoh

    from agent.runtime.session import open_session
    from agent.sdk import realm as realm_module
    monkeypatch.setattr(realm_module, "MAX_SUMMARY_BYTES", 20_000)
    with open_session() as session:
        tracker = realm_module.RealmTracker(session, realm, 0.1, lambda agent: False)
        try:
            def summary(agent: str) -> bytes:
                return msgpack.packb({"v": 1, "agent": agent, "rev": 1,
                                      "frames": [f"{agent}/f{j}" for j in range(500)]})
            tracker.take_summary(f"uma/{realm}/agent/nobody/supernode", summary("nobody"))
            for i in range(20):
                tracker._on_token(SimpleNamespace(key_expr=f"uma/{realm}/agent/g{i}",
                                                  kind=zenoh.SampleKind.PUT))
                tracker.take_summary(f"uma/{realm}/agent/g{i}/supernode", summary(f"g{i}"))
            kept = tracker.view().summaries
            assert "nobody" not in kept and 0 < len(kept) < 20
            assert sum(len(summary(a)) for a in kept) <= 20_000
            assert tracker.refused == 1 + 20 - len(kept)
        finally:
            tracker.close()


def test_token_churn_does_not_make_a_client_forget_a_live_agent(monkeypatch, realm) -> None:
    """A client remembers a bounded number of agents that had a token; tokens of new agent
    ids declared and dropped by a stranger pushed the oldest out, a live agent included,
    whose summaries the client then dropped."""
    from types import SimpleNamespace

    import msgpack
    import zenoh

    from agent.runtime.session import open_session
    from agent.sdk import realm as realm_module
    monkeypatch.setattr(realm_module, "MAX_AGENTS", 50)
    with open_session() as session:
        tracker = realm_module.RealmTracker(session, realm, 0.1, lambda agent: False)
        try:
            def token(agent: str, kind: zenoh.SampleKind) -> None:
                tracker._on_token(SimpleNamespace(key_expr=f"uma/{realm}/agent/{agent}",
                                                  kind=kind))
            token("real", zenoh.SampleKind.PUT)
            for i in range(200):
                token(f"churn{i}", zenoh.SampleKind.PUT)
                token(f"churn{i}", zenoh.SampleKind.DELETE)
            tracker.take_summary(f"uma/{realm}/agent/real/supernode", msgpack.packb(
                {"v": 1, "agent": "real", "rev": 1, "frames": ["real/world"]}))
            assert "real" in tracker.view().summaries and tracker.refused == 0
        finally:
            tracker.close()
