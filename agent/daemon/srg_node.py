"""The agent's SRG on the network: local graph, supernode summary, query service.

The agent daemon creates one ``SrgNode(session, realm, agent_id, static_edges, streams, client)``
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
- puts the newest sample of each local pose stream on ``uma/<realm>/agent/<id>/digest``
  while someone listens (:mod:`agent.daemon.digest`, for ``uma view``);
- answers ``uma/<realm>/agent/<id>/query`` (the messages: :mod:`agent.protocol.query`),
  whole routes with :mod:`agent.daemon.relay` (its own segment, other agents' from its
  supernode cache, the rest asked of their agents).

``SrgNode`` is a facade over parts with one job each: the graph store
(:mod:`agent.daemon.graph_store`), the query server (:mod:`agent.daemon.query_server`),
the summary publisher (:mod:`agent.daemon.summary_publisher`) and what it learns of the
other agents' summaries (:mod:`agent.daemon.peer_frames`).  It declares their Zenoh
endpoints and runs the worker they share.

Threads: Zenoh callbacks decode and answer queries under the graph lock (a query costs
tens of microseconds), queue local samples (their bytes, nothing decoded) and record other
agents' frames; the queued samples are decoded into the graph in batches, by the worker
(every ``PUBLISH_CHECK_S`` while samples come) and before anything reads the graph (a
query, a summary), so answers hold every sample that arrived before them.  Per sample
that is a queue append on the stream hub's thread instead of a decode and an insert there: at
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
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from agent.daemon.digest import StreamDigest
from agent.daemon.graph_store import LocalGraph
from agent.daemon.peer_frames import PeerFrames
from agent.daemon.query_server import QueryServer
from agent.daemon.relay import SegmentCache
from agent.daemon.streams import StreamHub
from agent.daemon.summary_publisher import SummaryPublisher
from agent.protocol import keys
from agent.protocol import query as proto
from agent.runtime.callbacks import guarded
from agent.runtime.logs import RateLimitedLog
from agent.runtime.worker import WakeLoop
from agent.srg import Graph

log = logging.getLogger("uma.srg")

#: how often the worker checks whether the summary must be republished
PUBLISH_CHECK_S = 0.05


class SrgNode:
    """One agent's SRG, its supernode summary and its query service (module docstring)."""

    def __init__(self, session: zenoh.Session, realm: str, agent_id: str,
                 static_edges: list[dict[str, Any]] | None = None,
                 streams: StreamHub | None = None, client: Callable[..., Any] | None = None,
                 ) -> None:
        """``client``: what the segment cache keeps other agents' segments with
        (:class:`agent.daemon.relay.SegmentCache`; None: it keeps none)."""
        self.session = session
        self.realm = realm
        self.agent_id = agent_id
        #: test-only skew of this agent's clock (agent.protocol.query.SKEW_ENV)
        self.skew_ns = proto.skew_from_env()
        self._log = RateLimitedLog(log)
        self._loop = WakeLoop("uma-srg", self._work, self._log, "supernode",
                              pause_s=PUBLISH_CHECK_S)
        lock = threading.Lock()

        def clock() -> int:  # looked up at each call: tests replace now_ns
            return self.now_ns()
        self.store = LocalGraph(streams if streams is not None else StreamHub(session), realm,
                                agent_id, static_edges or [], lock, clock, self._loop.wake,
                                self._log)
        self.queries = QueryServer(session, self.store, clock, self._log, client)
        self.peers = PeerFrames(session, realm, agent_id, lock, self._loop.wake, self._log)
        self.publisher = SummaryPublisher(session, self.store, self.peers, self._log)
        #: the newest sample of each local pose stream, for viewers
        self.digest = StreamDigest(session, realm, agent_id, lambda: self.store.newest,
                                   lambda: self.store.samples_seen)
        self._decls = [
            # answered in Zenoh's thread (a query costs tens of microseconds; a thread hop
            # would cost as much as the network round trip)
            session.declare_queryable(self.queries.key, zenoh.handlers.Callback(
                guarded(self.queries.on_query, "query", self._log), indirect=False)),
            session.declare_queryable(self.publisher.key, guarded(
                self.publisher.on_summary_query, "supernode query", self._log)),
            session.declare_subscriber(keys.all_agent_supernodes(realm), guarded(
                self.peers.on_summary, "supernode", self._log)),
            session.liveliness().declare_subscriber(keys.all_agent_tokens(realm), guarded(
                self.peers.on_agent_token, "agent token", self._log), history=True),
        ]
        self.peers.ask_all()
        self._loop.start()
        self._loop.wake()

    def now_ns(self) -> int:
        """This agent's clock (skewed in tests, see agent.protocol.query.SKEW_ENV)."""
        return time.time_ns() + self.skew_ns

    # ------------------------------------------------------------------ the parts' faces

    @property
    def graph(self) -> Graph:
        return self.store.graph

    @property
    def refused(self) -> int:
        """Local samples refused: stamped too far ahead of this host's clock."""
        return self.store.refused

    @property
    def answers_evicted(self) -> int:
        return self.queries.answers_evicted

    @property
    def summaries_refused(self) -> int:
        return self.peers.refused

    @property
    def instance(self) -> str:
        return self.publisher.instance

    @property
    def segment_cache(self) -> SegmentCache:
        return self.queries.segment_cache

    def set_local_abilities(self, service_id: str, abilities: list[Any]) -> None:
        """See :meth:`agent.daemon.graph_store.LocalGraph.set_local_abilities`."""
        self.store.set_local_abilities(service_id, abilities)

    def on_local_sample(self, service_id: str, ability: Any, measurement: Any) -> None:
        """See :meth:`agent.daemon.graph_store.LocalGraph.on_local_sample`."""
        self.store.on_local_sample(service_id, ability, measurement)

    def on_ability_removed(self, service_id: str, ability: Any) -> None:
        """See :meth:`agent.daemon.graph_store.LocalGraph.on_ability_removed`."""
        self.store.on_ability_removed(service_id, ability)

    def handle(self, msg: dict[str, Any]) -> dict[str, Any] | None:
        """See :meth:`agent.daemon.query_server.QueryServer.handle`."""
        return self.queries.handle(msg)

    # ------------------------------------------------------------------ the worker

    def _work(self) -> None:
        """Take the queued samples, then publish what they changed, at most every
        ``PUBLISH_CHECK_S``."""
        self.store.catch_up()
        self.digest.publish()
        self.peers.resync_if_due()
        self.peers.fetch_new()
        self.publisher.republish_if_changed()

    def close(self) -> None:
        """Stop publishing, answering and listening (before the agent closes its session)."""
        self._loop.close(2.0)
        self.queries.close()
        self.store.close()
        self.digest.close()
        for decl in self._decls:
            with contextlib.suppress(zenoh.ZError):
                decl.undeclare()
        self._decls.clear()
