"""A service's needs on the wire: the subscriptions each need holds (exactly the streams its
agent told it to take) and the dispatch of their samples to the user's ``on_sample``.

Samples are taken in Zenoh's own receiving thread and queued (at most ``SAMPLE_QUEUE``:
the oldest data is worth least): that callback only copies the bytes, so it runs there
rather than in a Python thread of Zenoh's, which would add a thread hand-off per sample.
One dispatch thread decodes them, moves their times onto this host's clock
(:mod:`agent.sdk.sampleclock`: a sample from another host is stamped on that host's clock)
and calls ``on_sample``, one at a time.

A need moved from one ability to another keeps the old subscription until the new one
delivers its first sample (at most ``RETIRE_S``): make before break, so the stream has no
gap while the new subscription reaches its publisher.

A need with ``standby`` is also subscribed to the next-best abilities its agent names.
Their samples are held, not delivered, while the chosen ones send: once a chosen link has
sent nothing for ``SILENT_PERIODS`` of its sample intervals (the longer of the one
measured on its arrivals and the one its ``frequency_hz`` advertises), the newest held
standby sample is delivered at once, and the standby's samples after it, until the chosen
link sends again.  A chosen ability that falls silent (a camera that lost its tag, a
stalled publisher) is thus stood in for within a sample interval or two, without waiting
for its agent to hear of it and match anew; when the agent does, the standby becomes the
chosen link without a new subscription.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import zenoh

from agent.protocol.registration import Match
from agent.protocol.sequence import stamp_refusal
from agent.runtime.logs import RateLimitedLog
from agent.runtime.payload import payload_bytes
from agent.sdk.sampleclock import SampleClocks
from schemas.codec import (
    MAX_IMAGE_BYTES,
    MAX_MESSAGE_BYTES,
    DecodeError,
    Measurement,
    decode_measurement,
)
from schemas.models import Need

if TYPE_CHECKING:
    from agent.sdk.service import Service

log = logging.getLogger("uma.service")

#: bound on received samples waiting for the dispatch thread (oldest data is worth least)
SAMPLE_QUEUE = 10_000
#: how long a replaced subscription is kept at most while its successor has sent nothing
RETIRE_S = 1.0
#: a chosen link is silent (its standby delivers) after this many of its sample intervals
#: without a sample: one interval is the stream's own pace, and arrivals jitter by a good
#: part of one on a loaded host
SILENT_PERIODS = 1.5
#: the sample interval assumed of a link that has shown none and advertises no
#: frequency_hz
DEFAULT_INTERVAL_S = 0.1
#: a link's sample interval is the median of its last this many arrival intervals (a
#: silence among them does not move it)
INTERVALS = 9

OnSample = Callable[[Measurement], Any]


@dataclass
class _Link:
    """One subscription of a need to a matched ability (the callback reads ``match``)."""

    match: Match
    subscriber: Any = None
    #: the newest stamp taken from it (``stamp_refusal``)
    newest_ns: int | None = None
    #: when a replaced link is dropped at the latest (monotonic s); None while current
    retire_at: float | None = None
    #: when it last delivered (or became a chosen link), monotonic s
    heard: float = 0.0
    #: its last arrival intervals, s (``INTERVALS``)
    intervals: deque[float] = field(default_factory=lambda: deque(maxlen=INTERVALS))
    #: whether ``heard`` is an arrival (not the moment it became a chosen link)
    delivered: bool = False

    def patience(self) -> float:
        """How long a chosen link may send nothing before its standby stands in: its
        sample interval, measured, but never shorter than the one it advertises (samples
        that arrive in bursts would make it too short)."""
        hz = self.match.attributes.get("frequency_hz")
        advertised = 1.0 / hz if isinstance(hz, (int, float)) and hz > 0 else 0.0
        measured = statistics.median(self.intervals) if self.intervals else 0.0
        return SILENT_PERIODS * (max(advertised, measured) or DEFAULT_INTERVAL_S)

    def arrived(self, now: float) -> None:
        """Count a sample that arrived at ``now``."""
        if self.delivered:
            self.intervals.append(now - self.heard)
        self.heard, self.delivered = now, True


@dataclass
class NeedHandle:
    """What ``Service.need`` returns; ``matches`` is the current set, best first."""

    need: Need
    on_sample: OnSample | None
    matches: tuple[Match, ...] = ()
    satisfied: bool = False
    links: dict[str, _Link] = field(default_factory=dict)
    #: replaced links, delivering until a current link delivers (make before break)
    retiring: dict[str, _Link] = field(default_factory=dict)
    #: the next-best links, delivering while a current link is silent (module docstring)
    standby: dict[str, _Link] = field(default_factory=dict)
    #: the newest standby sample not delivered (its link and bytes)
    held: tuple[_Link, bytes] | None = None
    #: stamp of the newest sample given to ``on_sample`` (a held one is never older)
    newest_ns: int | None = None
    last: tuple[int, int] = (-1, -1)  # (agent epoch, seq) of the last control applied
    last_at: float = 0.0  # when it was applied (monotonic s)

    @property
    def name(self) -> str:
        return self.need.name

    def standby_matches(self) -> tuple[Match, ...]:
        """The abilities subscribed as its standby."""
        return tuple(link.match for link in list(self.standby.values()))


class NeedLinks:
    """Subscribes each need to its matches and dispatches their samples (module
    docstring)."""

    def __init__(self, svc: Service, limited_log: RateLimitedLog) -> None:
        self._svc = svc
        self._log = limited_log
        #: a sample, () to wake the thread, None to end it
        self._samples: queue.Queue[tuple[NeedHandle, _Link, bytes] | tuple[()] | None] = (
            queue.Queue(SAMPLE_QUEUE))
        self._thread: threading.Thread | None = None
        #: guards the needs' link sets and held samples (the control and dispatch threads)
        self._retire_lock = threading.Lock()
        #: the needs holding a standby sample (dispatch thread)
        self._holding: set[str] = set()
        #: samples refused by their stamp (``stamp_refusal``), not given to ``on_sample``
        self.refused = 0
        #: the clocks of the agents whose streams the needs take
        self.clocks = SampleClocks(svc.agent_id, svc.realm, svc.now_ns, limited_log,
                                   on_ready=self._wake)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._dispatch, daemon=True,
                                        name=f"uma-service-{self._svc.service_id}-dispatch")
        self._thread.start()

    def close(self) -> None:
        """Undeclare every link and end the dispatch thread."""
        for need in self._svc._needs.values():
            with self._retire_lock:
                links = [*need.links.values(), *need.retiring.values(), *need.standby.values()]
                need.links.clear()
                need.retiring.clear()
                need.standby.clear()
                need.held = None
            for link in links:
                with contextlib.suppress(Exception):
                    link.subscriber.undeclare()
        with contextlib.suppress(queue.Full):
            self._samples.put_nowait(None)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(1.0)
        self.clocks.close()

    def apply(self, need: NeedHandle, matches: tuple[Match, ...], satisfied: bool,
              standby: tuple[Match, ...] = ()) -> None:
        """Subscribe to exactly ``matches`` and ``standby`` (keeping links that stay, a link
        moving between the two without a new subscription; a replaced link delivers until
        its successor does)."""
        svc = self._svc
        assert svc.session is not None
        wanted = {m.key: m for m in matches}
        spare = {m.key: m for m in standby if m.key not in wanted}
        replaced = any(key not in need.links for key in wanted)
        now = time.monotonic()
        with self._retire_lock:
            for key in list(need.links):
                if key in spare:
                    need.standby[key] = need.links.pop(key)
                elif key not in wanted:
                    link = need.links.pop(key)
                    link.retire_at = now + RETIRE_S
                    need.retiring[key] = link
            for key in [k for k in need.retiring if k in wanted or k in spare]:
                link = need.retiring.pop(key)  # wanted again before it was dropped
                link.retire_at = None
                (need.links if key in wanted else need.standby)[key] = link
            for key in [k for k in need.standby if k in wanted]:
                need.links[key] = need.standby.pop(key)
            gone = [need.standby.pop(k) for k in list(need.standby) if k not in spare]
            if need.held is not None and all(ln is not need.held[0]
                                             for ln in need.standby.values()):
                need.held = None
            self._drop_retiring(need, expired_only=replaced)
        for link in gone:
            with contextlib.suppress(Exception):
                link.subscriber.undeclare()
        for links, ms in ((need.links, wanted), (need.standby, spare)):
            for key, m in ms.items():
                link = links.get(key)
                if link is not None:
                    link.match = m  # attributes may have changed
                    continue
                link = _Link(m, heard=now)
                link.subscriber = svc.session.declare_subscriber(key, zenoh.handlers.Callback(
                    lambda smp, n=need, ln=link: self._on_data(n, ln, smp), indirect=False))
                links[key] = link
        with svc._cond:
            if need.matches != matches:
                log.info("service %s: need %s -> %s", svc.service_id, need.name,
                         ", ".join(m.key for m in matches) or "nothing")
            need.matches, need.satisfied = matches, satisfied
            svc._cond.notify_all()
        self.clocks.follow(svc.session, {m.agent_id for n in list(svc._needs.values())
                                         for m in (*n.matches, *n.standby_matches())})

    def _on_data(self, need: NeedHandle, link: _Link, smp: zenoh.Sample) -> None:
        limit = MAX_IMAGE_BYTES if need.need.type == "image" else MAX_MESSAGE_BYTES
        try:
            self._samples.put_nowait((need, link, payload_bytes(smp.payload, limit)))
        except DecodeError as exc:
            self._log.warning(f"data {link.match.key}", f"dropped: {exc}")
        except queue.Full:
            self._log.warning(f"service {self._svc.service_id} need {need.name}",
                              "callback queue full (on_sample too slow); samples dropped")

    def _wake(self, agent: str) -> None:
        """Have the dispatch thread take the held samples of ``agent`` (a full queue
        wakes it anyway)."""
        with contextlib.suppress(queue.Full):
            self._samples.put_nowait(())

    def _drop_retiring(self, need: NeedHandle, expired_only: bool = False) -> None:
        """Undeclare the need's replaced links (only those past ``retire_at``); lock held."""
        now = time.monotonic()
        for key, link in list(need.retiring.items()):
            if not expired_only or (link.retire_at or 0.0) <= now:
                del need.retiring[key]
                with contextlib.suppress(Exception):
                    link.subscriber.undeclare()

    def _current(self, need: NeedHandle, link: _Link) -> bool:
        """Whether a sample of ``link`` is still delivered: the link is current (its
        replaced predecessors are dropped then), or replaced but not yet succeeded."""
        with self._retire_lock:
            if need.links.get(link.match.key) is link:
                if need.retiring:
                    self._drop_retiring(need)
                return True
            self._drop_retiring(need, expired_only=True)
            return need.retiring.get(link.match.key) is link

    def _silent(self, need: NeedHandle, now: float) -> bool:
        """Whether a chosen link of ``need`` has sent nothing for its patience (its
        standby delivers then); lock held."""
        return any(now - c.heard > c.patience() for c in need.links.values())

    def _standing_in(self, need: NeedHandle, link: _Link, data: bytes, now: float) -> bool:
        """For a sample of a standby ``link``: whether it is delivered now (a chosen link
        is silent); else it is held as the newest (``_release``)."""
        with self._retire_lock:
            if need.standby.get(link.match.key) is not link:
                return False
            if self._silent(need, now):
                need.held = None
                return True
            need.held = (link, data)
        self._holding.add(need.name)
        return False

    def _release(self, now: float) -> None:
        """Deliver the held standby sample of each need whose chosen link fell silent."""
        for name in list(self._holding):
            need = self._svc._needs.get(name)
            held = None
            with self._retire_lock:
                if need is not None and need.held is not None and self._silent(need, now):
                    held, need.held = need.held, None
                if need is None or need.held is None:
                    self._holding.discard(name)
            if held is not None:
                self._deliver(need, *held, standby=True)

    def _wait(self) -> float | None:
        """Seconds until a need holding a standby sample may have to release it (None:
        none holds one)."""
        deadlines = []
        with self._retire_lock:
            for name in self._holding:
                need = self._svc._needs.get(name)
                if need is not None:
                    deadlines += [c.heard + c.patience() for c in need.links.values()]
        return max(min(deadlines) - time.monotonic(), 0.001) if deadlines else None

    def _dispatch(self) -> None:
        while True:
            try:
                item = self._samples.get(timeout=self._wait())
            except queue.Empty:
                item = ()
            if item is None or self._svc.closed:
                return
            now = time.monotonic()
            if item:
                need, link, data = item
                link.arrived(now)
                if self._current(need, link):
                    self._deliver(need, link, data)
                elif self._standing_in(need, link, data, now):
                    self._deliver(need, link, data, standby=True)
            if self._holding:
                self._release(now)
            if self.clocks.holding:
                for held in self.clocks.released():
                    self._pass_on(*held)

    def _deliver(self, need: NeedHandle, link: _Link, data: bytes,
                 standby: bool = False) -> None:
        """Decode one sample, move its time onto this host's clock and hand it to
        ``on_sample``; a standby's sample only when newer than what was delivered."""
        try:
            m = decode_measurement(data, expected_type=need.need.type)
        except DecodeError as exc:
            self._log.warning(f"data {link.match.key}", f"dropped: {exc}")
            return
        self._pass_on(need, link, m, standby, len(data))

    def _pass_on(self, need: NeedHandle, link: _Link, m: Measurement, standby: bool,
                 size: int) -> None:
        """``_deliver`` of a decoded sample; held while its agent's clock offset is not
        good enough yet (:mod:`agent.sdk.sampleclock`)."""
        agent = link.match.agent_id
        t_ns = self.clocks.to_local(agent, m.t_ns)
        if t_ns is None:
            self.clocks.hold(agent, (need, link, m, standby, size), size)
            return
        m.t_ns, m.time_error_ns = t_ns, self.clocks.error_ns(agent)
        if standby and need.newest_ns is not None and t_ns <= need.newest_ns:
            return
        refusal = stamp_refusal(t_ns, self._svc.now_ns(), link.newest_ns)
        if refusal is not None:
            self.refused += 1
            self._log.warning(f"data {link.match.key}", f"refused: {refusal} "
                              f"({self.refused} refused so far)")
            return
        link.newest_ns = max(m.t_ns, link.newest_ns or 0)
        need.newest_ns = max(m.t_ns, need.newest_ns or 0)
        m.edge, m.source, m.attributes = (link.match.edge, link.match.service_id,
                                          link.match.attributes)
        if need.on_sample is None:
            return
        try:
            need.on_sample(m)
        except Exception as exc:
            if self._log.warning(f"service {self._svc.service_id} need {need.name}",
                                 f"on_sample raised {type(exc).__name__}: {exc}"):
                log.debug("on_sample traceback", exc_info=True)
