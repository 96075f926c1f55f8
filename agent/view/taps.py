"""The view's own taps on the streams of edge abilities: the newest sample of each, the
stream's rate and the age of its newest sample, for drawing and for the stream's state.

Each tap is a Zenoh subscriber with a ring channel of one: Zenoh keeps only the newest
sample of the stream, in Rust, and Python never runs per sample.  The draw loop pulls the
newest one at most once per redraw (:meth:`Taps.latest`), so a realm publishing tens of
thousands of samples a second costs the view's Python a few pulls per redraw.  Zenoh itself
still receives every sample: a view process starved of CPU falls behind in its transport
(``bench/bench_view.py``: 200 frames at 100 Hz on a loaded 2-core host drew seconds-old
samples).  The rate is measured from the samples' own sequence
numbers and times (``s`` and ``t`` on the wire) over the last ``RATE_WINDOW_S``; the age of
the newest sample is the time since it was first pulled (one redraw period late at most).
"""

from __future__ import annotations

import contextlib
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from agent import Subscription
from agent.runtime import RateLimitedLog
from schemas.codec import DecodeError, Measurement, decode_measurement

#: the window of sample time over which a stream's rate is measured (s)
RATE_WINDOW_S = 1.0


@dataclass
class _Stream:
    type: str
    subscriber: Any
    newest: Measurement | None = None
    #: when the newest sample was first pulled (monotonic s)
    pulled: float | None = None
    #: (t_ns, seq) of the samples pulled within the rate window
    marks: deque[tuple[int, int]] = field(default_factory=deque)


@dataclass(frozen=True)
class StreamFacts:
    """What the view measured of one stream: rate over the last second (None: not yet
    measurable), seconds since the newest sample (None: none yet), and its sequence
    number."""

    rate_hz: float | None
    age_s: float | None
    seq: int | None


class Taps:
    """Ring-channel subscriptions to data keys, changed by :meth:`follow`; used by the
    draw loop's thread only (module docstring)."""

    def __init__(self, session: zenoh.Session, log: Any) -> None:
        self.session = session
        self._log = RateLimitedLog(log)
        self._streams: dict[str, _Stream] = {}

    def follow(self, wanted: Iterable[tuple[str, str]]) -> None:
        """Tap exactly these ``(data key, measurement type)`` streams."""
        wanted = dict(wanted)
        for key in set(self._streams) - set(wanted):
            with contextlib.suppress(zenoh.ZError):
                self._streams.pop(key).subscriber.undeclare()
        for key, type_ in wanted.items():
            if key not in self._streams:
                self._streams[key] = _Stream(type_, self.session.declare_subscriber(
                    key, zenoh.handlers.RingChannel(1)))

    def latest(self, key: str) -> Measurement | None:
        """The newest sample of ``key``, pulled now if a newer one came (None if none yet;
        a malformed one is skipped with a rate-limited log line naming the key and the
        reason)."""
        stream = self._streams.get(key)
        if stream is None:
            return None
        sample = stream.subscriber.try_recv()
        if sample is not None:
            try:
                m = decode_measurement(sample.payload.to_bytes(), stream.type)
            except DecodeError as exc:
                self._log.warning(key, f"dropped a malformed sample: {exc}")
            else:
                stream.newest, stream.pulled = m, time.monotonic()
                _mark(stream.marks, m)
        return stream.newest

    def facts(self, key: str) -> StreamFacts | None:
        """Rate, age and sequence number of a tapped stream (None if it is not tapped)."""
        stream = self._streams.get(key)
        if stream is None:
            return None
        age = None if stream.pulled is None else time.monotonic() - stream.pulled
        seq = None if stream.newest is None else stream.newest.seq
        return StreamFacts(_rate(stream.marks), age, seq)

    def close(self) -> None:
        self.follow(())


def _mark(marks: deque[tuple[int, int]], m: Measurement) -> None:
    if m.seq is None:
        return
    marks.append((m.t_ns, m.seq))
    while marks and marks[0][0] < m.t_ns - int(RATE_WINDOW_S * 1e9):
        marks.popleft()


def _rate(marks: deque[tuple[int, int]]) -> float | None:
    """Samples per second between the oldest and newest pulled samples of the window, by
    their sequence numbers and times (a restarted publisher's sequence is not counted)."""
    if len(marks) < 2:
        return None
    (t0, s0), (t1, s1) = marks[0], marks[-1]
    if t1 <= t0 or s1 <= s0:
        return None
    return (s1 - s0) / ((t1 - t0) / 1e9)


def stream_state(matched: bool, facts: StreamFacts | None, advertised_hz: float | None,
                 measured_hz: float | None) -> str:
    """``no route`` (nothing matched), ``stalled`` (no sample for as long as a subscription
    waits, :meth:`agent.Subscription.stall_limit`), else ``streaming``.  Streams the view
    does not tap itself are judged by the rate their consumer's agent measured."""
    if not matched:
        return "no route"
    if facts is not None:
        limit = Subscription.stall_limit(advertised_hz)
        return "streaming" if facts.age_s is not None and facts.age_s <= limit else "stalled"
    return "streaming" if measured_hz else "stalled"
