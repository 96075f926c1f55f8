"""Hostile peers: a plain Zenoh session in the test forges what an agent, a service or a
realm would say.  The realm keeps serving the honest services, no need is redirected, and
every refusal is counted and said."""

from __future__ import annotations

import threading
import time

import msgpack
import pytest
import zenoh
from agent_helpers.harness import agent, first_from, poll, service
from conftest import endpoint, free_port
from test_agent_robustness import register_raw, wait_token

from agent import Client
from agent.protocol import keys
from agent.protocol import query as proto
from agent.protocol.registration import (
    Match,
    control_message,
    parse_snapshot,
    register_request,
    reply_ok,
    snapshot_message,
)
from agent.runtime.session import open_session, query
from agent.sdk import realm as realm_module
from agent.sdk.service import SEQ_WINDOW, Service
from schemas.codec import encode_descriptor, encode_pose
from schemas.models import ServiceDescriptor

PRODUCER = ("--ability", "pose", "--edge", "ivy/world", "alice/head")


def snapshot(session: zenoh.Session, realm: str, agent_id: str):
    """The agent's snapshot, asked once its token is seen (a new session's links)."""
    wait_token(session, keys.agent_token(realm, agent_id))
    for reply in query(session, keys.agent_services(realm, agent_id), 5.0):
        if reply.ok is not None:
            return parse_snapshot(reply.ok.payload.to_bytes(), agent_id)
    raise AssertionError(f"agent {agent_id} did not answer with its snapshot")


def matched_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """A publisher on ``key`` once Zenoh says a subscriber of it is reachable: a fresh
    session's put before its links are up is delivered to nobody."""
    publisher = session.declare_publisher(key)
    matched = threading.Event()
    listener = publisher.declare_matching_listener(
        lambda status: matched.set() if status.matching else None)
    if not publisher.matching_status.matching and not matched.wait(10.0):
        raise AssertionError(f"no subscriber of {key} reachable after 10 s")
    listener.undeclare()
    return publisher


def counts_grow(proc, source: str) -> None:
    """The consumer's count of samples from ``source`` grows from now on."""
    mark = proc.mark
    first = proc.wait_for(lambda e: e.get("event") == "counts", after=mark)["counts"]
    proc.wait_for(lambda e: e.get("event") == "counts"
                  and e["counts"].get(source, 0) > first.get(source, 0) + 20, after=proc.mark)


@pytest.fixture
def honest(processes, realm):
    """An agent, a producer ``cam`` and a consumer ``fusion`` connected to it."""
    ep = endpoint(free_port())
    host = agent(processes, realm, "hostA", ep)
    cam = service(processes, realm, "cam", "hostA", ep, *PRODUCER)
    consumer = service(processes, realm, "fusion", "hostA", ep, "--need", "head")
    consumer.wait_for(lambda e: first_from(e, "cam"))
    return ep, host, cam, consumer


def test_forged_control_never_redirects_a_need(honest, realm) -> None:
    ep, _, _, consumer = honest
    evil = Match(keys.data(realm, "evil", "x", "pose"), "evil", "x", "pose", "pose6d",
                 ("ivy/world", "alice/head"), {})
    with open_session(connect=[ep]) as s:
        epoch = snapshot(s, realm, "hostA").epoch
        ctl = keys.control(realm, "hostA", "fusion")
        # the audit's message (real epoch, seq 2**62) signed with guessed keys, unsigned,
        # and in the old unsigned format
        for key in (bytes(16), None, b"k" * 16):
            s.put(ctl, control_message(key, epoch, 2**62, "head", [evil], True))
            s.put(ctl, control_message(key, epoch, 2**62, "head", [], False))
        s.put(ctl, msgpack.packb({"v": 1, "op": "connect", "epoch": epoch, "seq": 2**62,
                                  "need": "head", "matches": [evil.to_wire()]}))
        consumer.wait_log("refused (signature")
        publisher = s.declare_publisher(evil.key)
        for _ in range(50):
            publisher.put(encode_pose(time.time_ns(), [9, 9, 9], [0, 0, 0, 1]))
            time.sleep(0.01)
        counts_grow(consumer, "cam")
    assert not any(e.get("event") == "match" and evil.key in e["keys"]
                   for e in consumer.events)
    assert not any(e.get("event") == "first" and e.get("source") == "x"
                   for e in consumer.events)


def test_reregistering_a_running_instance_needs_its_key(honest, realm) -> None:
    ep, host, _, consumer = honest
    with open_session(connect=[ep]) as s:
        instance = snapshot(s, realm, "hostA").status["cam"]["instance"]
        forged = ServiceDescriptor(service_id="cam", agent_id="hostA", abilities=[
            {"name": "pose", "type": "pose6d", "edge": ["ivy/world", "alice/head"],
             "attributes": {"frequency_hz": 10_000, "latency_s": 0.0}}])
        ok, error = register_raw(s, realm, "hostA", register_request(
            encode_descriptor(forged), instance, 99, {}, key=bytes(16), challenge=bytes(16)))
        assert not ok and "does not carry its key" in error, error
        ok, error = register_raw(s, realm, "hostA", register_request(
            encode_descriptor(forged), instance, 99, {}))
        assert not ok and "does not carry its key" in error, error
        attrs = snapshot(s, realm, "hostA").services["cam"].abilities[0].attributes
        assert attrs.frequency_hz != 10_000
    host.wait_log("registration refused: it names the running instance")
    counts_grow(consumer, "cam")


def test_forged_summaries_and_replies_are_refused_and_bounded(honest, realm,
                                                              monkeypatch) -> None:
    ep, _, _, _ = honest
    monkeypatch.setattr(realm_module, "MAX_AGENTS", 50)
    with open_session(connect=[ep]) as s, Client(realm=realm, connect=[ep]) as c:
        assert c.pose("ivy/world", "alice/head").position[0] == pytest.approx(0.1)
        # a summary naming another agent than its key's, and a flood of distinct agents
        s.put(keys.agent_supernode(realm, "evil"), msgpack.packb(
            {"v": 1, "agent": "hostA", "frames": ["ivy/world"], "rev": 2**62}))
        for i in range(300):
            s.put(keys.agent_supernode(realm, f"ghost{i}"), msgpack.packb(
                {"v": 1, "agent": f"ghost{i}", "frames": [f"g{i}/x"], "rev": 1}))
        # a reply on hostA's query key that names another agent
        fake = s.declare_queryable(keys.all_agent_queries(realm), lambda q: (
            q.reply(keys.agent_query(realm, "hostA"), msgpack.packb(
                {"v": 1, "ok": True, "agent": "evil", "t2": 1, "t3": 2})), q.drop()))
        poll(lambda: c.tracker.refused >= 1, what="the mismatched summary refused")
        for _ in range(20):
            r = c.pose("ivy/world", "alice/head", at=None)
            assert r.position[0] == pytest.approx(0.1)
        answers = list(c.queries.answers(proto.clock_request()))
        assert [(a, r.get("agent")) for a, r, _, _ in answers] == [("hostA", "hostA")]
        fake.undeclare()
        view = c.tracker.view()
        assert len(view.summaries) <= 50 and not any(a.startswith("ghost") for a in view.alive)
        assert c.queries.refused > 0


def test_a_sample_a_day_ahead_does_not_poison_the_edge(honest, realm) -> None:
    ep, host, _, _ = honest
    with open_session(connect=[ep]) as s, Client(realm=realm, connect=[ep]) as c:
        forger = matched_publisher(s, keys.data(realm, "hostA", "cam", "pose"))
        forger.put(encode_pose(time.time_ns() + 86_400 * 10**9, [5, 5, 5], [0, 0, 0, 1]))
        host.wait_log("ahead of this clock")
        for _ in range(10):
            r = c.pose("ivy/world", "alice/head")
            assert r.position[0] == pytest.approx(0.1)
            assert abs(r.t_ns - time.time_ns()) < 5 * 10**9
        got: list = []
        sub = c.subscribe("ivy/world", "alice/head", got.append)
        # the subscription's Zenoh subscriber exists once it streams; a put before then
        # reaches nobody, so the forger puts again until the subscription has refused one
        poll(lambda: len(got) > 0, what="the subscription streaming")

        def refused_and_streaming() -> bool:
            if sub.refused == 0:
                forger.put(encode_pose(time.time_ns() + 86_400 * 10**9, [5, 5, 5],
                                       [0, 0, 0, 1]))
            return sub.refused >= 1 and len(got) > 50

        poll(refused_and_streaming, what="the stream going on")
        assert sub.status == "streaming"
        assert all(p.position[0] == pytest.approx(0.1) for p in got)


def test_a_forged_snapshot_epoch_does_not_freeze_the_realm(processes, realm) -> None:
    ea, eb = endpoint(free_port()), endpoint(free_port())
    host_a = agent(processes, realm, "hostA", ea)
    agent(processes, realm, "hostB", eb, connect=(ea,))
    consumer = service(processes, realm, "fusion", "hostA", ea, "--need", "head")
    with open_session(connect=[ea]) as s:
        wait_token(s, keys.agent_token(realm, "hostB"))
        real = snapshot(s, realm, "hostB")
        for epoch, revision in ((2**63 - 1, 1), (real.epoch, 2**62)):
            s.put(keys.agent_services(realm, "hostB"), snapshot_message(
                real.info, epoch, revision, []))
        host_a.wait_log("is not the agent's current run; asking it")
    # a real update of hostB after the forgeries still reaches hostA's matching
    service(processes, realm, "cam", "hostB", eb, *PRODUCER)
    consumer.wait_for(lambda e: first_from(e, "cam"))


@pytest.fixture
def camera_on_b(processes, realm):
    """hostA (endpoint, process) with a consumer matched to the camera of hostB."""
    ea, eb = endpoint(free_port()), endpoint(free_port())
    host_a = agent(processes, realm, "hostA", ea)
    agent(processes, realm, "hostB", eb, connect=(ea,))
    consumer = service(processes, realm, "fusion", "hostA", ea, "--need", "head")
    service(processes, realm, "cam", "hostB", eb, *PRODUCER)
    consumer.wait_for(lambda e: first_from(e, "cam"))
    return ea, host_a, consumer


def test_a_forged_snapshot_revision_jump_is_confirmed_first(camera_on_b, realm) -> None:
    """A snapshot of hostB under its real epoch, 5,000 revisions ahead and with no services,
    would take hostB's camera from hostA's matching until hostB's own revisions caught up
    (for good when they counted one per change); it is more than the time passed allows,
    so hostA asks hostB, which answers with its camera."""
    ea, host_a, consumer = camera_on_b
    with open_session(connect=[ea]) as s:
        real = snapshot(s, realm, "hostB")
        s.put(keys.agent_services(realm, "hostB"), snapshot_message(
            real.info, real.epoch, real.revision + 5000, []))
        host_a.wait_log("is not the agent's current run; asking it")
    mark = consumer.mark
    counts_grow(consumer, "cam")
    assert not any(e.get("event") == "match" and not e["keys"] for e in consumer.events[mark:])


def test_a_forged_snapshot_within_the_slack_is_not_applied(camera_on_b, realm) -> None:
    """A snapshot of hostB under its real epoch, a few milliseconds ahead and with no
    services, is within what the time passed allows; anyone can read the epoch, and here
    the forger also answers for hostB.  hostA applies only what hostB's ask is answered
    with, and refuses two different answers: the consumer keeps hostB's camera."""
    ea, host_a, consumer = camera_on_b
    mark = consumer.mark
    with open_session(connect=[ea]) as s:
        real = snapshot(s, realm, "hostB")
        forged = snapshot_message(real.info, real.epoch, real.revision + 5, [])
        key = keys.agent_services(realm, "hostB")
        answering = s.declare_queryable(key, lambda q: (q.reply(key, forged), q.drop()))
        matched_publisher(s, key).put(forged)
        host_a.wait_log("another process answers for it")
        answering.undeclare()
    counts_grow(consumer, "cam")
    assert not any(e.get("event") == "match" and not e["keys"] for e in consumer.events[mark:])


class _Recorder(Service):
    """A Service whose control handling is driven by the test (no session)."""

    def __init__(self) -> None:
        super().__init__("fusion", realm="lab", agent="hostA")
        self.need("head", type="pose6d", edge=("ivy/world", "*/head"))
        self.applied: list[tuple[str, ...]] = []
        self.presence.token = object()  # as if declared: the test has no session
        self.links.apply = lambda need, matches, satisfied, standby=(): self.applied.append(
            tuple(m.key for m in matches))


def test_control_needs_the_key_the_epoch_and_the_next_seq() -> None:
    svc, key = _Recorder(), bytes(range(16))
    m = Match(keys.data("lab", "hostB", "cam", "pose"), "hostB", "cam", "pose", "pose6d",
              None, {})
    # before the register reply: kept, applied once the reply gives the key
    svc.control.on_control(control_message(key, 7, 1, "head", [m], True))
    assert svc.applied == [] and svc.control_refused == {"no key yet": 1}
    svc.presence.agent_present = True
    svc.presence.on_register_reply(0, reply_ok(7, key), True)
    assert svc.applied == [(m.key,)]
    svc.control.on_control(control_message(key, 8, 2, "head", [], True))         # another epoch
    svc.control.on_control(control_message(key, 7, 2 + SEQ_WINDOW + 60_000, "head", [],
                                           True))  # a jump far beyond the time passed
    svc.control.on_control(control_message(bytes(16), 7, 2, "head", [], True))   # a wrong key
    svc.control.on_control(control_message(key, 7, 1, "head", [], True))         # a replay
    assert svc.applied == [(m.key,)]
    assert svc.control_refused == {"no key yet": 1, "epoch": 1, "seq": 1, "signature": 1}
    svc.control.on_control(control_message(key, 7, 5, "head", [], False))  # a few lost: fine
    assert svc.applied == [(m.key,), ()]
    svc.close()


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


#: what a flood of forged ids may add to a process's memory (the bounds keep ~1,000 agents)
FLOOD_RSS_MB = 60


def test_floods_of_distinct_ids_keep_every_process_within_bounds(honest, realm) -> None:
    ep, host, cam, consumer = honest
    procs = {"agent": host, "producer": cam, "consumer": consumer}
    with open_session(connect=[ep]) as s:
        snapshot(s, realm, "hostA")
        before = {name: rss_mb(p.popen.pid) for name, p in procs.items()}
        info = snapshot(s, realm, "hostA").info
        for i in range(3000):
            s.put(keys.agent_supernode(realm, f"ghost{i}"), msgpack.packb(
                {"v": 1, "agent": f"ghost{i}", "frames": [f"g{i}/x{j}" for j in range(20)],
                 "rev": 1}))
            s.put(keys.agent_services(realm, f"ghost{i}"), snapshot_message(
                {**info, "agent_id": f"ghost{i}"}, 1, 1, []))
        s.put(keys.data(realm, "hostA", "cam", "pose"), b"\x00" * (40 * 2**20),
              congestion_control=zenoh.CongestionControl.BLOCK)
        counts_grow(consumer, "cam")
        after = {name: rss_mb(p.popen.pid) for name, p in procs.items()}
    grew = {name: round(after[name] - before[name], 1) for name in procs}
    print(f"RSS before {before} MB, growth after the flood {grew} MB")
    assert all(g < FLOOD_RSS_MB for g in grew.values()), grew
    assert all(p.popen.poll() is None for p in procs.values())
