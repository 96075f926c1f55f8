"""A subscription: a stream of composed poses that follows route changes.

:meth:`agent.sdk.client.Client.subscribe` runs the query once with edge details, then a
:class:`Subscription` mirrors the route's edges in a local :class:`agent.srg.Graph`: static
edges from the answers, measured ones fed by subscribing directly to their services' data
keys.  Each sample of the fastest edge pushes a composed pose at its time; the other edges
are interpolated (or boundedly extrapolated) at that time: Ubitrack's push/pull rule.
``on_pose`` runs on the subscription's own thread, never on a Zenoh thread.

The mirror also answers :meth:`agent.sdk.client.Client.pose` on its route locally, as
tf2's buffer answers ``lookupTransform``: :meth:`Subscription.answer` interpolates the
mirrored edges at any time inside the buffer, with covariance, without the network.  A
route kept without a callback (:meth:`agent.sdk.client.Client.keep`) is a subscription that
only does that.  The mirror holds its samples on the clock of the agent whose edge pushes
(the route's clock) and converts times at each answer with the current offset estimate,
as a query to that agent does: a later, better offset estimate applies to old samples
too, and a kept answer equals the agents' on the same data.  A time the mirror would
extrapolate to, one outside its buffer, a stalled route or no route is left to the
agents: they may hold samples the mirror has not received.

Latency is the point of a stream, so the fastest edge's samples are not handed from Zenoh's
callback thread to ours through a Python queue (a lock, a condition and a GIL hand-off per
sample; docs/MEASUREMENTS.md).  Its subscriber has a Zenoh ring channel that
the subscription's thread reads itself, blocking in Zenoh's own receive; a subscription
that falls behind loses the oldest samples, counted in ``lost`` like any sequence gap.  The
other (pulled) edges only update the mirror, so they go straight into it from Zenoh's
callback.  A second thread follows the realm and watches for stalls.  A kept route has
no stream thread: nothing waits for its samples, so they wait in the ring, and the
watcher takes them into the mirror every ``WATCH_S``, as does every answer before it
reads the mirror (each answer holds every sample that arrived before it).  A thread woken
per sample cost a kept route about as much CPU as everything else its process did with
that sample, and put that wake-up on the path of every other stream of the host.

It follows the realm: whenever the client's ``topology`` moves it plans again, and if the
best route (or any edge of it) differs it rebuilds its mirror on the new route.  Of its
client it uses only the :class:`agent.sdk.query.Queries` (the query with details, the
session, the clock) and that one's :class:`agent.sdk.realm.RealmTracker` (``topology``,
who is alive); the client's own docstring describes outages and stalls.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from agent.attributes import EDGE_ATTRIBUTES
from agent.errors import InvalidInputError, UmaError
from agent.protocol import keys
from agent.protocol.query import edge_from_wire
from agent.protocol.sequence import SequenceGaps, stamp_refusal
from agent.result import PoseResult
from agent.runtime.callbacks import guarded
from agent.runtime.logs import RateLimitedLog
from agent.runtime.payload import payload_bytes
from agent.sdk.planner import Segment, SegmentError
from agent.sdk.query import Outcome, Queries
from agent.srg import Graph
from agent.srg.errors import EdgeUndefinedError
from schemas.codec import DecodeError, decode_pose

log = logging.getLogger("uma.client")

#: how often a subscription without a route tries again (besides at every realm change)
RETRY_S = 1.0
#: a subscription's fastest edge silent this many of its sample periods, and at least
#: STALL_MIN_S, is a stall (a route change takes up to a lease, 1 s, without samples)
STALL_PERIODS = 10
STALL_MIN_S = 1.5
#: samples of the fastest edge a subscription may fall behind before it loses the oldest
RING = 1024
#: how often a subscription checks whether the realm changed or its route stalled
WATCH_S = 0.05
#: how often the route's clock is measured again (a kept route asks the agents nothing
#: else, and an offset estimate older than ``ClockOffsets.max_age_s`` is dropped)
CLOCK_S = 10.0
#: samples a mirrored edge keeps per second of buffer (the fastest tracker's rate, and more)
MAX_RATE_HZ = 1000
#: the states in which a subscription holds a route's mirror
_ON_ROUTE = ("streaming", "stalled")


def stall_limit(rate_hz: float | None) -> float:
    """How long a stream of ``rate_hz`` may be silent before it is stalled: ``STALL_PERIODS``
    of its periods, at least ``STALL_MIN_S`` (``STALL_MIN_S`` when its rate is unknown).
    The one rule for subscriptions and for ``uma view``'s stream states."""
    return max(STALL_MIN_S, STALL_PERIODS / rate_hz) if rate_hz else STALL_MIN_S


#: what a route's mirror is made of: per segment, its agent and each edge's identity and
#: value (a different data key, attribute or static value means a different mirror)
Signature = tuple[tuple[str, tuple[tuple[Any, ...], ...]], ...]


def _signature(parts: list[tuple[Segment, list[dict[str, Any]]]]) -> Signature:
    """What the mirror of ``parts`` is made of, comparable and hashable."""
    def frozen(v: Any) -> Any:
        if isinstance(v, dict):
            return tuple(sorted((k, frozen(x)) for k, x in v.items()))
        if isinstance(v, list | tuple):
            return tuple(frozen(x) for x in v)
        return v
    return tuple((seg.agent, tuple(frozen(e) for e in edges)) for seg, edges in parts)


class Subscription:
    """A running stream of composed poses that follows route changes; ``close()`` stops it.

    ``status``: ``"streaming"``, ``"stalled"`` (on a route, but no sample of its fastest
    edge for ``stall_limit_s``), ``"no route"`` or ``"closed"``; ``route``: the segments
    in use; ``replans``: how many times it moved to another route; ``stalls``: how many
    times its route fell silent; ``lost``: samples of its edges lost on the way (gaps in
    their sequence numbers); ``refused``: samples refused (stamped more than
    ``agent.protocol.sequence.MAX_AHEAD_NS`` ahead of this clock); ``last_error``: the
    latest failure (bad sample, undefined pull, stall, no route); ``answered``: poses
    answered locally (:meth:`answer`).  ``on_pose`` None: a kept route, which only answers.
    """

    stall_limit = staticmethod(stall_limit)

    def __init__(self, queries: Queries, source: str, target: str,
                 on_pose: Callable[[PoseResult], Any] | None, error: str,
                 on_error: Callable[[Exception], Any] | None, first: Outcome,
                 topology: int, stall_s: float | None = None,
                 on_close: Callable[[Subscription], Any] = lambda sub: None,
                 buffer_s: float = 5.0) -> None:
        self.queries = queries
        self._on_close = on_close
        self._log = RateLimitedLog(log)
        self.source, self.target = source, target
        self.on_pose = on_pose
        self.on_error = on_error
        self.error = error
        self.delivered = 0
        self.failed = 0
        self.replans = 0
        self.stalls = 0
        self.refused = 0
        self.answered = 0
        self.buffer_s = float(buffer_s)
        self._gaps: dict[str, SequenceGaps] = {}
        #: the newest stamp taken from each feed (``stamp_refusal``)
        self._newest: dict[str, int] = {}
        self.last_error: Exception | None = None
        self.status = "streaming"
        self.stall_s = stall_s
        self.stall_limit_s = math.inf  # set for each route by _build
        self._last_push = time.monotonic()
        self.route: list[Segment] = []
        self.graph = self._new_graph()
        self.pusher: tuple | None = None
        #: the agent whose clock the mirror's samples are on (the pusher's), or None
        self.clock_agent: str | None = None
        self._next_clock = time.monotonic() + CLOCK_S
        #: the mirror (graph, feeds, pusher) is replaced by the watcher while samples
        #: arrive on Zenoh's threads and the stream's: every use of it holds this lock
        self._lock = threading.RLock()
        #: the pusher's subscriber, read by the stream thread; set when it changes
        self._pushed_by: tuple[str, str, zenoh.Subscriber] | None = None
        self._route_changed = threading.Event()
        self._decls: list[Any] = []
        self._feeds: dict[str, tuple[str, str, tuple, float]] = {}
        self._signature: Signature | None = None
        self._topology = topology
        self._next_retry = math.inf
        #: why the last re-planning failed while the route was kept (it still streamed)
        self._replan_failed: Exception | None = None
        self._closed = threading.Event()
        #: the mirror's query plan: (graph, its version, plan), see _compose
        self._plan: tuple[Graph, int, Any] | None = None
        self._build(first)
        #: a kept route has no stream thread: its samples are taken by ``_catch_up``
        self._streamer = None if on_pose is None else threading.Thread(
            target=self._stream, name="uma-subscription", daemon=True)
        self._watcher = threading.Thread(target=self._watch, name="uma-subscription-watch",
                                         daemon=True)
        if self._streamer is not None:
            self._streamer.start()
        self._watcher.start()

    # -- the mirror of one route
    def _build(self, outcome: Outcome) -> None:
        """Mirror the route of a query with details (dropping any previous mirror) and
        subscribe.  Zenoh's undeclarations happen outside the lock: a feed's callback may be
        waiting for it."""
        self._unsubscribe()
        with self._lock:
            self._mirror_route(outcome)
            streams = bool(self._feeds)
        self._route_changed.set()
        if not streams and self.on_pose is not None:
            self._deliver(outcome.pose)  # all static: the one answer is the stream

    def _mirror_route(self, outcome: Outcome) -> None:
        """The body of :meth:`_build` (lock held)."""
        parts = outcome.parts
        self._replan_failed = None
        self.graph = self._new_graph()
        feeds: list[tuple[str, str, tuple, float]] = []  # (agent, key, edge key, frequency)
        for seg, edges in parts:
            for e in edges:
                feeds += self._mirror(seg.agent, e)
        pushing = max(feeds, key=lambda f: f[3]) if feeds else None
        self.pusher = None if pushing is None else pushing[2]
        self.clock_agent = None if pushing is None else pushing[0]
        self.stall_limit_s = self._stall_limit(max((f[3] for f in feeds), default=0.0))
        self._last_push = time.monotonic()
        rates = [f[3] for f in feeds if f[3] > 0]
        if rates:  # a pulled edge may be extrapolated up to two of its sample periods
            self.graph.max_extrapolation_s = max(self.graph.max_extrapolation_s,
                                                 2.0 / min(rates))
        self._feeds = {f[1]: f for f in feeds}
        self.route = [seg for seg, _ in parts]
        self._signature = _signature(parts)
        self.status = "streaming"
        self._next_retry = math.inf
        session = self.queries.session
        for agent, key, edge_key, _ in feeds:
            if edge_key == self.pusher:
                sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(RING))
                self._pushed_by = (agent, key, sub)
            else:
                sub = session.declare_subscriber(key, zenoh.handlers.Callback(
                    guarded(lambda smp, a=agent, k=key: self._on_sample(
                        a, k, payload_bytes(smp.payload)), f"subscription {key}", self._log),
                    indirect=False))
            self._decls.append(sub)

    def _stall_limit(self, pusher_hz: float) -> float:
        """How long the fastest edge may be silent: ``stall_s``, or ``STALL_PERIODS`` of its
        advertised periods (never for a route without measured edges or stated rate)."""
        if self.pusher is None:
            return math.inf
        if self.stall_s is not None:
            return self.stall_s
        return stall_limit(pusher_hz) if pusher_hz > 0 else math.inf

    def _new_graph(self) -> Graph:
        """An empty mirror holding ``buffer_s`` of samples per edge."""
        return Graph(buffer_s=self.buffer_s,
                     max_samples=max(1000, math.ceil(self.buffer_s * MAX_RATE_HZ)))

    def _unsubscribe(self) -> None:
        """Undeclare every feed (which also ends the stream thread's read of the pusher)."""
        with self._lock:
            decls, self._decls = self._decls, []
            self._feeds = {}
            self._pushed_by = None
        for decl in decls:
            with contextlib.suppress(zenoh.ZError):
                decl.undeclare()
        self._route_changed.set()

    def _mirror(self, agent: str, wire: dict[str, Any]) -> list[tuple[str, str, tuple, float]]:
        """Copy one edge of the route into the local graph; measured ones become feeds."""
        e = edge_from_wire(wire)
        source = f"{agent}/{e.source}"
        attrs = {k: v for k, v in e.attributes.items()
                 if k in EDGE_ATTRIBUTES and k not in ("covariance", "static")}
        if e.static:
            self.graph.add_static(e.parent, e.child, e.position, e.quaternion,
                                  covariance=e.covariance, source=source, **attrs)
            return []
        if e.key is None:
            raise UmaError(f"agent {agent!r} gave no data key for edge "
                           f"{e.parent}->{e.child} [{e.source}]")
        owner = keys.parse_data(e.key, self.queries.realm)
        if owner is None or owner[0] != agent:
            raise UmaError(f"agent {agent!r} gave {e.key[:200]!r} as the data key of edge "
                           f"{e.parent}->{e.child}: not a stream of its own services")
        if e.covariance is not None:
            attrs["covariance"] = e.covariance
        key = self.graph.declare_measured(e.parent, e.child, source=source, **attrs)
        return [(agent, e.key, key, float(attrs.get("frequency_hz", 0.0)))]

    # -- following the realm
    def _follow(self) -> None:
        """Plan again if the realm changed (or, without a route, when it is time to retry);
        move to the new route if it differs from the mirrored one."""
        topology = self.queries.tracker.topology
        if topology == self._topology and time.monotonic() < self._next_retry:
            return
        self._topology = topology
        try:
            outcome = self.queries.ask(self.source, self.target, None, self.error,
                                       details=True)
            if self._closed.is_set() or (_signature(outcome.parts) == self._signature
                                         and self.status in _ON_ROUTE):
                self._replan_failed = None
                return
            was = [s.agent for s in self.route] if self.status in _ON_ROUTE else None
            self._build(outcome)
        except UmaError as exc:
            self._planning_failed(exc)
            return
        self.replans += 1
        log.info("subscription %s -> %s: now via %s (%s)", self.source, self.target,
                 ", ".join(str(s) for s in self.route),
                 "no route before" if was is None else f"was via agents {', '.join(was)}")

    def _planning_failed(self, exc: Exception) -> None:
        """Planning failed.  While the mirrored route's samples still arrive, keep
        delivering them: an agent's absence (its token lapsed on a frozen host, a
        partition) stops new plans, not a working stream; the stream ends only when it
        also stalls (:meth:`_check_stall`).  A segment that failed while every agent of the
        route is alive may be transient too (an answer late on a loaded machine).
        Otherwise stop delivering, say so once, and retry."""
        self.last_error = exc
        self._next_retry = time.monotonic() + RETRY_S
        recent = self.stall_limit_s if math.isfinite(self.stall_limit_s) else STALL_MIN_S
        flowing = (self.status == "streaming" and self.pusher is not None
                   and time.monotonic() - self._last_push <= recent)
        if self.status in _ON_ROUTE and (flowing or (
                isinstance(exc, SegmentError)
                and all(self.queries.tracker.is_alive(s.agent) for s in self.route))):
            self._replan_failed = exc
            self._log.warning(f"subscription {self.source} -> {self.target}",
                              f"re-planning failed, route kept while it streams: {exc}")
            return
        self._no_route(exc)

    def _no_route(self, exc: Exception) -> None:
        """Stop delivering, say so once (the worker retries every ``RETRY_S``)."""
        self._replan_failed = None
        if self.status == "no route":
            return
        self._unsubscribe()
        self.status = "no route"
        log.warning("subscription %s -> %s: no route (%s); will resume when one appears",
                    self.source, self.target, exc)
        if self.on_error is not None:
            try:
                self.on_error(exc)
            except Exception as cb_exc:
                self._log.warning("on_error", f"{type(cb_exc).__name__}: {cb_exc}")

    # -- samples
    def _stream(self) -> None:
        """Read the pusher's ring channel until the route changes, then the next one's."""
        while not self._closed.is_set():
            with self._lock:
                current = self._pushed_by
                self._route_changed.clear()
            if current is None:
                self._route_changed.wait(0.2)
                continue
            agent, key, sub = current
            try:
                for sample in sub:  # ends when the subscriber is undeclared
                    self._on_sample(agent, key, payload_bytes(sample.payload))
            except (zenoh.ZError, DecodeError) as exc:
                self._log.warning(f"subscription {key}", f"reading samples: {exc}")
            except Exception:  # a bug must not stop the stream; log it with its traceback
                log.exception("subscription %s -> %s: delivering failed", self.source,
                              self.target)

    def _catch_up(self) -> None:
        """A kept route: take the samples waiting in the pusher's ring into the mirror
        (module docstring); they were received, so they count as pushed."""
        if self.on_pose is not None:
            return
        with self._lock:
            self._take_waiting()

    def _take_waiting(self) -> None:
        """The body of :meth:`_catch_up` (lock held, a kept route)."""
        current = self._pushed_by
        if current is None:
            return
        agent, key, sub = current
        try:
            while (sample := sub.try_recv()) is not None:
                self._take(agent, key, payload_bytes(sample.payload))
        except (zenoh.ZError, DecodeError) as exc:
            self._log.warning(f"subscription {key}", f"reading samples: {exc}")

    def _watch(self) -> None:
        """Follow the realm and watch for stalls, every ``WATCH_S``; take a kept route's
        samples."""
        while not self._closed.wait(WATCH_S):
            try:
                self._catch_up()
                self._follow()
            except Exception:  # a bug must not stop the stream; log it with its traceback
                log.exception("subscription %s -> %s: re-planning failed", self.source,
                              self.target)
            self._check_stall()
            self._refresh_clock()

    def _refresh_clock(self) -> None:
        """Measure the route's clock again every ``CLOCK_S``: the mirror's times are
        converted with it, and nothing else asks the agent while the route is streaming."""
        now = time.monotonic()
        agent = self.clock_agent
        if now < self._next_clock or agent is None or self.status not in _ON_ROUTE:
            return
        self._next_clock = now + CLOCK_S
        self.queries.probe(agent)

    def _check_stall(self) -> None:
        """On a route whose fastest edge has been silent too long: say so, once."""
        silent = time.monotonic() - self._last_push
        if self.status != "streaming" or silent <= self.stall_limit_s:
            return
        if self._replan_failed is not None:  # kept only while it streamed: no longer
            self._no_route(self._replan_failed)
            return
        self.status = "stalled"
        self.stalls += 1
        edge = f"{self.pusher[0]} -> {self.pusher[1]}" if self.pusher else "?"
        self.last_error = UmaError(
            f"subscription {self.source} -> {self.target}: no sample of its fastest edge "
            f"{edge} for {silent:.1f} s, though the agents of its route "
            f"({', '.join(s.agent for s in self.route)}) are alive")
        log.warning("%s; staying on the route", self.last_error)

    def _pushed(self) -> None:
        """A sample of the fastest edge arrived: a stalled route streams again."""
        now = time.monotonic()
        if self.status == "stalled":
            self.status = "streaming"
            log.info("subscription %s -> %s: samples again after %.1f s", self.source,
                     self.target, now - self._last_push)
        self._last_push = now

    def _on_sample(self, agent: str, key: str, data: bytes) -> None:
        """One sample of a feed into the mirror; the pusher's also composes and delivers."""
        with self._lock:
            result = self._take(agent, key, data)
        if result is not None:
            self._deliver(result)

    def _take(self, agent: str, key: str, data: bytes) -> PoseResult | None:
        """The body of :meth:`_on_sample` (lock held): the pose to deliver, if any."""
        feed = self._feeds.get(key)
        if feed is None:
            return None  # a sample of a route left meanwhile
        edge_key = feed[2]
        clock = self.queries.clock
        gaps = self._gaps.get(key)
        if gaps is None:
            gaps = self._gaps[key] = SequenceGaps()
        seen = False
        try:
            t_ns, seq, p, q, cov = decode_pose(data)
            t = clock.to_local(agent, t_ns)
            refusal = stamp_refusal(t, time.time_ns(), self._newest.get(key))
            if refusal is not None:
                self.refused += 1
                raise InvalidInputError(f"{refusal}: refused ({self.refused} so far)")
            self._newest[key] = max(t, self._newest.get(key, 0))
            gap, seen = gaps.see(seq), True
            if gap:
                self._log.warning(f"subscription {key}", f"{gap} sample(s) lost before "
                                  f"s={seq} (dropped on the way, or this subscription fell "
                                  f"{RING} samples behind); {self.lost} so far")
            on_route_clock = (t_ns if agent == self.clock_agent or self.clock_agent is None
                              else clock.to_remote(self.clock_agent, t))
            self.graph.add_decoded(edge_key[0], edge_key[1], on_route_clock, p, q, cov,
                                   source=edge_key[2])
        except (DecodeError, ValueError) as exc:
            self.failed += 1
            if not seen:  # it arrived: no loss when the next one's s skips it
                gaps.skip()
            self.last_error = exc
            self._log.warning(f"subscription {key}", f"bad sample: {exc}")
            return None
        if edge_key != self.pusher:
            return None
        self._pushed()
        if self.on_pose is None:
            return None  # a kept route: composed only when asked (answer)
        try:
            r = self._compose(t_ns)
        except EdgeUndefinedError as exc:  # a pulled edge has no data at t yet
            self.failed += 1
            self.last_error = exc
            return None
        return _on_local_clock(r, t_ns - t)

    def answer(self, at: int | None) -> PoseResult | None:
        """The route's pose at ``at`` (ns on this clock, checked by the caller; None: the
        latest time every edge has data) from the mirror, or None where the agents must
        answer: not streaming, or ``at`` outside what the mirror holds without
        extrapolating (module docstring)."""
        agent = self.clock_agent
        offset = 0 if agent is None else self.queries.clock.offset(agent) or 0
        r = self.answer_on_route_clock(None if at is None else at + offset)
        return None if r is None else _on_local_clock(r, offset)

    def answer_on_route_clock(self, at: int | None) -> PoseResult | None:
        """:meth:`answer` with ``at`` and the result on the route's clock (that of
        ``clock_agent``): what that agent itself would answer on the same samples."""
        if self.status != "streaming":
            return None
        with self._lock:
            if self.on_pose is None:
                self._take_waiting()
            if self.status != "streaming":
                return None
            try:
                r = self._compose(at)
            except LookupError:
                return None
        if r.extrapolated_s:
            return None
        self.answered += 1
        return r

    def _compose(self, at: int | None) -> PoseResult:
        """The mirror's route at ``at`` (lock held): its graph's plan, kept while the graph
        is unchanged (a mirror's graph changes only when it is rebuilt)."""
        graph = self.graph
        if self.source == self.target:
            return graph.pose(self.source, self.target, at=at, error="hops")
        if self._plan is None or self._plan[0] is not graph or self._plan[1] != graph.version:
            self._plan = (graph, graph.version, graph.plan(self.source, self.target, "hops"))
        return self._plan[2].evaluate(at)

    @property
    def lost(self) -> int:
        """Samples of the route's edges lost on the way (since the subscription began)."""
        return sum(g.lost for g in list(self._gaps.values()))

    def _deliver(self, result: PoseResult) -> None:
        if self.on_pose is None:
            return
        try:
            self.on_pose(result)
            self.delivered += 1
        except Exception as exc:
            self.failed += 1
            self.last_error = exc
            self._log.warning("on_pose", f"{type(exc).__name__}: {exc}")

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        me = threading.current_thread()  # on_pose or on_error may close their subscription
        if self._watcher is not me:
            self._watcher.join(1.0 + self.queries.timeout)  # it may be re-planning
        self._unsubscribe()  # after the watcher: it may have subscribed a new route
        if self._streamer is not None and self._streamer is not me:
            self._streamer.join(1.0)
        self.status = "closed"
        self._on_close(self)


def _on_local_clock(r: PoseResult, offset: int) -> PoseResult:
    """A mirror's answer (on the route's clock) moved to this clock: ``offset`` is the
    route's clock minus ours.  The result is the query's own, so it is changed in place."""
    if offset:
        if r.t_ns is not None:
            r.t_ns -= offset
        r.stamps = [(a - offset, b - offset) for a, b in r.stamps]
    return r
