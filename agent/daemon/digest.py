"""The agent's stream digest (:mod:`agent.protocol.digest`): the newest sample of each local
pose stream, put by the SRG node's worker at its tick while a subscriber listens.

The stream hub's thread only stores a reference to each sample's bytes (the graph store keeps the
newest per stream, :class:`agent.daemon.graph_store.LocalGraph`); nothing is decoded or
encoded unless someone listens, and a digest is put only when a stream had a new sample
since the last one.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Mapping

import zenoh

from agent.protocol import keys
from agent.protocol.digest import MAX_DIGEST_STREAMS, digest_message
from agent.runtime.logs import RateLimitedLog

log = logging.getLogger("uma.srg")


class StreamDigest:
    """The digest of one agent's local pose streams: ``newest()`` gives the newest payload
    per (service id, ability name), ``seen()`` a count that moves with every sample."""

    def __init__(self, session: zenoh.Session, realm: str, agent_id: str,
                 newest: Callable[[], Mapping[tuple[str, str], bytes]],
                 seen: Callable[[], int]) -> None:
        self.agent_id = agent_id
        self._newest = newest
        self._seen = seen
        self._published = 0
        self._log = RateLimitedLog(log)
        self._publisher = session.declare_publisher(keys.agent_digest(realm, agent_id))

    def publish(self) -> None:
        """Put the digest if a stream had a sample since the last one and someone listens
        (the worker's thread)."""
        seen = self._seen()
        if seen == self._published:
            return
        try:
            if not self._publisher.matching_status.matching:
                return
        except zenoh.ZError:
            return
        self._published = seen
        newest = dict(self._newest())
        if len(newest) > MAX_DIGEST_STREAMS:
            self._log.warning("digest", f"{len(newest)} streams: the digest carries the "
                              f"first {MAX_DIGEST_STREAMS}")
            newest = dict(list(newest.items())[:MAX_DIGEST_STREAMS])
        try:
            self._publisher.put(digest_message(self.agent_id, newest))
        except (zenoh.ZError, ValueError) as exc:
            self._log.warning("digest", str(exc))

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self._publisher.undeclare()
