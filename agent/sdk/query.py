"""One pose query's life, top to bottom: plan, ask, compose, retry.

:meth:`Queries.ask` plans routes over the agents' supernode summaries
(:mod:`agent.sdk.planner`), asks the first agent of the best live route for the whole
route (one round trip: that agent answers its own segment, the others' from its supernode
cache, and asks the remaining agents itself, :mod:`agent.daemon.relay`), or, as the
fallback, each owning agent for its segment at ``t`` (all at once, one round trip; the
messages are :mod:`agent.protocol.query`'s),
composes the answers with their covariances as they arrive, and, if an agent does not
answer or cannot, tries the next route without it.  ``at`` is on this process's clock;
each agent's clock offset is estimated from the round trips (:mod:`agent.sdk.clock`) and
applied both ways.  ``at=None`` means the latest time at which every measured segment of
the route has data: segments answered at a later time are asked again at that one.

What queries share lives here too: planned routes (until a summary changes), encoded
requests for the latest time, the answers of all-static segments (until their agent's
summary changes), and one declared querier per query key.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from agent.errors import InvalidInputError, UmaError
from agent.protocol import keys
from agent.protocol import query as proto
from agent.result import PoseResult
from agent.runtime.logs import RateLimitedLog
from agent.sdk.clock import ClockOffsets
from agent.sdk.planner import (
    Route,
    RouteError,
    Segment,
    SegmentError,
    plan_routes,
    usable_routes,
    with_departed,
    with_silent,
)
from agent.sdk.realm import RealmTracker, RealmView
from agent.srg.composition import Composition, compose
from agent.srg.errorfn import ErrorFunction, error_function
from agent.srg.errors import UnknownFrameError, UnreachableError
from agent.srg.graph import identity

log = logging.getLogger("uma.client")

#: routes tried before a query gives up
MAX_ROUTES = 4
#: reply keys whose parse is remembered, and error functions whose parse is
MAX_REPLY_KEYS = 1024

#: one segment's answer: its pose and (when asked for) its edges' details, as sent
Answer = tuple[PoseResult, list[dict[str, Any]]]
#: one agent's reply as it arrives: (agent id, decoded reply, our send time, receive time)
Reply = tuple[str, dict[str, Any], int, int]


class NoAgentsError(UmaError):
    """Nobody in the realm answered."""


def check_time(at: Any) -> int | None:
    """A query's time as a plain int (None: the latest); ``ValueError`` for anything else."""
    if at is None or type(at) is int:
        return at
    if isinstance(at, bool) or not isinstance(at, (int, np.integer)):
        raise InvalidInputError(f"at must be integer ns since the epoch or None, got {at!r}")
    return int(at)


@dataclass
class Outcome:
    """A query's composed pose, and per segment of its route the edges' details (empty
    unless asked for: a subscription mirrors them)."""

    pose: PoseResult
    parts: list[tuple[Segment, list[dict[str, Any]]]]


class AgentQueries:
    """Queries to the agents of a realm by agent id, and the clock offsets their answers
    give: the transport every asker shares (:class:`Queries`' pose queries, a service's
    clock round trips, :mod:`agent.sdk.needs`).  ``now`` is this host's clock, on which
    the offsets are measured."""

    def __init__(self, session: zenoh.Session, realm: str, timeout: float,
                 clock: ClockOffsets, now: Callable[[], int] = time.time_ns) -> None:
        self.session = session
        self.realm = realm
        self.timeout = timeout
        self.clock = clock
        self.now = now
        self._lock = threading.Lock()
        self._log = RateLimitedLog(log)
        #: answers refused: they came on one agent's key naming another (or none)
        self.refused = 0
        #: agent id (or None) by the key a reply came on
        self._reply_keys: dict[str, str | None] = {}
        #: declared queriers by agent id (None: every agent's query key)
        self._queriers: dict[str | None, zenoh.Querier] = {}

    def close(self) -> None:
        with self._lock:
            queriers, self._queriers = list(self._queriers.values()), {}
        for querier in queriers:
            with contextlib.suppress(zenoh.ZError):
                querier.undeclare()

    # ------------------------------------------------------------------ clocks

    def probe(self, agent: str) -> bool:
        """One clock round trip to ``agent`` alone; True if it answered."""
        answered = False
        try:
            for who, reply, t1, t4 in self.answers(proto.clock_request(), [agent]):
                self._clock_sample(who, reply, t1, t4)
                answered = answered or who == agent
        except zenoh.ZError as exc:
            self._log.warning("probe", f"asking agent {agent!r}: {exc}")
        return answered

    def _clock_sample(self, agent: str, reply: dict[str, Any], t1: int, t4: int) -> None:
        times = proto.reply_times(reply)
        if times is not None:
            self.clock.add(agent, t1, times[0], times[1], t4)

    # ------------------------------------------------------------------ transport

    def answers(self, request: bytes, agents: Sequence[str] = ()) -> Iterator[Reply]:
        """One query (an encoded request) to the query key of every agent (or of the only
        one in ``agents``); yields each answer as it arrives.  One query rather than one
        per agent: a ``get`` costs about as much to issue as a loopback round trip.  Ends
        as soon as every agent in ``agents`` has answered (else when the query ends: all
        agents are done, or the timeout)."""
        expected, seen = set(agents), set()
        querier = self._querier(agents[0] if len(agents) == 1 else None)
        t1 = self.now()
        # Zenoh's FIFO channel, read here: a callback waking this thread through an Event
        # would add a GIL hand-off per reply (docs/MEASUREMENTS.md).  The query's timeout
        # closes the channel, so the loop always ends.
        for reply in querier.get(payload=request):
            t4 = self.now()
            if reply.ok is None:
                continue
            key = str(reply.ok.key_expr)
            agent = self._reply_agent(key)
            if agent is None:
                self._log.warning("query reply", f"unexpected key {key!r}")
                continue
            answer = proto.decode_reply(reply.ok.payload.to_bytes())
            if answer.get("agent") != agent:
                self.refused += 1
                self._log.warning("query reply", f"on {key} names agent "
                                  f"{str(answer.get('agent'))[:64]!r} "
                                  f"({answer.get('error', 'not the agent of its key')}): "
                                  f"refused ({self.refused} so far)")
                continue
            yield agent, answer, t1, t4
            seen.add(agent)
            if expected and expected <= seen:
                return  # no need to wait for agents that have nothing to say

    def _reply_agent(self, key: str) -> str | None:
        """The agent id of a reply's key (None: not an agent's query key); the few keys
        replies come on are parsed once."""
        agent = self._reply_keys.get(key, False)
        if agent is False:
            agent = keys.parse_agent_query(key, self.realm)
            if len(self._reply_keys) >= MAX_REPLY_KEYS:  # forged keys must not grow it
                self._reply_keys.clear()
            self._reply_keys[key] = agent
        return agent

    def _querier(self, agent: str | None) -> zenoh.Querier:
        """The querier of one agent's query key (None: every agent's), declared once: Zenoh
        then resolves the key expression once rather than at every get, and the key is
        built once.  No consolidation: every agent replies on
        its own key, so there is nothing to merge, and the default would hold every answer
        back until the slowest agent is done."""
        with self._lock:
            querier = self._queriers.get(agent)
            if querier is None:
                key = (keys.agent_query(self.realm, agent) if agent is not None
                       else keys.all_agent_queries(self.realm))
                querier = self.session.declare_querier(
                    key, timeout=self.timeout, consolidation=zenoh.ConsolidationMode.NONE)
                self._queriers[agent] = querier
        return querier


class Queries(AgentQueries):
    """Pose queries over one realm (module docstring)."""

    def __init__(self, session: zenoh.Session, realm: str, timeout: float,
                 tracker: RealmTracker, clock: ClockOffsets, connect: Sequence[str]) -> None:
        super().__init__(session, realm, timeout, clock)
        self.tracker = tracker
        self.connect = list(connect)
        #: planned routes by (source, target, error), for summaries of ``_planned_on``
        self._routes: dict[tuple[str, str, str], list[Route]] = {}
        #: encoded requests for the latest time (the same for every query of a round's
        #: segments), dropped with the routes
        self._requests: dict[tuple[tuple[Segment, ...], str, bool, str, bool], bytes] = {}
        self._planned_on = 0
        #: answers of all-static segments (valid at all times) by (agent, source, target,
        #: error), with the (instance, revision) of the agent's summary they belong to
        self._static: dict[tuple[str, str, str, str], tuple[tuple[str, int], PoseResult]] = {}
        #: False: ask for every segment every time (the benchmark's uncached figure)
        self.cache_static_segments = True
        #: False: ask every agent of a route itself (the fan-out) rather than its first
        self.relay = True
        #: segments answered from the supernode cache of a route's first agent
        self.cached_parts = 0
        #: error functions by their spec (``_error_function``)
        self._error_fns: dict[str, ErrorFunction] = {}

    # ------------------------------------------------------------------ one query

    def ask(self, source: str, target: str, at: int | None, error: str,
            details: bool = False) -> Outcome:
        """The pose of ``target`` in ``source``'s frame at ``at`` (ns on this clock; None:
        the latest common time): plan, ask each segment's agent, compose; on to the next
        route when an agent fails.  ``details``: with every edge's details."""
        fn = self._error_function(error)
        at = check_time(at)
        view = self._realm()
        if source == target and any(source in s.frames for s in view.summaries.values()):
            return Outcome(identity(source, at), [])
        view, routes = self._plan(view, source, target, fn)
        causes: list[SegmentError] = []
        for route in usable_routes(routes, view.alive, source, target)[:MAX_ROUTES]:
            asked = time.monotonic()
            try:
                return self._along(route, at, fn, details)
            except SegmentError as exc:
                causes.append(exc)
                if exc.missing:
                    self.tracker.missed(exc.segment.agent, asked)
        if len(causes) == 1:
            raise causes[0]
        raise RouteError(f"no route from {source!r} to {target!r} worked ({len(causes)} "
                         f"tried): " + "; ".join(str(c) for c in causes))

    def _error_function(self, spec: str) -> ErrorFunction:
        """The error function ``spec`` names, parsed once (an expression's parse costs more
        than a query's planning from cache); a bad one raises each time."""
        fn = self._error_fns.get(spec)
        if fn is None:
            fn = error_function(spec)
            if len(self._error_fns) >= MAX_REPLY_KEYS:
                self._error_fns.clear()
            self._error_fns[spec] = fn
        return fn

    def _realm(self) -> RealmView:
        """The realm to plan on; ``NoAgentsError`` if nobody is in it."""
        view = self.tracker.current()
        if not view.summaries:
            raise NoAgentsError(
                f"no agent answered in realm {self.realm!r} within {self.timeout:g} s "
                f"(connected to {', '.join(self.connect) or 'nothing'}); is 'uma agent' "
                "running there with the same --realm?")
        return view

    def _plan(self, view: RealmView, source: str, target: str, fn: ErrorFunction,
              ) -> tuple[RealmView, list[Route]]:
        """The routes, best first, and the realm they were planned on.  A frame or a link
        may be in a summary published before this client's subscription reached its agent
        (nothing re-sends it): before saying a frame is unknown or the pair unreachable,
        every agent is asked for its summary."""
        try:
            try:
                return view, self._routes_on(view, source, target, fn)
            except (UnknownFrameError, UnreachableError):
                self.tracker.refresh()
                view = self.tracker.view()
                return view, self._routes_on(view, source, target, fn)
        except UnreachableError as exc:
            raise with_departed(exc, view.summaries, view.alive) from None
        except UnknownFrameError as exc:
            raise with_silent(exc, view.summaries, view.alive) from None

    def _routes_on(self, view: RealmView, source: str, target: str,
                   fn: ErrorFunction) -> list[Route]:
        with self._lock:
            if view.summaries_rev != self._planned_on:
                self._routes.clear()
                self._requests.clear()
                self._planned_on = view.summaries_rev
            routes = self._routes.get((source, target, fn.key))
        if routes is None:
            routes = plan_routes(view.summaries, source, target, fn)
            with self._lock:
                self._routes[(source, target, fn.key)] = routes
        return routes

    def _along(self, route: Route, at: int | None, fn: ErrorFunction,
               details: bool) -> Outcome:
        """Every segment of ``route`` asked at ``at`` and composed as the answers arrive;
        at None, at the latest time every measured segment has data."""
        spec = fn.expr.text if fn.expr is not None else fn.key
        if at is not None:
            self._sync_clocks([a for a in route.agents if not self.clock.known(a)])
        segments = route.segments
        if self._composable(segments, spec, details):
            pose = self._composed(segments, at, spec)
            if pose is not None:
                return Outcome(pose, [(s, []) for s in segments])
        chain = Composition(len(segments))
        answers = self._segments(segments, at, spec, details, chain)
        if at is not None:
            pose = chain.result(at)
        else:
            at, asked_again = self._at_latest_common_time(segments, answers, spec, details)
            pose = compose([r for r, _ in answers], at) if asked_again else chain.result(at)
        return Outcome(pose, [(s, edges) for s, (_, edges) in zip(segments, answers,
                                                                  strict=True)])

    def _at_latest_common_time(self, segments: Sequence[Segment], answers: list[Answer],
                               spec: str, details: bool) -> tuple[int | None, bool]:
        """The latest time every measured segment has data (None: none is measured);
        segments answered at a later one are asked again at it (``answers`` updated in
        place).  True if any was: the chain composed as they arrived is then stale."""
        times = [None if r.attributes.get("static") else r.t_ns for r, _ in answers]
        measured = [t for t in times if t is not None]
        if not measured:
            return None, False
        common = min(measured)
        again = [i for i, t in enumerate(times) if t is not None and t != common]
        if again:
            redo = self._segments([segments[i] for i in again], common, spec, details)
            for i, answer in zip(again, redo, strict=True):
                answers[i] = answer
        return common, bool(again)

    # ------------------------------------------------------------------ asking the agents

    def _segments(self, segments: Sequence[Segment], at: int | None, spec: str,
                  details: bool, chain: Composition | None = None) -> list[Answer]:
        """Every segment's answer, in route order (each also added to ``chain`` as soon as
        it is in).  Cached static segments are not asked for; the others go out in one
        query per round, a round holding at most one segment per agent (a route may pass
        through an agent twice)."""
        answers: dict[int, Answer] = {}
        pending: list[int] = []
        for i, seg in enumerate(segments):
            hit = None if details else self._cached_static(seg, spec)
            if hit is not None:
                answers[i] = (hit, [])
                if chain is not None:
                    chain.add(i, hit)
            else:
                pending.append(i)
        while pending:
            round_, later, agents = [], [], set()
            for i in pending:
                (later if segments[i].agent in agents else round_).append(i)
                agents.add(segments[i].agent)
            answers.update(self._round([(i, segments[i]) for i in round_], at, spec,
                                       details, chain))
            pending = later
        return [answers[i] for i in range(len(segments))]

    def _round(self, todo: Sequence[tuple[int, Segment]], at: int | None, spec: str,
               details: bool, chain: Composition | None) -> dict[int, Answer]:
        """One query for the segments of ``todo`` (one per agent): to its first agent, which
        answers the whole route, or to all of them; SegmentError names the first segment (in
        route order) that failed."""
        if self.relay and len(todo) > 1 and not details:
            got = self._relayed(todo, at, spec, chain)
            if got is not None:
                return got
        return self._fan_out(todo, at, spec, details, chain)

    def _composable(self, segments: Sequence[Segment], spec: str, details: bool) -> bool:
        """Whether the route's first agent may compose it: every segment asked (none of
        them a cached static one), each of another agent, without details."""
        return (self.relay and not details and len(segments) > 1
                and len({s.agent for s in segments}) == len(segments)
                and all(self._cached_static(s, spec) is None for s in segments))

    def _composed(self, segments: Sequence[Segment], at: int | None, spec: str,
                  ) -> PoseResult | None:
        """The whole route asked of its first agent, composed there (module docstring):
        one answer to read rather than one per segment.  When it could not compose (a part
        it had to ask another agent for), its parts are composed here.  None if it does not
        answer routes (the caller then asks segment by segment)."""
        entry = segments[0]
        request = self._request(segments, at, spec, False, "route", compose=True)
        reply, t1, t4 = self._ask_entry(entry, request)
        try:
            routed = proto.route_result(reply)
        except ValueError as exc:
            raise SegmentError(entry, f"malformed answer: {exc}", False) from None
        if routed is None:
            got = self._route_parts(list(enumerate(segments)), entry, reply, spec, t1, t4,
                                    None)
            if got is None:
                return None
            answers = [got[i] for i in range(len(segments))]
            if at is None:
                at, _ = self._at_latest_common_time(segments, answers, spec, False)
            return compose([r for r, _ in answers], at)
        result, times = routed
        offsets = {a: self.clock.offset(a) or 0 for a in times}
        local = {a: t - offsets[a] for a, t in times.items() if t is not None}
        if at is None and len(set(local.values())) > 1:
            # each part at its latest time, and they differ: once more at the latest common
            # one, as _at_latest_common_time does
            return self._composed(segments, min(local.values()), spec)
        t = at if at is not None else next(iter(local.values()), None)
        try:
            pose = self._on_local_clock(result, times, offsets, t)
        except ValueError as exc:
            raise SegmentError(entry, f"malformed answer: {exc}", False) from None
        cached = reply.get("cached")
        self.cached_parts += cached if isinstance(cached, int) else 0
        return pose

    @staticmethod
    def _on_local_clock(result: dict[str, Any], times: dict[str, int | None],
                        offsets: dict[str, int], t: int | None) -> PoseResult:
        """A composed route's result at ``t`` (this clock), each edge's time moved by its
        owner's offset (a static part's edges: ``t``); ``ValueError`` if it is malformed."""
        pose = proto.pose_from_wire(result)
        static_t = t if t is not None else time.time_ns()
        for e in pose.edges:
            owner = e["owner"]
            if owner not in times:
                raise ValueError(f"edge {e['parent']}->{e['child']} of agent {owner!r}, "
                                 "which has no part of the route")
            e["t_ns"] = static_t if times[owner] is None else e["t_ns"] - offsets[owner]
        pose.t_ns = t
        pose.stamps = [(e["t_ns"], e["t_ns"]) for e in pose.edges]
        return pose

    def _ask_entry(self, entry: Segment, request: bytes) -> tuple[dict[str, Any], int, int]:
        """One request to the first agent of a route: its reply and our send and receive
        times (its clock sample taken); SegmentError if it does not answer."""
        got = next((r for r in self.answers(request, [entry.agent]) if r[0] == entry.agent),
                   None)
        if got is None:
            raise SegmentError(entry, f"agent {entry.agent!r} did not answer within "
                                      f"{self.timeout:g} s (gone or unreachable)", True)
        _, reply, t1, t4 = got
        self._clock_sample(entry.agent, reply, t1, t4)
        return reply, t1, t4

    def _relayed(self, todo: Sequence[tuple[int, Segment]], at: int | None, spec: str,
                 chain: Composition | None) -> dict[int, Answer] | None:
        """The whole of ``todo`` asked of its first agent (module docstring); None if that
        agent does not answer routes (the fan-out asks then)."""
        entry = todo[0][1]
        request = self._request([seg for _, seg in todo], at, spec, False, "route")
        reply, t1, t4 = self._ask_entry(entry, request)
        return self._route_parts(todo, entry, reply, spec, t1, t4, chain)

    def _route_parts(self, todo: Sequence[tuple[int, Segment]], entry: Segment,
                     reply: dict[str, Any], spec: str, t1: int, t4: int,
                     chain: Composition | None) -> dict[int, Answer] | None:
        """Each segment's answer from a route reply with parts (each also added to
        ``chain``); None if the agent does not answer routes."""
        try:
            parts = proto.route_parts(reply)
        except (proto.RefusedError, ValueError) as exc:
            self._log.warning("route", f"agent {entry.agent!r} did not answer the route "
                              f"({exc}): asking each agent")
            return None
        out: dict[int, Answer] = {}
        for i, seg in todo:
            part = parts.get(seg.agent)
            if part is None:
                raise SegmentError(seg, f"agent {seg.agent!r} did not answer agent "
                                        f"{entry.agent!r} (gone or unreachable)", True)
            answer = self._segment_answer(seg, spec, part, t1, t4)
            if isinstance(answer, SegmentError):
                raise answer
            self.cached_parts += part.get("cached") is True
            out[i] = answer
            if chain is not None:
                chain.add(i, answer[0])
        return out

    def _fan_out(self, todo: Sequence[tuple[int, Segment]], at: int | None, spec: str,
                 details: bool, chain: Composition | None) -> dict[int, Answer]:
        """One query to every agent of ``todo``.  Each answer is checked as it arrives,
        while the slower agents are still computing theirs."""
        index = {seg.agent: (i, seg) for i, seg in todo}
        got: dict[int, Answer | SegmentError] = {}
        request = self._request([seg for _, seg in todo], at, spec, details)
        for agent, reply, t1, t4 in self.answers(request, list(index)):
            if agent in index and index[agent][0] not in got:
                i, seg = index[agent]
                got[i] = answer = self._segment_answer(seg, spec, reply, t1, t4)
                if chain is not None and not isinstance(answer, SegmentError):
                    chain.add(i, answer[0])
        out = {}
        for i, seg in todo:
            answer = got.get(i)
            if answer is None:
                raise SegmentError(seg, f"agent {seg.agent!r} did not answer within "
                                        f"{self.timeout:g} s (gone or unreachable)", True)
            if isinstance(answer, SegmentError):
                raise answer
            out[i] = answer
        return out

    def _request(self, segments: Sequence[Segment], at: int | None, spec: str,
                 details: bool, op: str = "segments", compose: bool = False) -> bytes:
        """The request for one round; one for the latest time is encoded once."""
        key = (tuple(segments), spec, details, op, compose)
        with self._lock:
            request = self._requests.get(key) if at is None else None
        if request is None:
            request = proto.segments_request({
                seg.agent: proto.SegmentRequest(
                    seg.source, seg.target, spec,
                    None if at is None else self.clock.to_remote(seg.agent, at), details)
                for seg in segments}, op, compose)
            if at is None:
                with self._lock:
                    self._requests[key] = request
        return request

    def _segment_answer(self, seg: Segment, spec: str, reply: dict[str, Any], t1: int,
                        t4: int) -> Answer | SegmentError:
        """One agent's answer to its segment, or the error saying why it is unusable."""
        self._clock_sample(seg.agent, reply, t1, t4)
        offset = self.clock.offset(seg.agent) or 0
        try:
            answer = proto.read_segment_reply(reply, lambda t: t - offset)
        except proto.RefusedError as exc:
            return SegmentError(seg, str(exc), False)
        except (KeyError, TypeError, ValueError) as exc:
            return SegmentError(seg, f"malformed answer: {exc}", False)
        if self.cache_static_segments and answer[0].attributes.get("static"):
            self._remember_static(seg, spec, answer[0])
        return answer

    # ------------------------------------------------------------------ static segments

    def _cached_static(self, seg: Segment, spec: str) -> PoseResult | None:
        """The answer of a static segment if still valid: the owning agent's summary has not
        changed since (any change of its edges or their attributes republishes it)."""
        if not self.cache_static_segments:
            return None
        hit = self._static.get((seg.agent, seg.source, seg.target, spec))
        if hit is not None and hit[0] == self.tracker.summary_version(seg.agent):
            return hit[1]
        return None

    def _remember_static(self, seg: Segment, spec: str, result: PoseResult) -> None:
        version = self.tracker.summary_version(seg.agent)
        if version is not None:
            self._static[(seg.agent, seg.source, seg.target, spec)] = (version, result)

    # ------------------------------------------------------------------ clocks

    def _sync_clocks(self, agents: Sequence[str]) -> None:
        """One clock round trip to every agent (all answer the same query)."""
        if not agents:
            return
        for agent, reply, t1, t4 in self.answers(proto.clock_request()):
            self._clock_sample(agent, reply, t1, t4)
