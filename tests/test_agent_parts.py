"""Unit tests of the daemon's small shared parts: the StreamHub (one subscriber per data
key, fanned out) and the Worker loop (agent.runtime.worker)."""

from __future__ import annotations

import threading
import time
from unittest import mock

from agent.daemon.streams import StreamHub
from agent.runtime.worker import WakeLoop, Worker


def _sample(data: bytes) -> mock.Mock:
    sample = mock.Mock()
    sample.payload.to_bytes.return_value = data
    return sample


def test_one_subscriber_per_key_fans_out_to_every_listener() -> None:
    session = mock.MagicMock()
    hub = StreamHub(session)
    a: list[bytes] = []
    b: list[bytes] = []
    stop_a = hub.listen("uma/r/data/A/s/pose", a.append)
    stop_b = hub.listen("uma/r/data/A/s/pose", b.append)
    assert session.declare_subscriber.call_count == 1  # the second listener shares it
    deliver = session.declare_subscriber.call_args[0][1]
    deliver(_sample(b"x"))
    assert a == [b"x"] and b == [b"x"]
    stop_a()
    deliver(_sample(b"y"))
    assert a == [b"x"] and b == [b"x", b"y"]
    assert not session.declare_subscriber.return_value.undeclare.called
    stop_b()  # the last listener: the subscriber goes
    assert session.declare_subscriber.return_value.undeclare.called
    assert hub.subscribed() == set()


def test_a_listener_that_raises_does_not_starve_the_others() -> None:
    session = mock.MagicMock()
    hub = StreamHub(session)
    got: list[bytes] = []

    def broken(data: bytes) -> None:
        raise ValueError("bug")
    hub.listen("k", broken)
    hub.listen("k", got.append)
    session.declare_subscriber.call_args[0][1](_sample(b"z"))
    assert got == [b"z"]


def _wait(cond, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.005)


def test_worker_runs_calls_in_order_ticks_and_settles_after_each_batch() -> None:
    log: list[str] = []
    ticks = threading.Event()
    worker = Worker("test-worker", "test", mock.Mock(), ticks.set, 0.01,
                    settle=(lambda: log.append("settle"),))
    worker.start()
    try:
        for i in range(3):
            worker.put(log.append, f"call {i}")
        _wait(lambda: "call 2" in log and "settle" in log[log.index("call 2"):]
              and ticks.is_set())
        calls = [x for x in log if x.startswith("call")]
        assert calls == ["call 0", "call 1", "call 2"]
    finally:
        worker.stop(1.0)
    assert not worker.alive()


def test_worker_logs_a_failing_call_and_goes_on() -> None:
    logger = mock.Mock()
    done = threading.Event()

    def fails() -> None:
        raise RuntimeError("bug")
    worker = Worker("test-worker", "test", logger, lambda: None, 1.0)
    worker.start()
    try:
        worker.put(fails)
        worker.put(done.set)
        assert done.wait(5.0)
        logger.exception.assert_called_once_with("%s: %s failed", "test", "fails")
    finally:
        worker.stop(1.0)


def test_worker_names_a_call_that_does_not_return() -> None:
    """A call blocked inside Zenoh (a stalled session) shows as stuck, with its name and for
    how long; short calls and an idle worker do not."""
    release, entered = threading.Event(), threading.Event()

    def resync_agent_tokens() -> None:
        entered.set()
        release.wait(10.0)
    worker = Worker("test-worker", "test", mock.Mock(), lambda: None, 1.0)
    worker.start()
    try:
        assert worker.stuck(0.0) is None  # idle
        worker.put(resync_agent_tokens)
        assert entered.wait(5.0)
        _wait(lambda: worker.stuck(0.1) is not None)
        name, took = worker.stuck(0.1)
        assert name == "resync_agent_tokens" and took > 0.1
        assert worker.stuck(60.0) is None  # not yet past a longer limit
        release.set()
        _wait(lambda: worker.stuck(0.0) is None)
    finally:
        release.set()
        worker.stop(1.0)


def test_the_agents_own_keys_share_one_wildcard_subscriber() -> None:
    """Real Zenoh: local keys come through one ``uma/r/data/A/*/*`` subscriber, remote ones
    through their own; a local key nobody listens to is not delivered."""
    from agent.runtime.session import open_session

    session = open_session("peer", [], [])
    try:
        hub = StreamHub(session, local="uma/r/data/A/*/*")
        got: dict[str, list[bytes]] = {"a": [], "b": [], "remote": []}
        stops = [hub.listen("uma/r/data/A/s/a", got["a"].append),
                 hub.listen("uma/r/data/A/s/b", got["b"].append),
                 hub.listen("uma/r/data/B/s/x", got["remote"].append)]
        assert hub._local_subscriber is not None
        assert hub._keys["uma/r/data/A/s/a"].subscriber is None  # served by the wildcard
        assert hub._keys["uma/r/data/B/s/x"].subscriber is not None
        for key, data in (("uma/r/data/A/s/a", b"1"), ("uma/r/data/A/s/b", b"2"),
                          ("uma/r/data/A/s/unheard", b"3"), ("uma/r/data/B/s/x", b"4")):
            session.put(key, data)
        _wait(lambda: got == {"a": [b"1"], "b": [b"2"], "remote": [b"4"]})
        stops[0]()
        assert hub._local_subscriber is not None  # b still listens
        stops[1]()
        assert hub._local_subscriber is None  # the last local listener took it along
        # a witness on the same key and session: once it has the sample, the hub would
        # have had it too if it still listened
        seen: list[bytes] = []
        witness = session.declare_subscriber("uma/r/data/A/s/b",
                                             lambda s: seen.append(s.payload.to_bytes()))
        session.put("uma/r/data/A/s/b", b"5")
        stops[2]()
        assert hub.subscribed() == set()
        _wait(lambda: seen == [b"5"])
        witness.undeclare()
        assert got["b"] == [b"2"]
    finally:
        hub.close()
        session.close()


def test_a_local_listener_that_falls_behind_gets_the_newest_samples_not_a_backlog(
        monkeypatch) -> None:
    """Real Zenoh: while the local streams' listener is held up, at most ``LOCAL_RING``
    samples wait for it; the oldest go, the newest arrive (the agent stays current)."""
    from agent.daemon import streams
    from agent.runtime.session import open_session

    monkeypatch.setattr(streams, "LOCAL_RING", 4)
    session = open_session("peer", [], [])
    release, entered = threading.Event(), threading.Event()
    got: list[bytes] = []

    def slow(data: bytes) -> None:
        entered.set()
        release.wait(10.0)
        got.append(data)
    try:
        hub = StreamHub(session, local="uma/r/data/A/*/*")
        hub.listen("uma/r/data/A/s/a", slow)
        session.put("uma/r/data/A/s/a", b"0")
        assert entered.wait(5.0)  # the drain thread now waits in the listener with 0
        for i in range(1, 20):
            session.put("uma/r/data/A/s/a", str(i).encode())
        time.sleep(0.2)
        release.set()
        _wait(lambda: got and got[-1] == b"19")
        assert got[0] == b"0" and len(got) <= 1 + 4  # 0, then at most the ring's newest
        assert got[1:] == [str(i).encode() for i in range(20 - len(got) + 1, 20)]
    finally:
        release.set()
        hub.close()
        session.close()


def test_local_samples_come_in_batches_unless_a_listener_is_timely(monkeypatch) -> None:
    """Real Zenoh: with only batch listeners on local keys, the local streams' thread
    pauses after each batch (the samples wait in the ring) and ``flush_local`` hands the
    waiting ones over at once, in order; a timely listener ends the pauses."""
    from agent.daemon import streams
    from agent.runtime.session import open_session

    monkeypatch.setattr(streams, "LOCAL_PAUSE_S", 30.0)
    session = open_session("peer", [], [])
    try:
        hub = StreamHub(session, local="uma/r/data/A/*/*")
        batch: list[bytes] = []
        hub.listen("uma/r/data/A/s/a", batch.append, timely=False)
        session.put("uma/r/data/A/s/a", b"0")
        _wait(lambda: batch == [b"0"])  # the first one wakes the thread, which then pauses
        time.sleep(0.1)
        for i in range(1, 6):
            session.put("uma/r/data/A/s/a", str(i).encode())
        time.sleep(0.3)
        assert batch == [b"0"]  # waiting in the ring
        hub.flush_local()
        assert batch == [str(i).encode() for i in range(6)]
        timely: list[bytes] = []
        hub.listen("uma/r/data/A/s/b", timely.append)  # ends the pause
        for data in (b"x", b"y"):
            session.put("uma/r/data/A/s/b", data)
        _wait(lambda: timely == [b"x", b"y"])
    finally:
        hub.close()
        session.close()


def test_the_digest_is_put_only_while_someone_listens_and_a_stream_moved() -> None:
    """Real Zenoh: nothing is put (nor taken as put) before a subscriber is there; then the
    newest samples, once per new sample."""
    from agent.daemon.digest import StreamDigest
    from agent.protocol import keys
    from agent.protocol.digest import read_digest
    from agent.runtime.session import open_session

    session = open_session("peer", [], [])
    newest = {("s", "a"): b"sample"}
    seen = [1]
    digest = StreamDigest(session, "r", "A", lambda: newest, lambda: seen[0])
    try:
        digest.publish()  # nobody listens
        got: list[dict[str, bytes]] = []
        sub = session.declare_subscriber(keys.agent_digest("r", "A"), lambda smp: got.append(
            read_digest(smp.payload.to_bytes(), "r", "A")))

        def published() -> bool:
            digest.publish()
            return bool(got)
        _wait(published)  # the sample seen before the subscriber came is put now
        digest.publish()  # no new sample since
        time.sleep(0.2)
        assert len(got) == 1 and list(got[0].values()) == [b"sample"]
        seen[0] = 2
        digest.publish()
        _wait(lambda: len(got) == 2)
        sub.undeclare()
    finally:
        digest.close()
        session.close()


def test_wake_loop_runs_its_step_when_woken_says_why_a_step_failed_and_stops() -> None:
    log = mock.Mock()
    calls: list[int] = []
    ran = threading.Event()

    def step() -> None:
        calls.append(len(calls))
        ran.set()
        if len(calls) == 1:
            raise RuntimeError("bug")
    loop = WakeLoop("test-wake", step, log, "test step", period_s=30.0)
    loop.start()
    try:
        for expected in (1, 2):
            loop.wake()
            assert ran.wait(5.0)
            ran.clear()
            assert len(calls) == expected
        log.warning.assert_called_once_with("test step", "RuntimeError: bug")
    finally:
        loop.close(2.0)
    assert loop.stopping and not loop._thread.is_alive()
    loop.wake()
    time.sleep(0.05)
    assert len(calls) == 2  # closed: no more steps
