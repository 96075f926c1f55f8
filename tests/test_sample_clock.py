"""A need's samples arrive with their times on the receiving host's clock: real agents and
services in separate processes, two hosts whose clocks are 20 ms ahead and 20 ms behind
(``UMA_CLOCK_SKEW_NS`` for everything of a host), the publisher stamping on its host's clock."""

from __future__ import annotations

import statistics
import time

from agent_helpers.harness import agent, service
from conftest import endpoint, free_port

from agent.runtime.logs import RateLimitedLog
from agent.sdk.sampleclock import SampleClocks

SKEW_A = 20_000_000    # the publisher's host
SKEW_C = -20_000_000   # the receiver's host


def test_samples_of_another_host_are_moved_onto_the_receivers_clock(processes, realm) -> None:
    ep_a, ep_c = endpoint(free_port()), endpoint(free_port())
    agent(processes, realm, "hostA", ep_a, env={"UMA_CLOCK_SKEW_NS": str(SKEW_A)})
    agent(processes, realm, "hostC", ep_c, connect=(ep_a,),
          env={"UMA_CLOCK_SKEW_NS": str(SKEW_C)})
    rx = service(processes, realm, "rx", "hostC", ep_c, "--need", "head", "--each-sample",
                 env={"UMA_CLOCK_SKEW_NS": str(SKEW_C)})
    service(processes, realm, "cam", "hostA", ep_a, "--ability", "pose", "--rate", "50",
            "--skew-ns", str(SKEW_A))
    first = rx.wait_for(lambda ev: ev.get("event") == "sample", timeout=60)
    after = rx.events.index(first)
    rx.wait_for(lambda ev: ev.get("event") == "sample" and ev["recv_ns"] > first["recv_ns"]
                + 1_000_000_000, after=after)
    samples = [ev for ev in rx.events[after:] if ev.get("event") == "sample"]
    # the receiver's host clock at arrival (recv_ns is the system clock) minus the stamp:
    # the transport's latency if the stamp was moved, latency + 40 ms if it was not
    age_ms = statistics.median((ev["recv_ns"] + SKEW_C - ev["t_ns"]) / 1e6 for ev in samples)
    assert 0.0 <= age_ms < 10.0, age_ms


def test_samples_are_held_back_until_their_agents_offset_is_known() -> None:
    import logging
    clocks = SampleClocks("hostC", "r", lambda: 0, RateLimitedLog(logging.getLogger("t")))
    assert clocks.to_local("hostC", 123) == 123          # this host's own agent
    assert clocks.to_local("hostA", 123) is None and clocks.unsynced == 1
    clocks.offsets.add("hostA", 1_000, 21_000, 21_000, 2_000)   # 19.5 us ahead, 1 us delay
    assert clocks.to_local("hostA", 1_000_000) == 1_000_000 - 19_500


def test_the_fastest_early_round_trip_sets_the_offset_for_good() -> None:
    """A burst on a busy host may be slow throughout: the early round trips, a fifth of a
    second apart, find a fast one, and the filter keeps it through all the slower ones."""
    import logging

    from agent.sdk import sampleclock

    class Queries:     # an agent 20 ms ahead, its round trips slow but for one
        def __init__(self, offsets) -> None:
            self.offsets, self.n = offsets, 0

        def probe(self, agent: str) -> bool:
            self.n += 1
            delay = 200_000 if self.n == sampleclock.BURST + 1 else 10_000_000
            t1 = 1_000_000_000 * self.n
            # the slow ones' delay all on the way back: their offsets 5 ms off
            self.offsets.add(agent, t1, t1 + 20_000_000, t1 + 20_000_000, t1 + delay)
            return True

    clocks = SampleClocks("hostC", "r", lambda: 0, RateLimitedLog(logging.getLogger("t")))
    queries = Queries(clocks.offsets)
    clocks._due = {"hostA": 0.0}
    waits = []
    for _ in range(sampleclock.EARLY + 3):
        before = time.monotonic()
        clocks._measure(queries, "hostA")
        waits.append(clocks._due["hostA"] - before)
    assert queries.n == sampleclock.BURST + sampleclock.EARLY + 2
    assert abs(clocks.offsets.offset("hostA") - 19_900_000) <= 1
    assert max(waits[:sampleclock.EARLY - 1]) < sampleclock.EARLY_EVERY_S + 0.05
    assert min(waits[sampleclock.EARLY:]) > sampleclock.REFRESH_S - 0.05
