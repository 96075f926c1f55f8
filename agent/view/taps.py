"""The view's own taps on the streams of edge abilities: the newest sample of each, the
stream's rate and the age of its newest sample, for drawing and for the stream's state.

A pose stream is tapped through its agent's digest (:mod:`agent.protocol.digest`): the
agent puts the newest sample of each of its pose streams a few tens of times a second
while someone listens, so the view receives one message per agent per digest rather than
every sample (subscribed to every data key, a view receives every sample in its transport:
200 frames at 100 Hz, 20,000 a second, put seconds-old samples on the page of a loaded
2-core host).  Other edge streams (position, rotation) are tapped directly.  Each tap is
a Zenoh subscriber with a ring channel of one: Zenoh keeps only the newest message, in
Rust, and Python never runs per message.  The draw loop pulls the newest one at most once
per redraw (:meth:`Taps.latest`).  The rate is measured from the samples' own sequence
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
from agent.protocol import keys, read_digest
from agent.runtime import RateLimitedLog
from schemas.codec import DecodeError, Measurement, decode_measurement

#: the window of sample time over which a stream's rate is measured (s)
RATE_WINDOW_S = 1.0


@dataclass
class _Stream:
    type: str
    #: its own subscriber, or None for a stream read from its agent's digest
    subscriber: Any
    #: the agent whose digest carries it (None: tapped directly)
    agent: str | None = None
    #: the payload the newest sample was decoded from (a digest repeats it until a new one)
    payload: bytes | None = None
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

    def __init__(self, session: zenoh.Session, log: Any, realm: str) -> None:
        self.session = session
        self.realm = realm
        self._log = RateLimitedLog(log)
        self._streams: dict[str, _Stream] = {}
        #: per agent: its digest's subscriber and the newest payload of each of its keys
        self._digests: dict[str, tuple[Any, dict[str, bytes]]] = {}

    def follow(self, wanted: Iterable[tuple[str, str]]) -> None:
        """Tap exactly these ``(data key, measurement type)`` streams."""
        wanted = dict(wanted)
        for key in set(self._streams) - set(wanted):
            subscriber = self._streams.pop(key).subscriber
            if subscriber is not None:
                _undeclare(subscriber)
        for key, type_ in wanted.items():
            if key not in self._streams:
                owner = keys.parse_data(key, self.realm) if type_ == "pose6d" else None
                if owner is None:
                    self._streams[key] = _Stream(type_, self.session.declare_subscriber(
                        key, zenoh.handlers.RingChannel(1)))
                else:
                    self._streams[key] = _Stream(type_, None, owner[0])
        agents = {s.agent for s in self._streams.values() if s.agent is not None}
        for agent in set(self._digests) - agents:
            _undeclare(self._digests.pop(agent)[0])
        for agent in agents - set(self._digests):
            self._digests[agent] = (self.session.declare_subscriber(
                keys.agent_digest(self.realm, agent), zenoh.handlers.RingChannel(1)), {})

    def latest(self, key: str) -> Measurement | None:
        """The newest sample of ``key``, pulled now if a newer one came (None if none yet;
        a malformed one is skipped with a rate-limited log line naming the key and the
        reason)."""
        stream = self._streams.get(key)
        if stream is None:
            return None
        data = self._pull(key, stream)
        if data is not None and data is not stream.payload:
            stream.payload = data
            try:
                m = decode_measurement(data, stream.type)
            except DecodeError as exc:
                self._log.warning(key, f"dropped a malformed sample: {exc}")
            else:
                if stream.newest is None or m.t_ns != stream.newest.t_ns:
                    stream.newest, stream.pulled = m, time.monotonic()
                    _mark(stream.marks, m)
        return stream.newest

    def _pull(self, key: str, stream: _Stream) -> bytes | None:
        """The newest payload of ``key``: from its own tap, or from its agent's newest
        digest (None: nothing new)."""
        if stream.agent is None:
            sample = stream.subscriber.try_recv()
            return None if sample is None else sample.payload.to_bytes()
        subscriber, payloads = self._digests[stream.agent]
        message = subscriber.try_recv()
        if message is not None:
            try:
                payloads.update(read_digest(message.payload.to_bytes(), self.realm,
                                            stream.agent))
            except DecodeError as exc:
                self._log.warning(f"digest of {stream.agent}", f"dropped: {exc}")
        return payloads.get(key)

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


def _undeclare(subscriber: Any) -> None:
    with contextlib.suppress(zenoh.ZError):
        subscriber.undeclare()


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
