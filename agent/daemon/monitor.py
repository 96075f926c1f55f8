"""Stream monitoring: what the streams the local needs are connected to deliver, measured
on this host, and which of them are excluded from which need.

The agent listens (through its ``agent.daemon.streams.StreamHub``) to every stream its
local needs are connected to, and to every stream a need has excluded, and measures its
rate (arrivals in the last ``rate_window_s``, once the stream has been watched that long)
and latency (median of receive time minus sample time, the time read with
``schemas.codec.peek_time``: nothing else of a sample is decoded).  When the measured
values fail a need's predicate (``agent.daemon.matching.judge``) continuously for
``grace_s`` the ability is *excluded* for that need; the monitor keeps watching it, and
once it satisfies the predicate again for ``grace_s`` the exclusion is lifted.  The agent
asks :meth:`StreamMonitor.excluded` when it matches, and re-matches when
:meth:`StreamMonitor.judge` says an exclusion came or went (so the need moves to the next
best, and back if the stream recovers and ranks better).

A rate drop is noticed after about ``rate_window_s`` (for the window to reflect it) +
``grace_s``.  All methods run in the agent's worker thread but ``_Stream.on_sample``, which
Zenoh calls: it only counts the arrival and keeps the payload in a bounded inbox
(``INBOX``: a flood must not grow the agent; the rate counts every arrival, also those the
inbox had no room for).  Samples lost on the way (gaps in their sequence numbers,
``agent.protocol.sequence``) are counted and shown as ``measured_lost``.
"""

from __future__ import annotations

import logging
import statistics
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

from agent.daemon.matching import OfferIndex, Requirement, judge
from agent.daemon.streams import StreamHub
from agent.protocol.sequence import SequenceGaps
from agent.runtime.logs import RateLimitedLog
from schemas.codec import DecodeError, peek_time_seq

log = logging.getLogger("uma.agent")

#: a local need: (service id, need name)
NeedId = tuple[str, str]
#: payloads a stream keeps between two measurements (the worker's tick); more are counted,
#: not kept
INBOX = 2000


class _Stream:
    """Rate and latency of one data stream as this host receives it: the stream hub's thread appends
    (arrival, payload), ``measure`` (the worker) reads the sample times."""

    def __init__(self, key: str, type_: str, window_s: float, now: float,
                 bad: RateLimitedLog) -> None:
        self.key = key
        self.type = type_
        self.window_s = window_s
        self.started = now
        self.inbox: deque[tuple[float, int, bytes]] = deque()
        #: arrivals the inbox had no room for (the hub's thread counts, the worker reads)
        self.overflow = 0
        self._overflow_seen = 0
        #: (arrival mono, samples, latency s or None: uninspected overflow, or out of order)
        self.window: deque[tuple[float, int, float | None]] = deque()
        self.gaps = SequenceGaps()
        #: the newest stamp taken (samples stamped before it do not measure latency)
        self.newest_ns = 0
        self.stop_listening: Callable[[], None] = lambda: None
        self._log = bad

    def on_sample(self, data: bytes) -> None:
        if len(self.inbox) < INBOX:
            self.inbox.append((time.monotonic(), time.time_ns(), data))
        else:
            self.overflow += 1

    def measure(self, now: float) -> dict[str, float] | None:
        """Measured values, or ``None`` until the stream was watched for a full window."""
        self._take_inbox(now)
        while self.window and self.window[0][0] <= now - self.window_s:
            self.window.popleft()
        if now - self.started < self.window_s:
            return None
        out = {"measured_frequency_hz": sum(n for _, n, _ in self.window) / self.window_s,
               "measured_lost": float(max(0, self.gaps.lost - self.overflow))}
        latencies = [lat for _, _, lat in self.window if lat is not None]
        if latencies:
            out["measured_latency_s"] = statistics.median(latencies)
        return out

    def _take_inbox(self, now: float) -> None:
        for _ in range(len(self.inbox)):
            mono, wall_ns, data = self.inbox.popleft()
            try:
                t_ns, seq = peek_time_seq(data, expected_type=self.type)
            except DecodeError as exc:
                self._log.warning(f"data {self.key}", f"dropped a malformed sample: {exc}")
                self.gaps.skip()
                continue
            self.gaps.see(seq)
            # latency from the stream's present only: a sample stamped before the newest
            # one taken (out of order: a forged or replayed one) counts in the rate only
            latency = (wall_ns - t_ns) / 1e9 if t_ns >= self.newest_ns else None
            self.newest_ns = max(self.newest_ns, t_ns)
            self.window.append((mono, 1, latency))
        overflow = self.overflow
        if overflow > self._overflow_seen:
            self.window.append((now, overflow - self._overflow_seen, None))
            self._log.warning(f"data {self.key}", f"{overflow} samples arrived faster than "
                              "the monitor reads them: counted in the rate, not inspected")
            self._overflow_seen = overflow


@dataclass
class _Verdicts:
    """One need's judgement of its streams."""

    failing: dict[str, float] = field(default_factory=dict)     # key -> failing since
    excluded: dict[str, str] = field(default_factory=dict)      # key -> reason
    recovering: dict[str, float] = field(default_factory=dict)  # excluded key -> passing since


class StreamMonitor:
    """The measured streams and every local need's exclusions (module docstring)."""

    def __init__(self, hub: StreamHub, grace_s: float, window_s: float,
                 bad: RateLimitedLog) -> None:
        self._hub = hub
        self.grace_s = grace_s
        self.window_s = window_s
        self._log = bad
        self._streams: dict[str, _Stream] = {}
        self._verdicts: dict[NeedId, _Verdicts] = {}
        #: the values of the last ``judge``, by data key (shown in snapshots)
        self.measured: dict[str, dict[str, float]] = {}

    # -- what the agent asks
    def excluded(self, need: NeedId) -> dict[str, str]:
        """The streams excluded from ``need`` and why (a copy)."""
        verdicts = self._verdicts.get(need)
        return dict(verdicts.excluded) if verdicts else {}

    def forget(self, need: NeedId) -> None:
        """A need went or changed: its judgement starts afresh."""
        self._verdicts.pop(need, None)

    def drop_unoffered(self, index: OfferIndex) -> None:
        """Lift the exclusions of streams that are no longer offered (one that comes back
        is a new stream)."""
        for verdicts in self._verdicts.values():
            for k in [k for k in verdicts.excluded if k not in index.by_key]:
                del verdicts.excluded[k]
                verdicts.recovering.pop(k, None)

    def watch(self, connected: Mapping[NeedId, set[str]], index: OfferIndex,
              now: float) -> None:
        """Listen to exactly the streams the needs are connected to or have excluded."""
        wanted: dict[str, str] = {}
        for need, current in connected.items():
            for k in current | self.excluded(need).keys():
                offer = index.by_key.get(k)
                if offer is not None:
                    wanted[k] = offer.type
        for k in self._streams.keys() - wanted.keys():
            self._streams.pop(k).stop_listening()
        for k, type_ in wanted.items():
            if k not in self._streams:
                stream = _Stream(k, type_, self.window_s, now, self._log)
                stream.stop_listening = self._hub.listen(k, stream.on_sample)
                self._streams[k] = stream

    def close(self) -> None:
        for stream in self._streams.values():
            stream.stop_listening()
        self._streams.clear()

    # -- measuring and judging
    @property
    def watching(self) -> bool:
        """Whether any stream is measured (``judge`` has work at every tick)."""
        return bool(self._streams)

    def judge(self, needs: Iterable[tuple[Requirement, set[str]]], index: OfferIndex,
              now: float) -> bool:
        """Measure every stream, then judge each need's connected and excluded streams;
        True if an exclusion came or went (the needs must be re-matched)."""
        self.measured = {k: m for k, m in ((k, s.measure(now))
                                           for k, s in self._streams.items()) if m is not None}
        changed = False
        for req, current in needs:
            verdicts = self._verdicts.setdefault((req.service_id, req.name), _Verdicts())
            changed |= self._exclude_failing(req, verdicts, current, index, now)
            changed |= self._readmit_passing(req, verdicts, index, now)
        return changed

    def _exclude_failing(self, req: Requirement, verdicts: _Verdicts, current: set[str],
                         index: OfferIndex, now: float) -> bool:
        """Exclude connected streams failing the predicate for ``grace_s``."""
        changed = False
        for k in current:
            offer, values = index.by_key.get(k), self.measured.get(k)
            if offer is None or values is None:
                verdicts.failing.pop(k, None)
                continue
            ok, reason = judge(req, offer, values)
            if ok:
                verdicts.failing.pop(k, None)
                continue
            since = verdicts.failing.setdefault(k, now)
            if now - since >= self.grace_s:
                verdicts.failing.pop(k)
                verdicts.excluded[k] = f"{reason} for {now - since:.2f} s: " + _fmt(values)
                log.info("need %s/%s: %s fails its predicate as measured (%s); re-matching",
                         req.service_id, req.name, k, verdicts.excluded[k])
                changed = True
        return changed

    def _readmit_passing(self, req: Requirement, verdicts: _Verdicts, index: OfferIndex,
                         now: float) -> bool:
        """Lift the exclusion of streams passing the predicate for ``grace_s``."""
        changed = False
        for k in list(verdicts.excluded):
            offer, values = index.by_key.get(k), self.measured.get(k)
            if offer is None or values is None or not judge(req, offer, values)[0]:
                verdicts.recovering.pop(k, None)
                continue
            since = verdicts.recovering.setdefault(k, now)
            if now - since >= self.grace_s:
                del verdicts.excluded[k]
                verdicts.recovering.pop(k)
                log.info("need %s/%s: %s satisfies its predicate again (%s)",
                         req.service_id, req.name, k, _fmt(values))
                changed = True
        return changed


def _fmt(values: Mapping[str, float]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in sorted(values.items()))
