"""A need moved from one ability to another keeps the old subscription until the new one
delivers (make before break), and drops it at once when nothing replaces it; a need's
standby delivers only while its chosen link is silent, at once when it falls silent."""

from __future__ import annotations

import logging
import time
import types

import agent.sdk.needs as needs
from agent.protocol.registration import Match
from agent.runtime.logs import RateLimitedLog
from agent.sdk.needs import NeedHandle, NeedLinks
from schemas.codec import Measurement, encode_measurement
from schemas.models import Need


class _Cond:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None

    def notify_all(self) -> None:
        return None


class _Subscriber:
    def __init__(self, key: str, undeclared: list[str]) -> None:
        self.key, self._undeclared = key, undeclared

    def undeclare(self) -> None:
        self._undeclared.append(self.key)


def _links(on_sample=None) -> tuple[NeedLinks, NeedHandle, list[str]]:
    undeclared: list[str] = []
    declared: list[str] = []

    def declare(key: str, callback: object) -> _Subscriber:
        declared.append(key)
        return _Subscriber(key, undeclared)

    session = types.SimpleNamespace(declare_subscriber=declare, declared=declared)
    svc = types.SimpleNamespace(agent_id="a", realm="r", service_id="app", session=session,
                                now_ns=time.time_ns, _needs={}, _cond=_Cond(), closed=False)
    links = NeedLinks(svc, RateLimitedLog(logging.getLogger("test")))
    need = NeedHandle(Need(name="tag", type="pose6d", edge=("lab/*", "markers/t")),
                      on_sample)
    svc._needs["tag"] = need
    return links, need, undeclared


def _match(service: str, **attributes: float) -> Match:
    return Match(f"uma/r/data/a/{service}/tag", "a", service, "tag", "pose6d",
                 ("lab/cam", "markers/t"), attributes)


def test_the_old_stream_delivers_until_the_new_one_does():
    links, need, undeclared = _links()
    left, right = _match("cam-left"), _match("cam-right")
    links.apply(need, (left,), True)
    old = need.links[left.key]
    links.apply(need, (right,), True)
    new = need.links[right.key]
    assert links._current(need, old) and undeclared == []  # still delivering
    assert links._current(need, new)  # the new one's first sample ...
    assert undeclared == [left.key] and not links._current(need, old)  # ... ends the old


def test_a_need_left_without_matches_drops_its_stream_at_once():
    links, need, undeclared = _links()
    left = _match("cam-left")
    links.apply(need, (left,), True)
    old = need.links[left.key]
    links.apply(need, (), False)
    assert undeclared == [left.key] and not links._current(need, old)


def test_a_replaced_stream_is_dropped_after_retire_s_without_a_successor(monkeypatch):
    links, need, undeclared = _links()
    left, right = _match("cam-left"), _match("cam-right")
    links.apply(need, (left,), True)
    old = need.links[left.key]
    links.apply(need, (right,), True)
    later = needs.time.monotonic() + needs.RETIRE_S + 1
    monkeypatch.setattr(needs.time, "monotonic", lambda: later)
    assert not links._current(need, old) and undeclared == [left.key]


def _sample(links: NeedLinks, need: NeedHandle, match: Match) -> None:
    link = need.links.get(match.key) or need.standby[match.key]
    links._samples.put((need, link, encode_measurement(Measurement(
        type="pose6d", t_ns=time.time_ns(), position=[0.0, 0.0, 1.0],
        quaternion=[0.0, 0.0, 0.0, 1.0]))))


def _until(cond, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.005)
    return cond()


def _standby_pair(chosen_hz: float) -> tuple[NeedLinks, NeedHandle, Match, Match, list[str]]:
    got: list[str] = []
    links, need, _ = _links(lambda m: got.append(m.source))
    left, right = _match("cam-left", frequency_hz=chosen_hz), _match("cam-right")
    links.apply(need, (left,), True, standby=(right,))
    assert set(need.standby) == {right.key} and need.matches == (left,)
    links.start()
    return links, need, left, right, got


def test_a_standby_is_held_while_the_chosen_stream_sends():
    links, need, left, right, got = _standby_pair(chosen_hz=0.5)  # silent after 3 s
    try:
        _sample(links, need, left)
        _sample(links, need, right)
        assert _until(lambda: got == ["cam-left"])
        time.sleep(0.2)
        assert got == ["cam-left"]
    finally:
        links.close()


def test_a_standby_stands_in_at_once_when_the_chosen_stream_falls_silent():
    links, need, left, right, got = _standby_pair(chosen_hz=20.0)  # silent after 75 ms
    try:
        _sample(links, need, left)
        _sample(links, need, right)
        # the held standby sample is delivered once the chosen link is late, without
        # waiting for the standby's next sample ...
        assert _until(lambda: got == ["cam-left", "cam-right"])
        _sample(links, need, right)  # ... and the next while it stays silent
        assert _until(lambda: got == ["cam-left", "cam-right", "cam-right"])
        _sample(links, need, left)  # the chosen one is back: delivered
        assert _until(lambda: len(got) == 4 and got[-1] == "cam-left")
    finally:
        links.close()


def test_the_agent_promoting_the_standby_needs_no_new_subscription():
    links, need, undeclared = _links()
    left, right = _match("cam-left"), _match("cam-right")
    links.apply(need, (left,), True, standby=(right,))
    declared = list(links._svc.session.declared)
    links.apply(need, (right,), True, standby=(left,))  # the two swap
    assert links._svc.session.declared == declared == [left.key, right.key]
    assert set(need.links) == {right.key} and set(need.standby) == {left.key}
    links.apply(need, (right,), True)  # no standby wanted any more: dropped
    assert undeclared == [left.key] and not need.standby


def test_through_an_agent_a_silent_chosen_stream_is_stood_in_for_before_any_rematch(realm):
    """Two services offer the same edge; the better one stops publishing and says nothing
    (no re-advertisement, no predicate the agent could find failing): without a standby
    the need's stream would stop; with one, the other service's samples keep coming while
    the agent still has the silent one chosen."""
    from conftest import endpoint, free_port

    from agent.daemon.agent import Agent
    from agent.daemon.settings import AgentSettings
    from agent.sdk.service import Service

    ep = endpoint(free_port())
    agent = Agent(AgentSettings(realm=realm, agent_id="hostA", listen=[ep]))
    agent.start()
    got: list[str] = []
    try:
        with Service("good", realm=realm, agent="hostA", connect=[ep]) as good, \
                Service("fair", realm=realm, agent="hostA", connect=[ep]) as fair, \
                Service("app", realm=realm, agent="hostA", connect=[ep]) as app:
            edge = ("lab/cam", "markers/t")
            outs = {"good": good.ability("tag", type="pose6d", edge=edge, pos_std_m=0.001,
                                         frequency_hz=50),
                    "fair": fair.ability("tag", type="pose6d", edge=edge, pos_std_m=0.01,
                                         frequency_hz=50)}
            app.need("tag", type="pose6d", edge=("lab/*", "markers/t"), prefer="pos_std_m",
                     standby=1, on_sample=lambda m: got.append(m.source))
            for svc in (good, fair, app):
                svc.start()
            (m,) = app.wait_matched("tag", timeout=10)
            assert m.service_id == "good"
            assert _until(lambda: app._needs["tag"].standby_matches(), timeout=10)

            def publish(names: tuple[str, ...], n: int) -> None:
                for _ in range(n):
                    for name in names:
                        outs[name].publish(time.time_ns(), [0.0, 0.0, 1.0], [0, 0, 0, 1])
                    time.sleep(0.02)

            publish(("good", "fair"), 50)
            assert _until(lambda: "good" in got)
            assert got.count("fair") < got.count("good")  # held while the chosen one sends
            before = len(got)
            publish(("fair",), 50)  # the chosen one falls silent
            assert _until(lambda: got[before:].count("fair") >= 25)
            assert app.matches("tag")[0].service_id == "good"  # no re-match was needed
    finally:
        agent.close()
