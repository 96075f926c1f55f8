"""A need moved from one ability to another keeps the old subscription until the new one
delivers (make before break), and drops it at once when nothing replaces it."""

from __future__ import annotations

import logging
import types

import agent.sdk.needs as needs
from agent.protocol.registration import Match
from agent.runtime.logs import RateLimitedLog
from agent.sdk.needs import NeedHandle, NeedLinks
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


def _links() -> tuple[NeedLinks, NeedHandle, list[str]]:
    undeclared: list[str] = []
    session = types.SimpleNamespace(
        declare_subscriber=lambda key, callback: _Subscriber(key, undeclared))
    svc = types.SimpleNamespace(agent_id="a", realm="r", service_id="app", session=session,
                                now_ns=lambda: 0, _needs={}, _cond=_Cond())
    links = NeedLinks(svc, RateLimitedLog(logging.getLogger("test")))
    need = NeedHandle(Need(name="tag", type="pose6d", edge=("lab/*", "markers/t")), None)
    svc._needs["tag"] = need
    return links, need, undeclared


def _match(service: str) -> Match:
    return Match(f"uma/r/data/a/{service}/tag", "a", service, "tag", "pose6d",
                 ("lab/cam", "markers/t"), {})


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
