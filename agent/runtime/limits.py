"""Rate and byte bounds on what peers make a component do: token buckets, one per sender.

A peer's messages cost the receiver work (a registration is decoded, validated and
re-matched; a liveliness token starts a query).  Bounding the bytes of one message is not
enough: a flood of small ones costs as much.  :class:`TokenBucket` lets ``burst`` events
through at once and ``rate`` per second after that; :class:`SenderLimits` keeps one bucket
per sender (a key the caller chooses: a service id, an agent id), at most ``max_senders``
of them (the least recently used forgotten first, so a flood of distinct senders grows
nothing), under one lock: Zenoh calls its callbacks from several threads.
:class:`Coalescer` keeps only the latest event per key before the worker runs it.
:class:`ByteBudget` bounds the bytes peers' messages occupy while they wait for the worker.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

#: liveliness token events whose work (a query, a re-match) one sender, the agent id in
#: the token's key, may start: at once, then per second; and all senders together (an
#: agent joining a realm of a thousand services takes the rest from its next resync)
TOKEN_BURST, TOKEN_RATE = 200, 20.0
TOKEN_TOTAL_BURST, TOKEN_TOTAL_RATE = 1000, 100.0


def token_limits() -> SenderLimits:
    """The bounds on one component's liveliness token events (``TOKEN_*``)."""
    return SenderLimits(TOKEN_RATE, TOKEN_BURST, (TOKEN_TOTAL_RATE, TOKEN_TOTAL_BURST))


class TokenBucket:
    """``burst`` events at once, ``rate`` per second sustained."""

    __slots__ = ("_at", "_tokens", "burst", "rate")

    def __init__(self, rate: float, burst: float, now: float | None = None) -> None:
        self.rate, self.burst = rate, burst
        self._tokens = burst
        self._at = time.monotonic() if now is None else now

    def allow(self, now: float) -> bool:
        """Take one token if there is one (callers hold whatever lock guards the bucket)."""
        if now > self._at:
            self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate)
            self._at = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True

    def refund(self) -> None:
        """Give back the token just taken (what it paid for did not go on)."""
        self._tokens = min(self.burst, self._tokens + 1.0)


class SenderLimits:
    """A bucket per sender and, given ``total``, one for all of them together (module
    docstring)."""

    def __init__(self, rate: float, burst: float, total: tuple[float, float] | None = None,
                 max_senders: int = 1024, now: float | None = None) -> None:
        self.rate, self.burst, self.max_senders = rate, burst, max_senders
        self._total = None if total is None else TokenBucket(*total, now=now)
        self._senders: OrderedDict[str, TokenBucket] = OrderedDict()
        self._lock = threading.Lock()

    def allow(self, sender: str, now: float | None = None) -> str | None:
        """None if one more event of ``sender`` may go on now, else why not ("sender" or
        "total"); a refused event takes no token."""
        now = time.monotonic() if now is None else now
        with self._lock:
            bucket = self._senders.get(sender)
            if bucket is None:
                bucket = self._senders[sender] = TokenBucket(self.rate, self.burst, now)
                while len(self._senders) > self.max_senders:
                    self._senders.popitem(last=False)
            else:
                self._senders.move_to_end(sender)
            if not bucket.allow(now):
                return "sender"
            if self._total is not None and not self._total.allow(now):
                bucket.refund()
                return "total"
            return None


class Coalescer:
    """Events from Zenoh's threads, keyed by what they are about (a liveliness token's
    key): only the latest of each is kept until the worker takes them all in one call, so
    a churning key costs one entry however fast it flips, and the worker's queue holds at
    most one such call.  A key not already waiting is rated per sender first
    (``limits``); a refused event is counted and told to ``on_refused`` (the caller's
    periodic resync repairs what it missed)."""

    def __init__(self, put: Callable[[Callable[[], None]], bool],
                 handle: Callable[[Any], None], limits: SenderLimits,
                 on_refused: Callable[[str, str], None], max_pending: int = 4096) -> None:
        self._put, self._handle, self._limits = put, handle, limits
        self._on_refused = on_refused
        self.max_pending = max_pending
        self._pending: dict[str, Any] = {}
        self._scheduled = False  # a drain is queued with the worker
        self._lock = threading.Lock()
        #: events refused (rate or pending bound)
        self.refused = 0

    def offer(self, key: str, sender: str, event: Any) -> None:
        with self._lock:
            if key in self._pending:
                self._pending[key] = event  # coalesced: the latest wins, no new work
                return
            why = self._limits.allow(sender)
            if why is None and len(self._pending) >= self.max_pending:
                why = "pending"
            if why is not None:
                self.refused += 1
            else:
                self._pending[key] = event
                schedule, self._scheduled = not self._scheduled, True
        if why is not None:
            self._on_refused(sender, why)
        elif schedule and not self._put(self._drain):
            with self._lock:
                self._scheduled = False  # the worker's queue was full: the next offer asks

    def _drain(self) -> None:
        with self._lock:
            batch, self._pending, self._scheduled = self._pending, {}, False
        for event in batch.values():
            self._handle(event)


class ByteBudget:
    """Bytes of peers' messages received and not yet handled, at most ``limit``: a flood
    of large messages waits in Zenoh (or is not asked for) instead of in the worker's
    queue, whose bound counts calls, not bytes."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.held = 0
        self._lock = threading.Lock()

    def take(self, size: int) -> bool:
        """Whether ``size`` more bytes may be held now (then they are, until ``give``)."""
        with self._lock:
            if self.held + size > self.limit:
                return False
            self.held += size
            return True

    def give(self, size: int) -> None:
        with self._lock:
            self.held = max(0, self.held - size)

    def room(self, size: int) -> bool:
        """Whether ``size`` bytes would fit now (nothing is taken)."""
        with self._lock:
            return self.held + size <= self.limit
