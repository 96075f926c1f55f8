"""The planner over supernode summaries (pure: no Zenoh), and the agent's query handler."""

from __future__ import annotations

import itertools
import math
from unittest import mock

import numpy as np
import pytest

from agent import geometry as geo
from agent.daemon.srg_node import SrgNode
from agent.protocol.query import parse_summary
from agent.sdk.planner import RouteError, Segment, plan_routes, usable_routes
from agent.srg import Graph
from agent.srg.composition import Composition, compose
from agent.srg.errorfn import error_function
from agent.srg.errors import UnknownFrameError, UnreachableError
from agent.srg.supernode import summarize


def graph(*edges) -> Graph:
    g = Graph()
    for parent, child, std in edges:
        g.add_static(parent, child, [0.1, 0.2, 0.3], [0, 0, 0, 1], pos_std_m=std)
    return g


def summaries(graphs: dict[str, Graph]):
    """Each agent's summary, with its boundary = frames another agent also knows."""
    out = {}
    for name, g in graphs.items():
        others = set().union(*(set(h.frames()) for n, h in graphs.items() if n != name))
        msg = summarize(g, others)
        msg.update(agent=name, rev=1)
        out[name] = parse_summary(msg)
    return out


def test_summary_links_every_frame_to_the_boundary_with_attributes():
    g = graph(("w", "cam", 0.01), ("cam", "rig", 0.02), ("x", "y", 0.1))
    s = summarize(g, ["rig", "y", "elsewhere"])
    assert s["boundary"] == ["rig", "y"]
    pairs = {(link["a"], link["b"]) for link in s["links"]}
    assert pairs == {("w", "rig"), ("cam", "rig"), ("x", "y")}
    attrs = next(link for link in s["links"] if link["a"] == "w")["attrs"]
    assert attrs["hops"]["hops"] == 2 and attrs["latency"]["frequency_hz"] is None
    assert attrs["accuracy"]["pos_std_m"] == pytest.approx(math.sqrt(0.01**2 + 0.02**2))


def test_routes_cross_agents_through_shared_frames_and_merge_per_agent():
    sums = summaries({"A": graph(("w", "cam", 0.01)),
                      "B": graph(("cam", "rig", 0.01), ("rig", "imu", 0.01)),
                      "C": graph(("rig", "head", 0.01))})
    routes = plan_routes(sums, "w", "head", error_function("hops"))
    assert routes[0].segments == [Segment("A", "w", "cam"), Segment("B", "cam", "rig"),
                                  Segment("C", "rig", "head")]
    assert routes[0].attributes["hops"] == 3
    # a frame only B knows, behind an internal B frame: one B segment
    r = plan_routes(sums, "w", "imu", error_function("hops"))[0]
    assert r.segments == [Segment("A", "w", "cam"), Segment("B", "cam", "imu")]


def test_error_function_picks_the_route_and_dead_agents_are_named():
    sums = summaries({"A": graph(("w", "cam", 0.001)),
                      "B": graph(("cam", "rig", 0.001), ("rig", "imu", 0.001)),
                      "C": graph(("rig", "head", 0.001), ("w", "rig", 0.2))})
    fast = plan_routes(sums, "w", "head", error_function("hops"))
    assert fast[0].segments == [Segment("C", "w", "head")]
    best = plan_routes(sums, "w", "head", error_function("accuracy"))
    assert [s.agent for s in best[0].segments] == ["A", "B", "C"]
    ok = usable_routes(best, {"A", "C"}, "w", "head")
    assert ok[0].segments == [Segment("C", "w", "head")]
    # cam -> rig survives B (through w, over A and C); only B knows the IMU
    assert usable_routes(plan_routes(sums, "cam", "rig", error_function("accuracy")),
                         {"A", "C"}, "cam", "rig")[0].agents == ["A", "C"]
    with pytest.raises(RouteError, match=r"cam -> imu of agent 'B'.*B left the realm"):
        usable_routes(plan_routes(sums, "cam", "imu", error_function("accuracy")),
                      {"A", "C"}, "cam", "imu")


def test_unknown_and_unreachable_frames_are_named():
    sums = summaries({"A": graph(("w", "cam", 0.01)), "B": graph(("x", "y", 0.01))})
    with pytest.raises(UnknownFrameError, match=r"'nope'; known frames: cam, w, x, y"):
        plan_routes(sums, "w", "nope", error_function("hops"))
    with pytest.raises(UnreachableError, match=r"no path from 'w' to 'y'"):
        plan_routes(sums, "w", "y", error_function("hops"))


@pytest.mark.parametrize("bad", [
    {"agent": 3, "frames": []},
    {"agent": "A", "frames": "w"},
    {"agent": "A", "frames": ["w"], "links": [{"a": "w"}]},
    {"agent": "A", "frames": ["w"], "links": [{"a": "w", "b": "c", "attrs": {"hops": {}}}]},
])
def test_malformed_summaries_are_refused(bad):
    with pytest.raises(ValueError):
        parse_summary(bad)


def test_composition_of_segments_matches_one_graph():
    rng = np.random.default_rng(5)
    whole = Graph()
    parts = []
    for i in range(3):
        p, q = rng.normal(size=3), geo.rotvec_to_quat(rng.normal(size=3))
        whole.add_static(f"f{i}", f"f{i + 1}", p, q, pos_std_m=0.01 * (i + 1), rot_std_rad=0.01)
        g = Graph()
        g.add_static(f"f{i}", f"f{i + 1}", p, q, pos_std_m=0.01 * (i + 1), rot_std_rad=0.01)
        parts.append(g.pose(f"f{i}", f"f{i + 1}"))
    r = compose(parts, 7)
    ref = whole.pose("f0", "f3")
    np.testing.assert_allclose(r.position, ref.position, atol=1e-12)
    assert geo.quat_angle(r.quaternion, ref.quaternion) < 1e-12
    np.testing.assert_allclose(r.covariance, ref.covariance, rtol=1e-10, atol=1e-16)
    assert r.path == ["f0", "f1", "f2", "f3"] and r.t_ns == 7
    assert r.attributes["hops"] == 3


@pytest.fixture
def node():
    n = SrgNode(mock.MagicMock(), "lab", "A", [
        {"parent": "w", "child": "cam", "position": [1, 0, 0], "quaternion": [0, 0, 0, 1],
         "pos_std_m": 0.01}])
    yield n
    n.close()


def test_node_answers_segments_and_refuses_malformed_queries(node):
    ok = node.handle({"op": "segment", "source": "w", "target": "cam", "t": None,
                      "error": "hops", "details": True})
    assert ok["ok"] and ok["result"]["position"] == [1.0, 0.0, 0.0]
    assert ok["result"]["edges"][0]["owner"] == "A"
    assert ok["edges"][0]["static"] and ok["edges"][0]["position"] == [1.0, 0.0, 0.0]
    assert node.handle({"op": "segments", "parts": {"B": {}}}) is None  # not for A
    for bad, reason in [({"op": "teleport"}, "unknown op"),
                        ({"op": "segment", "source": "w"}, "target must be"),
                        ({"op": "segment", "source": "w", "target": "cam", "t": 1.5},
                         "t must be integer"),
                        ({"op": "segments", "parts": [1]}, "parts must be"),
                        ({"op": "segment", "source": "w", "target": "zz"}, "unknown frame")]:
        with pytest.raises((ValueError, LookupError), match=reason):
            node.handle(bad)


def test_node_turns_query_failures_into_error_replies(node):
    """The Zenoh callback answers every query, also garbage, with ok=false and a reason."""
    from schemas.codec import decode_message, encode_message

    replies = []
    for payload in (b"\xc1 not msgpack", encode_message({"op": "segment", "source": "w",
                                                         "target": "nowhere"})):
        q = mock.MagicMock()
        q.payload.to_bytes.return_value = payload
        q.reply.side_effect = lambda key, data: replies.append(decode_message(data))
        node.queries.on_query(q)
    assert [r["ok"] for r in replies] == [False, False]
    assert "unknown frame 'nowhere'" in replies[1]["error"]
    assert all(isinstance(r["t2"], int) and r["t3"] >= r["t2"] for r in replies)


def test_a_composition_fed_in_any_order_equals_compose():
    rng = np.random.default_rng(9)
    parts = []
    for i in range(4):
        g = Graph()
        g.add_static(f"f{i}", f"f{i + 1}", rng.normal(size=3),
                     geo.rotvec_to_quat(rng.normal(size=3)), pos_std_m=0.01 if i != 2 else None)
        parts.append(g.pose(f"f{i}", f"f{i + 1}"))
    whole = compose(parts, 3)
    chain = Composition(4)
    for i in (2, 0, 3):
        chain.add(i, parts[i])
    with pytest.raises(ValueError, match=r"\[1\] missing"):
        chain.result(3)
    chain.add(1, parts[1])
    with pytest.raises(ValueError, match="already added"):
        chain.add(1, parts[1])
    assert chain.result(3).path == whole.path == [f"f{i}" for i in range(5)]
    for order in itertools.permutations(range(4)):
        chain = Composition(4)
        for i in order:
            chain.add(i, parts[i])
        r = chain.result(3)
        np.testing.assert_allclose(r.position, whole.position, atol=1e-12)
        assert geo.quat_angle(r.quaternion, whole.quaternion) < 1e-12
        np.testing.assert_allclose(r.covariance, whole.covariance, atol=1e-15)
    single = compose(parts[:1], 3)
    single.position[0] += 1.0  # the composed result does not alias its segments
    assert not np.allclose(single.position, parts[0].position)
    exact = [parts[1], parts[2]]  # only the first has a covariance: it passes through
    assert compose(exact, 3).covariance is not parts[1].covariance
