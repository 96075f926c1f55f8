"""A service's needs on the wire: the subscriptions each need holds (exactly the streams its
agent told it to take) and the dispatch of their samples to the user's ``on_sample``.

Samples are taken in Zenoh's thread and queued (at most ``SAMPLE_QUEUE``: the oldest data
is worth least); one dispatch thread decodes them, moves their times onto this host's clock
(:mod:`agent.sdk.sampleclock`: a sample from another host is stamped on that host's clock)
and calls ``on_sample``, one at a time.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
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

OnSample = Callable[[Measurement], Any]


@dataclass
class _Link:
    """One subscription of a need to a matched ability (the callback reads ``match``)."""

    match: Match
    subscriber: Any = None
    #: the newest stamp taken from it (``stamp_refusal``)
    newest_ns: int | None = None


@dataclass
class NeedHandle:
    """What ``Service.need`` returns; ``matches`` is the current set, best first."""

    need: Need
    on_sample: OnSample | None
    matches: tuple[Match, ...] = ()
    satisfied: bool = False
    links: dict[str, _Link] = field(default_factory=dict)
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
            for link in need.links.values():
                with contextlib.suppress(Exception):
                    link.subscriber.undeclare()
            need.links.clear()
        with contextlib.suppress(queue.Full):
            self._samples.put_nowait(None)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(1.0)
        self.clocks.close()

    def apply(self, need: NeedHandle, matches: tuple[Match, ...], satisfied: bool) -> None:
        """Subscribe to exactly ``matches`` (keeping links that stay)."""
        svc = self._svc
        assert svc.session is not None
        wanted = {m.key: m for m in matches}
        for key in list(need.links):
            if key not in wanted:
                with contextlib.suppress(Exception):
                    need.links.pop(key).subscriber.undeclare()
        for key, m in wanted.items():
            link = need.links.get(key)
            if link is not None:
                link.match = m  # attributes may have changed
                continue
            link = _Link(m)
            link.subscriber = svc.session.declare_subscriber(
                key, lambda smp, n=need, ln=link: self._on_data(n, ln, smp))
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

    def _dispatch(self) -> None:
        while True:
            item = self._samples.get()
            if item is None or self._svc.closed:
                return
            need, link, data = item
            if link.match.key not in need.links:
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
