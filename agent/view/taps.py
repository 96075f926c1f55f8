"""The view's own taps on the streams of edge abilities: the newest sample of each (kept as
bytes, decoded only when drawn) and its arrival times, for the measured rate, the age of
the newest sample and the stream's state.

Zenoh's callback only keeps a reference to the payload and the arrival time under a lock
(a few microseconds, no copy), so a realm publishing thousands of samples a second costs
the view little; copying and decoding happen at most once per redraw per stream.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from agent.runtime.logs import RateLimitedLog
from schemas.codec import DecodeError, Measurement, decode_measurement

#: the window over which a stream's rate is measured (s)
RATE_WINDOW_S = 1.0
#: a stream is stalled after this many of its advertised periods without a sample, and
#: never before STALL_MIN_S (the subscription SDK's rule, agent.sdk.subscription)
STALL_PERIODS = 10
STALL_MIN_S = 1.5


@dataclass
class _Stream:
    type: str
    data: Any = None  # the newest payload (zenoh.ZBytes), copied out only when drawn
    arrivals: deque[float] = field(default_factory=lambda: deque(maxlen=4096))
    decoded: Measurement | None = None
    decoded_from: Any = None


@dataclass(frozen=True)
class StreamFacts:
    """What the view measured of one stream: rate over the last second, seconds since the
    newest sample (None: none yet), and samples seen."""

    rate_hz: float
    age_s: float | None
    count: int


class Taps:
    """Subscriptions to data keys, changed by :meth:`follow` (module docstring)."""

    def __init__(self, session: zenoh.Session, log: Any) -> None:
        self.session = session
        self._bad = RateLimitedLog(log)
        self._lock = threading.Lock()
        self._streams: dict[str, _Stream] = {}
        self._counts: dict[str, int] = {}
        self._subs: dict[str, Any] = {}

    def follow(self, wanted: Iterable[tuple[str, str]]) -> None:
        """Tap exactly these ``(data key, measurement type)`` streams."""
        wanted = dict(wanted)
        for key in set(self._subs) - set(wanted):
            with contextlib.suppress(zenoh.ZError):
                self._subs.pop(key).undeclare()
            with self._lock:
                self._streams.pop(key, None)
        for key, type_ in wanted.items():
            if key in self._subs:
                continue
            with self._lock:
                self._streams[key] = _Stream(type_)
                self._counts.setdefault(key, 0)
            self._subs[key] = self.session.declare_subscriber(
                key, zenoh.handlers.Callback(lambda s, k=key: self._on_sample(k, s),
                                             indirect=False))

    def _on_sample(self, key: str, sample: zenoh.Sample) -> None:
        data, now = sample.payload, time.monotonic()
        with self._lock:
            stream = self._streams.get(key)
            if stream is not None:
                stream.data = data
                stream.arrivals.append(now)
                self._counts[key] += 1

    def latest(self, key: str) -> Measurement | None:
        """The newest sample of ``key`` decoded (None if none, or if it was malformed: then
        a rate-limited log line names the key and the reason)."""
        with self._lock:
            stream = self._streams.get(key)
            if stream is None or stream.data is None:
                return None
            data, type_ = stream.data, stream.type
            if stream.decoded_from is data:
                return stream.decoded
        try:
            m = decode_measurement(data.to_bytes(), type_)
        except DecodeError as exc:
            self._bad.warning(key, f"dropped a malformed sample: {exc}")
            m = None
        with self._lock:
            if key in self._streams:
                self._streams[key].decoded, self._streams[key].decoded_from = m, data
        return m

    def facts(self, key: str) -> StreamFacts | None:
        """Rate, age and count of a tapped stream (None if it is not tapped)."""
        now = time.monotonic()
        with self._lock:
            stream = self._streams.get(key)
            if stream is None:
                return None
            times = stream.arrivals
            recent = sum(1 for t in reversed(times) if t > now - RATE_WINDOW_S)
            age = now - times[-1] if times else None
            return StreamFacts(recent / RATE_WINDOW_S, age, self._counts.get(key, 0))

    def close(self) -> None:
        self.follow(())


def stream_state(matched: bool, facts: StreamFacts | None, advertised_hz: float | None,
                 measured_hz: float | None) -> str:
    """``no route`` (nothing matched), ``stalled`` (no sample for ``STALL_PERIODS``
    advertised periods, at least ``STALL_MIN_S``), else ``streaming``.  Streams the view
    does not tap itself are judged by the rate their consumer's agent measured."""
    if not matched:
        return "no route"
    if facts is not None:
        limit = max(STALL_MIN_S, STALL_PERIODS / advertised_hz) if advertised_hz else STALL_MIN_S
        return "streaming" if facts.age_s is not None and facts.age_s <= limit else "stalled"
    return "streaming" if measured_hz else "stalled"
