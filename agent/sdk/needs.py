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
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
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
    last: tuple[int, int] = (-1, -1)  # (agent epoch, seq) of the last control applied
    last_at: float = 0.0  # when it was applied (monotonic s)

    @property
    def name(self) -> str:
        return self.need.name


class NeedLinks:
    """Subscribes each need to its matches and dispatches their samples (module
    docstring)."""

    def __init__(self, svc: Service, limited_log: RateLimitedLog) -> None:
        self._svc = svc
        self._log = limited_log
        self._samples: queue.Queue[tuple[NeedHandle, _Link, bytes] | None] = queue.Queue(
            SAMPLE_QUEUE)
        self._thread: threading.Thread | None = None
        #: guards the needs' ``retiring`` links (the control and dispatch threads)
        self._retire_lock = threading.Lock()
        #: samples refused by their stamp (``stamp_refusal``), not given to ``on_sample``
        self.refused = 0
        #: the clocks of the agents whose streams the needs take
        self.clocks = SampleClocks(svc.agent_id, svc.realm, svc.now_ns, limited_log)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._dispatch, daemon=True,
                                        name=f"uma-service-{self._svc.service_id}-dispatch")
        self._thread.start()

    def close(self) -> None:
        """Undeclare every link and end the dispatch thread."""
        for need in self._svc._needs.values():
            with self._retire_lock:
                links = [*need.links.values(), *need.retiring.values()]
                need.links.clear()
                need.retiring.clear()
            for link in links:
                with contextlib.suppress(Exception):
                    link.subscriber.undeclare()
        with contextlib.suppress(queue.Full):
            self._samples.put_nowait(None)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(1.0)
        self.clocks.close()

    def apply(self, need: NeedHandle, matches: tuple[Match, ...], satisfied: bool) -> None:
        """Subscribe to exactly ``matches`` (keeping links that stay; a replaced link
        delivers until its successor does)."""
        svc = self._svc
        assert svc.session is not None
        wanted = {m.key: m for m in matches}
        replaced = any(key not in need.links for key in wanted)
        with self._retire_lock:
            for key in list(need.links):
                if key not in wanted:
                    link = need.links.pop(key)
                    link.retire_at = time.monotonic() + RETIRE_S
                    need.retiring[key] = link
            for key in list(need.retiring):
                if key in wanted:  # wanted again before it was dropped
                    need.links[key] = need.retiring.pop(key)
                    need.links[key].retire_at = None
            self._drop_retiring(need, expired_only=replaced)
        for key, m in wanted.items():
            link = need.links.get(key)
            if link is not None:
                link.match = m  # attributes may have changed
                continue
            link = _Link(m)
            link.subscriber = svc.session.declare_subscriber(key, zenoh.handlers.Callback(
                lambda smp, n=need, ln=link: self._on_data(n, ln, smp), indirect=False))
            need.links[key] = link
        with svc._cond:
            if need.matches != matches:
                log.info("service %s: need %s -> %s", svc.service_id, need.name,
                         ", ".join(m.key for m in matches) or "nothing")
            need.matches, need.satisfied = matches, satisfied
            svc._cond.notify_all()
        self.clocks.follow(svc.session, {m.agent_id for n in list(svc._needs.values())
                                         for m in n.matches})

    def _on_data(self, need: NeedHandle, link: _Link, smp: zenoh.Sample) -> None:
        limit = MAX_IMAGE_BYTES if need.need.type == "image" else MAX_MESSAGE_BYTES
        try:
            self._samples.put_nowait((need, link, payload_bytes(smp.payload, limit)))
        except DecodeError as exc:
            self._log.warning(f"data {link.match.key}", f"dropped: {exc}")
        except queue.Full:
            self._log.warning(f"service {self._svc.service_id} need {need.name}",
                              "callback queue full (on_sample too slow); samples dropped")

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

    def _dispatch(self) -> None:
        while True:
            item = self._samples.get()
            if item is None or self._svc.closed:
                return
            need, link, data = item
            if not self._current(need, link):
                continue  # disconnected meanwhile
            try:
                m = decode_measurement(data, expected_type=need.need.type)
            except DecodeError as exc:
                self._log.warning(f"data {link.match.key}", f"dropped: {exc}")
                continue
            t_ns = self.clocks.to_local(link.match.agent_id, m.t_ns)
            if t_ns is None:
                continue
            m.t_ns = t_ns
            refusal = stamp_refusal(t_ns, self._svc.now_ns(), link.newest_ns)
            if refusal is not None:
                self.refused += 1
                self._log.warning(f"data {link.match.key}", f"refused: {refusal} "
                                  f"({self.refused} refused so far)")
                continue
            link.newest_ns = max(m.t_ns, link.newest_ns or 0)
            m.edge, m.source, m.attributes = (link.match.edge, link.match.service_id,
                                              link.match.attributes)
            if need.on_sample is None:
                continue
            try:
                need.on_sample(m)
            except Exception as exc:
                if self._log.warning(f"service {self._svc.service_id} need {need.name}",
                                     f"on_sample raised {type(exc).__name__}: {exc}"):
                    log.debug("on_sample traceback", exc_info=True)
