"""The realm as the view sees it, kept current by one background thread.

Every ``POLL_S`` (and at once when an agent publishes a new snapshot of its services, or a
service's liveliness token goes: that service leaves the page before its agent's next
snapshot says so, since a killed service's token goes within milliseconds) it collects the
realm as ``uma services`` does (:func:`agent.collect_realm`: every
agent's snapshot, with its services, needs, abilities, matches and the rates and latencies
their consumers' agents measured), turns the difference to the previous look into event
lines (:mod:`agent.view.events`), measures every live agent's clock offset and delay every
``CLOCK_S`` (one probe each, :meth:`agent.sdk.query.Queries.probe`), and, when an agent's
SRG summary changes, asks it for the details of its static edges (one segment request with
details per frame of its summary, from the first frame of each connected component):
the summaries say which frames an agent has, not where they are.

Each look is published as one immutable :class:`Look`; the draw loop reads the latest.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import zenoh

from agent import Client, collect_realm
from agent import protocol as proto
from agent.protocol import keys
from agent.view import events
from agent.view.space import EdgeView
from schemas.models import EDGE_TYPES

log = logging.getLogger("uma.view")

#: seconds between looks at the realm when nothing is published
POLL_S = 0.5
#: seconds between clock probes of each agent
CLOCK_S = 2.0
#: lines kept in the event log
EVENT_LINES = 200


@dataclass(frozen=True)
class Look:
    """One look at the realm: the collected realm (``uma services --json``'s object), the
    live agents with their clock offset and delay (ms, None until measured), the edges the
    view knows (by name) and the event log, newest last."""

    realm: dict[str, Any]
    clocks: dict[str, tuple[float | None, float | None]] = field(default_factory=dict)
    edges: dict[str, EdgeView] = field(default_factory=dict)
    events: tuple[tuple[float, str], ...] = ()
    seq: int = 0


class Watch:
    """Looks at the realm on its own thread (module docstring)."""

    def __init__(self, client: Client, timeout: float = 1.0) -> None:
        self.client = client
        self.realm = client.realm
        self.timeout = timeout
        self.look = Look({"realm": client.realm, "agents": [], "problems": []})
        self._digest = events.Digest()
        self._events: deque[tuple[float, str]] = deque(maxlen=EVENT_LINES)
        #: per agent: the summary version its static edges were fetched for, and the edges
        self._statics: dict[str, tuple[tuple[str, int] | tuple[()], dict[str, EdgeView]]] = {}
        self._clock_due = 0.0
        self._wake = threading.Event()
        self._stop = threading.Event()
        #: services whose token went (and did not come back) while their agent still listed
        #: them: dropped from the page at once, before the agent's snapshot says so
        self._dead: set[tuple[str, str]] = set()
        self._dead_lock = threading.Lock()
        self._subs = [
            client.session.declare_subscriber(keys.all_agent_services(self.realm),
                                              lambda _s: self._wake.set()),
            client.session.liveliness().declare_subscriber(keys.service_tokens(self.realm),
                                                           self._on_service_token)]
        self._thread = threading.Thread(target=self._run, name="uma-view-watch", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(self.timeout * 4 + 2.0)
        for sub in self._subs:
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()

    def _on_service_token(self, sample: zenoh.Sample) -> None:
        """A service's token went: show it gone now, before its agent's next snapshot."""
        found = keys.parse_service_token(str(sample.key_expr), self.realm)
        if found is None:
            return
        with self._dead_lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._dead.add(found)
            else:
                self._dead.discard(found)
        self._wake.set()

    def _run(self) -> None:
        first = True
        while not self._stop.is_set():
            self._wake.clear()
            try:
                self._drop_gone()
                self._look(first)
                first = False
            except Exception as exc:  # a bad answer must not end the view
                log.warning("looking at realm %s failed: %s", self.realm, exc)
            self._wake.wait(POLL_S)

    def _look(self, first: bool) -> None:
        realm = self._carry_over(collect_realm(self.client.session, self.realm, self.timeout,
                                         settle_s=0.0))
        self._forget_dropped(realm)
        realm = self._without_dead(realm)
        self._record(realm, first)
        alive = [a["agent_id"] for a in realm["agents"]]
        if time.monotonic() >= self._clock_due:
            self._clock_due = time.monotonic() + CLOCK_S
            for agent in alive:
                self.client.queries.probe(agent)
        self._publish(realm, alive)
        if self._refresh_statics(alive):
            self._publish(realm, alive)

    def _drop_gone(self) -> None:
        """Publish the last look without the services whose token went, if it showed any
        (the next look says whether their agent dropped them too)."""
        realm = self._without_dead(self.look.realm)
        if realm is not self.look.realm:
            self._record(realm)
            self._publish(realm, [a["agent_id"] for a in realm["agents"]])

    def _without_dead(self, realm: dict[str, Any]) -> dict[str, Any]:
        """``realm`` without the services whose token went (itself if it has none)."""
        with self._dead_lock:
            dead = set(self._dead)
        if not any((a["agent_id"], s["service_id"]) in dead
                   for a in realm["agents"] for s in a["services"]):
            return realm
        return {**realm, "agents": [
            {**a, "services": [s for s in a["services"]
                               if (a["agent_id"], s["service_id"]) not in dead]}
            for a in realm["agents"]]}

    def _forget_dropped(self, realm: dict[str, Any]) -> None:
        """Forget the dead services that their agents no longer list."""
        listed = {(a["agent_id"], s["service_id"]) for a in realm["agents"]
                  for s in a["services"]}
        with self._dead_lock:
            self._dead &= listed

    def _record(self, realm: dict[str, Any], first: bool = False) -> None:
        """The event lines from the previous look to ``realm``."""
        new = events.digest(realm)
        lines = events.changes(self._digest, new)
        if first and not realm["agents"]:
            lines = [f"no agents in realm {self.realm} yet"]
        now = time.time()
        self._events.extend((now, line) for line in lines)
        self._digest = new

    def _carry_over(self, realm: dict[str, Any]) -> dict[str, Any]:
        """An agent whose token is still there but whose snapshot came too late (a loaded
        host) keeps its last one: it has not left, and the page must not say so."""
        answered = {a["agent_id"] for a in realm["agents"]}
        kept = [a for a in self.look.realm["agents"]
                if a["agent_id"] not in answered and self.client.tracker.is_alive(a["agent_id"])]
        if kept:
            realm["agents"] = sorted([*realm["agents"], *kept], key=lambda a: a["agent_id"])
        return realm

    def _publish(self, realm: dict[str, Any], alive: list[str]) -> None:
        edges = measured_edges(realm)
        for agent in alive:
            edges.update(self._statics.get(agent, ((), {}))[1])
        self.look = Look(realm, {a: self._clock(a) for a in alive}, edges,
                         tuple(self._events), self.look.seq + 1)

    def _clock(self, agent: str) -> tuple[float | None, float | None]:
        best = self.client.clock.best(agent)
        return (None, None) if best is None else (best.offset_ns / 1e6, best.delay_ns / 1e6)

    def _refresh_statics(self, alive: list[str]) -> bool:
        """Fetch the static edges of every agent whose summary changed; True if any did."""
        changed = False
        for agent in alive:
            version = self.client.tracker.summary_version(agent)
            if version is None:
                self.client.tracker.refresh()
                version = self.client.tracker.summary_version(agent)
            known = self._statics.get(agent)
            if version is None or (known is not None and known[0] == version):
                continue
            summary = self.client.tracker.view().summaries.get(agent)
            if summary is not None:
                self._statics[agent] = (version, self._fetch_statics(agent, summary))
                changed = True
        for agent in set(self._statics) - set(alive):
            del self._statics[agent]
        return changed

    def _fetch_statics(self, agent: str, summary: proto.Summary) -> dict[str, EdgeView]:
        """One segment request with details from the first frame of each component to every
        other frame, all sent at once (one round trip, not one per frame)."""
        found: dict[str, EdgeView] = {}
        lock, pending = threading.Lock(), []
        done = threading.Semaphore(0)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            try:
                answer = proto.decode_reply(reply.ok.payload.to_bytes())
            except ValueError as exc:
                log.warning("agent %s sent an unreadable answer: %s", agent, exc)
                return
            if answer.get("ok"):
                edges = _statics_of(agent, answer.get("edges") or [])
                with lock:
                    found.update(edges)

        key = keys.agent_query(self.realm, agent)
        for component in summary.components:
            frames = sorted(component)
            for target in frames[1:]:
                request = proto.segments_request({agent: proto.SegmentRequest(
                    frames[0], target, "hops", None, details=True)})
                self.client.session.get(key, zenoh.handlers.Callback(on_reply, done.release),
                                        payload=request, timeout=self.timeout)
                pending.append(target)
        deadline = time.monotonic() + self.timeout + 1.0
        for _ in pending:
            if not done.acquire(timeout=max(0.0, deadline - time.monotonic())):
                break
        with lock:
            return dict(found)


def _statics_of(agent: str, details: list[Any]) -> dict[str, EdgeView]:
    out = {}
    for d in details:
        try:
            e = proto.edge_from_wire(d)
        except ValueError as exc:
            log.warning("agent %s sent unreadable edge details: %s", agent, exc)
            continue
        if e.static:
            view = EdgeView(e.parent, e.child, agent, True, e.source, None, "pose6d",
                            {**e.attributes, "position": e.position,
                             "quaternion": e.quaternion})
            out[view.name] = view
    return out


def measured_edges(realm: dict[str, Any]) -> dict[str, EdgeView]:
    """Every edge ability of the realm's live services (by :attr:`EdgeView.name`)."""
    out = {}
    for a in realm["agents"]:
        for s in a["services"]:
            for ab in s["abilities"]:
                if ab["type"] not in EDGE_TYPES or "edge" not in ab:
                    continue
                attrs = ab.get("attributes", {})
                key = keys.data(realm["realm"], a["agent_id"], s["service_id"], ab["name"])
                e = EdgeView(ab["edge"][0], ab["edge"][1], a["agent_id"],
                             bool(attrs.get("static")), f"{s['service_id']}/{ab['name']}",
                             key, ab["type"], attrs)
                out[e.name] = e
    return out
