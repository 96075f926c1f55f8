"""The compact wire form of supernode summaries: it reads exactly as the summary
``summarize`` builds, whatever the graph, and is smaller; a malformed one is refused."""

from __future__ import annotations

import pytest

from agent.protocol.query import decode_summary, parse_summary, summary_to_wire
from agent.srg import Graph
from agent.srg.supernode import summarize
from schemas.codec import encode_message


def graph_with_a_cycle() -> Graph:
    """Two cameras see one object: its best path to the world differs by error function."""
    g = Graph()
    g.add_static("room/world", "room/marker", [1, 0, 0], [0, 0, 0, 1], pos_std_m=0.001)
    g.add_static("room/world", "h/cam0", [0, 1, 2], [0, 0, 0, 1], pos_std_m=0.001)
    g.add_static("room/world", "h/cam1", [1, 1, 2], [0, 0, 0, 1], pos_std_m=0.004)
    g.add_measurement("h/cam0", "h/obj", 1, [0, 0, 1], [0, 0, 0, 1], source="s/a",
                      latency_s=0.02, frequency_hz=30.0, pos_std_m=0.001)
    g.add_measurement("h/cam1", "h/obj", 1, [0, 0, 1], [0, 0, 0, 1], source="s/b",
                      latency_s=0.005, frequency_hz=100.0, pos_std_m=0.01)
    g.add_measurement("h/obj", "h/tip", 1, [0, 0, 0.1], [0, 0, 0, 1], source="s/c",
                      frequency_hz=100.0)
    return g


def summary() -> dict:
    s = summarize(graph_with_a_cycle(), ["room/world", "room/marker"])
    return s | {"agent": "A", "rev": 3, "instance": "0123456789ab"}


def test_compact_summary_reads_as_spelt_out_and_is_smaller() -> None:
    s = summary()
    compact = summary_to_wire(s)
    assert any(isinstance(link[2], list) for link in compact["links"])  # errors disagree
    assert any(isinstance(link[2], int) for link in compact["links"])  # and agree
    assert decode_summary(encode_message(compact)) == parse_summary(s)
    assert len(encode_message(compact)) < len(encode_message(s)) / 3


@pytest.mark.parametrize("damage", [
    lambda m: m["links"].append([0, 999, 0]),
    lambda m: m["links"].append([0, 1, [0, 0]]),
    lambda m: m["links"].append([0, 1, -1]),
    lambda m: m["links"].append({"a": 0, "b": 1}),
    lambda m: m["components"].append([0, "1"]),
    lambda m: m.update(paths="none"),
])
def test_malformed_compact_summary_is_refused(damage) -> None:
    msg = summary_to_wire(summary())
    damage(msg)
    with pytest.raises(ValueError, match="summary"):
        parse_summary(msg)
