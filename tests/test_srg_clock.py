"""The NTP-style offset estimate with its minimum-delay filter."""

from __future__ import annotations

import random

import pytest

from agent.protocol.query import skew_from_env
from agent.sdk.clock import ClockOffsets


def test_offset_from_a_symmetric_round_trip():
    c = ClockOffsets()
    # agent 5 s ahead; 100 us each way; 20 us processing
    t1 = 1_000_000_000
    c.add("b", t1, t1 + 100_000 + 5 * 10**9, t1 + 120_000 + 5 * 10**9, t1 + 220_000)
    assert c.offset("b") == 5 * 10**9
    assert c.to_remote("b", 10) == 10 + 5 * 10**9 and c.to_local("b", 5 * 10**9) == 0
    assert c.best("b").delay_ns == 200_000


def test_min_delay_sample_wins_over_asymmetric_slow_ones():
    c = ClockOffsets()
    skew = -3_000_000
    # slow round trips with asymmetric delays bias the estimate by up to half the asymmetry
    c.add("b", 0, 900_000 + skew, 900_000 + skew, 1_000_000)  # biased by +400 us
    c.add("b", 2_000_000, 2_050_000 + skew, 2_060_000 + skew, 2_110_000)  # symmetric, fast
    c.add("b", 3_000_000, 3_100_000 + skew, 3_100_000 + skew, 3_800_000)  # biased by -300 us
    assert c.offset("b") == skew


def test_impossible_samples_are_refused_and_unknown_agents_have_no_offset():
    c = ClockOffsets()
    assert c.add("b", 10, 5, 4, 20) is None  # replied before receiving
    assert c.add("b", 10, 5, 6, 9) is None  # received before sending
    assert c.offset("b") is None and c.to_remote("b", 7) == 7
    c.add("b", 0, 10, 10, 20)
    c.forget("b")
    assert not c.known("b")


def test_old_samples_age_out_even_when_nothing_new_arrives(monkeypatch):
    """The remembered best sample gives way when it (or any sample of the window) ages
    out, without a new sample to trigger it."""
    import agent.sdk.clock as clock

    now = [100.0]
    monkeypatch.setattr(clock.time, "monotonic", lambda: now[0])
    c = ClockOffsets(max_age_s=10.0)
    c.add("b", 0, 50, 50, 100)  # fast: the best, offset 0
    now[0] = 105.0
    c.add("b", 1000, 1600 + 7, 1600 + 7, 2200)  # slow, offset 7
    assert c.offset("b") == 0
    now[0] = 111.0  # the first sample is 11 s old now
    assert c.offset("b") == 7
    now[0] = 116.0
    assert c.offset("b") is None and not c.known("b")


def test_skew_env(monkeypatch):
    monkeypatch.setenv("UMA_CLOCK_SKEW_NS", "123")
    assert skew_from_env() == 123
    monkeypatch.setenv("UMA_CLOCK_SKEW_NS", "soon")
    with pytest.raises(ValueError, match="UMA_CLOCK_SKEW_NS"):
        skew_from_env()
    monkeypatch.delenv("UMA_CLOCK_SKEW_NS")
    assert skew_from_env() == 0


def test_best_is_the_minimum_delay_of_the_window_as_samples_come_and_go():
    """The best sample is kept up to date as samples arrive (not rescanned each time): it
    must equal the minimum-delay sample of the last ``window`` samples, also when the best
    is pushed out of the window."""
    rng = random.Random(7)
    clock = ClockOffsets(window=4)
    window: dict[str, list[int]] = {"a": [], "b": []}
    for _ in range(400):
        agent = rng.choice("ab")
        delay = rng.randrange(1, 50)
        t1 = rng.randrange(0, 10**9)
        sample = clock.add(agent, t1, t1 + 5, t1 + 5, t1 + delay)
        assert sample is not None and sample.delay_ns == delay
        window[agent] = (window[agent] + [delay])[-4:]
        for name, delays in window.items():
            best = clock.best(name)
            assert (best.delay_ns if best else None) == (min(delays) if delays else None)
