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

Until an agent's offset is measured, its samples are held back: counted (``unsynced``) and
said in a rate-limited line, never passed on with a time that may be tens of ms off.  One
thread measures: ``BURST`` round trips when an agent's stream is first matched (the best of
them bounds the error by half the smallest delay), then ``EARLY`` more ``EARLY_EVERY_S``
apart (a loaded host's round trips vary: a millisecond's delay is half a millisecond of
doubt, half a millimetre at a walking body's speed, and the filter keeps the fastest one
it sees; a burst on a host busy starting its services may be slow throughout, and ten
round trips a second apart left the first ten seconds' offsets up to a millisecond off),
then one every ``REFRESH_S`` so that the estimate follows a drifting clock and never ages
out; an agent that does not answer is asked again every ``RETRY_S``.  The window of
round trips the filter keeps holds all of them.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable

import zenoh

from agent.runtime.logs import RateLimitedLog
from agent.sdk.clock import ClockOffsets
from agent.sdk.query import AgentQueries

log = logging.getLogger("uma.service")

#: round trips when an agent is first matched
BURST = 5
#: round trips after the burst, EARLY_EVERY_S apart
EARLY = 50
EARLY_EVERY_S = 0.2
#: seconds between round trips to an agent whose offset is known, after those
REFRESH_S = 10.0
#: seconds between tries while an agent has not answered
RETRY_S = 0.5
#: how long one round trip may take
TIMEOUT_S = 1.0


class SampleClocks:
    """The offsets of the agents a service receives samples from (module docstring)."""

    def __init__(self, own_agent: str, realm: str, now: Callable[[], int],
                 limited_log: RateLimitedLog) -> None:
        self.own_agent = own_agent
        self.realm = realm
        self.now = now
        self.offsets = ClockOffsets(window=BURST + EARLY + 16)
        self._log = limited_log
        self._queries: AgentQueries | None = None
        #: agent id -> when (monotonic s) it is next asked
        self._due: dict[str, float] = {}
        #: agent id -> round trips it answered
        self._answered: dict[str, int] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closed = threading.Event()
        self._thread: threading.Thread | None = None
        #: samples held back because their agent's offset was not known yet
        self.unsynced = 0

    def follow(self, session: zenoh.Session, agents: Iterable[str]) -> None:
        """Measure the clocks of ``agents`` (those of the current matches) from now on,
        and only theirs: an agent left out is not asked again."""
        remote = set(agents) - {self.own_agent}
        with self._lock:
            if self._queries is None and remote:
                self._queries = AgentQueries(session, self.realm, TIMEOUT_S, self.offsets,
                                             self.now)
            self._due = {a: self._due.get(a, 0.0) for a in remote}
            self._answered = {a: n for a, n in self._answered.items() if a in remote}
            if remote and self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="uma-service-clocks")
                self._thread.start()
        self._wake.set()

    def to_local(self, agent: str, t_ns: int) -> int | None:
        """A sample's time from a service of ``agent`` on this host's clock; None while
        that agent's offset is unknown (the sample is then held back and counted)."""
        if agent == self.own_agent:
            return t_ns
        offset = self.offsets.offset(agent)
        if offset is None:
            self.unsynced += 1
            self._log.warning(f"clock of agent {agent}", "samples held back until its clock "
                              f"offset is measured ({self.unsynced} so far)")
            return None
        return t_ns - offset

    def close(self) -> None:
        self._closed.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2 * TIMEOUT_S)
        if self._queries is not None:
            self._queries.close()

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
        """One round trip (a burst while the agent's offset is unknown); the next one
        scheduled."""
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
        if best is not None and (not known or (answered and n == EARLY)):
            log.info("clock of agent %s: %+.3f ms from this host's (fastest round trip "
                     "%.3f ms)", agent, best.offset_ns / 1e6, best.delay_ns / 1e6)
        with self._lock:
            if agent in self._due:
                wait = RETRY_S if not answered else EARLY_EVERY_S if n <= EARLY else REFRESH_S
                self._due[agent] = time.monotonic() + wait
