"""The agent's SRG on the network: local graph, supernode summary, query service.

The agent daemon creates one ``SrgNode(session, realm, agent_id, static_edges, streams)``
after opening its Zenoh session (``static_edges``: the config file's ``[[static]]`` tables
as checked by ``agent.daemon.settings.check_static_edge``; ``streams``: the daemon's
``agent.daemon.streams.StreamHub``, so the node and the stream monitor share one
subscription per data key), tells it which abilities each local service has
(``set_local_abilities``: on every registration, and with none when the service goes)
and calls ``close()`` at shutdown.  The node subscribes to its local ``pose6d`` streams
itself and puts each sample into its graph (``on_local_sample``), as tf2's
``TransformListener`` feeds its buffer: the daemon never handles a pose.  The node:

- keeps a :class:`agent.srg.Graph` of the configuration's static edges (source
  ``config``) and one measured edge per local ``pose6d`` ability (source
  ``<service_id>/<ability>``, the data key's last two chunks);
- publishes its supernode summary (:mod:`agent.srg.supernode`) on
  ``uma/<realm>/agent/<id>/supernode`` whenever its graph's structure or attributes or its
  boundary (the frames other agents also know, learnt from their summaries) change, and
  answers queries there with the latest one;
- answers ``uma/<realm>/agent/<id>/query`` (the messages: :mod:`agent.protocol.query`),
  whole routes with :mod:`agent.daemon.relay` (its own segment, other agents' from its
  supernode cache, the rest asked of their agents).

Threads: Zenoh callbacks decode and answer queries under the graph lock (a query costs
tens of microseconds), queue local samples (their bytes, nothing decoded) and record other
agents' frames; the queued samples are decoded into the graph in batches, by the worker
(every ``PUBLISH_CHECK_S`` while samples come) and before anything reads the graph (a
query, a summary), so answers hold every sample that arrived before them.  Per sample
that is a queue append on Zenoh's thread instead of a decode and an insert there: at
tracking rates the thread hop into Python finds the interpreter's caches cold, and a
batch decoded in one go is several times cheaper per sample.  One worker thread republishes the
summary when needed (computed from a copy of the graph's topology, off the lock) and asks
every agent for its summary every ``RESYNC_S`` (a summary put before our subscription
reached its author is never sent again).  A failing query is answered with an error, never
raised into Zenoh.
"""

from __future__ import annotations

import contextlib
import logging
import secrets
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any

import zenoh

from agent.daemon.relay import RouteRelay, SegmentCache
from agent.daemon.streams import StreamHub
from agent.protocol import keys
from agent.protocol import query as proto
from agent.protocol.sequence import too_far_ahead
from agent.runtime.callbacks import guarded
from agent.runtime.logs import RateLimitedLog
from agent.runtime.payload import payload_bytes
from agent.srg import Graph
from agent.srg.supernode import Topology, summarize
from schemas.codec import (
    DecodeError,
    decode_measurement,
    decode_message,
    encode_message,
    unpack_covariance,
)

log = logging.getLogger("uma.srg")

CONFIG_SOURCE = "config"
#: how often the worker checks whether the summary must be republished
PUBLISH_CHECK_S = 0.05
#: how often every agent is asked for its summary again (see ``_resync_if_due``)
RESYNC_S = 2.0
#: answers cached (least recently used dropped first): a query names its own error
#: expression, so distinct expressions from a peer must not grow the cache
MAX_ANSWERS = 1024
#: other agents whose frames are remembered, and frames remembered per agent: summaries
#: arrive from any peer, so what they make this agent hold is bounded
MAX_REMOTE_AGENTS = 1024
MAX_REMOTE_FRAMES = 4096
#: local samples queued before the thread that queues one decodes the batch itself (the
#: worker normally does, within PUBLISH_CHECK_S): a flood must not grow the agent
MAX_PENDING = 4096
#: edge attributes an ability may carry that the SRG uses
_SRG_ATTRIBUTES = ("latency_s", "frequency_hz", "confidence", "pos_std_m", "rot_std_rad",
                   "ttl_s", "cost")


def ability_attributes(ability: Any) -> dict[str, Any]:
    """The SRG attributes of a ``schemas.models.Ability`` (unset ones left out)."""
    attrs = ability.attributes
    out = {name: getattr(attrs, name) for name in _SRG_ATTRIBUTES
           if getattr(attrs, name, None) is not None}
    if getattr(attrs, "covariance", None) is not None:
        out["covariance"] = unpack_covariance(attrs.covariance)
    return out


class SrgNode:
    """One agent's SRG, its supernode summary and its query service (module docstring)."""

    def __init__(self, session: zenoh.Session, realm: str, agent_id: str,
                 static_edges: list[dict[str, Any]] | None = None,
                 streams: StreamHub | None = None) -> None:
        self.session = session
        self._streams = streams if streams is not None else StreamHub(session)
        #: local pose6d abilities -> (the ability, stop listening to its data key)
        self._local: dict[tuple[str, str], tuple[Any, Callable[[], None]]] = {}
        self.realm = realm
        self.agent_id = agent_id
        #: test-only skew of this agent's clock (agent.protocol.query.SKEW_ENV)
        self.skew_ns = proto.skew_from_env()
        self.graph = Graph()
        self._lock = threading.Lock()
        #: held while a summary is computed and published (not the graph's lock)
        self._publishing = threading.Lock()
        self._log = RateLimitedLog(log)
        self._sources: dict[tuple[str, str], tuple[Any, str]] = {}  # -> (ability, source)
        self._data_keys: dict[str, str] = {}  # edge source -> data key
        self._static_values: dict[str, tuple[bytes, bytes, bytes | None]] = {}
        #: wire answers by (source, target, error) with the graph version and sample count
        #: they were computed at (see ``_cached_answer``); the count is None for an
        #: all-static path, whose answer holds at every time
        self._answers: OrderedDict[tuple[str, str, str],
                                   tuple[int, int | None, dict[str, Any]]] = OrderedDict()
        self._remote_frames: dict[str, set[str]] = {}
        #: local samples refused: stamped too far ahead of this host's clock
        self.refused = 0
        #: what the bounds above refused or dropped: answers evicted, summaries refused
        self.answers_evicted = 0
        self.summaries_refused = 0
        self._to_fetch: set[str] = set()  # agents whose summary to ask for
        self._boundary: set[str] = set()
        self._published: tuple[int, frozenset[str]] | None = None
        #: distinguishes this run's summary revisions from a restarted agent's
        self.instance = secrets.token_hex(6)
        self._summary = encode_message({"agent": agent_id, "rev": 0, "frames": [],
                                        "boundary": [], "components": [], "links": []})
        self._rev = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        #: local samples not decoded yet: (service id, ability name), payload
        self._pending: deque[tuple[tuple[str, str], bytes]] = deque()
        self._next_resync = time.monotonic() + RESYNC_S
        for i, edge in enumerate(static_edges or []):
            self._add_static(i, edge)
        self._query_key = keys.agent_query(realm, agent_id)
        #: other agents' segments this agent is asked for often, and whole routes
        self.segment_cache = SegmentCache(session, realm)
        self._relay = RouteRelay(session, realm, agent_id, self._own_part, self.now_ns,
                                 self.segment_cache)
        self._summary_key = keys.agent_supernode(realm, agent_id)
        self._decls = [
            # answered in Zenoh's thread (a query costs tens of microseconds; a thread hop
            # would cost as much as the network round trip)
            session.declare_queryable(self._query_key, zenoh.handlers.Callback(
                guarded(self._on_query, "query", self._log), indirect=False)),
            session.declare_queryable(self._summary_key, guarded(
                self._on_summary_query, "supernode query", self._log)),
            session.declare_subscriber(keys.all_agent_supernodes(realm), guarded(
                self._on_summary, "supernode", self._log)),
            session.liveliness().declare_subscriber(keys.all_agent_tokens(realm), guarded(
                self._on_agent_token, "agent token", self._log), history=True),
        ]
        self._on_reply = guarded(self._on_summary_reply, "supernode reply", self._log)
        session.get(keys.all_agent_supernodes(realm), self._on_reply, timeout=2.0)
        self._worker = threading.Thread(target=self._work, name="uma-srg", daemon=True)
        self._worker.start()
        self._wake.set()

    def now_ns(self) -> int:
        """This agent's clock (skewed in tests, see agent.protocol.query.SKEW_ENV)."""
        return time.time_ns() + self.skew_ns

    # ------------------------------------------------------------------ feeding the graph

    def _add_static(self, i: int, edge: dict[str, Any]) -> None:
        try:
            self.graph.add_static(edge["parent"], edge["child"], edge["position"],
                                  edge["quaternion"], source=CONFIG_SOURCE,
                                  pos_std_m=edge.get("pos_std_m"),
                                  rot_std_rad=edge.get("rot_std_rad"))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"static edge #{i + 1} ({edge!r}): {exc}") from None

    def set_local_abilities(self, service_id: str, abilities: list[Any]) -> None:
        """The abilities a local service has now (none: it went): listen to the data of
        its new ``pose6d`` ones, stop listening to the ones it dropped (their edges leave
        the graph).  An ability whose attributes changed keeps its subscription; its next
        sample brings the new attributes into the graph."""
        wanted = {a.name: a for a in abilities if a.type == "pose6d"}
        for (sid, name), (ability, stop) in list(self._local.items()):
            if sid != service_id:
                continue
            if name in wanted:
                self._local[(sid, name)] = (wanted[name], stop)
                continue
            stop()
            del self._local[(sid, name)]
            self.on_ability_removed(sid, ability)
        for name, ability in wanted.items():
            if (service_id, name) not in self._local:
                key = keys.data(self.realm, self.agent_id, service_id, name)
                stop = self._streams.listen(
                    key, lambda data, k=(service_id, name): self._on_local_data(k, data))
                self._local[(service_id, name)] = (ability, stop)

    def _on_local_data(self, local: tuple[str, str], data: bytes) -> None:
        """A local pose sample (Zenoh's thread): queued for the next batch (module
        docstring); the first of a batch wakes the worker."""
        pending = self._pending
        if not pending:
            self._wake.set()
        pending.append((local, data))
        if len(pending) >= MAX_PENDING:
            self.drain()

    def drain(self) -> None:
        """Decode the queued local samples into the graph (any thread; each sample once)."""
        pending = self._pending
        while pending:
            try:
                local, data = pending.popleft()
            except IndexError:  # another thread took the last one
                return
            self._take_local(local, data)

    def _take_local(self, local: tuple[str, str], data: bytes) -> None:
        """One queued local sample: decode it and put it into the graph."""
        entry = self._local.get(local)
        if entry is None:
            return  # the ability went away meanwhile
        try:
            m = decode_measurement(data, expected_type="pose6d")
            if too_far_ahead(m.t_ns, self.now_ns()):
                self.refused += 1
                raise DecodeError(f"stamped {(m.t_ns - self.now_ns()) / 1e9:.3g} s ahead of "
                                  f"this host's clock ({self.refused} refused so far)")
        except DecodeError as exc:
            key = keys.data(self.realm, self.agent_id, *local)
            self._log.warning(f"data {key}", f"dropped a malformed sample: {exc}")
            return
        self.on_local_sample(local[0], entry[0], m)

    def on_local_sample(self, service_id: str, ability: Any, measurement: Any) -> None:
        """A sample of a local pose6d ability.  A static ability (a calibration, e.g. the
        result of tracker alignment) sets its static edge, valid at all times; any other
        appends the sample to its measured edge."""
        key = (service_id, ability.name)
        source = f"{service_id}/{ability.name}"
        parent, child = ability.edge
        with self._lock:
            known = self._sources.get(key)
            # the same Ability object comes with every sample until it changes (see
            # set_local_abilities): `is` spares the per-sample model comparison
            changed = known is None or (known[0] is not ability and known[0] != ability)
            if changed and known is not None and (
                    known[0].attributes.static != ability.attributes.static):
                self.graph.remove_source(source)  # measured <-> static: a different edge kind
                known = None
            if ability.attributes.static:
                self._set_static(key, source, ability, measurement, known)
                return
            if changed:
                self.graph.declare_measured(parent, child, source=source,
                                            **ability_attributes(ability))
                self._sources[key] = (ability, source)
                self._data_keys[source] = keys.data(self.realm, self.agent_id, service_id,
                                                    ability.name)
                self._wake.set()
            self.graph.add_measurement(parent, child, measurement.t_ns, measurement.position,
                                       measurement.quaternion, measurement.covariance,
                                       source=source)

    def _set_static(self, key: tuple[str, str], source: str, ability: Any, measurement: Any,
                    known: tuple[Any, str] | None) -> None:
        """Replace a static edge only when its value or attributes change: a replacement
        invalidates the query plans that use it, and calibrations are re-published often."""
        value = (measurement.position.tobytes(), measurement.quaternion.tobytes(),
                 None if measurement.covariance is None else measurement.covariance.tobytes())
        if known is not None and known[0] == ability and self._static_values.get(source) == value:
            return
        parent, child = ability.edge
        attrs = ability_attributes(ability)
        advertised = attrs.pop("covariance", None)  # the sample's own covariance wins
        cov = measurement.covariance if measurement.covariance is not None else advertised
        self.graph.add_static(parent, child, measurement.position, measurement.quaternion,
                              cov, source=source, **attrs)
        self._sources[key] = (ability, source)
        self._static_values[source] = value
        self._wake.set()

    def on_ability_removed(self, service_id: str, ability: Any) -> None:
        """A local ability went away: its edge leaves the graph (and the summary)."""
        with self._lock:
            entry = self._sources.pop((service_id, ability.name), None)
            if entry is not None:
                self.graph.remove_source(entry[1])
                self._data_keys.pop(entry[1], None)
                self._static_values.pop(entry[1], None)
        self._wake.set()

    # ------------------------------------------------------------------ queries

    def _on_query(self, query: zenoh.Query) -> None:
        t2 = self.now_ns()
        try:
            msg = proto.decode_request(payload_bytes(query.payload))
            if msg["op"] == "route":  # the whole route: the relay replies, maybe later
                self._relay.answer(query, proto.parse_request(msg, self.agent_id), t2)
                return
            reply = self.handle(msg)
            if reply is None:
                return  # a multi-agent request with no part for this agent
        except (DecodeError, ValueError, LookupError, TypeError) as exc:
            reply = proto.error_reply(exc)
        except Exception as exc:  # never into Zenoh's thread: answer and log
            self._log.warning("query", f"{type(exc).__name__}: {exc}")
            reply = proto.internal_error_reply(exc)
        try:
            query.reply(self._query_key, proto.stamped(reply, self.agent_id, t2, self.now_ns()))
        except (zenoh.ZError, ValueError) as exc:
            self._log.warning("query reply", str(exc))

    def handle(self, msg: dict[str, Any]) -> dict[str, Any] | None:
        """Answer one decoded query message (:mod:`agent.protocol.query`); None: not for us."""
        request = proto.parse_request(msg, self.agent_id)
        if request is None:
            return None
        self.drain()
        if isinstance(request, proto.ClockRequest):
            return proto.clock_reply()
        if isinstance(request, proto.RouteRequest):  # what is here; no other agent asked
            return {"ok": True, "parts": self._relay.local_parts(request)[0]}
        return self._segment(request)

    def _own_part(self, req: proto.SegmentRequest) -> dict[str, Any]:
        """This agent's part of a route: its segment's answer, or the error saying why."""
        self.drain()
        try:
            return self._segment(req)
        except (ValueError, LookupError, TypeError) as exc:
            return proto.error_reply(exc)

    def _segment(self, req: proto.SegmentRequest) -> dict[str, Any]:
        """One segment's answer, from the cache when it still holds (``_cached_answer``)."""
        with self._lock:
            key = (req.source, req.target, req.error)
            cached = None if req.details else self._cached_answer(key, req.t)
            if cached is not None:
                return proto.segment_reply(cached)
            evicted = self.graph.plans_evicted
            r = self.graph.pose(req.source, req.target, at=req.t, error=req.error)
            if self.graph.plans_evicted > evicted:
                self._log.warning("query plans", f"{self.graph.max_plans} plans cached: "
                                  "dropped the least recently used "
                                  f"({self.graph.plans_evicted} so far)")
            t_used = r.t_ns if r.t_ns is not None else (
                req.t if req.t is not None else self.now_ns())
            result = proto.result_to_wire(r, req.source, req.target, self.agent_id, t_used)
            if req.details:
                return proto.segment_reply(result, [self._edge_details(e) for e in r.edges])
            if result["attributes"].get("static"):
                self._remember(key, (self.graph.version, None, result))
            elif req.t is None:
                self._remember(key, (self.graph.version, self.graph.samples, result))
        return proto.segment_reply(result)

    def _remember(self, key: tuple[str, str, str],
                  answer: tuple[int, int | None, dict[str, Any]]) -> None:
        """Cache an answer, dropping the least recently used beyond ``MAX_ANSWERS``."""
        self._answers[key] = answer
        self._answers.move_to_end(key)
        if len(self._answers) > MAX_ANSWERS:
            self._answers.popitem(last=False)
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
        hit = self._answers.get(key)
        if hit is None or hit[0] != self.graph.version:
            return None
        self._answers.move_to_end(key)
        _, samples, result = hit
        if samples is None:
            return proto.at_time(result, t if t is not None else self.now_ns())
        return result if t is None and samples == self.graph.samples else None

    def _edge_details(self, e: dict[str, Any]) -> dict[str, Any]:
        """What a streaming client needs to rebuild an edge: its data key or its value."""
        return proto.edge_details(e, self.graph.edge(e["parent"], e["child"], e["source"]),
                                  self._data_keys.get(e["source"]))

    # ------------------------------------------------------------------ summaries

    def _on_summary_query(self, query: zenoh.Query) -> None:
        try:
            query.reply(self._summary_key, self._summary)
        except zenoh.ZError as exc:
            self._log.warning("supernode reply", str(exc))

    def _on_summary(self, sample: zenoh.Sample) -> None:
        self._learn(str(sample.key_expr), sample.payload)

    def _on_summary_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self._learn(str(reply.ok.key_expr), reply.ok.payload)

    def _learn(self, key: str, payload: zenoh.ZBytes | bytes) -> None:
        """Record the frames another agent knows (they decide our boundary)."""
        try:
            data = payload if isinstance(payload, bytes) else payload_bytes(payload)
            msg = decode_message(data, required=("agent", "frames"))
            agent, frames = msg["agent"], msg["frames"]
            if not isinstance(agent, str) or not isinstance(frames, list) or not all(
                    isinstance(f, str) for f in frames):
                raise DecodeError("agent must be a string and frames a list of strings")
            if agent != keys.parse_agent_supernode(key, self.realm):
                raise DecodeError(f"it names agent {agent[:64]!r}, not the agent of its key")
        except DecodeError as exc:
            self.summaries_refused += 1
            self._log.warning(f"supernode {key}", f"dropped a malformed summary: {exc}")
            return
        if agent == self.agent_id:
            return
        with self._lock:
            refused = self._refusal(agent, frames)
            if refused is None:
                self._remote_frames[agent] = set(frames)
        if refused is not None:
            self.summaries_refused += 1
            self._log.warning(f"supernode {key}", f"summary refused: {refused} "
                              f"({self.summaries_refused} refused so far)")
            return
        self._wake.set()

    def _refusal(self, agent: str, frames: list[str]) -> str | None:
        """Why a summary would exceed what this node keeps of other agents, or None.  Lock
        held."""
        if len(frames) > MAX_REMOTE_FRAMES:
            return f"{len(frames)} frames, more than {MAX_REMOTE_FRAMES}"
        if agent not in self._remote_frames and len(self._remote_frames) >= MAX_REMOTE_AGENTS:
            return f"frames of {MAX_REMOTE_AGENTS} agents kept already"
        return None

    def _on_agent_token(self, sample: zenoh.Sample) -> None:
        """An agent appeared (fetch its summary: it may have published before we were
        linked) or left (forget its frames)."""
        agent = keys.parse_agent_token(str(sample.key_expr), self.realm)
        if agent is None or agent == self.agent_id:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._remote_frames.pop(agent, None)
                self._to_fetch.discard(agent)
            else:
                self._to_fetch.add(agent)
        self._wake.set()

    def _work(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(1.0)
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                self.drain()
                self._resync_if_due()
                self._fetch_new()
                self._republish_if_changed()
            except Exception as exc:  # keep the agent alive; say why once in a while
                self._log.warning("supernode", f"{type(exc).__name__}: {exc}")
            self._stop.wait(PUBLISH_CHECK_S)

    def _resync_if_due(self) -> None:
        """Ask every agent for its summary every ``RESYNC_S``: a summary put before this
        agent's subscription reached its author is not sent again, and a boundary that
        misses it hides a link from every planner (bench setups were seen stuck on it)."""
        now = time.monotonic()
        if now < self._next_resync:
            return
        self._next_resync = now + RESYNC_S
        self.session.get(keys.all_agent_supernodes(self.realm), self._on_reply,
                         timeout=2.0)

    def _fetch_new(self) -> None:
        with self._lock:
            agents, self._to_fetch = self._to_fetch, set()
        for agent in sorted(agents):
            self.session.get(keys.agent_supernode(self.realm, agent), self._on_reply,
                             timeout=2.0)

    def _republish_if_changed(self) -> None:
        """Publish a new summary when the graph or the boundary changed.  Only the copy
        of the graph's topology is taken under the lock: the summary is computed without
        it, so queries and samples are never held up by it (a large graph's summary takes
        a while).  Publishers take turns (``_publishing``):
        a summary of an older state must not overwrite a newer one."""
        with self._publishing:
            with self._lock:
                local = set(self.graph.frames())
                remote = (set().union(*self._remote_frames.values()) if self._remote_frames
                          else set())
                boundary = frozenset(local & remote)
                state = (self.graph.version, boundary)
                if state == self._published:
                    return
                topology = Topology.of(self.graph)
            self._rev += 1
            summary = summarize(topology, boundary)
            summary.update(agent=self.agent_id, rev=self._rev, instance=self.instance)
            self._warn_if_refused(summary)
            data = encode_message(proto.summary_to_wire(summary))
            self._summary = data
            self._published = state
            self.session.put(self._summary_key, data)

    def _warn_if_refused(self, summary: dict[str, Any]) -> None:
        """Say so when every other agent and client will refuse this summary: queries that
        need this host's frames then fail elsewhere with "unknown frame", and the reason is
        only here.  Links grow with frames x boundary frames (``agent.srg.supernode``)."""
        frames, links = len(summary["frames"]), len(summary["links"])
        if max(frames, links) > proto.MAX_SUMMARY_FRAMES:
            self._log.warning("supernode", f"this agent's summary has {frames} frames and "
                              f"{links} links (frames x {len(summary['boundary'])} boundary "
                              f"frames); receivers refuse more than "
                              f"{proto.MAX_SUMMARY_FRAMES} of either, so no other host can "
                              "plan a query through this one: fewer frames or fewer frames "
                              "shared with other hosts")

    def close(self) -> None:
        """Stop publishing, answering and listening (before the agent closes its session)."""
        self._stop.set()
        self._wake.set()
        self._worker.join(2.0)
        self.segment_cache.close()
        for _, stop in self._local.values():
            stop()
        self._local.clear()
        for decl in self._decls:
            with contextlib.suppress(zenoh.ZError):
                decl.undeclare()
        self._decls.clear()
