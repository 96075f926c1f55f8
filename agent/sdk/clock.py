"""Clock offsets between this process and remote agents, NTP style
(``docs/ARCHITECTURE.md``, "Time").

Every query round trip to an agent gives four timestamps: ``t1`` we sent (our clock),
``t2`` the agent received and ``t3`` it replied (its clock), ``t4`` we received (ours).
Then ``offset = ((t2 - t1) + (t3 - t4)) / 2`` (the agent's clock minus ours) and
``delay = (t4 - t1) - (t3 - t2)`` (network time).  The offset error is at most half the
asymmetry of the path, so of several recent samples the one with the smallest delay is
the most trustworthy: a minimum-delay filter over a short window (NTP's clock filter).
Samples age out so that a drifting clock is followed.

Tests skew an agent's clock (``agent.protocol.query.SKEW_ENV``) to test this module end to
end.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class ClockSample:
    offset_ns: int
    delay_ns: int
    taken: float  # time.monotonic() when measured


class ClockOffsets:
    """Per remote agent, the offset of its clock from ours (min-delay filtered)."""

    def __init__(self, window: int = 16, max_age_s: float = 60.0,
                 max_agents: int = 1000) -> None:
        self.window = window
        self.max_age_s = max_age_s
        #: agents kept (the least recently measured is forgotten first): answers under
        #: forged agent keys must not grow a client without bound
        self.max_agents = max_agents
        self._samples: dict[str, deque[ClockSample]] = {}
        #: per agent, the best sample and until when it stays the best (the first moment
        #: one of the window's samples ages out): a query asks for each agent's offset
        #: several times and adds a sample per answer, and rescanning the window at every
        #: one was a visible share of a query's CPU time.  A new sample only replaces the
        #: best if its delay is smaller; the window is rescanned when the best ages out or
        #: is pushed out of the window
        self._best: dict[str, tuple[ClockSample | None, float]] = {}
        self._lock = threading.Lock()

    def add(self, agent: str, t1: int, t2: int, t3: int, t4: int) -> ClockSample | None:
        """Record one round trip; returns the sample, or None if its times are impossible
        (the agent replied before it received, or we received before we sent)."""
        delay = (t4 - t1) - (t3 - t2)
        if t4 < t1 or t3 < t2 or delay < 0:
            return None
        sample = ClockSample(((t2 - t1) + (t3 - t4)) // 2, delay, time.monotonic())
        with self._lock:
            samples = self._samples.pop(agent, None) or deque(maxlen=self.window)
            pushed_out = samples[0] if len(samples) == self.window else None
            samples.append(sample)
            self._samples[agent] = samples  # last: the dict's order is recency
            cached = self._best.get(agent)
            if cached is not None and cached[0] is not None and cached[0] is not pushed_out:
                if delay < cached[0].delay_ns:  # the expiry stays: it only comes sooner
                    self._best[agent] = (sample, cached[1])
            else:
                self._best.pop(agent, None)
            while len(self._samples) > self.max_agents:
                oldest = next(iter(self._samples))
                del self._samples[oldest]
                self._best.pop(oldest, None)
        return sample

    def best(self, agent: str) -> ClockSample | None:
        """The minimum-delay sample among the recent ones, or None if none is recent."""
        now = time.monotonic()
        cached = self._best.get(agent)  # one atomic read: the lock only to rescan
        if cached is not None and now < cached[1]:
            return cached[0]
        with self._lock:
            cached = self._best.get(agent)
            if cached is not None and now < cached[1]:
                return cached[0]
            samples = [s for s in self._samples.get(agent, ()) if s.taken >= now - self.max_age_s]
            # of equal delays the newest: it stays in the window longest (the oldest would be
            # pushed out by the next sample and the window scanned again)
            best = min(reversed(samples), key=lambda s: s.delay_ns) if samples else None
            expires = min(s.taken for s in samples) + self.max_age_s if samples else now
            self._best[agent] = (best, expires)
            return best

    def offset(self, agent: str) -> int | None:
        """The agent's clock minus ours in ns, or None if never measured (recently)."""
        best = self.best(agent)
        return None if best is None else best.offset_ns

    def to_remote(self, agent: str, t_local: int) -> int:
        """Our time ``t_local`` on the agent's clock (unchanged if the offset is unknown)."""
        return t_local + (self.offset(agent) or 0)

    def to_local(self, agent: str, t_remote: int) -> int:
        """A timestamp of the agent's clock on ours."""
        return t_remote - (self.offset(agent) or 0)

    def known(self, agent: str) -> bool:
        return self.best(agent) is not None

    def forget(self, agent: str) -> None:
        with self._lock:
            self._samples.pop(agent, None)
            self._best.pop(agent, None)
