"""Whole routes answered by one agent: its own segment, other agents' segments from its
supernode cache, and one request to the remaining agents for what it lacks.

A client asks the first agent of a route (``{"op": "route"}``, :mod:`agent.protocol.query`)
instead of every agent of it: one round trip, answered here.  Each part carries its
time on its own agent's clock, as the client computed it for the fan-out, so an answer
from the cache is what that agent would say on the same samples.

The supernode cache (:class:`SegmentCache`) holds the segments of other agents that this
agent is asked for often (``HOT_REQUESTS`` within ``HOT_WINDOW_S``): each is a kept route
(``Client.keep`` of the SDK over this agent's session, the SDK's own mirror,
fed by subscription to the segment's data keys), used only while its route is exactly
that agent's segment.  At most ``MAX_KEPT`` are kept; one unused for ``UNUSED_S`` is
dropped, and the least recently used goes first when room is needed.

What the cache lacks is asked of its agents in one request whose replies are collected on
Zenoh's threads (never blocking the thread that received the route), and the route is
answered when the last one is in or after ``FORWARD_TIMEOUT_S``, without the parts whose
agent did not answer (the client then treats that agent as it treats a missing answer).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import zenoh

from agent.protocol import keys
from agent.protocol import query as proto
from agent.result import PoseResult
from agent.runtime.logs import RateLimitedLog
from agent.runtime.payload import payload_bytes
from agent.runtime.worker import WakeLoop
from agent.srg.composition import compose

log = logging.getLogger("uma.srg")

#: requests of one remote segment within HOT_WINDOW_S that make this agent keep it
HOT_REQUESTS = 3
HOT_WINDOW_S = 5.0
#: remote segments kept at once, and how long one may go unused before it is dropped
MAX_KEPT = 32
UNUSED_S = 10.0
#: how much of a kept segment's history is held (clients ask past times inside it)
KEPT_BUFFER_S = 10.0
#: remote segments whose requests are counted (strangers' requests must not grow it)
MAX_COUNTED = 1024
#: how long the agents asked for missing parts have, and how many such requests may wait
FORWARD_TIMEOUT_S = 1.0
MAX_FORWARDS = 64

#: a remote segment: (agent, source, target, error)
SegmentKey = tuple[str, str, str, str]


class SegmentCache:
    """Other agents' segments kept fresh by subscription (module docstring).

    ``answer`` runs on Zenoh's threads and never waits; keeping and dropping happen on
    the cache's own thread, which opens a client (``client``: called as
    ``client(realm, session=..., timeout=...)``, :class:`agent.Client` in ``uma agent``) on
    the agent's session when the first segment gets hot.  The daemon never imports the SDK:
    whoever starts the agent hands the client class in; without one nothing is kept.
    """

    def __init__(self, session: zenoh.Session, realm: str,
                 client: Callable[..., Any] | None, timeout_s: float = 2.0) -> None:
        self.session = session
        self.realm = realm
        self.timeout_s = timeout_s
        self._open_client = client
        self._lock = threading.Lock()
        self._client: Any = None
        #: kept segments: key -> [subscription, last used (monotonic)], least recent first
        self._kept: OrderedDict[SegmentKey, list[Any]] = OrderedDict()
        #: per remote segment not kept: (requests in the window, window start)
        self._counts: dict[SegmentKey, tuple[int, float]] = {}
        self._wanted: set[SegmentKey] = set()
        #: segments that could not be kept (no route, not that agent's), not tried again
        #: until HOT_WINDOW_S has passed
        self._refused: dict[SegmentKey, float] = {}
        self.hits = 0
        self.misses = 0
        self._log = RateLimitedLog(log)
        self._loop = WakeLoop("uma-segment-cache", self._work, self._log, "segment cache")
        self._loop.start()

    def answer(self, agent: str, req: proto.SegmentRequest) -> dict[str, Any] | None:
        """The wire result of ``agent``'s segment from the cache, or None (counted: a
        segment asked for often is kept from then on)."""
        r = self.result(agent, req)
        if r is None:
            return None
        return proto.result_to_wire(r, req.source, req.target, agent, self.time_of(agent, r, req))

    def result(self, agent: str, req: proto.SegmentRequest) -> PoseResult | None:
        """``agent``'s segment from the cache, on ``agent``'s clock, or None (counted)."""
        key = (agent, req.source, req.target, req.error)
        entry = None if req.details else self._kept.get(key)
        if entry is not None:
            sub = entry[0]
            r = None
            if (sub.clock_agent in (None, agent) and len(sub.route) == 1
                    and sub.route[0].agent == agent):
                r = sub.answer_on_route_clock(req.t)
            if r is not None:
                entry[1] = time.monotonic()
                self.hits += 1
                return r
        self.misses += 1
        if entry is None and not req.details:
            self._count(key)
        return None

    def time_of(self, agent: str, r: PoseResult, req: proto.SegmentRequest) -> int:
        """The time of a cached answer on ``agent``'s clock (an all-static one: the asked
        time, or now on that clock)."""
        if r.t_ns is not None:
            return r.t_ns
        if req.t is not None:
            return req.t
        return time.time_ns() + (self._client.clock.offset(agent) or 0)

    def _count(self, key: SegmentKey) -> None:
        now = time.monotonic()
        with self._lock:
            n, since = self._counts.get(key, (0, now))
            if now - since > HOT_WINDOW_S:
                n, since = 0, now
            n += 1
            if n >= HOT_REQUESTS and now >= self._refused.get(key, 0.0):
                self._counts.pop(key, None)
                self._wanted.add(key)
                self._loop.wake()
                return
            if len(self._counts) >= MAX_COUNTED and key not in self._counts:
                self._counts.clear()
            self._counts[key] = (n, since)

    @property
    def kept(self) -> list[SegmentKey]:
        """The segments kept now, least recently used first."""
        return list(self._kept)

    # ------------------------------------------------------------------ the worker

    def _work(self) -> None:
        """Keep the segments asked for often; drop those unused for the idle time."""
        self._drop_unused()
        with self._lock:
            wanted, self._wanted = self._wanted, set()
        for key in sorted(wanted):
            if self._loop.stopping:
                return
            self._keep(key)

    def _keep(self, key: SegmentKey) -> None:
        """Keep one segment, making room first (the least recently used goes)."""
        if key in self._kept:
            return
        if self._open_client is None:
            self._refuse(key, "this agent was started without a client to keep segments with")
            return
        if self._client is None:
            self._client = self._open_client(self.realm, session=self.session,
                                             timeout=self.timeout_s)
        while len(self._kept) >= MAX_KEPT:
            self._close(next(iter(self._kept)))
        agent, source, target, error = key
        try:
            sub = self._client.keep(source, target, buffer_s=KEPT_BUFFER_S, error=error)
        except (LookupError, ValueError, proto.RefusedError) as exc:
            self._refuse(key, str(exc))
            return
        except Exception as exc:  # an UmaError of the realm (no agents): try again later
            self._refuse(key, f"{type(exc).__name__}: {exc}")
            return
        if [s.agent for s in sub.route] != [agent]:
            sub.close()
            self._refuse(key, f"its best route is {', '.join(map(str, sub.route))}, not "
                              f"agent {agent!r}'s segment")
            return
        self._kept[key] = [sub, time.monotonic()]
        log.info("segment cache: keeping %s -> %s of agent %r (%d kept)", source, target,
                 agent, len(self._kept))

    def _refuse(self, key: SegmentKey, why: str) -> None:
        with self._lock:
            self._refused[key] = time.monotonic() + HOT_WINDOW_S
            if len(self._refused) > MAX_COUNTED:
                self._refused.pop(next(iter(self._refused)))
        self._log.warning("segment cache", f"not keeping {key[1]} -> {key[2]} of agent "
                          f"{key[0]!r}: {why}")

    def _drop_unused(self) -> None:
        now = time.monotonic()
        for key, (sub, used) in list(self._kept.items()):
            if now - used > UNUSED_S or sub.status == "closed":
                self._close(key)

    def _close(self, key: SegmentKey) -> None:
        entry = self._kept.pop(key, None)
        if entry is not None:
            entry[0].close()
            log.info("segment cache: dropped %s -> %s of agent %r", key[1], key[2], key[0])

    def close(self) -> None:
        self._loop.close(5.0)
        for key in list(self._kept):
            self._close(key)
        if self._client is not None:
            self._client.close()


class RouteRelay:
    """Answers ``route`` requests for one agent (module docstring)."""

    def __init__(self, session: zenoh.Session, realm: str, agent_id: str,
                 own: Callable[[proto.SegmentRequest], dict[str, Any]],
                 now_ns: Callable[[], int], cache: SegmentCache,
                 own_result: Callable[[proto.SegmentRequest], PoseResult]) -> None:
        self.session = session
        self.realm = realm
        self.agent_id = agent_id
        self._own = own
        self._own_result = own_result
        self._now_ns = now_ns
        self.cache = cache
        self._key = keys.agent_query(realm, agent_id)
        self._forwards = 0
        self._lock = threading.Lock()
        self._log = RateLimitedLog(log)

    def local_parts(self, request: proto.RouteRequest,
                    ) -> tuple[dict[str, dict[str, Any]], dict[str, proto.SegmentRequest]]:
        """The parts answered here (this agent's own, the cache's) and those missing."""
        parts: dict[str, dict[str, Any]] = {}
        missing: dict[str, proto.SegmentRequest] = {}
        for agent, req in request.parts.items():
            if agent == self.agent_id:
                parts[agent] = self._own(req)
                continue
            hit = self.cache.answer(agent, req)
            if hit is not None:
                parts[agent] = {**proto.segment_reply(hit), "cached": True}
            else:
                missing[agent] = req
        return parts, missing

    def composed(self, request: proto.RouteRequest) -> dict[str, Any] | None:
        """The whole route composed here when every part is (this agent's own, the
        cache's), as the ``route`` answer of :mod:`agent.protocol.query`; else None."""
        parts = []
        for agent, req in request.parts.items():
            if agent == self.agent_id:
                try:
                    r = self._own_result(req)
                except (LookupError, ValueError, TypeError):
                    return None  # its error is answered with the parts
            else:
                r = self.cache.result(agent, req)
                if r is None:
                    return None
            parts.append((agent, req, r))
        whole = compose([r for _, _, r in parts], None)
        edges, times = [], {}
        for agent, req, r in parts:
            static = not r.stamps
            t = (r.t_ns if r.t_ns is not None else req.t if req.t is not None else 0)
            edges += proto.wire_edges(r, agent, t)
            times[agent] = None if static else r.t_ns
        reference = next((t for t in times.values() if t is not None), 0)
        first, last = parts[0][1], parts[-1][1]
        result = proto.result_to_wire(whole, first.source, last.target, self.agent_id,
                                      reference, edges)
        return {"ok": True, "route": {"result": result, "times": times},
                "cached": len(parts) - (self.agent_id in request.parts)}

    def answer(self, query: zenoh.Query, request: proto.RouteRequest, t2: int) -> None:
        """Reply to ``query`` with the route composed here, or every part of it (now, or
        once the agents asked for the missing parts have answered)."""
        if request.compose:
            whole = self.composed(request)
            if whole is not None:
                self.reply(query, whole, t2)
                return
        parts, missing = self.local_parts(request)
        if not missing or not self._may_forward():
            self.reply(query, {"ok": True, "parts": parts}, t2)
            return
        pending = _Pending(self, query, parts, t2, set(missing))
        selector = (keys.agent_query(self.realm, next(iter(missing))) if len(missing) == 1
                    else keys.all_agent_queries(self.realm))
        try:
            self.session.get(selector, zenoh.handlers.Callback(pending.on_reply,
                                                               pending.done),
                             payload=proto.segments_request(missing),
                             consolidation=zenoh.ConsolidationMode.NONE,
                             timeout=FORWARD_TIMEOUT_S)
        except zenoh.ZError as exc:
            self._log.warning("route", f"asking {', '.join(missing)}: {exc}")
            pending.done()

    def _may_forward(self) -> bool:
        with self._lock:
            if self._forwards >= MAX_FORWARDS:
                self._log.warning("route", f"{MAX_FORWARDS} routes wait for other agents: "
                                  "answered without the parts this agent lacks")
                return False
            self._forwards += 1
            return True

    def forwarded(self) -> None:
        with self._lock:
            self._forwards -= 1

    def reply(self, query: zenoh.Query, answer: dict[str, Any], t2: int) -> None:
        try:
            query.reply(self._key, proto.stamped(answer, self.agent_id, t2, self._now_ns()))
        except (zenoh.ZError, ValueError) as exc:
            self._log.warning("route reply", str(exc))


class _Pending:
    """One route waiting for the answers of the agents asked for its missing parts."""

    def __init__(self, relay: RouteRelay, query: zenoh.Query, parts: dict[str, dict[str, Any]],
                 t2: int, expected: set[str]) -> None:
        self.relay = relay
        self.query: zenoh.Query | None = query
        self.parts = parts
        self.t2 = t2
        self.expected = expected
        self._lock = threading.Lock()

    def on_reply(self, reply: zenoh.Reply) -> None:
        """One agent's answer (Zenoh's thread): its part, without its clock stamps."""
        if reply.ok is None:
            return
        agent = keys.parse_agent_query(str(reply.ok.key_expr), self.relay.realm)
        if agent not in self.expected:
            return
        answer = proto.decode_reply(payload_bytes(reply.ok.payload))
        if answer.get("agent") != agent:
            return  # an answer naming another agent than its key's: not taken
        for stamp in ("agent", "t2", "t3"):
            answer.pop(stamp, None)
        with self._lock:
            if self.query is None:
                return  # answered already (the request ended)
            self.parts[agent] = answer
            complete = self.expected <= self.parts.keys()
        if complete:
            self.done()

    def done(self) -> None:
        """Every expected agent answered, or the request ended: reply once (the parts are
        not changed after this)."""
        with self._lock:
            query, self.query = self.query, None
        if query is None:
            return
        self.relay.forwarded()
        self.relay.reply(query, {"ok": True, "parts": self.parts}, self.t2)
        with contextlib.suppress(Exception):
            query.drop()
