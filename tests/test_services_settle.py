"""``uma services`` asks the agents once the set of live agents has settled: a client of an
agent takes the agent's view at its first answer; a listening peer, still discovering the
realm by itself, waits until the set stops changing."""

from __future__ import annotations

import time

from agent.sdk import inventory as services


def answers(monkeypatch, *sets: set[str]) -> list[float]:
    """Make ``live_agents`` return ``sets`` in turn (then the last one); the times it was
    asked at."""
    asked: list[float] = []

    def live(*_: object) -> set[str]:
        asked.append(time.monotonic())
        return set(sets[min(len(asked), len(sets)) - 1])

    monkeypatch.setattr(services, "live_agents", live)
    return asked


def test_a_client_of_an_agent_takes_the_first_answer_naming_agents(monkeypatch) -> None:
    asked = answers(monkeypatch, set(), {"a", "b"}, {"a", "b", "c"})
    assert services.settled_agents(None, "r", time.monotonic() + 5, 0.0) == {"a", "b"}
    assert len(asked) == 2


def test_a_listening_peer_waits_until_the_set_stops_changing(monkeypatch) -> None:
    asked = answers(monkeypatch, {"a"}, {"a", "b"}, {"a", "b", "c"})
    start = time.monotonic()
    assert services.settled_agents(None, "r", start + 5, services.SETTLE_S) == {"a", "b", "c"}
    assert asked[-1] - asked[2] >= services.SETTLE_S


def test_nobody_alive_ends_at_the_deadline(monkeypatch) -> None:
    answers(monkeypatch, set())
    start = time.monotonic()
    assert services.settled_agents(None, "r", start + 0.3, 0.0) == set()
    assert time.monotonic() - start >= 0.3
