"""The agent's query service: answers ``uma/<realm>/agent/<id>/query`` (the messages:
:mod:`agent.protocol.query`) from the local graph, whole routes with
:mod:`agent.daemon.relay` (its own segment, other agents' from its segment cache, the rest
asked of their agents).

Queries are answered in Zenoh's thread under the graph's lock (a query costs tens of
microseconds; a thread hop would cost as much as the network round trip).  Answers are
cached (``_cached_answer``: all-static paths at every time, the latest pose until the
next sample), at most ``MAX_ANSWERS`` of them.  A failing query is answered with an error,
never raised into Zenoh.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import zenoh

from agent.daemon.graph_store import LocalGraph
from agent.daemon.relay import RouteRelay, SegmentCache
from agent.protocol import keys
from agent.protocol import query as proto
from agent.result import PoseResult
from agent.runtime.logs import RateLimitedLog
from agent.runtime.payload import payload_bytes
from schemas.codec import DecodeError

log = logging.getLogger("uma.srg")

#: answers cached (least recently used dropped first): a query names its own error
#: expression, so distinct expressions from a peer must not grow the cache
MAX_ANSWERS = 1024


class QueryServer:
    """Answers pose queries, clock probes and routes for one agent (module docstring)."""

    def __init__(self, session: zenoh.Session, store: LocalGraph, now_ns: Callable[[], int],
                 limited_log: RateLimitedLog, client: Callable[..., Any] | None = None) -> None:
        """``client``: what the segment cache keeps other agents' segments with
        (:class:`agent.daemon.relay.SegmentCache`; None: it keeps none)."""
        self._store = store
        self.agent_id = store.agent_id
        self._now_ns = now_ns
        self._log = limited_log
        self.key = keys.agent_query(store.realm, store.agent_id)
        #: wire answers by (source, target, error) with the graph version and sample count
        #: they were computed at (see ``_cached_answer``); the count is None for an
        #: all-static path, whose answer holds at every time
        self.answers: OrderedDict[tuple[str, str, str],
                                  tuple[int, int | None, dict[str, Any]]] = OrderedDict()
        #: answers evicted by the bound above
        self.answers_evicted = 0
        #: other agents' segments this agent is asked for often, and whole routes
        self.segment_cache = SegmentCache(session, store.realm, client)
        self._relay = RouteRelay(session, store.realm, store.agent_id, self.own_part,
                                 now_ns, self.segment_cache, self.own_result)

    def on_query(self, query: zenoh.Query) -> None:
        t2 = self._now_ns()
        try:
            msg = proto.decode_request(payload_bytes(query.payload))
            if msg["op"] == "route":  # the whole route: the relay replies, maybe later
                self._relay.answer(query, proto.parse_request(msg, self.agent_id), t2)
                return
            reply = self.handle(msg)
        except (DecodeError, ValueError, LookupError, TypeError) as exc:
            reply = proto.error_reply(exc)
        except Exception as exc:  # never into Zenoh's thread: answer and log
            self._log.warning("query", f"{type(exc).__name__}: {exc}")
            reply = proto.internal_error_reply(exc)
        try:
            if reply is not None:  # None: a multi-agent request with no part for us
                query.reply(self.key, proto.stamped(reply, self.agent_id, t2,
                                                    self._now_ns()))
        except (zenoh.ZError, ValueError) as exc:
            self._log.warning("query reply", str(exc))
        finally:
            # answered: close it now (an exception's traceback holds the query, and it
            # would close only when the garbage collector frees that cycle, the asker
            # waiting its whole timeout meanwhile)
            query.drop()

    def handle(self, msg: dict[str, Any]) -> dict[str, Any] | None:
        """Answer one decoded query message (:mod:`agent.protocol.query`); None: not for us."""
        request = proto.parse_request(msg, self.agent_id)
        if request is None:
            return None
        self._store.catch_up()
        if isinstance(request, proto.ClockRequest):
            return proto.clock_reply()
        if isinstance(request, proto.RouteRequest):  # what is here; no other agent asked
            whole = self._relay.composed(request) if request.compose else None
            return whole or {"ok": True, "parts": self._relay.local_parts(request)[0]}
        return self._segment(request)

    def own_result(self, req: proto.SegmentRequest) -> PoseResult:
        """This agent's segment of a route composed here, on its clock (raises like
        :meth:`agent.srg.Graph.pose`)."""
        self._store.catch_up()
        with self._store.lock:
            return self._store.graph.pose(req.source, req.target, at=req.t, error=req.error)

    def own_part(self, req: proto.SegmentRequest) -> dict[str, Any]:
        """This agent's part of a route: its segment's answer, or the error saying why."""
        self._store.catch_up()
        try:
            return self._segment(req)
        except (ValueError, LookupError, TypeError) as exc:
            return proto.error_reply(exc)

    def _segment(self, req: proto.SegmentRequest) -> dict[str, Any]:
        """One segment's answer, from the cache when it still holds (``_cached_answer``)."""
        with self._store.lock:
            key = (req.source, req.target, req.error)
            cached = None if req.details else self._cached_answer(key, req.t)
            if cached is not None:
                return proto.segment_reply(cached)
            evicted = self._store.graph.plans_evicted
            r = self._store.graph.pose(req.source, req.target, at=req.t, error=req.error)
            if self._store.graph.plans_evicted > evicted:
                self._log.warning("query plans", f"{self._store.graph.max_plans} plans cached: "
                                  "dropped the least recently used "
                                  f"({self._store.graph.plans_evicted} so far)")
            t_used = r.t_ns if r.t_ns is not None else (
                req.t if req.t is not None else self._now_ns())
            result = proto.result_to_wire(r, req.source, req.target, self.agent_id, t_used)
            if req.details:
                return proto.segment_reply(result, [self._edge_details(e) for e in r.edges])
            if result["attributes"].get("static"):
                self._remember(key, (self._store.graph.version, None, result))
            elif req.t is None:
                self._remember(key, (self._store.graph.version, self._store.graph.samples, result))
        return proto.segment_reply(result)

    def _remember(self, key: tuple[str, str, str],
                  answer: tuple[int, int | None, dict[str, Any]]) -> None:
        """Cache an answer, dropping the least recently used beyond ``MAX_ANSWERS``."""
        self.answers[key] = answer
        self.answers.move_to_end(key)
        if len(self.answers) > MAX_ANSWERS:
            self.answers.popitem(last=False)
            self.answers_evicted += 1
            self._log.warning("query cache", f"{MAX_ANSWERS} answers cached: dropped the least "
                              f"recently used ({self.answers_evicted} so far)")

    def _cached_answer(self, key: tuple[str, str, str], t: int | None,
                       ) -> dict[str, Any] | None:
        """A wire answer computed before that still holds, or None.  Lock held.

        Any change of the graph's structure or attributes (``graph.version``) drops them
        all.  An all-static path's answer holds at every time (restamped at ``t``): the
        path search, composition and attribute aggregation are skipped, most of an
        answer's cost.  An answer at the latest time (``t`` nil) holds until the graph
        takes its next sample: clients may poll faster than trackers publish.
        """
        hit = self.answers.get(key)
        if hit is None or hit[0] != self._store.graph.version:
            return None
        self.answers.move_to_end(key)
        _, samples, result = hit
        if samples is None:
            return proto.at_time(result, t if t is not None else self._now_ns())
        return result if t is None and samples == self._store.graph.samples else None

    def _edge_details(self, e: dict[str, Any]) -> dict[str, Any]:
        """What a streaming client needs to rebuild an edge: its data key or its value."""
        return proto.edge_details(e, self._store.graph.edge(e["parent"], e["child"], e["source"]),
                                  self._store.data_key(e["source"]))

    def close(self) -> None:
        self.segment_cache.close()
