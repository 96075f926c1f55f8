"""The client's query logic with in-process agents (their query handlers called directly,
no network): routes that pass through an agent twice, the static-segment cache, at=None."""

from __future__ import annotations

import time
from types import SimpleNamespace
from unittest import mock

import numpy as np
import pytest
import zenoh

from agent import geometry as geo
from agent.daemon.srg_node import SrgNode
from agent.protocol.query import parse_summary
from agent.sdk import realm as realm_module
from agent.sdk.client import Client
from agent.sdk.planner import RouteError, SegmentError, plan_routes
from agent.srg import Graph
from agent.srg.errorfn import error_function
from agent.srg.errors import UnreachableError
from schemas.codec import decode_message, encode_message

S = 1_000_000_000
EDGES = {  # A holds both ends of the route, B the middle: the route is A, B, A
    "A": [("w", "cam", [1.0, 0.0, 2.0], 0.2), ("rig", "head", [0.0, 0.0, 0.1], 0.5)],
    "B": [("cam", "rig", [0.5, 0.5, 0.0], -0.3)],
}


def static(parent, child, p, yaw):
    return {"parent": parent, "child": child, "position": p,
            "quaternion": geo.rotvec_to_quat(np.array([0.0, 0.0, yaw])).tolist(),
            "pos_std_m": 0.01, "rot_std_rad": 0.002}


class Realm:
    """SrgNodes on mock sessions, and a client whose queries reach them directly."""

    def __init__(self, edges):
        self.nodes = {name: SrgNode(mock.MagicMock(), "lab", name, [static(*e) for e in es])
                      for name, es in edges.items()}
        self.client = Client(realm="lab", session=mock.MagicMock())
        self.asked: list[set[str]] = []
        self.client.queries.answers = self.ask
        self.client.queries.relay = False  # each agent asked: the fan-out is what is tested
        self.publish()

    def publish(self):
        frames = {n: set(node.graph.frames()) for n, node in self.nodes.items()}
        for name, node in self.nodes.items():
            node.peers.frames = {o: f for o, f in frames.items() if o != name}
            node.publisher.republish_if_changed()
            self.client.tracker._on_token(SimpleNamespace(key_expr=f"uma/lab/agent/{name}",
                                                          kind=zenoh.SampleKind.PUT))
            self.client.tracker.take_summary(f"uma/lab/agent/{name}/supernode",
                                             node.publisher.summary)
        self.client.tracker._looked = True

    def ask(self, request, agents=()):
        """What the agents' query handlers answer (without t2/t3: same clock, no offset)."""
        self.asked.append(set(agents))
        msg = decode_message(request)
        for name in agents or self.nodes:
            t1 = time.time_ns()
            reply = self.nodes[name].handle(msg)
            if reply is not None:
                yield name, decode_message(encode_message(reply)), t1, time.time_ns()

    def close(self):
        self.client.close()
        for node in self.nodes.values():
            node.close()


@pytest.fixture
def realm_ab():
    r = Realm(EDGES)
    yield r
    r.close()


def test_a_route_through_an_agent_twice_is_asked_in_two_rounds(realm_ab):
    r = realm_ab.client.pose("w", "head", error="hops")
    assert r.path == ["w", "cam", "rig", "head"]
    assert [e["owner"] for e in r.edges] == ["A", "B", "A"]
    assert realm_ab.asked == [{"A", "B"}, {"A"}]
    whole = Graph()
    for es in EDGES.values():
        for e in es:
            s = static(*e)
            whole.add_static(s["parent"], s["child"], s["position"], s["quaternion"],
                             pos_std_m=0.01, rot_std_rad=0.002)
    ref = whole.pose("w", "head")
    np.testing.assert_allclose(r.position, ref.position, atol=1e-12)
    np.testing.assert_allclose(r.covariance, ref.covariance, rtol=1e-9, atol=1e-16)


def test_static_segments_are_cached_until_the_agent_summary_changes(realm_ab):
    c = realm_ab.client
    c.pose("w", "head", error="hops")
    realm_ab.asked.clear()
    c.pose("w", "head", error="hops")
    assert realm_ab.asked == []  # every segment static and unchanged: nobody asked
    realm_ab.nodes["B"].graph.set_attributes("cam", "rig", "config", pos_std_m=0.05)
    realm_ab.publish()
    r = c.pose("w", "head", error="hops")
    assert realm_ab.asked == [{"B"}]  # only the agent whose summary changed
    assert r.attributes["pos_std_m"] > 0.05
    c.cache_static_segments = False
    realm_ab.asked.clear()
    c.pose("w", "head", error="hops")
    assert realm_ab.asked == [{"A", "B"}, {"A"}]


def test_at_none_composes_measured_segments_at_their_latest_common_time():
    realm = Realm({"A": [("w", "cam", [1.0, 0.0, 2.0], 0.2)], "B": []})
    try:
        b = realm.nodes["B"]
        ability = _ability("pose", "cam", "head", latency_s=0.001, frequency_hz=100.0,
                           pos_std_m=0.01)
        for k in range(5):
            b.on_local_sample("tracker", ability, _sample(k * S // 100, [0.0, k * 0.1, 0.0], 0))
        realm.publish()
        r = realm.client.pose("w", "head", error="hops")
        assert r.t_ns == 4 * S // 100 and r.edges[1]["t_ns"] == r.t_ns
        r = realm.client.pose("w", "head", at=3 * S // 100 - S // 200, error="hops")
        assert r.extrapolated_s == 0.0
        np.testing.assert_allclose(
            r.position, geo.compose(*[np.array(x) for x in (
                [1.0, 0.0, 2.0], geo.rotvec_to_quat(np.array([0, 0, 0.2])), [0.0, 0.25, 0.0],
                [0, 0, 0, 1])])[0], atol=1e-12)
    finally:
        realm.close()


def _ability(name, parent, child, **attributes):
    from schemas.models import Ability

    return Ability(name=name, type="pose6d", edge=(parent, child), attributes=attributes)


def _sample(t_ns, p, yaw):
    from schemas.codec import Measurement

    return Measurement(type="pose6d", t_ns=t_ns, position=np.array(p, float),
                       quaternion=geo.rotvec_to_quat(np.array([0.0, 0.0, yaw])),
                       covariance=None)


def test_a_single_measured_segment_at_none_reports_its_sample_time():
    r = Realm({"A": []})
    try:
        node = r.nodes["A"]
        ability = _ability("pose", "w", "head", frequency_hz=100)
        for k in range(5):
            node.on_local_sample("tracker", ability, _sample(k * 10_000_000, [0, 0, k], 0.0))
        r.publish()
        res = r.client.pose("w", "head", at=None)
        assert res.t_ns == 40_000_000
        assert np.allclose(res.position, [0, 0, 4])
    finally:
        r.close()


def test_a_static_ability_becomes_a_static_edge_replaced_only_when_it_changes():
    node = SrgNode(mock.MagicMock(), "lab", "A", [])
    try:
        calib = _ability("calibration", "laser", "accel", static=True, pos_std_m=0.002,
                         covariance=[1e-6 if i in (0, 6, 11, 15, 18, 20) else 0.0
                                     for i in range(21)])  # as alignment advertises it
        node.on_local_sample("alignment", calib, _sample(5 * S, [0.1, 0, 0], 0.3))
        edge = node.graph.edge("laser", "accel", "alignment/calibration")
        assert edge.is_static
        r = node.graph.pose("laser", "accel", at=123)  # valid at any time
        assert np.allclose(r.position, [0.1, 0, 0])
        assert np.allclose(np.diag(r.covariance), 1e-6)
        assert node.graph.has_plan("laser", "accel")
        node.on_local_sample("alignment", calib, _sample(6 * S, [0.1, 0, 0], 0.3))
        assert node.graph.has_plan("laser", "accel"), "the same value must not invalidate plans"
        node.on_local_sample("alignment", calib, _sample(7 * S, [0.2, 0, 0], 0.3))
        assert np.allclose(node.graph.pose("laser", "accel", at=1).position, [0.2, 0, 0])
        node.on_ability_removed("alignment", calib)
        assert "laser" not in node.graph.frames()
    finally:
        node.close()


def test_an_unreachable_pair_names_the_departed_agents_that_held_its_frames():
    from types import SimpleNamespace

    from agent.sdk.planner import RouteError, with_departed
    from agent.srg.errors import UnreachableError

    summaries = {"A": SimpleNamespace(frames={"w", "cam"}),
                 "B": SimpleNamespace(frames={"cam", "head"}),
                 "C": SimpleNamespace(frames={"elsewhere"})}
    exc = UnreachableError("w", "head", {"w", "cam"}, {"head"})
    named = with_departed(exc, summaries, alive={"A"})
    assert isinstance(named, RouteError)
    assert "B" in str(named) and "left the realm" in str(named)
    assert "C" not in str(named).split("left the realm")[0].split("agent(s)")[1]
    assert with_departed(exc, summaries, alive={"A", "B"}) is exc


def test_a_summary_the_client_missed_is_fetched_when_the_pair_looks_unreachable(realm_ab):
    """An agent's newer summary published before the client's subscription reached it is
    never sent again: an unreachable pair makes the client ask every agent for its summary
    before giving up."""
    c = realm_ab.client
    fresh = realm_ab.nodes["B"].publisher.summary
    stale = decode_message(fresh)
    stale.update(rev=stale["rev"] - 1, links=[], boundary=[])
    c.tracker._summaries["B"] = parse_summary(stale)
    c.queries._routes.clear()
    with pytest.raises(UnreachableError):
        plan_routes(c.tracker._summaries, "w", "head", error_function("hops"))
    reply = mock.MagicMock()
    reply.ok.key_expr = "uma/lab/agent/B/supernode"
    reply.ok.payload.to_bytes.return_value = fresh
    c.session.get.return_value = [reply]
    c.session.liveliness.return_value.get.return_value = []
    assert c.pose("w", "head", error="hops").path == ["w", "cam", "rig", "head"]


def test_refresh_does_not_revive_an_agent_whose_token_was_removed(realm_ab):
    """A liveliness answer can still list a departed agent (a peer not yet done with its
    departure): only a new token of that agent makes it alive again."""
    c = realm_ab.client
    c.tracker._on_token(_token(zenoh.SampleKind.DELETE))
    listed = mock.MagicMock()
    listed.ok.key_expr = "uma/lab/agent/B"
    c.session.liveliness.return_value.get.return_value = [listed]
    c.session.get.return_value = []
    c.refresh()
    assert not c.tracker.is_alive("B")
    c.tracker._on_token(_token(zenoh.SampleKind.PUT))
    assert c.tracker.is_alive("B")


def _silent(realm, agent, meanwhile=lambda: None):
    """Make ``agent`` miss its next answer (``meanwhile`` runs while it is being asked)."""
    answer = realm.client.queries.answers

    def ask(request, agents=()):
        realm.client.queries.answers = answer
        meanwhile()
        yield from (a for a in answer(request, [n for n in agents or realm.nodes
                                                if n != agent]))
    realm.client.queries.answers = ask


def test_an_agent_that_restarts_while_it_is_asked_is_not_marked_gone(realm_ab):
    """A restarting agent declares its token before its query handler, then publishes its
    summary: a query that reached it in between goes unanswered.  Its new summary, come in
    meanwhile, says it is back; the missed answer must not mark it gone after that."""
    c = realm_ab.client
    restarted = decode_message(realm_ab.nodes["B"].publisher.summary)
    restarted.update(instance="new-instance", rev=0)
    _silent(realm_ab, "B", lambda: c.tracker.take_summary("uma/lab/agent/B/supernode",
                                                   encode_message(restarted)))
    with pytest.raises(SegmentError, match="'B' did not answer"):
        c.pose("w", "head", error="hops")
    assert c.tracker.is_alive("B")
    assert c.pose("w", "head", error="hops").path == ["w", "cam", "rig", "head"]


def test_an_agent_that_missed_an_answer_is_not_asked_until_it_shows_life(realm_ab):
    """Gone after a missed answer: the next query fails at once, naming it, rather than
    waiting for it again; its next summary (or token, or probe answer) brings it back."""
    c = realm_ab.client
    c.cache_static_segments = False  # B is asked every time
    _silent(realm_ab, "B")
    with pytest.raises(SegmentError, match="'B' did not answer"):
        c.pose("w", "head", error="hops")
    assert not c.tracker.is_alive("B")
    asked = len(realm_ab.asked)
    with pytest.raises(RouteError, match="agent\\(s\\) B left the realm"):
        c.pose("w", "head", error="hops")
    assert len(realm_ab.asked) == asked
    c.tracker.take_summary("uma/lab/agent/B/supernode", realm_ab.nodes["B"].publisher.summary)
    assert c.pose("w", "head", error="hops").path == ["w", "cam", "rig", "head"]


def _token(kind):
    s = mock.MagicMock()
    s.key_expr = "uma/lab/agent/B"
    s.kind = kind
    return s


def test_an_agent_that_missed_an_answer_is_probed_until_it_answers(realm_ab, monkeypatch):
    """Alive again as soon as it answers a probe, with no query of the application's: a
    subscription that moved off its route then moves back."""
    monkeypatch.setattr(realm_module, "PROBE_S", 0.05)
    c = realm_ab.client
    _silent(realm_ab, "B")
    with pytest.raises(SegmentError):
        c.pose("w", "head", error="hops")
    assert not c.tracker.is_alive("B")
    before = c.topology
    deadline = time.monotonic() + 10.0
    while not c.tracker.is_alive("B") and time.monotonic() < deadline:
        time.sleep(0.02)
    assert c.tracker.is_alive("B") and c.topology > before
    assert {"B"} in realm_ab.asked  # the probe, to B alone
    c.close()
    assert c.tracker._prober is None


def test_an_agent_whose_token_went_is_not_probed(realm_ab, monkeypatch):
    monkeypatch.setattr(realm_module, "PROBE_S", 0.05)
    c = realm_ab.client
    _silent(realm_ab, "B")
    with pytest.raises(SegmentError):
        c.pose("w", "head", error="hops")
    c.tracker._on_token(_token(zenoh.SampleKind.DELETE))
    asked = len(realm_ab.asked)
    # the prober ends only when it wakes and finds no suspect: once it has, B's probe
    # would have gone out had B still been one
    deadline = time.monotonic() + 10.0
    while c.tracker._prober is not None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert c.tracker._prober is None
    assert not c.tracker.is_alive("B") and len(realm_ab.asked) == asked


def test_routes_are_planned_again_only_when_a_summary_changes(realm_ab):
    c = realm_ab.client
    c.pose("w", "head", error="hops")
    with mock.patch("agent.sdk.query.plan_routes", wraps=plan_routes) as plan:
        c.pose("w", "head", error="hops")
        assert plan.call_count == 0
        realm_ab.nodes["B"].graph.set_attributes("cam", "rig", "config", pos_std_m=0.05)
        realm_ab.publish()
        c.pose("w", "head", error="hops")
        assert plan.call_count == 1
