"""The pose-query protocol's two sides agree (agent.protocol.query): what a client encodes
an agent parses back, and what an agent answers a client reads, or refuses with a reason."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest

from agent import geometry as geo
from agent.daemon.srg_node import SrgNode
from agent.protocol import query as proto
from schemas.codec import decode_message, encode_message


def test_a_segments_request_parses_back_to_each_agents_part():
    parts = {"A": proto.SegmentRequest("w", "cam", "latency", 5, details=True),
             "B": proto.SegmentRequest("cam", "head", "1 + hops")}
    msg = proto.decode_request(proto.segments_request(parts))
    assert proto.parse_request(msg, "A") == parts["A"]
    assert proto.parse_request(msg, "B") == parts["B"]
    assert proto.parse_request(msg, "C") is None
    assert isinstance(proto.parse_request(proto.decode_request(proto.clock_request()), "A"),
                      proto.ClockRequest)


@pytest.fixture
def node():
    quat = geo.rotvec_to_quat(np.array([0.0, 0.0, 0.3])).tolist()
    n = SrgNode(mock.MagicMock(), "lab", "A",
                [{"parent": "w", "child": "cam", "position": [1.0, 2.0, 3.0],
                  "quaternion": quat, "pos_std_m": 0.01, "rot_std_rad": 0.002}])
    yield n
    n.close()


def _sent(reply):
    """A reply as the client gets it: stamped, encoded, decoded."""
    return proto.decode_reply(proto.stamped(reply, "hostA", 10, 12))


def test_an_agents_answer_reads_back_with_its_edge_details(node):
    request = proto.segments_request({"A": proto.SegmentRequest("w", "cam", "hops",
                                                                details=True)})
    reply = _sent(node.handle(proto.decode_request(request)))
    assert proto.reply_times(reply) == (10, 12)
    pose, edges = proto.read_segment_reply(reply, lambda t: t - 7)
    np.testing.assert_allclose(pose.position, [1.0, 2.0, 3.0])
    assert pose.edges[0]["owner"] == "A" and pose.t_ns == reply["result"]["t_ns"] - 7
    edge = proto.edge_from_wire(edges[0])
    assert (edge.parent, edge.child, edge.source, edge.static) == ("w", "cam", "config", True)
    assert edge.position == [1.0, 2.0, 3.0] and edge.covariance.shape == (6, 6)


def test_a_refusal_and_an_unreadable_answer_say_why(node):
    refused = _sent(proto.error_reply(LookupError("unknown frame 'zz'")))
    with pytest.raises(proto.RefusedError, match="unknown frame 'zz'"):
        proto.read_segment_reply(refused, lambda t: t)
    garbage = proto.decode_reply(b"\xc1 not msgpack")
    with pytest.raises(proto.RefusedError, match="unreadable answer"):
        proto.read_segment_reply(garbage, lambda t: t)
    assert proto.reply_times(garbage) is None
    with pytest.raises(ValueError, match="no result"):
        proto.read_segment_reply({"ok": True}, lambda t: t)


@pytest.mark.parametrize("change, reason", [
    ({"parent": ""}, "parent"),
    ({"source": 3}, "source must be a string"),
    ({"covariance": [1.0] * 35}, "covariance"),
    ({"position": [0.0, "x", 0.0]}, "position"),
])
def test_malformed_edge_details_name_the_field(change, reason):
    good = {"parent": "w", "child": "cam", "source": "config", "static": True,
            "attributes": {}, "position": [0.0, 0.0, 0.0], "quaternion": [0.0, 0.0, 0.0, 1.0]}
    proto.edge_from_wire(good)
    with pytest.raises(ValueError, match=reason):
        proto.edge_from_wire({**good, **change})


def test_a_measured_edge_without_a_key_reads_as_none():
    e = proto.edge_from_wire(decode_message(encode_message(
        {"parent": "w", "child": "cam", "source": "t/pose", "static": False,
         "attributes": {"frequency_hz": 50.0}, "key": ""})))
    assert e.key is None and e.covariance is None and e.attributes == {"frequency_hz": 50.0}


def test_a_route_request_and_its_composed_answer_read_back_and_malformed_ones_say_why():
    parts = {"A": proto.SegmentRequest("w", "cam", "hops", 5),
             "B": proto.SegmentRequest("cam", "head", "hops", 7)}
    request = proto.parse_request(decode_message(proto.segments_request(parts, "route", True)),
                                  "A")
    assert request == proto.RouteRequest(parts, True)
    assert list(request.parts) == ["A", "B"]  # route order kept
    plain = proto.parse_request(decode_message(proto.segments_request(parts, "route")), "A")
    assert plain.compose is False
    with pytest.raises(ValueError, match="1 to 16 entries"):
        proto.parse_request({"op": "route", "parts": {}}, "A")
    assert proto.route_result({"ok": True, "parts": {}}) is None
    result = {"source": "w", "target": "head"}
    assert proto.route_result({"ok": True, "route": {"result": result,
                                                     "times": {"A": None, "B": 7}}}) == (
        result, {"A": None, "B": 7})
    with pytest.raises(ValueError, match="times must be"):
        proto.route_result({"ok": True, "route": {"result": result, "times": {"A": "x"}}})
    with pytest.raises(ValueError, match="a map with a result"):
        proto.route_result({"ok": True, "route": []})
