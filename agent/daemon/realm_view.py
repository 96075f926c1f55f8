"""What one agent knows of its realm (local services, other agents' snapshots, live tokens)
and what it tells the realm of its own services: its snapshot.

:class:`RealmView` keeps the offers of every present service; :func:`build_snapshot`
builds the snapshot ``uma/R/agent/A/services`` (``agent.protocol.registration``) of this
agent's live local services with their needs' current matches, exclusions and the rates
and latencies measured here.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from agent.daemon.matching import Choice, Offer, OfferIndex, Pattern, Requirement
from agent.protocol import keys
from agent.protocol.registration import (
    PENDING_TIMEOUT_S,
    Registration,
    Snapshot,
    snapshot_message,
)
from agent.runtime.logs import RateLimitedLog
from schemas.codec import encode_descriptor
from schemas.models import AgentInfo, ServiceDescriptor

#: how far a published snapshot's revision (its agent's milliseconds since it started,
#: ``next_seq``) may run ahead of the applied one plus the milliseconds passed since it
#: was applied before it is confirmed with the agent: a forged jump holds the agent's own
#: snapshots back this long at most
REVISION_SLACK_MS = 2000
#: bytes (on the wire) of other agents' snapshots held in all: a realm of twenty hosts
#: with a hundred services each needs about 4 MiB; snapshots of invented agents (each
#: with a token, on a plain realm) must not grow an agent without bound
MAX_REMOTE_SNAPSHOT_BYTES = 16 * 1024 * 1024

_log = RateLimitedLog(logging.getLogger("uma.agent"))


@dataclass
class LocalService:
    """A service registered with this agent."""

    descriptor: ServiceDescriptor
    instance: str
    revision: int
    registered: float  # monotonic time of the (last) registration
    connected: dict[str, list[str]]
    #: the descriptor as snapshots carry it (encoded once per registration)
    encoded: bytes = field(init=False)

    def __post_init__(self) -> None:
        self.encoded = encode_descriptor(self.descriptor)


class RealmView:
    """What this agent knows: its local services, other agents' snapshots, live tokens.

    Keeps ``index`` (every offer of the realm that is present, see the module docstring)
    up to date; every mutator returns whether the offers or the local needs changed, so
    the daemon re-matches only when something did.
    """

    def __init__(self, realm: str, agent_id: str) -> None:
        self.realm = realm
        self.agent_id = agent_id
        self.index = OfferIndex(on_refused=self._candidate_refused)
        self.local: dict[str, LocalService] = {}
        self.remote: dict[str, Snapshot] = {}
        #: when each remote snapshot was applied (monotonic s)
        self._applied_at: dict[str, float] = {}
        self.live_agents: set[str] = set()
        self.live_services: set[tuple[str, str]] = set()
        self._offered: dict[tuple[str, str], dict[str, Offer]] = {}
        self._requirements: list[Requirement] | None = None

    def _candidate_refused(self, pattern: Pattern, key: str, refused: int) -> None:
        _log.warning(f"agent {self.agent_id} need pattern {pattern[1]} -> {pattern[2]}",
                     f"more than {self.index.max_candidates} {pattern[0]} abilities fit: "
                     f"{key} refused ({refused} refused so far)")

    # -- queries
    def descriptor(self, agent_id: str, service_id: str) -> ServiceDescriptor | None:
        if agent_id == self.agent_id:
            entry = self.local.get(service_id)
            return entry.descriptor if entry else None
        snap = self.remote.get(agent_id)
        return snap.services.get(service_id) if snap else None

    def present(self, agent_id: str, service_id: str) -> bool:
        """Known descriptor and live token: its abilities may be matched."""
        return ((agent_id, service_id) in self.live_services
                and self.descriptor(agent_id, service_id) is not None)

    def requirements(self) -> list[Requirement]:
        """The needs of the local services, compiled (cached until a local change)."""
        if self._requirements is None:
            self._requirements = [Requirement.of(sid, n) for sid, e in self.local.items()
                                  for n in e.descriptor.needs]
        return self._requirements

    def expired_pending(self, now: float) -> list[str]:
        """Local services registered long ago whose token never appeared."""
        return [sid for sid, e in self.local.items()
                if (self.agent_id, sid) not in self.live_services
                and now - e.registered > PENDING_TIMEOUT_S]

    # -- mutators (each returns True if offers or local needs changed)
    def register_local(self, reg: Registration, now: float) -> bool:
        sid = reg.descriptor.service_id
        old = self.local.get(sid)
        self.local[sid] = LocalService(reg.descriptor, reg.instance, reg.revision, now,
                                       reg.connected)
        if old is not None and old.descriptor == reg.descriptor:
            return False
        self._requirements = None
        self._sync(self.agent_id, sid)
        return True

    def remove_local(self, service_id: str) -> bool:
        if self.local.pop(service_id, None) is None:
            return False
        self._requirements = None
        self._sync(self.agent_id, service_id)
        return True

    def service_alive(self, agent_id: str, service_id: str) -> bool:
        self.live_services.add((agent_id, service_id))
        return self._sync(agent_id, service_id)

    def service_gone(self, agent_id: str, service_id: str) -> bool:
        self.live_services.discard((agent_id, service_id))
        changed = self._sync(agent_id, service_id)
        if agent_id == self.agent_id:
            changed |= self.remove_local(service_id)
        return changed

    def suspect(self, snap: Snapshot, now: float | None = None) -> bool:
        """Whether a published snapshot must be confirmed by asking its agent before it is
        applied: another epoch than the one its agent's token came with (an agent's epoch
        is fixed for its token's life; a forged far-future epoch would otherwise outrank
        every real update), or a revision further ahead of the applied one than the time
        passed since allows (``REVISION_SLACK_MS``)."""
        old = self.remote.get(snap.agent_id)
        if old is None:
            return False
        now = time.monotonic() if now is None else now
        passed_ms = int((now - self._applied_at.get(snap.agent_id, now)) * 1000)
        return (snap.epoch != old.epoch
                or snap.revision > old.revision + passed_ms + REVISION_SLACK_MS)

    def snapshot_refusal(self, snap: Snapshot) -> str | None:
        """Why a remote snapshot may not be held (the byte bound), or None."""
        return self.size_refusal(snap.agent_id, snap.size)

    def size_refusal(self, agent_id: str, size: int) -> str | None:
        """Why a snapshot of ``size`` bytes from ``agent_id`` may not be held, or None."""
        old = self.remote.get(agent_id)
        held = sum(s.size for s in self.remote.values()) - (old.size if old else 0)
        if held + size > MAX_REMOTE_SNAPSHOT_BYTES:
            return (f"{size} bytes would take the snapshots held past "
                    f"{MAX_REMOTE_SNAPSHOT_BYTES} bytes")
        return None

    def apply_snapshot(self, snap: Snapshot, confirmed: bool = False,
                       now: float | None = None) -> bool:
        """Apply a remote agent's snapshot unless older than the one applied;
        ``confirmed`` (the agent's own answer to a fetch) may also change the epoch."""
        if snap.agent_id == self.agent_id or snap.agent_id not in self.live_agents:
            return False
        old = self.remote.get(snap.agent_id)
        if old is not None and snap.version <= old.version and not (
                confirmed and snap.epoch != old.epoch):
            return False
        self.remote[snap.agent_id] = snap
        self._applied_at[snap.agent_id] = time.monotonic() if now is None else now
        changed = False
        for sid in set(snap.services) | set(old.services if old else ()):
            changed |= self._sync(snap.agent_id, sid)
        return changed

    def agent_alive(self, agent_id: str) -> None:
        self.live_agents.add(agent_id)

    def agent_gone(self, agent_id: str) -> bool:
        """Forget an agent that left, and its services, except those whose own token is
        still live: a service attached to a router publishes without its agent, and a
        need matched to it keeps a stream that still flows.  They go when their
        token does; the kept snapshot is marked older than any, so the agent's next one
        applies when it comes back."""
        self.live_agents.discard(agent_id)
        self._applied_at.pop(agent_id, None)
        old = self.remote.pop(agent_id, None)
        if old is None:
            return False
        kept = {sid: d for sid, d in old.services.items()
                if (agent_id, sid) in self.live_services}
        if kept:
            self.remote[agent_id] = replace(old, services=kept, revision=-1)
        changed = False
        for sid in old.services:
            changed |= self._sync(agent_id, sid)
        return changed

    def _sync(self, agent_id: str, service_id: str) -> bool:
        """Make the index hold exactly the offers of this service if it is present."""
        k = (agent_id, service_id)
        want: dict[str, Offer] = {}
        desc = self.descriptor(agent_id, service_id) if self.present(*k) else None
        if desc is not None:
            for a in desc.abilities:
                key = keys.data(self.realm, agent_id, service_id, a.name)
                want[key] = Offer.of(key, agent_id, service_id, a)
        have = self._offered.get(k, {})
        if have.keys() == want.keys() and all(
                have[x].ability == want[x].ability for x in want):
            return False
        for key in have.keys() - want.keys():
            self.index.remove(key)
        for offer in want.values():
            self.index.add(offer)
        if want:
            self._offered[k] = want
        else:
            self._offered.pop(k, None)
        return True


# --------------------------------------------------------------------------- snapshots


@dataclass(frozen=True)
class NeedStatus:
    """What a snapshot says of one local need."""

    chosen: tuple[Choice, ...] = ()
    satisfied: bool = False
    excluded: Mapping[str, str] = field(default_factory=dict)  # key -> why


@dataclass(frozen=True)
class Identity:
    """Who this agent is, as its snapshot says."""

    agent_id: str
    realm: str
    epoch: int
    endpoints: list[str]


def build_snapshot(view: RealmView, me: Identity, revision: int,
                   need_status: Callable[[str, str], NeedStatus],
                   measured: Mapping[str, dict[str, float]]) -> bytes:
    """The snapshot of the live local services: descriptors, needs' matches with their
    measured values, satisfaction and exclusions."""
    present = [sid for sid in sorted(view.local) if view.present(me.agent_id, sid)]
    services = []
    for sid in present:
        entry = view.local[sid]
        status = {need.name: need_status(sid, need.name) for need in entry.descriptor.needs}
        services.append({
            "descriptor": entry.encoded, "instance": entry.instance,
            "matches": {name: [choice_status(c, measured.get(c.offer.key))
                               for c in st.chosen] for name, st in status.items()},
            "satisfied": {name: st.satisfied for name, st in status.items()},
            "excluded": {name: dict(st.excluded) for name, st in status.items()}})
    info = AgentInfo(agent_id=me.agent_id, realm=me.realm, version=_version(),
                     started_ns=me.epoch, endpoints=me.endpoints, services=present)
    return snapshot_message(info.model_dump(mode="json"), me.epoch, revision, services)


def choice_status(c: Choice, measured: dict[str, float] | None) -> dict[str, Any]:
    """A need's chosen ability as a snapshot shows it."""
    o: Offer = c.offer
    return {"key": o.key, "agent_id": o.agent_id, "service_id": o.service_id,
            "ability": o.ability.name, "score": c.score if math.isfinite(c.score) else None,
            "local": c.local, "measured": dict(measured or {})}


def _version() -> str:
    try:
        return version("uma-tracking")
    except PackageNotFoundError:
        return "unknown"
