"""The agent's caches of answers: all-static answers, the same as a fresh computation at any
time and dropped when a static edge changes; answers at the latest time, kept only until
the next sample or change."""

from __future__ import annotations

import re
from unittest import mock

import numpy as np

from agent.daemon.srg_node import SrgNode

S = 1_000_000_000


def node() -> SrgNode:
    edges = [{"parent": "w", "child": "cam", "position": [1.0, 0.0, 2.0],
              "quaternion": [0.0, 0.0, 0.38268343, 0.92387953], "pos_std_m": 0.01},
             {"parent": "cam", "child": "rig", "position": [0.0, 0.5, 0.0],
              "quaternion": [0.0, 0.0, 0.0, 1.0]}]
    return SrgNode(mock.MagicMock(), "lab", "A", edges)


def ask(n: SrgNode, t, source="rig", target="w"):
    return n.handle({"op": "segment", "source": source, "target": target, "t": t,
                     "error": "hops"})


def test_a_cached_static_answer_equals_a_fresh_one_at_every_time():
    n = node()
    first = ask(n, 5 * S)
    assert [h[1] for h in n.queries.answers.values()] == [None], "an all-static answer is cached"
    for t in (5 * S, 7 * S + 3, None):
        with mock.patch.object(n, "now_ns", return_value=9 * S):
            cached = ask(n, t)
            n.queries.answers.clear()
            fresh = ask(n, t)
        assert cached == fresh
        assert cached["result"]["t_ns"] == (t if t is not None else 9 * S)
        assert all(e["t_ns"] == cached["result"]["t_ns"] for e in cached["result"]["edges"])
    assert first["result"]["t_ns"] == 5 * S  # restamping did not touch the cached original


def test_changing_a_static_edge_drops_the_cached_answer():
    n = node()
    before = ask(n, S)["result"]["position"]
    n.graph.add_static("cam", "rig", [0.0, 0.7, 0.0], [0.0, 0.0, 0.0, 1.0], source="config")
    after = ask(n, S)["result"]["position"]
    assert not np.allclose(before, after)
    n.queries.answers.clear()
    assert ask(n, S)["result"]["position"] == after


def test_measured_and_detailed_answers_are_not_cached():
    n = node()
    n.graph.add_measurement("rig", "head", S, [0.0, 0.0, 0.1], [0.0, 0.0, 0.0, 1.0])
    ask(n, S, "w", "head")
    n.handle({"op": "segment", "source": "w", "target": "rig", "t": S, "error": "hops",
              "details": True})
    assert not n.queries.answers


def test_a_latest_answer_is_reused_only_until_the_next_sample():
    n = node()
    n.graph.add_measurement("rig", "head", S, [0.0, 0.0, 0.1], [0.0, 0.0, 0.0, 1.0])
    first = ask(n, None, "w", "head")["result"]
    assert ask(n, None, "w", "head")["result"] is first  # nothing new: the same answer
    assert ask(n, S, "w", "head")["result"] is not first  # an explicit time is computed
    n.graph.add_measurement("rig", "head", 2 * S, [0.0, 0.0, 0.2], [0.0, 0.0, 0.0, 1.0])
    second = ask(n, None, "w", "head")["result"]
    assert second["t_ns"] == 2 * S and second["position"] != first["position"]
    n.graph.add_static("cam", "rig", [0.0, 0.7, 0.0], [0.0, 0.0, 0.0, 1.0], source="config")
    third = ask(n, None, "w", "head")["result"]  # a changed edge: computed again
    assert third["t_ns"] == 2 * S and third["position"] != second["position"]
    n.queries.answers.clear()
    assert ask(n, None, "w", "head")["result"] == third


def test_summaries_are_asked_for_again_periodically(monkeypatch):
    """A summary put before this agent's subscription reached its author is never sent
    again: the worker asks every agent for its summary every RESYNC_S."""
    import time

    from agent.daemon import peer_frames

    monkeypatch.setattr(peer_frames, "RESYNC_S", 0.05)
    n = node()
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            asked = [c for c in n.session.get.call_args_list
                     if c.args and c.args[0] == "uma/lab/agent/*/supernode"]
            if len(asked) >= 2:  # the one at start and a resync
                break
            time.sleep(0.05)
        assert len(asked) >= 2
    finally:
        n.close()


def test_a_summary_every_receiver_would_refuse_is_reported_by_its_agent(caplog):
    """Receivers refuse summaries of more than MAX_SUMMARY_FRAMES frames or links; the
    agent that publishes one says so, since elsewhere it only shows as unknown frames."""
    n = node()
    # the node's own thread may republish as soon as the graph changes: the limit is
    # lowered first, so whichever republish comes first says so
    with mock.patch("agent.protocol.query.MAX_SUMMARY_FRAMES", 20), caplog.at_level("WARNING"):
        n.peers.frames["B"] = {"w", "cam", "rig"}  # shared with agent B: 15 x 3 - 6 links
        for i in range(12):
            n.graph.add_static("rig", f"tool{i}", [0.0, 0.0, 0.1 * i], [0.0, 0.0, 0.0, 1.0])
        n.publisher.republish_if_changed()
    # said once (rate-limited), by whichever republish came first: 13-15 frames by then
    said = re.search(r"has (\d+) frames and (\d+) links \(frames x 3 boundary frames\)",
                     caplog.text)
    assert said and int(said.group(2)) > 20, caplog.text
    assert "receivers refuse more than 20" in caplog.text
    caplog.clear()
    n.graph.add_static("rig", "tool99", [0.0, 0.0, 2.0], [0.0, 0.0, 0.0, 1.0])
    with caplog.at_level("WARNING"):  # within the limit: nothing to say
        n.publisher.republish_if_changed()
    assert "receivers refuse" not in caplog.text
