"""The client SDK: pose queries and streaming subscriptions over every agent of a realm.

::

    from agent import Client
    with Client(realm="lab", connect=["tcp/127.0.0.1:7447"]) as c:
        r = c.pose("ivy/world", "alice/head", at=None, error="latency")
        r.position, r.quaternion, r.matrix, r.covariance, r.path, r.attributes, r.extrapolated_s
        sub = c.subscribe("ivy/world", "alice/head", on_pose=handle)
        ...
        sub.close()

``pose`` plans a route over the agents' supernode summaries (:mod:`agent.sdk.planner`), asks
each owning agent for its segment at ``t`` (all at once, one round trip), and composes the
answers with their covariances.  ``at`` is on this process's clock; each agent's clock
offset is estimated from the round trips (:mod:`agent.sdk.clock`) and applied both ways.
``at=None`` means the latest time at which every measured edge of the route has data.
If an agent does not answer, the next route without it is tried; if none is left the
error names the missing segment and agent.  An agent that missed an answer counts as gone
until it shows life again: a new token or summary, or an answer to the probe it gets every
``PROBE_S`` while its token is still there (it may only have been slow).

``subscribe`` runs the query once with edge details, then mirrors the route's edges in a
local :class:`agent.srg.Graph`: static edges from the answers, measured ones fed by
subscribing directly to their services' data keys.  Each sample of the fastest edge pushes
a composed pose at its time; the other edges are interpolated (or boundedly
extrapolated) at that time: Ubitrack's push/pull rule.  ``on_pose`` runs on the
subscription's own thread, never on a Zenoh thread.

A subscription follows the realm: whenever an agent leaves or joins or a supernode summary
changes, it plans again, and if the best route (or any edge of it) differs it rebuilds its
mirror on the new route and goes on delivering.  When no route is left it says so (a log
line, ``status == "no route"``, ``last_error``, and ``on_error(exc)`` once per outage),
stops delivering, and retries every ``RETRY_S`` and at every change until a route is back.
A route that is alive but silent -- its fastest edge sent nothing for ``stall_s`` (by default
``STALL_PERIODS`` of its sample periods, at least ``STALL_MIN_S``): the tracker lost its
target or hung, or the network drops its data -- is a different outage, since no other route
would do better: the subscription stays on it, says so once (a log line,
``status == "stalled"``, ``stalls``) and goes back to ``"streaming"`` at the next sample.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import zenoh

from agent.errors import UmaError
from agent.protocol import keys
from agent.runtime.logs import RateLimitedLog
from agent.runtime.session import acquire_session, release_session, sdk_mode
from agent.sdk.clock import ClockOffsets
from agent.sdk.planner import (
    Composition,
    Route,
    RouteError,
    Segment,
    SegmentError,
    Summary,
    parse_summary,
    plan_routes,
    pose_from_wire,
    usable_routes,
)
from agent.srg import Graph
from agent.srg.attributes import EDGE_ATTRIBUTES
from agent.srg.errorfn import ErrorFunction, error_function
from agent.srg.errors import (
    EdgeUndefinedError,
    SrgLookupError,
    UnknownFrameError,
    UnreachableError,
    list_names,
)
from agent.srg.graph import identity
from agent.srg.result import PoseResult
from schemas.codec import DecodeError, decode_measurement, decode_message, encode_message

log = logging.getLogger("uma.client")

#: routes tried before a query gives up
MAX_ROUTES = 4
#: how long the first look at the realm waits for the set of agents to settle
SETTLE_S = 0.15
#: how often a subscription without a route tries again (besides at every realm change)
RETRY_S = 1.0
#: how often an agent that missed an answer, its token still there, is asked whether it
#: answers again
PROBE_S = 2.0
#: a subscription's fastest edge silent this many of its sample periods, and at least
#: STALL_MIN_S, is a stall (a route change takes up to a lease, 1 s, without samples)
STALL_PERIODS = 10
STALL_MIN_S = 1.5
#: the states in which a subscription holds a route's mirror
_ON_ROUTE = ("streaming", "stalled")


class NoAgentsError(UmaError):
    """Nobody in the realm answered."""


class Client:
    """A connection to a realm for pose queries and subscriptions (module docstring)."""

    def __init__(self, realm: str = "default", connect: Iterable[str] = (), *,
                 listen: Sequence[str] | None = None, mode: str | None = None,
                 timeout: float = 2.0, session: zenoh.Session | None = None,
                 shared: bool = True) -> None:
        keys.check_name("realm", realm)
        if not timeout > 0:
            raise ValueError(f"timeout must be > 0 s, got {timeout!r}")
        self.realm = realm
        self.timeout = float(timeout)
        self.connect = list(connect)
        self._own_session = session is None
        self.session = session or acquire_session(sdk_mode(mode, self.connect), listen,
                                                  self.connect, realm, shared=shared)
        self.clock = ClockOffsets()
        self._lock = threading.Lock()
        self._summaries: dict[str, Summary] = {}
        #: planned routes by (source, target, error), dropped when any summary changes
        self._routes: dict[tuple[str, str, str], list[Route]] = {}
        #: encoded requests for the latest time (the same for every query of a round's
        #: segments), dropped with the routes
        self._requests: dict[tuple[tuple[Segment, ...], str, bool], bytes] = {}
        #: answers of all-static segments (valid at all times) by (agent, source, target,
        #: error), with the (instance, revision) of the agent's summary they belong to
        self._static: dict[tuple[str, str, str, str], tuple[tuple[str, int], PoseResult]] = {}
        #: False: ask for every segment every time (the benchmark's uncached figure)
        self.cache_static_segments = True
        self._alive: set[str] = set()
        #: when each agent last showed life (its token or a summary; monotonic s): a missed
        #: answer marks it gone only if that came before the query went out
        self._heard: dict[str, float] = {}
        #: agents whose token the subscription saw removed (and not declared again)
        self._departed: set[str] = set()
        #: agents marked gone after a missed answer, not by their token: probed every
        #: PROBE_S by a thread that runs while there are any
        self._suspects: set[str] = set()
        self._prober: threading.Thread | None = None
        self._closing = threading.Event()
        #: bumped whenever the summaries or the set of live agents change (subscriptions
        #: re-plan when it moves)
        self.topology = 0
        self._looked = False
        self._subscriptions: list[Subscription] = []
        #: declared queriers by query key (every agent's, or one agent's)
        self._queriers: dict[str, zenoh.Querier] = {}
        self._bad = RateLimitedLog(log)
        self._decls = [
            self.session.declare_subscriber(keys.all_agent_supernodes(realm),
                                            self._on_summary),
            self.session.liveliness().declare_subscriber(keys.all_agent_tokens(realm),
                                                         self._on_token, history=True),
        ]

    # ------------------------------------------------------------------ life cycle

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop every subscription and leave; never raises (a session that cannot close in
        time is logged, see :func:`agent.runtime.session.close_session`)."""
        if self._closing.is_set():
            return
        self._closing.set()
        for sub in list(self._subscriptions):
            sub.close()
        prober = self._prober
        if prober is not None:
            prober.join(PROBE_S + self.timeout)
        for decl in [*self._decls, *self._queriers.values()]:
            with contextlib.suppress(zenoh.ZError):
                decl.undeclare()
        self._decls.clear()
        self._queriers.clear()
        if self._own_session:
            release_session(self.session)

    # ------------------------------------------------------------------ the realm

    def _on_summary(self, sample: zenoh.Sample) -> None:
        self._take_summary(str(sample.key_expr), sample.payload.to_bytes())

    def _take_summary(self, key: str, data: bytes) -> None:
        try:
            summary = parse_summary(decode_message(data, required=("agent", "frames")))
        except ValueError as exc:
            self._bad.warning(f"supernode {key}", f"dropped a malformed summary: {exc}")
            return
        with self._lock:
            old = self._summaries.get(summary.agent)
            if old is None or summary.rev > old.rev or summary.instance != old.instance:
                self._summaries[summary.agent] = summary
                self._routes.clear()
                self._requests.clear()
                self.topology += 1
            self._mark_alive(summary.agent, True)

    def _mark_alive(self, agent: str, alive: bool) -> None:
        """Update the live set (lock held); a change moves ``topology``."""
        if alive:
            self._heard[agent] = time.monotonic()
            self._suspects.discard(agent)
        if (agent in self._alive) != alive:
            self.topology += 1
            (self._alive.add if alive else self._alive.discard)(agent)

    def _on_token(self, sample: zenoh.Sample) -> None:
        agent = keys.parse_agent_token(str(sample.key_expr), self.realm)
        if agent is None:
            return
        with self._lock:
            gone = sample.kind == zenoh.SampleKind.DELETE
            (self._departed.add if gone else self._departed.discard)(agent)
            self._suspects.discard(agent)  # its token says what it is now
            self._mark_alive(agent, not gone)

    def _missed(self, agent: str, asked: float) -> None:
        """``agent`` did not answer a query sent at ``asked``: count it as gone, unless it
        showed life since (a query that reached a restarting agent's old self gets no
        answer, and marking it gone after its new token and summary came would outlive them:
        nothing else would bring it back).  Unless its token is gone too, it is probed
        until it answers again: it may only have been slow."""
        with self._lock:
            if self._heard.get(agent, -math.inf) >= asked:
                return
            self._mark_alive(agent, False)
            if agent in self._departed:
                return
            self._suspects.add(agent)
            if self._prober is None and not self._closing.is_set():
                self._prober = threading.Thread(target=self._probe_suspects,
                                                name="uma-client-probe", daemon=True)
                self._prober.start()

    def _probe_suspects(self) -> None:
        """Ask the agents that missed an answer whether they answer now; one that does is
        alive again, and subscriptions re-plan (and move back to it if it is on their best
        route).  Runs on its own thread: an agent still too slow costs a query timeout."""
        request = encode_message({"op": "clock"})
        try:
            while not self._closing.wait(PROBE_S):
                with self._lock:
                    suspects = sorted(self._suspects)
                    if not suspects:  # done, in the lock in which _missed would start one
                        self._prober = None
                        return
                for agent in suspects:
                    self._probe(agent, request)
        finally:
            with self._lock:
                if self._prober is threading.current_thread():
                    self._prober = None

    def _probe(self, agent: str, request: bytes) -> None:
        try:
            for who, reply, t1, t4 in self._answers(request, [agent]):
                self._clock_sample(who, reply, t1, t4)
                with self._lock:
                    if who in self._suspects:
                        self._mark_alive(who, True)
        except zenoh.ZError as exc:
            self._bad.warning("probe", f"asking agent {agent!r}: {exc}")

    def refresh(self) -> None:
        """Ask every agent for its summary now (also learns who is alive)."""
        alive = set()
        for reply in self.session.liveliness().get(keys.all_agent_tokens(self.realm),
                                                   timeout=self.timeout):
            if reply.ok is not None:
                agent = keys.parse_agent_token(str(reply.ok.key_expr), self.realm)
                if agent is not None:
                    alive.add(agent)
        with self._lock:
            # a token whose removal the subscription has seen can still be in the answer
            # (a peer not yet done with the departure): only a new token brings it back
            for agent in alive - self._departed:
                self._mark_alive(agent, True)
        for reply in self.session.get(keys.all_agent_supernodes(self.realm),
                                      timeout=self.timeout):
            if reply.ok is not None:
                self._take_summary(str(reply.ok.key_expr), reply.ok.payload.to_bytes())

    def _look(self) -> None:
        """The first look at the realm: refresh until the set of agents stops growing
        (peers learn of each other by gossip within tens of ms), bounded by the timeout."""
        deadline = time.monotonic() + self.timeout
        seen: set[str] = set()
        while True:
            self.refresh()
            with self._lock:
                now = set(self._summaries)
            if now and now == seen:
                break
            seen = now
            if time.monotonic() + SETTLE_S > deadline:
                break
            time.sleep(SETTLE_S)
        self._looked = True

    def agents(self) -> dict[str, dict[str, Any]]:
        """The agents this client knows: alive or not, and their frames."""
        if not self._looked:
            self._look()
        with self._lock:
            return {a: {"alive": a in self._alive, "frames": sorted(s.frames)}
                    for a, s in self._summaries.items()}

    def _snapshot(self) -> tuple[dict[str, Summary], set[str]]:
        with self._lock:
            return dict(self._summaries), set(self._alive)

    # ------------------------------------------------------------------ queries

    def pose(self, source: str, target: str, at: int | None = None,
             error: str = "latency") -> PoseResult:
        """The pose of ``target`` in ``source``'s frame at ``at`` (ns on this clock; None:
        the latest common time), composed across agents (module docstring)."""
        return self._query(source, target, at, error, details=False)[0]

    def _query(self, source: str, target: str, at: int | None, error: str, details: bool,
               ) -> tuple[PoseResult, list[tuple[Segment, list[dict[str, Any]]]]]:
        fn = error_function(error)
        if at is not None and (isinstance(at, bool) or not isinstance(at, (int, np.integer))):
            raise ValueError(f"at must be integer ns since the epoch or None, got {at!r}")
        summaries, alive = self._snapshot()
        if not self._looked or not summaries:
            self._look()
            summaries, alive = self._snapshot()
        elif alive - set(summaries):  # an agent appeared whose summary we have not seen
            self.refresh()
            summaries, alive = self._snapshot()
        if not summaries:
            raise NoAgentsError(
                f"no agent answered in realm {self.realm!r} within {self.timeout:g} s "
                f"(connected to {', '.join(self.connect) or 'nothing'}); is 'uma agent' "
                "running there with the same --realm?")
        if source == target and any(source in s.frames for s in summaries.values()):
            return identity(source, None if at is None else int(at)), []
        try:
            try:
                routes = self._plan(summaries, source, target, fn)
            except (UnknownFrameError, UnreachableError):
                # a frame or a link may be in a summary published before this client's
                # subscription reached its agent (nothing re-sends it): ask for them all
                self.refresh()
                summaries, alive = self._snapshot()
                routes = self._plan(summaries, source, target, fn)
        except UnreachableError as exc:
            raise _with_departed(exc, summaries, alive) from None
        causes: list[SegmentError] = []
        for route in usable_routes(routes, alive, source, target)[:MAX_ROUTES]:
            asked = time.monotonic()
            try:
                return self._run(route, None if at is None else int(at), fn, details)
            except SegmentError as exc:
                causes.append(exc)
                if exc.missing:
                    self._missed(exc.segment.agent, asked)
        if len(causes) == 1:
            raise causes[0]
        raise RouteError(f"no route from {source!r} to {target!r} worked ({len(causes)} "
                         f"tried): " + "; ".join(str(c) for c in causes))

    def _plan(self, summaries: dict[str, Summary], source: str, target: str,
              fn: ErrorFunction) -> list[Route]:
        key = (source, target, fn.key)
        routes = self._routes.get(key)
        if routes is None:
            routes = plan_routes(summaries, source, target, fn)
            with self._lock:
                self._routes[key] = routes
        return routes

    def _run(self, route: Route, at: int | None, fn: ErrorFunction, details: bool,
             ) -> tuple[PoseResult, list[tuple[Segment, list[dict[str, Any]]]]]:
        spec = fn.expr.text if fn.expr is not None else fn.key
        if at is not None:
            self._probe_clocks([a for a in route.agents if not self.clock.known(a)])
        segments = route.segments
        chain = Composition(len(segments))
        answers = self._segments(segments, at, spec, details, chain)
        results = [r for r, _ in answers]
        if at is None:  # the latest time every measured segment has data
            measured = [r.t_ns for r in results if not r.attributes.get("static")]
            if measured and max(measured) != min(measured):
                common = min(measured)
                again = [i for i, r in enumerate(results)
                         if not r.attributes.get("static") and r.t_ns != common]
                redo = self._segments([segments[i] for i in again], common, spec, details)
                for i, answer in zip(again, redo, strict=True):
                    answers[i] = answer
                results = [r for r, _ in answers]
                at = common
                chain = Composition(len(segments))
                for i, r in enumerate(results):
                    chain.add(i, r)
            elif measured:
                at = measured[0]
        return chain.result(at), [(s, d) for s, (_, d) in zip(segments, answers, strict=True)]

    def _segments(self, segments: Sequence[Segment], at: int | None, spec: str,
                  details: bool, chain: Composition | None = None,
                  ) -> list[tuple[PoseResult, list[dict[str, Any]]]]:
        """Every segment's answer, in route order (each also added to ``chain`` as soon as
        it is in).  Cached static segments are not asked for; the others go out in one
        query per round, a round holding at most one segment per agent (a route may pass
        through an agent twice)."""
        answers: dict[int, tuple[PoseResult, list[dict[str, Any]]]] = {}
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
            answers.update(self._ask_round([(i, segments[i]) for i in round_], at, spec,
                                           details, chain))
            pending = later
        return [answers[i] for i in range(len(segments))]

    def _ask_round(self, todo: Sequence[tuple[int, Segment]], at: int | None, spec: str,
                   details: bool, chain: Composition | None,
                   ) -> dict[int, tuple[PoseResult, list[dict[str, Any]]]]:
        """One query to the agents of ``todo`` (one segment each); SegmentError names the
        first segment (in route order) that failed.  Each answer is checked as it arrives,
        while the slower agents are still computing theirs."""
        index = {seg.agent: (i, seg) for i, seg in todo}
        key = (tuple(seg for _, seg in todo), spec, details)
        request = self._requests.get(key) if at is None else None
        if request is None:
            parts = {}
            for _, seg in todo:
                part = {"source": seg.source, "target": seg.target, "error": spec,
                        "t": None if at is None else self.clock.to_remote(seg.agent, at)}
                if details:
                    part["details"] = True
                parts[seg.agent] = part
            request = encode_message({"op": "segments", "parts": parts})
            if at is None:
                self._requests[key] = request
        got: dict[int, tuple[PoseResult, list[dict[str, Any]]] | SegmentError] = {}
        for agent, reply, t1, t4 in self._answers(request, list(index)):
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

    def _segment_answer(self, seg: Segment, spec: str, reply: dict[str, Any], t1: int,
                        t4: int) -> tuple[PoseResult, list[dict[str, Any]]] | SegmentError:
        """One agent's answer to its segment, or the error saying why it is unusable."""
        self._clock_sample(seg.agent, reply, t1, t4)
        if not reply.get("ok"):
            return SegmentError(seg, str(reply.get("error", "no reason given")), False)
        try:
            result = self._to_pose(seg.agent, reply["result"])
        except (KeyError, TypeError, ValueError) as exc:
            return SegmentError(seg, f"malformed answer: {exc}", False)
        if self.cache_static_segments and result.attributes.get("static"):
            self._remember_static(seg, spec, result)
        return result, reply.get("edges") or []

    def _summary_version(self, agent: str) -> tuple[str, int] | None:
        with self._lock:
            s = self._summaries.get(agent)
            return None if s is None else (s.instance, s.rev)

    def _cached_static(self, seg: Segment, spec: str) -> PoseResult | None:
        """The answer of a static segment if still valid: the owning agent's summary has not
        changed since (any change of its edges or their attributes republishes it)."""
        if not self.cache_static_segments:
            return None
        hit = self._static.get((seg.agent, seg.source, seg.target, spec))
        if hit is not None and hit[0] == self._summary_version(seg.agent):
            return hit[1]
        return None

    def _remember_static(self, seg: Segment, spec: str, result: PoseResult) -> None:
        version = self._summary_version(seg.agent)
        if version is not None:
            self._static[(seg.agent, seg.source, seg.target, spec)] = (version, result)

    def _probe_clocks(self, agents: Sequence[str]) -> None:
        """One clock round trip to every agent (all answer the same query)."""
        if not agents:
            return
        for agent, reply, t1, t4 in self._answers(encode_message({"op": "clock"})):
            self._clock_sample(agent, reply, t1, t4)

    def _clock_sample(self, agent: str, reply: dict[str, Any], t1: int, t4: int) -> None:
        t2, t3 = reply.get("t2"), reply.get("t3")
        if isinstance(t2, int) and isinstance(t3, int):
            self.clock.add(agent, t1, t2, t3, t4)

    def _answers(self, request: bytes, agents: Sequence[str] = (),
                 ) -> Iterator[tuple[str, dict[str, Any], int, int]]:
        """One query (an encoded message) to the query key of every agent (or of the only
        one in ``agents``); yields each answer as it arrives: (agent id, decoded answer, our
        send time, our receive time).  One query rather than one per agent: a ``get`` costs
        about as much to issue as a loopback round trip.  Ends as soon as every agent in
        ``agents`` has answered (else when the query ends: all agents are done, or the
        timeout)."""
        expected, seen = set(agents), set()
        selector = (keys.agent_query(self.realm, agents[0]) if len(agents) == 1
                    else keys.all_agent_queries(self.realm))
        t1 = time.time_ns()
        # Zenoh's FIFO channel, read here: measured ~300 us faster per query than a callback
        # that wakes this thread through an Event (the GIL hand-off costs that much).  The
        # query's timeout closes the channel, so the loop always ends.
        for reply in self._querier(selector).get(payload=request):
            t4 = time.time_ns()
            if reply.ok is None:
                continue
            key = str(reply.ok.key_expr)
            agent = keys.parse_agent_query(key, self.realm)
            if agent is None:
                self._bad.warning("query reply", f"unexpected key {key!r}")
                continue
            try:
                answer = decode_message(reply.ok.payload.to_bytes())
            except DecodeError as exc:
                answer = {"ok": False, "error": f"unreadable answer: {exc}"}
            yield agent, answer, t1, t4
            seen.add(agent)
            if expected and expected <= seen:
                return  # no need to wait for agents that have nothing to say

    def _querier(self, key: str) -> zenoh.Querier:
        """The querier of one query key, declared once: Zenoh then resolves the key
        expression once rather than at every get.  No consolidation: every agent replies on
        its own key, so there is nothing to merge, and the default would hold every answer
        back until the slowest agent is done."""
        with self._lock:
            querier = self._queriers.get(key)
            if querier is None:
                querier = self.session.declare_querier(
                    key, timeout=self.timeout, consolidation=zenoh.ConsolidationMode.NONE)
                self._queriers[key] = querier
        return querier

    def _to_pose(self, agent: str, d: dict[str, Any]) -> PoseResult:
        """A segment answer (a ``schemas.models.PoseResult`` map) on this process's clock,
        checked by the planner's light twin of the model (tens of us less per segment)."""
        offset = self.clock.offset(agent) or 0
        return pose_from_wire(d, lambda t: t - offset)

    # ------------------------------------------------------------------ streaming

    def subscribe(self, source: str, target: str, on_pose: Callable[[PoseResult], Any],
                  error: str = "latency",
                  on_error: Callable[[Exception], Any] | None = None,
                  stall_s: float | None = None) -> Subscription:
        """Push a composed pose to ``on_pose`` at every sample of the route's fastest edge,
        following route changes; ``on_error(exc)`` is told when no route is left, and a
        route silent for ``stall_s`` is reported as stalled (module docstring).  Raises like
        :meth:`pose` if there is no route to begin with."""
        if not callable(on_pose):
            raise ValueError("on_pose must be callable")
        if on_error is not None and not callable(on_error):
            raise ValueError("on_error must be callable or None")
        if stall_s is not None and not (isinstance(stall_s, int | float)
                                        and math.isfinite(stall_s) and stall_s > 0):
            raise ValueError(f"stall_s must be a positive number of seconds or None, got "
                             f"{stall_s!r}")
        seen = self.topology
        first, parts = self._query(source, target, None, error, details=True)
        sub = Subscription(self, source, target, on_pose, error, on_error, parts, first, seen,
                           stall_s)
        self._subscriptions.append(sub)
        return sub


#: what a route's mirror is made of: per segment, its agent and each edge's identity and
#: value (a different data key, attribute or static value means a different mirror)
Signature = tuple[tuple[str, tuple[tuple[Any, ...], ...]], ...]


def _signature(parts: list[tuple[Segment, list[dict[str, Any]]]]) -> Signature:
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
    times its route fell silent; ``last_error``: the latest failure (bad sample, undefined
    pull, stall, no route).
    """

    def __init__(self, client: Client, source: str, target: str,
                 on_pose: Callable[[PoseResult], Any], error: str,
                 on_error: Callable[[Exception], Any] | None,
                 parts: list[tuple[Segment, list[dict[str, Any]]]], first: PoseResult,
                 topology: int, stall_s: float | None = None) -> None:
        self.client = client
        self.source, self.target = source, target
        self.on_pose = on_pose
        self.on_error = on_error
        self.error = error
        self.delivered = 0
        self.failed = 0
        self.replans = 0
        self.stalls = 0
        self.last_error: Exception | None = None
        self.status = "streaming"
        self.stall_s = stall_s
        self.stall_limit_s = math.inf  # set for each route by _build
        self._last_push = time.monotonic()
        self.route: list[Segment] = []
        self.graph = Graph(buffer_s=5.0)
        self.pusher: tuple | None = None
        self._q: queue.Queue[tuple[str, str, bytes] | None] = queue.Queue(10_000)
        self._decls: list[Any] = []
        self._feeds: dict[str, tuple[str, str, tuple, float]] = {}
        self._signature: Signature | None = None
        self._topology = topology
        self._next_retry = math.inf
        self._closed = threading.Event()
        self._build(parts, first)
        self._thread = threading.Thread(target=self._work, name="uma-subscription",
                                        daemon=True)
        self._thread.start()

    # -- the mirror of one route
    def _build(self, parts: list[tuple[Segment, list[dict[str, Any]]]],
               first: PoseResult) -> None:
        """Mirror the route of ``parts`` (dropping any previous mirror) and subscribe."""
        self._unsubscribe()
        self.graph = Graph(buffer_s=5.0)
        feeds: list[tuple[str, str, tuple, float]] = []  # (agent, key, edge key, frequency)
        for seg, edges in parts:
            for e in edges:
                feeds += self._mirror(seg.agent, e)
        self.pusher = max(feeds, key=lambda f: f[3])[2] if feeds else None
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
        session = self.client.session
        for agent, key, _, _ in feeds:
            # enqueue straight from Zenoh's thread (it only copies the payload); the pose is
            # composed and delivered on this subscription's own thread
            self._decls.append(session.declare_subscriber(
                key, zenoh.handlers.Callback(lambda smp, a=agent, k=key: self._enqueue(a, k, smp),
                                             indirect=False)))
        if not feeds:  # all static: the one answer is the stream
            self._deliver(first)

    def _stall_limit(self, pusher_hz: float) -> float:
        """How long the fastest edge may be silent: ``stall_s``, or ``STALL_PERIODS`` of its
        advertised periods (never for a route without measured edges or stated rate)."""
        if self.pusher is None:
            return math.inf
        if self.stall_s is not None:
            return self.stall_s
        return max(STALL_MIN_S, STALL_PERIODS / pusher_hz) if pusher_hz > 0 else math.inf

    def _unsubscribe(self) -> None:
        for decl in self._decls:
            with contextlib.suppress(zenoh.ZError):
                decl.undeclare()
        self._decls.clear()
        self._feeds = {}

    def _mirror(self, agent: str, e: dict[str, Any]) -> list[tuple[str, str, tuple, float]]:
        """Copy one edge of the route into the local graph; measured ones become feeds."""
        source = f"{agent}/{e['source']}"
        attrs = {k: v for k, v in (e.get("attributes") or {}).items()
                 if k in EDGE_ATTRIBUTES and k not in ("covariance", "static")}
        cov = e.get("covariance")
        cov = None if cov is None else np.array(cov, dtype=float).reshape(6, 6)
        if e.get("static"):
            self.graph.add_static(e["parent"], e["child"], e["position"], e["quaternion"],
                                  covariance=cov, source=source, **attrs)
            return []
        if not e.get("key"):
            raise UmaError(f"agent {agent!r} gave no data key for edge "
                           f"{e['parent']}->{e['child']} [{e['source']}]")
        if cov is not None:
            attrs["covariance"] = cov
        key = self.graph.declare_measured(e["parent"], e["child"], source=source, **attrs)
        return [(agent, e["key"], key, float(attrs.get("frequency_hz", 0.0)))]

    # -- following the realm
    def _follow(self) -> None:
        """Plan again if the realm changed (or, without a route, when it is time to retry);
        move to the new route if it differs from the mirrored one."""
        topology = self.client.topology
        if topology == self._topology and time.monotonic() < self._next_retry:
            return
        self._topology = topology
        try:
            first, parts = self.client._query(self.source, self.target, None, self.error,
                                              details=True)
            if self._closed.is_set() or (_signature(parts) == self._signature
                                         and self.status in _ON_ROUTE):
                return
            was = [s.agent for s in self.route] if self.status in _ON_ROUTE else None
            self._build(parts, first)
        except (LookupError, UmaError, ValueError) as exc:
            self._lost(exc)
            return
        self.replans += 1
        log.info("subscription %s -> %s: now via %s (%s)", self.source, self.target,
                 ", ".join(str(s) for s in self.route),
                 "no route before" if was is None else f"was via agents {', '.join(was)}")

    def _lost(self, exc: Exception) -> None:
        """Planning failed.  A segment that failed while every agent of the mirrored route
        is alive may be transient (an answer late on a loaded machine): keep streaming.
        Otherwise stop delivering, say so once, and retry."""
        self.last_error = exc
        self._next_retry = time.monotonic() + RETRY_S
        alive = self.client._snapshot()[1]
        if (self.status in _ON_ROUTE and isinstance(exc, SegmentError)
                and {s.agent for s in self.route} <= alive):
            self.client._bad.warning(f"subscription {self.source} -> {self.target}",
                                     f"re-planning failed, route kept: {exc}")
            return
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
                self.client._bad.warning("on_error", f"{type(cb_exc).__name__}: {cb_exc}")

    # -- samples
    def _enqueue(self, agent: str, key: str, sample: zenoh.Sample) -> None:
        try:
            self._q.put_nowait((agent, key, sample.payload.to_bytes()))
        except queue.Full:
            self.client._bad.warning(f"subscription {key}", "queue full; sample dropped")

    def _work(self) -> None:
        while not self._closed.is_set():
            try:
                item = self._q.get(timeout=0.2)
            except queue.Empty:
                item = ()
            if item is None:
                return
            try:
                self._follow()
            except Exception:  # a bug must not stop the stream; log it with its traceback
                log.exception("subscription %s -> %s: re-planning failed", self.source,
                              self.target)
            if item:
                self._on_sample(*item)
            self._check_stall()

    def _check_stall(self) -> None:
        """On a route whose fastest edge has been silent too long: say so, once."""
        silent = time.monotonic() - self._last_push
        if self.status != "streaming" or silent <= self.stall_limit_s:
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
        feed = self._feeds.get(key)
        if feed is None:
            return  # a sample of a route left meanwhile
        edge_key = feed[2]
        try:
            m = decode_measurement(data, expected_type="pose6d")
            t = self.client.clock.to_local(agent, m.t_ns)
            self.graph.add_measurement(edge_key[0], edge_key[1], t, m.position,
                                       m.quaternion, m.covariance, source=edge_key[2])
        except (DecodeError, ValueError) as exc:
            self.failed += 1
            self.last_error = exc
            self.client._bad.warning(f"subscription {key}", f"bad sample: {exc}")
            return
        if edge_key != self.pusher:
            return
        self._pushed()
        try:
            result = self.graph.pose(self.source, self.target, at=t, error="hops")
        except EdgeUndefinedError as exc:  # a pulled edge has no data at t yet
            self.failed += 1
            self.last_error = exc
            return
        self._deliver(result)

    def _deliver(self, result: PoseResult) -> None:
        try:
            self.on_pose(result)
            self.delivered += 1
        except Exception as exc:
            self.failed += 1
            self.last_error = exc
            self.client._bad.warning("on_pose", f"{type(exc).__name__}: {exc}")

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        with contextlib.suppress(queue.Full):
            self._q.put_nowait(None)
        self._thread.join(1.0 + self.client.timeout)
        self._unsubscribe()
        self.status = "closed"
        with contextlib.suppress(ValueError):
            self.client._subscriptions.remove(self)


def _with_departed(exc: UnreachableError, summaries: Mapping[str, Summary],
                   alive: set[str]) -> SrgLookupError:
    """An unreachable pair, naming the departed agents that held frames of either side: the
    link between the two sides was most likely one of their segments."""
    sides = exc.source_side | exc.target_side
    gone = sorted(a for a, s in summaries.items() if a not in alive and s.frames & sides)
    if not gone:
        return exc
    return RouteError(f"{exc}; agent(s) {list_names(gone)} left the realm and held frames "
                      f"of these parts: the missing segment was probably theirs")
