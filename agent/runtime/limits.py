"""Rate bounds on what peers make a component do: token buckets, one per sender.

A peer's messages cost the receiver work (a registration is decoded, validated and
re-matched; a liveliness token starts a query).  Bounding the bytes of one message is not
enough: a flood of small ones costs as much.  :class:`TokenBucket` lets ``burst`` events
through at once and ``rate`` per second after that; :class:`SenderLimits` keeps one bucket
per sender (a key the caller chooses: a service id, an agent id), at most ``max_senders``
of them (the least recently used forgotten first, so a flood of distinct senders grows
nothing), under one lock: Zenoh calls its callbacks from several threads.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict


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
