"""This agent's supernode summary (:mod:`agent.srg.supernode`) on
``uma/<realm>/agent/<id>/supernode``: published whenever the local graph's structure or
attributes or its boundary (the frames other agents also know, :mod:`agent.daemon.
peer_frames`) change, and the latest one given to whoever asks.  A summary is computed from
a copy of the graph's topology, off the graph's lock.
"""

from __future__ import annotations

import logging
import secrets
import threading
from typing import Any

import zenoh

from agent.daemon.graph_store import LocalGraph
from agent.daemon.peer_frames import PeerFrames
from agent.protocol import keys
from agent.protocol import query as proto
from agent.runtime.logs import RateLimitedLog
from agent.srg.supernode import Topology, summarize
from schemas.codec import encode_message

log = logging.getLogger("uma.srg")


class SummaryPublisher:
    """Publishes and answers this agent's summary (module docstring)."""

    def __init__(self, session: zenoh.Session, store: LocalGraph, peers: PeerFrames,
                 limited_log: RateLimitedLog) -> None:
        self._session = session
        self._store = store
        self._peers = peers
        self._log = limited_log
        self.agent_id = store.agent_id
        self.key = keys.agent_supernode(store.realm, store.agent_id)
        #: held while a summary is computed and published (not the graph's lock)
        self._publishing = threading.Lock()
        #: distinguishes this run's summary revisions from a restarted agent's
        self.instance = secrets.token_hex(6)
        self.summary = encode_message({"agent": store.agent_id, "rev": 0, "frames": [],
                                       "boundary": [], "components": [], "links": []})
        self._rev = 0
        self._published: tuple[int, frozenset[str]] | None = None

    def on_summary_query(self, query: zenoh.Query) -> None:
        try:
            query.reply(self.key, self.summary)
        except zenoh.ZError as exc:
            self._log.warning("supernode reply", str(exc))

    def republish_if_changed(self) -> None:
        """Publish a new summary when the graph or the boundary changed.  Only the copy
        of the graph's topology is taken under the lock: the summary is computed without
        it, so queries and samples are never held up by it (a large graph's summary takes
        a while).  Publishers take turns (``_publishing``):
        a summary of an older state must not overwrite a newer one."""
        with self._publishing:
            with self._store.lock:
                local = set(self._store.graph.frames())
                remote = self._peers.known_elsewhere()
                boundary = frozenset(local & remote)
                state = (self._store.graph.version, boundary)
                if state == self._published:
                    return
                topology = Topology.of(self._store.graph)
            self._rev += 1
            summary = summarize(topology, boundary)
            summary.update(agent=self.agent_id, rev=self._rev, instance=self.instance)
            self._warn_if_refused(summary)
            data = encode_message(proto.summary_to_wire(summary))
            self.summary = data
            self._published = state
            self._session.put(self.key, data)

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
