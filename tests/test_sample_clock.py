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
    """The receiver's first round trips all slow (read 100 ms late, as on a host busy
    starting its services: offsets 50 ms off): no sample passes on with such a time, the
    ones held meanwhile pass on later, none lost."""
    from agent.sdk.sampleclock import BURST, MAX_ERROR_NS
    ep_a, ep_c = endpoint(free_port()), endpoint(free_port())
    agent(processes, realm, "hostA", ep_a, env={"UMA_CLOCK_SKEW_NS": str(SKEW_A)})
    agent(processes, realm, "hostC", ep_c, connect=(ep_a,),
          env={"UMA_CLOCK_SKEW_NS": str(SKEW_C)})
    rx = service(processes, realm, "rx", "hostC", ep_c, "--need", "head", "--each-sample",
                 "--late-round-trips", str(BURST + 15), env={"UMA_CLOCK_SKEW_NS": str(SKEW_C)})
    service(processes, realm, "cam", "hostA", ep_a, "--ability", "pose", "--rate", "50",
            "--skew-ns", str(SKEW_A))
    first = rx.wait_for(lambda ev: ev.get("event") == "sample", timeout=60)
    after = rx.events.index(first)
    rx.wait_for(lambda ev: ev.get("event") == "sample" and ev["recv_ns"] > first["recv_ns"]
                + 1_000_000_000, after=after)
    samples = [ev for ev in rx.events[after:] if ev.get("event") == "sample"]
    # the receiver's host clock at arrival (recv_ns is the system clock) minus the stamp:
    # the transport's latency if the stamp was moved, latency + 40 ms if it was not, 50 ms
    # less with an offset of the late round trips
    ages_ms = [(ev["recv_ns"] + SKEW_C - ev["t_ns"]) / 1e6 for ev in samples]
    assert min(ages_ms) > -MAX_ERROR_NS / 1e6, ages_ms[:20]
    assert 0.0 <= statistics.median(ages_ms) < 10.0, ages_ms[:20]
    assert all(0 <= ev["time_error_ns"] <= MAX_ERROR_NS for ev in samples)
    assert [ev["seq"] for ev in samples] == list(range(first["seq"], first["seq"] + len(samples)))


class _Queries:
    """Round trips to an agent 20 ms ahead, all their delay on the way back (each offset
    off by half of it, as when this host is too busy to read a reply in time): ``delays``
    (ns) in turn, the last one from then on."""

    def __init__(self, offsets, delays) -> None:
        self.offsets, self.delays, self.n = offsets, list(delays), 0

    def probe(self, agent: str) -> bool:
        delay = self.delays[min(self.n, len(self.delays) - 1)]
        self.n += 1
        t1 = 1_000_000_000 * self.n
        self.offsets.add(agent, t1, t1 + 20_000_000, t1 + 20_000_000, t1 + delay)
        return True


def _clocks(ready=None) -> SampleClocks:
    import logging
    return SampleClocks("hostC", "r", lambda: 0, RateLimitedLog(logging.getLogger("t")),
                        on_ready=(ready.append if ready is not None else lambda a: None))


def test_samples_are_held_until_their_agents_offset_is_known_within_the_bound() -> None:
    """The first round trips all slow (180 ms: the offset 90 ms off): the samples are held,
    round trips come fast until one is fast enough, and the held ones pass on then, in the
    order they came, with the good offset and its bound."""
    from agent.sdk import sampleclock
    ready: list[str] = []
    clocks = _clocks(ready)
    assert clocks.to_local("hostC", 123) == 123          # this host's own agent
    assert clocks.error_ns("hostC") == 0
    queries = _Queries(clocks.offsets, [180_000_000] * (sampleclock.BURST + 3) + [1_000_000])
    clocks._due = {"hostA": 0.0}
    clocks._since = {"hostA": time.monotonic()}
    clocks._measure(queries, "hostA")                    # the burst
    assert abs(clocks.offsets.offset("hostA") - 20_000_000) > 80_000_000
    assert clocks.to_local("hostA", 10**12) is None
    for i in range(3):
        clocks.hold("hostA", i, 100)
    assert clocks.status()["hostA"]["state"] == "measuring"
    assert clocks.status()["hostA"]["held"] == 3 and clocks.unsynced == 3
    waits = []
    while clocks.status()["hostA"]["state"] == "measuring":
        assert queries.n < 20
        before = time.monotonic()
        clocks._measure(queries, "hostA")
        waits.append(clocks._due["hostA"] - before)
    assert queries.n == sampleclock.BURST + 4
    assert max(waits[:-1]) < sampleclock.FAST_EVERY_S + 0.05   # asked fast meanwhile
    assert ready == ["hostA"] and clocks.released() == [0, 1, 2] and not clocks.holding
    assert clocks.to_local("hostA", 10**12) == 10**12 - 19_500_000
    assert clocks.error_ns("hostA") == 500_000 and clocks.dropped == 0
    assert clocks.status()["hostA"] == {"state": "synced", "offset_ms": 19.5,
                                        "error_ms": 0.5, "held": 0}


def test_samples_pass_on_with_their_bound_said_when_no_round_trip_is_fast_enough(
        caplog) -> None:
    import logging

    from agent.sdk import sampleclock
    caplog.set_level(logging.INFO, "uma.service")
    clocks = _clocks()
    queries = _Queries(clocks.offsets, [10_000_000] * (sampleclock.BURST + 1) + [1_000_000])
    clocks._due = {"hostA": 0.0}
    clocks._since = {"hostA": time.monotonic()}
    clocks._measure(queries, "hostA")
    assert clocks.to_local("hostA", 10**12) is None       # 5 ms off at most: held
    clocks.hold("hostA", "s", 10)
    clocks._since["hostA"] -= sampleclock.SYNC_TIMEOUT_S  # the time to reach it is up
    clocks._measure(queries, "hostA")
    assert "no round trip within 5 s was fast enough" in caplog.text
    assert clocks.status()["hostA"]["state"] == "coarse"
    assert clocks.released() == ["s"] and clocks.error_ns("hostA") == 5_000_000
    assert clocks.to_local("hostA", 10**12) == 10**12 - 15_000_000
    clocks._measure(queries, "hostA")                     # a fast one at last
    assert clocks.status()["hostA"]["state"] == "synced" and "now within 2 ms" in caplog.text


def test_held_samples_are_bounded_the_oldest_dropped_and_counted(monkeypatch) -> None:
    from agent.sdk import sampleclock
    monkeypatch.setattr(sampleclock, "HELD_SAMPLES", 4)
    monkeypatch.setattr(sampleclock, "HELD_BYTES", 1000)
    clocks = _clocks()
    for i in range(6):
        clocks.hold("hostA", i, 10)
    clocks.hold("hostA", 6, 995)              # 0 and 1 went, this one's bytes: 2 to 5 go
    clocks.hold("hostB", "b", 10)
    assert clocks.dropped == 6 and clocks.unsynced == 8
    clocks._passing.add("hostA")
    clocks.offsets.add("hostA", 1_000, 21_000, 21_000, 2_000)
    assert clocks.released() == [6] and clocks.holding          # hostB's still held
    clocks._closed.set()             # no thread measures here
    clocks.follow(None, ["hostA"])   # hostB no longer matched: its samples go too
    assert not clocks.holding and clocks.dropped == 7
    clocks.close()


def test_the_fastest_early_round_trip_sets_the_offset_for_good() -> None:
    """A burst on a busy host may be slow throughout: the early round trips, a fifth of a
    second apart, find a fast one, and the filter keeps it through all the slower ones."""
    from agent.sdk import sampleclock
    clocks = _clocks()
    queries = _Queries(clocks.offsets, [10_000_000] * sampleclock.BURST + [200_000]
                       + [10_000_000])
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
