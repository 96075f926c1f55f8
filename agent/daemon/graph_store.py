"""The agent's local SRG: the configuration's static edges and one edge per local ``pose6d``
ability, fed from their data keys as tf2's ``TransformListener`` feeds its buffer.

It keeps a :class:`agent.srg.Graph` of the configuration's static edges (source ``config``)
and one measured edge per local ``pose6d`` ability (source ``<service_id>/<ability>``, the
data key's last two chunks); a static ability (a calibration) sets a static edge instead.
Samples are queued in the stream hub's thread (their bytes, nothing decoded; the hub
hands them over in batches, ``agent.daemon.streams``) and decoded into the graph in
batches by :meth:`LocalGraph.drain`; :meth:`LocalGraph.catch_up` takes what waits in the
hub too, and the agent's worker and every reader of the graph call it first
(``agent.daemon.srg_node``, "Threads").  ``wake()`` wakes
the agent's worker: samples wait to be decoded, or the graph's structure or attributes
changed (the summary must be published again).
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from agent.daemon.streams import StreamHub
from agent.errors import InvalidInputError
from agent.protocol import keys
from agent.protocol.sequence import stamp_refusal
from agent.runtime.logs import RateLimitedLog
from agent.srg import Graph
from schemas.codec import DecodeError, Measurement, decode_pose, unpack_covariance

log = logging.getLogger("uma.srg")

CONFIG_SOURCE = "config"
#: local samples queued before the thread that queues one decodes the batch itself (the
#: worker normally does, within its tick): a flood must not grow the agent
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


class LocalGraph:
    """The graph store of one agent (module docstring)."""

    def __init__(self, streams: StreamHub, realm: str, agent_id: str,
                 static_edges: list[dict[str, Any]], lock: threading.Lock,
                 now_ns: Callable[[], int], wake: Callable[[], None],
                 limited_log: RateLimitedLog) -> None:
        self._streams = streams
        self.realm = realm
        self.agent_id = agent_id
        self.graph = Graph()
        #: the graph's lock, shared with the query server and the summary publisher
        self.lock = lock
        self._now_ns = now_ns
        self._wake = wake
        self._log = limited_log
        #: local pose6d abilities -> (the ability, stop listening to its data key)
        self._local: dict[tuple[str, str], tuple[Any, Callable[[], None]]] = {}
        self._sources: dict[tuple[str, str], tuple[Any, str]] = {}  # -> (ability, source)
        self._data_keys: dict[str, str] = {}  # edge source -> data key
        self._static_values: dict[str, tuple[bytes, bytes, bytes | None]] = {}
        #: local samples refused: stamped too far ahead of this host's clock
        self.refused = 0
        #: local samples not decoded yet: (service id, ability name), payload
        self._pending: deque[tuple[tuple[str, str], bytes]] = deque()
        #: the newest payload of each local pose stream, and samples seen (the digest for
        #: viewers puts them, :mod:`agent.daemon.digest`)
        self.newest: dict[tuple[str, str], bytes] = {}
        self.samples_seen = 0
        for i, edge in enumerate(static_edges):
            self._add_static(i, edge)

    def data_key(self, source: str) -> str | None:
        """The data key of a measured edge's source (None: a static one)."""
        return self._data_keys.get(source)

    def _add_static(self, i: int, edge: dict[str, Any]) -> None:
        try:
            self.graph.add_static(edge["parent"], edge["child"], edge["position"],
                                  edge["quaternion"], source=CONFIG_SOURCE,
                                  pos_std_m=edge.get("pos_std_m"),
                                  rot_std_rad=edge.get("rot_std_rad"))
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidInputError(f"static edge #{i + 1} ({edge!r}): {exc}") from None

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
            self.newest.pop((sid, name), None)
            self.on_ability_removed(sid, ability)
        for name, ability in wanted.items():
            if (service_id, name) not in self._local:
                key = keys.data(self.realm, self.agent_id, service_id, name)
                stop = self._streams.listen(
                    key, lambda data, k=(service_id, name): self._on_local_data(k, data),
                    timely=False)
                self._local[(service_id, name)] = (ability, stop)

    def _on_local_data(self, local: tuple[str, str], data: bytes) -> None:
        """A local pose sample (the stream hub's thread): queued for the next batch (module
        docstring); the first of a batch wakes the worker."""
        pending = self._pending
        if not pending:
            self._wake()
        pending.append((local, data))
        self.newest[local] = data
        self.samples_seen += 1
        if len(pending) >= MAX_PENDING:
            self.drain()

    def catch_up(self) -> None:
        """Take the local samples that arrived so far into the graph: those the stream
        hub still holds, then the queue (before reading the graph)."""
        self._streams.flush_local()
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
            t, _, p, q, cov = decode_pose(data)
            refusal = stamp_refusal(t, self._now_ns())
            if refusal is not None:
                self.refused += 1
                raise DecodeError(f"{refusal} ({self.refused} refused so far)")
        except DecodeError as exc:
            key = keys.data(self.realm, self.agent_id, *local)
            self._log.warning(f"data {key}", f"dropped a malformed sample: {exc}")
            return
        ability = entry[0]
        if ability.attributes.static:
            self.on_local_sample(local[0], ability, Measurement(
                "pose6d", t, position=np.array(p), quaternion=np.array(q), covariance=cov))
            return
        source = f"{local[0]}/{ability.name}"
        with self.lock:
            self._declare(local, source, ability, self._known(local, source, ability))
            self.graph.add_decoded(*ability.edge, t, p, q, cov, source=source)

    def on_local_sample(self, service_id: str, ability: Any, measurement: Any) -> None:
        """A sample of a local pose6d ability.  A static ability (a calibration, e.g. the
        result of tracker alignment) sets its static edge, valid at all times; any other
        appends the sample to its measured edge."""
        key = (service_id, ability.name)
        source = f"{service_id}/{ability.name}"
        with self.lock:
            known = self._known(key, source, ability)
            if ability.attributes.static:
                self._set_static(key, source, ability, measurement, known)
                return
            self._declare(key, source, ability, known)
            self.graph.add_measurement(*ability.edge, measurement.t_ns, measurement.position,
                                       measurement.quaternion, measurement.covariance,
                                       source=source)

    def _known(self, key: tuple[str, str], source: str,
               ability: Any) -> tuple[Any, str] | None:
        """What the graph holds of ``key``'s edge, None once a change of kind (measured <->
        static: a different edge) removed it (lock held)."""
        known = self._sources.get(key)
        if known is not None and known[0] is not ability and (
                known[0].attributes.static != ability.attributes.static):
            self.graph.remove_source(source)
            return None
        return known

    def _declare(self, key: tuple[str, str], source: str, ability: Any,
                 known: tuple[Any, str] | None) -> None:
        """Declare the measured edge of ``ability`` when it is new or changed (lock held).
        The same Ability object comes with every sample until it changes (see
        set_local_abilities): ``is`` spares the per-sample model comparison."""
        if known is not None and (known[0] is ability or known[0] == ability):
            return
        self.graph.declare_measured(*ability.edge, source=source, **ability_attributes(ability))
        self._sources[key] = (ability, source)
        self._data_keys[source] = keys.data(self.realm, self.agent_id, *key)
        self._wake()

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
        self._wake()

    def on_ability_removed(self, service_id: str, ability: Any) -> None:
        """A local ability went away: its edge leaves the graph (and the summary)."""
        with self.lock:
            entry = self._sources.pop((service_id, ability.name), None)
            if entry is not None:
                self.graph.remove_source(entry[1])
                self._data_keys.pop(entry[1], None)
                self._static_values.pop(entry[1], None)
        self._wake()

    def close(self) -> None:
        """Stop listening to the local data keys."""
        for _, stop in self._local.values():
            stop()
        self._local.clear()
