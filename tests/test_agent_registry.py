"""The registration protocol and the realm view without Zenoh: messages and rules."""

from __future__ import annotations

import logging

import msgpack
import pytest

from agent.daemon.realm_view import RealmView
from agent.protocol import keys
from agent.protocol.registration import (
    PENDING_TIMEOUT_S,
    Match,
    Registration,
    UnverifiedControlError,
    control_message,
    control_need,
    parse_control,
    parse_register_request,
    parse_reply,
    parse_snapshot,
    register_request,
    reply_error,
    reply_ok,
    snapshot_message,
)
from agent.runtime.logs import RateLimitedLog
from schemas.codec import DecodeError, encode_descriptor
from schemas.models import ServiceDescriptor

R = "lab"


def desc(sid: str, agent: str, *abilities: str, latency: float = 0.01) -> ServiceDescriptor:
    return ServiceDescriptor(service_id=sid, agent_id=agent, abilities=[
        {"name": a, "type": "pose6d", "edge": ["ivy/world", "alice/head"],
         "attributes": {"latency_s": latency}} for a in abilities])


def snapshot(agent: str, revision: int, *descs: ServiceDescriptor, epoch: int = 1):
    data = snapshot_message({"agent_id": agent}, epoch, revision,
                            [{"descriptor": encode_descriptor(d), "instance": "x"}
                             for d in descs])
    return parse_snapshot(data, agent)


def test_register_request_round_trip_and_refusals() -> None:
    d = desc("cam", "hostA", "pose")
    data = register_request(encode_descriptor(d), "inst1", 3, {"head": ["k1"]})
    reg = parse_register_request(data, "hostA")
    assert (reg.descriptor, reg.instance, reg.revision, reg.connected) == (
        d, "inst1", 3, {"head": ["k1"]})
    with pytest.raises(DecodeError, match="registered with agent 'hostB'"):
        parse_register_request(data, "hostB")
    bad = register_request(msgpack.packb({"v": 1, "service_id": "cam", "agent_id": "hostA",
                                          "abilities": [{"name": "p"}]}), "i", 1, {})
    with pytest.raises(DecodeError, match="service 'cam': invalid service descriptor"):
        parse_register_request(bad, "hostA")
    with pytest.raises(DecodeError, match="revision"):
        parse_register_request(register_request(encode_descriptor(d), "i", -1, {}), "hostA")
    key = bytes(range(16))
    assert parse_reply(reply_ok(5, key)) == (True, "", False, 5, key, False, None)
    assert parse_reply(reply_error("nope", retry=True)) == (False, "nope", True, None, None,
                                                            False, None)
    assert parse_reply(reply_error("held", renew=True)).renew
    assert parse_reply(reply_ok(5, key, challenge=bytes(16))).challenge == bytes(16)
    # a registration proves the key without carrying it, over a challenge and its content
    signed = parse_register_request(register_request(
        encode_descriptor(d), "inst1", 3, {"head": ["k1"]}, key=key, challenge=bytes(16)),
        "hostA")
    assert signed.proof is not None and signed.proof.verifies(key)
    assert not signed.proof.verifies(bytes(16)) and key not in data
    other = parse_register_request(register_request(
        encode_descriptor(d), "inst1", 4, {"head": ["k1"]}, key=key, challenge=bytes(16)),
        "hostA")
    assert other.proof is not None and other.proof.mac != signed.proof.mac
    with pytest.raises(DecodeError, match="control key"):
        parse_reply(msgpack.packb({"v": 1, "ok": True, "epoch": 5}))


def test_control_round_trip_and_keys_outside_the_realm() -> None:
    m = Match(keys.data(R, "hostB", "cam", "pose"), "hostB", "cam", "pose", "pose6d",
              ("ivy/world", "alice/head"), {"latency_s": 0.01})
    key = bytes(range(16))
    ctl = parse_control(control_message(key, 7, 2, "head", [m], True), R, key)
    assert (ctl.epoch, ctl.seq, ctl.need, ctl.matches, ctl.satisfied) == (7, 2, "head", (m,),
                                                                          True)
    other = Match(keys.data("elsewhere", "hostB", "cam", "pose"), "hostB", "cam", "pose",
                  "pose6d", None, {})
    with pytest.raises(DecodeError, match="not a data key of realm 'lab'"):
        parse_control(control_message(key, 7, 3, "head", [other], True), R, key)
    with pytest.raises(DecodeError, match="expected a signed envelope"):
        parse_control(msgpack.packb({"v": 1, "op": "explode", "body": b"", "mac": 1}), R, key)


def test_control_must_be_signed_with_the_services_key() -> None:
    m = Match(keys.data(R, "hostB", "cam", "pose"), "hostB", "cam", "pose", "pose6d",
              None, {})
    key, wrong = bytes(range(16)), bytes(16)
    data = control_message(key, 7, 2, "head", [m], True)
    assert control_need(data) == "head"
    for k in (wrong, None):
        with pytest.raises(UnverifiedControlError):
            parse_control(data, R, k)
    with pytest.raises(UnverifiedControlError):
        parse_control(control_message(None, 7, 2, "head", [m], True), R, key)
    tampered = msgpack.unpackb(data)
    tampered["body"] = tampered["body"].replace(b"head", b"hexd")
    with pytest.raises(UnverifiedControlError):
        parse_control(msgpack.packb(tampered), R, key)
    with pytest.raises(DecodeError, match="more than 64"):
        parse_control(control_message(key, 7, 3, "head", [m] * 65, True), R, key)


def test_snapshot_drops_bad_entries_but_keeps_good_ones() -> None:
    good = desc("cam", "hostB", "pose")
    data = snapshot_message({"agent_id": "hostB"}, 1, 4, [
        {"descriptor": encode_descriptor(good)},
        {"descriptor": b"junk"},
        {"descriptor": encode_descriptor(desc("spy", "hostC", "pose"))},
        "not a map"])
    snap = parse_snapshot(data, "hostB")
    assert list(snap.services) == ["cam"] and len(snap.errors) == 3
    assert "names agent 'hostC'" in snap.errors[1]
    with pytest.raises(DecodeError, match="published as 'hostX'"):
        parse_snapshot(data, "hostX")


def test_remote_ability_needs_both_snapshot_and_live_token() -> None:
    view = RealmView(R, "hostA")
    view.agent_alive("hostB")
    assert view.apply_snapshot(snapshot("hostB", 1, desc("cam", "hostB", "pose"))) is False
    assert len(view.index) == 0  # descriptor known, token not seen yet
    assert view.service_alive("hostB", "cam") is True
    assert list(view.index.by_key) == [keys.data(R, "hostB", "cam", "pose")]
    assert view.service_gone("hostB", "cam") is True  # SIGKILL: token DELETE
    assert len(view.index) == 0
    view.service_alive("hostB", "cam")
    view.service_alive("hostB", "mic")  # a service with no descriptor: nothing to keep
    assert view.agent_gone("hostB") is False  # cam's own token is live: kept
    assert list(view.index.by_key) == [keys.data(R, "hostB", "cam", "pose")]
    assert view.service_gone("hostB", "cam") is True  # it goes with its token
    assert len(view.index) == 0


def test_an_agent_gone_takes_the_services_without_a_live_token_and_gets_them_back() -> None:
    view = RealmView(R, "hostA")
    view.agent_alive("hostB")
    view.service_alive("hostB", "cam")
    view.apply_snapshot(snapshot("hostB", 1, desc("cam", "hostB", "pose"),
                                 desc("mic", "hostB", "pose")))
    view.service_alive("hostB", "mic")
    view.service_gone("hostB", "mic")  # its token went through the frozen agent
    assert view.agent_gone("hostB") is False  # cam's token is live: kept, matchable
    assert list(view.index.by_key) == [keys.data(R, "hostB", "cam", "pose")]
    view.service_alive("hostB", "mic")
    view.agent_alive("hostB")  # back: its snapshot of the same revision applies again
    assert view.apply_snapshot(snapshot("hostB", 1, desc("cam", "hostB", "pose"),
                                        desc("mic", "hostB", "pose"))) is True
    assert len(view.index) == 2


def test_stale_snapshots_are_ignored_and_changes_applied() -> None:
    view = RealmView(R, "hostA")
    view.agent_alive("hostB")
    view.service_alive("hostB", "cam")
    view.apply_snapshot(snapshot("hostB", 2, desc("cam", "hostB", "pose", latency=0.02)))
    assert view.apply_snapshot(snapshot("hostB", 1, desc("cam", "hostB", "pose"))) is False
    offer = view.index.by_key[keys.data(R, "hostB", "cam", "pose")]
    assert offer.values["latency_s"] == 0.02
    assert view.apply_snapshot(snapshot("hostB", 3, desc("cam", "hostB", "pose", "raw")))
    assert len(view.index) == 2
    # a restarted agent (new epoch) starts its revisions again
    assert view.apply_snapshot(snapshot("hostB", 1, desc("cam", "hostB", "raw"), epoch=2))
    assert list(view.index.by_key) == [keys.data(R, "hostB", "cam", "raw")]
    # an agent whose token is not (or no longer) alive is not applied
    assert view.apply_snapshot(snapshot("hostC", 1, desc("x", "hostC", "pose"))) is False


def test_local_services_needs_and_pending_registrations() -> None:
    view = RealmView(R, "hostA")
    d = ServiceDescriptor(service_id="fusion", agent_id="hostA", needs=[
        {"name": "head", "type": "pose6d", "edge": ["ivy/world", "*/head"]}],
        abilities=desc("x", "hostA", "fused").abilities)
    assert view.register_local(Registration(d, "i1", 1, {}), now=100.0)
    assert [r.name for r in view.requirements()] == ["head"]
    assert len(view.index) == 0  # abilities offered only once its token is seen
    assert view.expired_pending(100.0 + PENDING_TIMEOUT_S + 0.1) == ["fusion"]
    view.service_alive("hostA", "fusion")
    assert view.expired_pending(1e9) == []
    assert len(view.index) == 1
    assert view.register_local(Registration(d, "i1", 2, {}), now=101.0) is False  # same
    assert view.service_gone("hostA", "fusion")
    assert view.local == {} and view.requirements() == [] and len(view.index) == 0


def test_rate_limited_log_counts_what_it_swallowed(caplog) -> None:
    rl = RateLimitedLog(logging.getLogger("uma.test"), interval=60)
    with caplog.at_level(logging.WARNING, logger="uma.test"):
        assert rl.warning("key a", "bad") is True
        assert rl.warning("key a", "bad") is False
        assert rl.warning("key b", "bad") is True
    assert [r.getMessage() for r in caplog.records] == ["key a: bad", "key b: bad"]
    rl.interval = 0
    with caplog.at_level(logging.WARNING, logger="uma.test"):
        rl.warning("key a", "bad")
    assert caplog.records[-1].getMessage() == "key a: bad (1 similar since)"


def test_agent_query_keys_round_trip() -> None:
    """The client's selector of every agent's queryable and the parse of a reply's key."""
    sel = keys.all_agent_queries(R)
    assert keys.agent_query(R, "hostB") == sel.replace("*", "hostB")
    assert keys.parse_agent_query(keys.agent_query(R, "hostB"), R) == "hostB"
    for other in (keys.agent_supernode(R, "hostB"), keys.agent_query("elsewhere", "hostB"),
                  keys.agent_token(R, "hostB"), f"{keys.realm_root(R)}/agent/a/b/query"):
        assert keys.parse_agent_query(other, R) is None, other
