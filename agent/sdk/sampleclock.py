"""The times of the samples a service's needs receive, on the receiving host's clock.

A publisher stamps its samples on its own host's clock, and hosts disagree: tens of
milliseconds between unsynchronised machines, as much as a fast tracker's frame period.
A service that combines streams of several hosts (an outside-in reconstruction with
cameras on two hosts) would pair the wrong frames.  So every sample from a service of
another agent is moved onto this host's clock before ``on_sample`` sees it, with the
offset of that agent's clock measured as a :class:`agent.sdk.client.Client` measures it:
NTP-style round trips to the agent's query key, the minimum-delay sample of a short window
(:mod:`agent.sdk.clock`).  The publishing service runs on its agent's host, so the agent's
clock is the sample's.  Samples of services of this service's own agent are on this host's
clock already and are left as they are.

An offset's error is at most half the delay of the round trip that measured it, and a
round trip on a host busy starting its services can take tens of milliseconds: an offset
from the first few alone may be as far off.  So an agent's samples are held back
(:meth:`SampleClocks.hold`: in arrival order, at most ``HELD_SAMPLES`` and ``HELD_BYTES``
of them per agent, the oldest dropped beyond that, counted and logged) until its offset is
known within ``MAX_ERROR_NS``, and passed on then.  Should no round trip within
``SYNC_TIMEOUT_S`` be fast enough (a slow network), they are passed on with the bound
they have, said in a warning and in :meth:`SampleClocks.status` ("coarse"); every
sample passed on carries its bound (``Measurement.time_error_ns``).

One thread measures: ``BURST`` round trips when an agent's stream is first matched, then
one every ``FAST_EVERY_S`` while the bound is not reached, then ``EARLY`` more
``EARLY_EVERY_S`` apart (a loaded host's round trips vary, and the filter keeps the fastest
it sees: ten round trips a second apart left the first ten seconds' offsets up to a
millisecond off), then one every ``REFRESH_S`` so that the estimate follows a drifting clock
and never ages out; an agent that does not answer is asked again every ``RETRY_S``.  The
window of round trips the filter keeps holds all of them.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from agent.runtime.logs import RateLimitedLog
from agent.sdk.clock import ClockOffsets
from agent.sdk.query import AgentQueries

log = logging.getLogger("uma.service")

#: round trips when an agent is first matched
BURST = 5
#: an agent's samples are passed on once its offset is known within this (ns).  2 ms is
#: 2 mm of a body moving 1 m/s, a quarter of a 120 Hz tracker's frame period (frames of two
#: hosts are paired within half of one), and a round trip of 4 ms, which a loopback or
#: wired link gives within the first few even on a loaded host (0.5-1.6 ms median at load
#: 13-21, a 4 ms one within 0.05 s of probing)
MAX_ERROR_NS = 2_000_000
#: seconds between round trips while the offset is not known within ``MAX_ERROR_NS``
FAST_EVERY_S = 0.02
#: seconds after which samples are passed on with the bound they have (a warning says so)
SYNC_TIMEOUT_S = 5.0
#: samples held per agent at most (5 s of a 100 Hz stream), and their bytes (one image at
#: its largest)
HELD_SAMPLES = 500
HELD_BYTES = 32 << 20
#: round trips after the offset is known within the bound, EARLY_EVERY_S apart
EARLY = 50
EARLY_EVERY_S = 0.2
#: seconds between round trips to an agent whose offset is known, after those
REFRESH_S = 10.0
#: seconds between tries while an agent has not answered
RETRY_S = 0.5
#: how long one round trip may take
TIMEOUT_S = 1.0


class SampleClocks:
    """The offsets of the agents a service receives samples from, and the samples held
    until an offset is good enough (module docstring).  ``on_ready(agent)`` is called (on
    the measuring thread) when an agent's held samples may be taken (:meth:`released`)."""

    def __init__(self, own_agent: str, realm: str, now: Callable[[], int],
                 limited_log: RateLimitedLog,
                 on_ready: Callable[[str], None] = lambda agent: None) -> None:
        self.own_agent = own_agent
        self.realm = realm
        self.now = now
        self.offsets = ClockOffsets(window=BURST + EARLY + 16)
        self._log = limited_log
        self._on_ready = on_ready
        self._queries: AgentQueries | None = None
        #: agent id -> when (monotonic s) it is next asked
        self._due: dict[str, float] = {}
        #: agent id -> round trips it answered
        self._answered: dict[str, int] = {}
        #: agent id -> when it was first followed (monotonic s; ``SYNC_TIMEOUT_S``)
        self._since: dict[str, float] = {}
        #: agents whose samples are passed on; of those, the ones above ``MAX_ERROR_NS``
        self._passing: set[str] = set()
        self._coarse: set[str] = set()
        #: agent id -> its held samples, oldest first: (item, size in bytes)
        self._held: dict[str, deque[tuple[Any, int]]] = {}
        self._held_bytes: dict[str, int] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closed = threading.Event()
        self._thread: threading.Thread | None = None
        #: samples held back so far, and of those the ones dropped (over the bounds, or
        #: their agent not among those followed)
        self.unsynced = 0
        self.dropped = 0

    def follow(self, session: zenoh.Session, agents: Iterable[str]) -> None:
        """Measure the clocks of ``agents`` (those of the current matches) from now on,
        and only theirs: an agent left out is not asked again, its held samples are
        dropped."""
        remote = set(agents) - {self.own_agent}
        now = time.monotonic()
        with self._lock:
            if self._queries is None and remote:
                self._queries = AgentQueries(session, self.realm, TIMEOUT_S, self.offsets,
                                             self.now)
            self._due = {a: self._due.get(a, 0.0) for a in remote}
            self._answered = {a: n for a, n in self._answered.items() if a in remote}
            self._since = {a: self._since.get(a, now) for a in remote}
            gone = [a for a in self._held if a not in remote]
            for agent in gone:
                self._drop(agent, len(self._held[agent]), "no matched stream comes from it")
            if remote and self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="uma-service-clocks")
                self._thread.start()
        self._wake.set()

    def to_local(self, agent: str, t_ns: int) -> int | None:
        """A sample's time from a service of ``agent`` on this host's clock; None while
        its samples are held (:meth:`hold` it then)."""
        if agent == self.own_agent:
            return t_ns
        if agent not in self._passing or agent in self._held:
            return None
        offset = self.offsets.offset(agent)
        return None if offset is None else t_ns - offset

    def error_ns(self, agent: str) -> int | None:
        """The bound on the error of ``agent``'s offset (half the delay of the round trip
        that measured it); 0 for this host's own agent, None while unmeasured."""
        if agent == self.own_agent:
            return 0
        best = self.offsets.best(agent)
        return None if best is None else best.delay_ns // 2

    def hold(self, agent: str, item: Any, size: int) -> None:
        """Keep ``item`` (a sample of ``agent``, ``size`` bytes) until :meth:`released`
        gives it back; beyond the bounds the agent's oldest are dropped."""
        with self._lock:
            held = self._held.setdefault(agent, deque())
            held.append((item, size))
            self._held_bytes[agent] = self._held_bytes.get(agent, 0) + size
            self.unsynced += 1
            over = 0
            while len(held) > HELD_SAMPLES or (len(held) > 1
                                               and self._held_bytes[agent] > HELD_BYTES):
                self._held_bytes[agent] -= held.popleft()[1]
                over += 1
            if over:
                self.dropped += over
                self._log.warning(f"clock of agent {agent}", f"held samples over "
                                  f"{HELD_SAMPLES} or {HELD_BYTES / 2**20:g} MiB: the oldest "
                                  f"dropped ({self.dropped} dropped so far)")
        self._log.warning(f"clock of agent {agent}", "samples held back until its clock "
                          f"offset is known within {MAX_ERROR_NS / 1e6:g} ms "
                          f"({self.unsynced} so far)")

    @property
    def holding(self) -> bool:
        """Whether any samples are held."""
        return bool(self._held)

    def released(self) -> list[Any]:
        """The held samples of the agents whose samples are passed on now, each agent's in
        the order they came; they are not held any more."""
        with self._lock:
            ready = [a for a in self._held if a in self._passing and self.offsets.known(a)]
            items = [item for a in ready for item, _ in self._held.pop(a)]
            for agent in ready:
                self._held_bytes.pop(agent, None)
        return items

    def status(self) -> dict[str, dict[str, Any]]:
        """Per agent followed: ``state`` ("measuring": its samples are held; "synced":
        passed on, the offset within ``MAX_ERROR_NS``; "coarse": passed on after
        ``SYNC_TIMEOUT_S`` with a larger bound), ``offset_ms`` and ``error_ms`` (None while
        unmeasured) and ``held`` (samples held now)."""
        with self._lock:
            agents = sorted(self._since)
            held = {a: len(h) for a, h in self._held.items()}
        out = {}
        for agent in agents:
            best = self.offsets.best(agent)
            state = ("measuring" if agent not in self._passing or best is None
                     else "coarse" if agent in self._coarse else "synced")
            out[agent] = {"state": state,
                          "offset_ms": None if best is None else best.offset_ns / 1e6,
                          "error_ms": None if best is None else best.delay_ns / 2e6,
                          "held": held.get(agent, 0)}
        return out

    def close(self) -> None:
        self._closed.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2 * TIMEOUT_S)
        if self._queries is not None:
            self._queries.close()
        with self._lock:
            self._held.clear()
            self._held_bytes.clear()

    def _drop(self, agent: str, n: int, why: str) -> None:
        """Drop the held samples of ``agent`` (lock held)."""
        del self._held[agent]
        self._held_bytes.pop(agent, None)
        self.dropped += n
        log.warning("clock of agent %s: %d held samples dropped: %s (%d dropped so far)",
                    agent, n, why, self.dropped)

    def _run(self) -> None:
        while not self._closed.is_set():
            self._wake.clear()
            now = time.monotonic()
            with self._lock:
                due = [a for a, t in self._due.items() if t <= now]
                queries = self._queries
            for agent in due:
                if self._closed.is_set() or queries is None:
                    return
                self._measure(queries, agent)
            with self._lock:
                wait = min(self._due.values(), default=now + REFRESH_S) - time.monotonic()
            self._wake.wait(max(0.0, min(wait, REFRESH_S)))

    def _measure(self, queries: AgentQueries, agent: str) -> None:
        """One round trip (a burst while the agent's offset is unknown); whether its
        samples pass on now; the next one scheduled."""
        known = self.offsets.known(agent)
        answered = False
        for _ in range(1 if known else BURST):
            answered = queries.probe(agent) or answered
        if not answered and not known:
            self._log.warning(f"clock of agent {agent}", "its agent does not answer clock "
                              f"round trips; asking again every {RETRY_S:g} s")
        with self._lock:
            n = self._answered[agent] = self._answered.get(agent, 0) + answered
        best = self.offsets.best(agent)
        within = best is not None and best.delay_ns <= 2 * MAX_ERROR_NS
        if best is not None:
            self._judge(agent, best.offset_ns, best.delay_ns, within, answered and n == EARLY)
        with self._lock:
            passing = agent in self._passing
            if agent in self._due:
                self._due[agent] = time.monotonic() + (
                    RETRY_S if not answered else FAST_EVERY_S if not passing
                    else EARLY_EVERY_S if n <= EARLY or not within else REFRESH_S)
            ready = passing and agent in self._held
        if ready:
            self._on_ready(agent)

    def _judge(self, agent: str, offset_ns: int, delay_ns: int, within: bool,
               settled: bool) -> None:
        """Pass ``agent``'s samples on once its offset is within the bound or the time to
        reach it is up (saying which), and say when a coarse one reaches it."""
        figures = (f"{offset_ns / 1e6:+.3f} ms from this host's, within "
                   f"{delay_ns / 2e6:.3f} ms (fastest round trip {delay_ns / 1e6:.3f} ms)")
        with self._lock:
            since = self._since.get(agent, time.monotonic())
            passing, coarse = agent in self._passing, agent in self._coarse
            timed_out = time.monotonic() - since >= SYNC_TIMEOUT_S
            if not passing and (within or timed_out):
                self._passing.add(agent)
                if not within:
                    self._coarse.add(agent)
            elif coarse and within:
                self._coarse.discard(agent)
        if not passing and within:
            log.info("clock of agent %s: %s; its samples pass on", agent, figures)
        elif not passing and timed_out:
            log.warning("clock of agent %s: %s; no round trip within %g s was fast enough "
                        "for %g ms: its samples pass on with times up to %.3f ms off",
                        agent, figures, SYNC_TIMEOUT_S, MAX_ERROR_NS / 1e6, delay_ns / 2e6)
        elif coarse and within:
            log.info("clock of agent %s: %s; now within %g ms", agent, figures,
                     MAX_ERROR_NS / 1e6)
        elif settled:
            log.info("clock of agent %s: %s", agent, figures)
