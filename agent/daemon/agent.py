"""The agent daemon: one per host (DWARF's service manager, Ubitrack's UMA).

``Agent`` is the wiring of its parts, in one Zenoh peer session:

- **registrar** (``agent.daemon.registrar``; the protocol: ``agent.protocol.registration``):
  accepts its local services' registrations on ``uma/R/agent/A/register``, refuses
  duplicates, watches every service token and checks a departure before tearing anything
  down, re-adopts a local service whose token came back;
- **realm view and snapshot** (``agent.daemon.realm_view``): the agent advertises its live
  local services through its snapshot ``uma/R/agent/A/services`` (queryable + publication
  on change), and learns every other agent's services through their tokens and snapshots
  (here: ``_on_agent_token``, ``_on_snapshot``);
- **matching** (``agent.daemon.matching``): re-matches all local needs whenever the realm
  changes and tells each service, on ``uma/R/ctl/A/S``, the complete set of data keys each
  need must subscribe to.  Data then flows service to service;
- **measuring** (``agent.daemon.monitor``): measures the streams the local needs are
  connected to and excludes, for a need, one that fails its predicate as measured (the
  need is re-matched to the next best, and moves back once the stream recovers);
- **SRG** (``agent.daemon.srg_node``): after opening its session the agent creates
  ``SrgNode(session, realm, agent_id, static_edges, streams, client)`` and tells it which
  abilities each local service has (``set_local_abilities``); the node subscribes to the
  local pose streams itself.  At shutdown ``node.close()`` before the session closes.  If
  ``agent.daemon.srg_node`` cannot be imported the agent runs without an SRG and says so;
- **one subscription per data key** (``agent.daemon.streams``): the monitor and the SRG
  node listen to the same local streams through one ``StreamHub``;
- **hosted services**: ``--service NAME`` runs the ``uma.services`` plug-in NAME in a thread
  with the plug-in's default options and ``realm``/``agent``/``connect`` pointing at this
  agent's own listening endpoints; stopped (their ``stop`` event set) at shutdown.

Threads: Zenoh callbacks only enqueue; one worker (``agent.runtime.worker``) owns all
state (no locks), does the matching and all Zenoh calls.  The SRG node's and the stream
hub's callbacks run in Zenoh's threads (see their modules).

Robustness: every ``RESEND_S`` (5 s) the agent re-sends each need's set (idempotent) and
asks for all live tokens: agent tokens its liveliness subscription missed count as PUTs,
and the registrar reconciles the service tokens.  After a restart it holds back changes
to the connections its services report for ``STARTUP_HOLD_S`` (2 s), while its view of
the realm fills up, so restarting an agent never interrupts data; what vanished meanwhile
is disconnected after that.

Timing defaults (``[matching]`` / ``[zenoh]`` in the TOML config): ``grace_s`` 0.5,
``rate_window_s`` 0.5, lease 1000 ms (``agent.runtime.session``).  A SIGKILLed service is
noticed in ~2 ms (its sockets close), a frozen one after the lease; a rate drop after about
``rate_window_s`` (for the window to reflect it) + ``grace_s``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from agent.daemon.matching import MatchResult, Offer, Requirement, rematch
from agent.daemon.monitor import NeedId, StreamMonitor
from agent.daemon.realm_view import Identity, NeedStatus, RealmView, build_snapshot
from agent.daemon.registrar import DEPARTURE_CHECK_S, Registrar, token_churn
from agent.daemon.settings import AgentSettings
from agent.daemon.streams import StreamHub
from agent.errors import UmaError
from agent.protocol import keys
from agent.protocol.registration import (
    RESEND_S,
    Match,
    Registration,
    Snapshot,
    control_message,
    next_seq,
    parse_snapshot,
)
from agent.runtime import plugins
from agent.runtime.callbacks import guarded
from agent.runtime.limits import ByteBudget, Coalescer, token_limits
from agent.runtime.logs import RateLimitedLog
from agent.runtime.payload import payload_bytes
from agent.runtime.session import ask_all, listening_endpoints, open_session, query
from agent.runtime.worker import Worker
from schemas.codec import MAX_MESSAGE_BYTES, DecodeError

log = logging.getLogger("uma.agent")

#: while the agent's view of the realm may be incomplete (just started), it does not tear
#: down connections its services report (an agent restart must not interrupt data)
STARTUP_HOLD_S = 2.0
#: the worker's tick while no stream is measured (``tick_s`` otherwise): what is left to a
#: tick then (re-sends, registrations that never got a token, the start-up hold) is
#: counted in seconds, and every tick is a wake-up of an otherwise idle agent
IDLE_TICK_S = 0.25
#: how long start() waits for a first link to its connect endpoints
LINK_WAIT_S = 1.0
#: seconds to wait for a snapshot query's replies
FETCH_TIMEOUT_S = 2.0
#: bytes of other agents' snapshots (published, or answers to a fetch) held at once before
#: the worker handles them: a flood of invented agents' snapshots, each up to a message's
#: limit, waits for room instead of growing the agent
MAX_SNAPSHOT_BYTES_IN_FLIGHT = 8 * MAX_MESSAGE_BYTES


@dataclass
class NeedState:
    """The matching state of one local need."""

    req: Requirement
    result: MatchResult | None = None
    sent: tuple[Match, ...] | None = None     # the set last sent to the service
    sent_standby: tuple[Match, ...] = ()      # and its standby
    sent_at: float = 0.0
    seq: int = 0

    @property
    def current(self) -> set[str]:
        return {m.key for m in self.sent or ()}


class Agent:
    """The per-host daemon (see the module docstring): ``start()``, then ``close()``."""

    def __init__(self, settings: AgentSettings, client: Callable[..., Any] | None = None,
                 ) -> None:
        """``client``: the SDK's :class:`agent.Client` (or one called like it), with which
        the agent keeps the segments of other agents it is asked for often
        (:mod:`agent.daemon.relay`); the daemon does not import the SDK itself.  None: it
        keeps none and forwards every such part."""
        self.s = settings.check()
        self._client_class = client
        self.realm, self.agent_id = self.s.realm, self.s.agent_id
        self.epoch = time.time_ns()
        self.view = RealmView(self.realm, self.agent_id)
        self.needs: dict[NeedId, NeedState] = {}
        self.endpoints: list[str] = []
        self.revision = 0
        self.session: zenoh.Session | None = None
        self.srg: Any = None
        self._log = RateLimitedLog(log)
        self._worker = Worker("uma-agent", f"agent {self.agent_id}", log, self._tick,
                              self.s.tick_s, settle=(self._rematch_if_dirty,
                                                     self._publish_if_dirty))
        self.registrar = Registrar(self.view, self.epoch, self._worker.put, self, self._log)
        #: agent token events, coalesced per token and rated per agent (token churn)
        self._agent_tokens = Coalescer(self._worker.put, self._on_agent_token, token_limits(),
                                       lambda sender, why: token_churn(
                                           self._log, sender, why, self._agent_tokens.refused))
        self.streams = StreamHub(local=keys.all_data(self.realm, self.agent_id))
        self.monitor = StreamMonitor(self.streams, self.s.grace_s, self.s.rate_window_s,
                                     self._log)
        self._decls: list[Any] = []
        self._token: Any = None
        #: agents whose token went, being asked whether they still answer (check number)
        self._agent_checks: dict[str, int] = {}
        self._checks = 0
        #: agents whose snapshot is being fetched, and those published again meanwhile
        self._fetching: set[str] = set()
        self._refetch: set[str] = set()
        #: agents to fetch once the snapshots in flight leave room (oldest first)
        self._fetch_waiting: dict[str, None] = {}
        self._in_flight = ByteBudget(MAX_SNAPSHOT_BYTES_IN_FLIGHT)
        self.snapshots_suspect = 0
        #: snapshots refused by the byte bound (``RealmView.snapshot_refusal``) or because
        #: another process answered for their agent with a different one
        self.snapshots_refused = 0
        self._dirty = False           # re-match needed
        self._snapshot_dirty = False  # publish a new snapshot
        self._hosted: list[tuple[str, threading.Thread, threading.Event]] = []
        self._started_mono = time.monotonic()
        self._last_resend = time.monotonic()
        self._hold_over = False

    # -- life cycle
    def start(self) -> None:
        """Open the session, join the realm, start the worker, the SRG and hosted services."""
        s = self.s
        hosted = [(name, plugins.load(plugins.SERVICE_GROUP, name)) for name in s.services]
        self.session = open_session(s.mode, s.listen, s.connect, self.realm,
                                    lease_ms=s.lease_ms, exposed_as="uma agent",
                                    insecure=s.insecure)
        self.streams.open(self.session)
        try:
            self._join()
            if s.mode == "peer" or s.listen:  # a client without listeners has none
                self.endpoints = listening_endpoints(self.session)
            self._start_srg()
            # last: the token tells clients and agents this one is here, so its query
            # handlers must already be up (a query between the two would go unanswered)
            self._token = self.session.liveliness().declare_token(
                keys.agent_token(self.realm, self.agent_id))
            self._worker.start()
            for name, plugin in hosted:
                self._host(name, plugin)
        except BaseException:
            self.close()
            raise
        log.info("agent %s of realm %s up (epoch %d), listening on %s", self.agent_id,
                 self.realm, self.epoch, ", ".join(self.endpoints) or "nothing")

    def _join(self) -> None:
        """Check that the id is free; declare the queryables and subscriptions."""
        sess, r, a = self.session, self.realm, self.agent_id
        assert sess is not None
        if self.s.connect:  # give the links a moment, so the check below sees the realm
            deadline = time.monotonic() + LINK_WAIT_S
            while (time.monotonic() < deadline and not any(sess.info.peers_zid())
                   and not any(sess.info.routers_zid())):
                time.sleep(0.01)
        for reply in query(sess, keys.agent_token(r, a), 0.5, liveliness=True):
            if reply.ok is not None:
                raise UmaError(f"an agent with id {a!r} is already running in realm {r!r}; "
                               "give this one another --id")
        self.registrar.declare(sess)
        put = self._worker.put
        self._decls += [
            sess.declare_queryable(keys.agent_services(r, a),
                                   lambda q: put(self._on_services_query, q)),
            sess.declare_subscriber(keys.all_agent_services(r), guarded(
                self._offer_snapshot, keys.all_agent_services(r), self._log)),
            sess.liveliness().declare_subscriber(
                keys.all_agent_tokens(r), lambda smp: self._agent_tokens.offer(
                    str(smp.key_expr), keys.parse_agent_token(str(smp.key_expr), r) or "?",
                    smp), history=True),
        ]

    def _start_srg(self) -> None:
        try:
            from agent.daemon.srg_node import SrgNode
        except ImportError as exc:
            log.warning("agent %s runs without a spatial relationship graph: "
                        "agent.daemon.srg_node is not available (%s)", self.agent_id, exc)
            return
        self.srg = SrgNode(self.session, self.realm, self.agent_id, self.s.static_edges,
                           self.streams, self._client_class)

    def _host(self, name: str, plugin: plugins.ServicePlugin) -> None:
        """Run a service plug-in in a thread, registered with this agent."""
        parser = argparse.ArgumentParser(prog=f"uma agent --service {name}")
        plugins.add_service_arguments(parser, plugin)
        argv = ["--realm", self.realm, "--agent", self.agent_id]
        # a peer agent: connect to it; a client agent has no listener: use its router
        for ep in self.endpoints or self.s.connect:
            argv += ["--connect", ep]
        args = parser.parse_args(argv)
        stop = threading.Event()
        service_run = plugins.runner(plugin.run)

        def run() -> None:
            try:
                code = service_run(args, stop)
                if code and not stop.is_set():
                    log.error("hosted service %s exited with code %s", name, code)
            except Exception:
                log.exception("hosted service %s failed", name)

        t = threading.Thread(target=run, name=f"uma-service-{name}", daemon=True)
        t.start()
        self._hosted.append((name, t, stop))

    def alive(self) -> bool:
        """Whether the worker runs (it only stops on close, or on a bug)."""
        return self._worker.alive()

    def stalled(self, limit_s: float) -> str | None:
        """What the worker has been blocked in for more than ``limit_s`` s, or None.  Its
        tick asks Zenoh for the live tokens every ``RESEND_S``, so a session whose routing
        tables deadlocked (eclipse-zenoh/zenoh#2581, under peer churn: many agents joining
        at once on a loaded host) blocks it within seconds, while the process looks alive
        and its peers no longer see it."""
        stuck = self._worker.stuck(limit_s)
        return None if stuck is None else f"its worker is blocked in {stuck[0]} for " \
            f"{stuck[1]:.0f} s"

    def close(self, timeout: float = 1.5) -> None:
        """Stop hosted services, the SRG, the worker; undeclare everything; close the session.

        Bounded by ``timeout`` seconds overall (hosted services that do not stop in time are
        left to die with the process: their threads are daemons).
        """
        deadline = time.monotonic() + timeout
        for _, _, stop in self._hosted:
            stop.set()
        for name, t, _ in self._hosted:
            t.join(max(0.0, deadline - time.monotonic() - 0.5))
            if t.is_alive():
                log.warning("hosted service %s did not stop in time", name)
        self._worker.stop(max(0.1, deadline - time.monotonic() - 0.3))
        if self.srg is not None:
            try:
                self.srg.close()
            except Exception:
                log.exception("closing the SRG node failed")
            self.srg = None
        self.monitor.close()
        self.streams.close()
        self.registrar.close()
        for obj in [self._token, *self._decls]:
            if obj is not None:
                with contextlib.suppress(Exception):
                    obj.undeclare()
        self._token, self._decls = None, []
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
            self.session = None
        # a worker still inside a blocking put returns once the session is closed; let it
        # leave Zenoh before the interpreter finalises (else the process may abort)
        self._worker.join(0.5)

    # -- what the registrar tells (agent.daemon.registrar.RegistrarHost)
    def service_admitted(self, reg: Registration, new_instance: bool) -> None:
        """A local service registered: tell the SRG its abilities, (re)make its needs."""
        sid = reg.descriptor.service_id
        if new_instance:
            self._drop_needs(sid)
        if self.srg is not None:
            self.srg.set_local_abilities(sid, reg.descriptor.abilities)
        for need in reg.descriptor.needs:
            state = self.needs.get((sid, need.name))
            if state is None or state.req.need != need:
                self._set_need((sid, need.name), NeedState(self._requirement(sid, need.name)))
            if new_instance:
                # what the service is subscribed to right now (agent restart): keep it
                self.needs[(sid, need.name)].sent = tuple(
                    _match(offer) if offer else Match.unknown(k, need.type, self.realm)
                    for k in reg.connected.get(need.name, ())
                    for offer in [self.view.index.by_key.get(k)])
        names = {n.name for n in reg.descriptor.needs}
        for k in [k for k in self.needs if k[0] == sid and k[1] not in names]:
            self._set_need(k, None)

    def service_left(self, service_id: str) -> None:
        if self.srg is not None:
            self.srg.set_local_abilities(service_id, [])
        self._drop_needs(service_id)

    def realm_changed(self) -> None:
        self._dirty = True

    def snapshot_changed(self) -> None:
        self._snapshot_dirty = True

    def _requirement(self, sid: str, need_name: str) -> Requirement:
        for req in self.view.requirements():
            if req.service_id == sid and req.name == need_name:
                return req
        raise KeyError((sid, need_name))

    def _set_need(self, need: NeedId, state: NeedState | None) -> None:
        """A need is new, changed or gone: the monitor's judgement of it starts afresh."""
        self.monitor.forget(need)
        if state is None:
            self.needs.pop(need, None)
        else:
            self.needs[need] = state
        self._dirty = True

    def _drop_needs(self, sid: str) -> None:
        for k in [k for k in self.needs if k[0] == sid]:
            self._set_need(k, None)
        self._dirty = True

    # -- other agents
    def _on_agent_token(self, smp: zenoh.Sample) -> None:
        agent_id = keys.parse_agent_token(str(smp.key_expr), self.realm)
        if agent_id is None:
            self._log.warning(f"liveliness {smp.key_expr}", "not an agent token key")
            return
        if agent_id == self.agent_id:
            return
        if smp.kind == zenoh.SampleKind.PUT:
            self._agent_checks.pop(agent_id, None)  # back: a pending check is moot
            self.view.agent_alive(agent_id)
            self._fetch_snapshot(agent_id)
        else:
            self._check_agent_departure(agent_id)

    def _check_agent_departure(self, agent_id: str) -> None:
        """An agent token's DELETE: ask the agent for its snapshot before dropping its
        services.  A token is not the only sign of life: on a CPU-starved host a lease can
        lapse while the agent's links and its services' data are up, and tearing down every
        match of its services then would cut streams that still flow.  A killed agent has
        no queryable left, so the answer is "nobody" at once and failover stays fast."""
        if agent_id not in self.view.live_agents or agent_id in self._agent_checks:
            return
        assert self.session is not None
        self._checks += 1
        check = self._agent_checks[agent_id] = self._checks
        ask_all(self.session, keys.agent_services(self.realm, agent_id), DEPARTURE_CHECK_S,
                lambda answers: self._worker.put(self._on_agent_checked, agent_id, check,
                                                 answers))

    def _on_agent_checked(self, agent_id: str, check: int, answers: list[bytes]) -> None:
        if self._agent_checks.get(agent_id) != check:
            return  # its token came back meanwhile, or a newer check runs
        del self._agent_checks[agent_id]
        known = self.view.remote.get(agent_id)
        for data in answers:
            try:
                snap = parse_snapshot(data, agent_id)
            except DecodeError:
                continue
            if known is None or snap.epoch == known.epoch:
                self._log.warning(f"agent {agent_id}",
                                  "its liveliness token went but it still answers; kept")
                return
        if self.view.agent_gone(agent_id):
            log.info("agent %s left realm %s", agent_id, self.realm)
            self._dirty = True

    def _fetch_snapshot(self, agent_id: str) -> None:
        """Ask the agent for its snapshot (it appeared, or it published one); its answers
        are applied as confirmed unless they disagree.  One fetch per agent at a time: a
        snapshot published during one is fetched again once it ends.  Without room for
        another answer in flight, the fetch waits (``_start_waiting_fetch``)."""
        if agent_id in self._fetching:
            self._refetch.add(agent_id)
            return
        if not self._in_flight.room(MAX_MESSAGE_BYTES):
            self._fetch_waiting[agent_id] = None
            return
        assert self.session is not None
        self._fetching.add(agent_id)
        key = keys.agent_services(self.realm, agent_id)
        refused: list[int] = []

        def admit(size: int) -> bool:
            if self._in_flight.take(size):
                return True
            refused.append(size)
            return False

        def done(answers: list[bytes]) -> None:
            if not self._worker.put(self._on_fetched, key, answers, bool(refused)):
                self._in_flight.give(sum(map(len, answers)))
        ask_all(self.session, key, FETCH_TIMEOUT_S, done, every_reply=True, admit=admit)

    def _start_waiting_fetch(self) -> None:
        """Fetch the oldest waiting agent still here, if the answers in flight leave room."""
        while self._fetch_waiting and self._in_flight.room(MAX_MESSAGE_BYTES):
            agent_id = next(iter(self._fetch_waiting))
            del self._fetch_waiting[agent_id]
            if agent_id in self.view.live_agents:
                self._fetch_snapshot(agent_id)
                return

    def _on_fetched(self, key: str, answers: list[bytes], incomplete: bool = False) -> None:
        """``incomplete``: an answer found no room in flight; the agent is asked again
        once there is."""
        try:
            self._apply_fetched(key, answers, incomplete)
        finally:
            self._in_flight.give(sum(map(len, answers)))
            self._start_waiting_fetch()

    def _apply_fetched(self, key: str, answers: list[bytes], incomplete: bool) -> None:
        agent_id = keys.parse_agent_services(key, self.realm)
        self._fetching.discard(agent_id)
        if incomplete and agent_id is not None:
            self._refetch.discard(agent_id)
            self._fetch_waiting[agent_id] = None
            return
        if agent_id in self._refetch:
            self._refetch.discard(agent_id)
            self._fetch_snapshot(agent_id)
        snaps = {data: s for data in set(answers)
                 if (s := self._parse_held(key, agent_id, data)) is not None}
        if len({s.epoch for s in snaps.values()}) > 1:
            self._log.warning(f"agent {agent_id}", "answers with snapshots of different "
                              "epochs: two processes claim its id; kept what was applied")
            return
        if len(snaps) > 1:
            self.snapshots_refused += 1
            self._log.warning(f"agent {agent_id}", f"{len(snaps)} different answers to one "
                              "ask for its snapshot: another process answers for it; kept "
                              f"what was applied ({self.snapshots_refused} refused so far)")
            return
        for snap in snaps.values():
            self._apply_snapshot(key, snap, confirmed=True)

    def _resync_agent_tokens(self) -> None:
        """Anti-entropy: ask for the live agent tokens (a liveliness subscription declared
        before its links were up may not get the tokens that existed then), and check again
        every agent kept without a token (it may have gone since it last answered)."""
        assert self.session is not None
        seen: set[str] = set()

        def on_agent(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                seen.add(str(reply.ok.key_expr))
                self._worker.put(self._on_resync_agent_token, reply.ok)
        self.session.liveliness().get(
            keys.all_agent_tokens(self.realm), zenoh.handlers.Callback(
                on_agent, lambda: self._worker.put(self._recheck_tokenless, seen)),
            timeout=1.0)

    def _recheck_tokenless(self, token_keys: set[str]) -> None:
        for agent_id in self.view.live_agents - {self.agent_id}:
            if keys.agent_token(self.realm, agent_id) not in token_keys:
                self._check_agent_departure(agent_id)

    def _on_resync_agent_token(self, smp: zenoh.Sample) -> None:
        agent_id = keys.parse_agent_token(str(smp.key_expr), self.realm)
        if agent_id is not None and agent_id != self.agent_id and (
                agent_id not in self.view.live_agents):
            self._on_agent_token(smp)

    def _offer_snapshot(self, smp: zenoh.Sample) -> None:
        """A published snapshot, in Zenoh's thread: handed to the worker with its bytes
        while the snapshots in flight leave room, else as a bare notice that its agent
        changed (``_on_snapshot_notice``)."""
        key, size = str(smp.key_expr), len(smp.payload)
        if not self._in_flight.take(size):
            self._worker.put_peer(self._on_snapshot_notice, key)
            return
        try:
            data = payload_bytes(smp.payload)
        except DecodeError:
            self._in_flight.give(size)
            raise
        if not self._worker.put_peer(self._on_snapshot, key, data):
            self._in_flight.give(size)

    def _on_snapshot_notice(self, key: str) -> None:
        """A snapshot published while there was no room for its bytes: its agent is asked
        as for any other (only the early look at its revision is missed)."""
        agent_id = keys.parse_agent_services(key, self.realm)
        if agent_id is not None and agent_id != self.agent_id and (
                agent_id in self.view.live_agents):
            self._fetch_snapshot(agent_id)

    def _on_snapshot(self, key: str, data: bytes) -> None:
        try:
            self._handle_snapshot(key, data)
        finally:
            self._in_flight.give(len(data))
            self._start_waiting_fetch()

    def _handle_snapshot(self, key: str, data: bytes) -> None:
        """A published snapshot only says that its agent changed: on a plain realm anyone
        can put one under the agent's epoch, which every snapshot shows, so the agent is
        asked (``_fetch_snapshot``) and its answer applied.  A version that its agent's run
        cannot have reached (``RealmView.suspect``) is counted and said."""
        snap = self._parse_snapshot(key, data)
        if snap is None:
            return
        if snap.agent_id == self.agent_id:
            self._apply_snapshot(key, snap)
            return
        if snap.agent_id not in self.view.live_agents:
            return  # fetched when its token comes
        if self.view.suspect(snap):
            self.snapshots_suspect += 1
            self._log.warning(f"snapshot {key}", f"epoch {snap.epoch} revision "
                              f"{snap.revision} is not the agent's current run; asking it "
                              f"({self.snapshots_suspect} so far)")
        self._fetch_snapshot(snap.agent_id)

    def _parse_held(self, key: str, agent_id: str | None, data: bytes) -> Snapshot | None:
        """``_parse_snapshot`` for an answer that could be held: one that the byte bound on
        held snapshots refuses anyway is refused before it is decoded."""
        refusal = None if agent_id is None else self.view.size_refusal(agent_id, len(data))
        if refusal is not None:
            self.snapshots_refused += 1
            self._log.warning(f"snapshot {key}", f"refused: {refusal} "
                              f"({self.snapshots_refused} so far)")
            return None
        return self._parse_snapshot(key, data)

    def _parse_snapshot(self, key: str, data: bytes) -> Snapshot | None:
        agent_id = keys.parse_agent_services(key, self.realm)
        if agent_id is None:
            self._log.warning(key, "not an agent services key")
            return None
        try:
            return parse_snapshot(data, agent_id)
        except DecodeError as exc:
            self._log.warning(f"snapshot {key}", f"dropped: {exc}")
            return None

    def _apply_snapshot(self, key: str, snap: Snapshot, confirmed: bool = False) -> None:
        agent_id = snap.agent_id
        if agent_id == self.agent_id:
            if snap.epoch != self.epoch:
                self._log.warning(f"agent {agent_id}", "another agent with this id runs in "
                                  f"realm {self.realm} (epoch {snap.epoch}); give each agent "
                                  "its own --id")
            return
        for err in snap.errors:
            self._log.warning(f"snapshot {key}", f"service dropped: {err}")
        refusal = self.view.snapshot_refusal(snap)
        if refusal is not None:
            self.snapshots_refused += 1
            self._log.warning(f"snapshot {key}", f"refused: {refusal} "
                              f"({self.snapshots_refused} so far)")
            return
        if self.view.apply_snapshot(snap, confirmed):
            self._dirty = True

    # -- matching
    def _rematch_if_dirty(self) -> None:
        if not self._dirty:
            return
        self._dirty = False
        now = time.monotonic()
        self.monitor.drop_unoffered(self.view.index)
        touched = self.view.index.take_touched()
        for need, state in list(self.needs.items()):
            before = state.result
            state.result = rematch(before, state.req, self.view.index, self.agent_id, touched,
                                   excluded=self.monitor.excluded(need).keys(),
                                   current=state.current)
            if (before is None or before.chosen != state.result.chosen
                    or before.satisfied != state.result.satisfied):
                self._snapshot_dirty = True
            self._send_if_changed(state, now)
        self.monitor.watch({need: state.current for need, state in self.needs.items()},
                           self.view.index, now)

    def _send_if_changed(self, state: NeedState, now: float) -> None:
        assert state.result is not None
        matches = tuple(_match(c.offer) for c in state.result.chosen)
        standby = tuple(_match(c.offer) for c in state.result.standby)
        if state.sent is not None and (matches, standby) == (state.sent, state.sent_standby):
            return
        if state.sent and now - self._started_mono < STARTUP_HOLD_S:
            return  # the view may still be filling up: keep what the service has
        self._send(state, matches, now, standby)

    def _send(self, state: NeedState, matches: tuple[Match, ...], now: float,
              standby: tuple[Match, ...]) -> None:
        assert self.session is not None and state.result is not None
        state.seq = next_seq(state.seq, now - self._started_mono)
        sid = state.req.service_id
        payload = control_message(self.registrar.control_key(sid), self.epoch, state.seq,
                                  state.req.name, matches, state.result.satisfied, standby)
        self.session.put(keys.control(self.realm, self.agent_id, sid), payload,
                         congestion_control=zenoh.CongestionControl.BLOCK)
        if matches != state.sent:
            log.info("need %s/%s -> %s", sid, state.req.name,
                     ", ".join(f"{m.agent_id}/{m.service_id}/{m.ability}" for m in matches)
                     or "nothing")
        state.sent, state.sent_standby, state.sent_at = matches, standby, now

    # -- time-driven work
    def _tick(self) -> None:
        self._worker.pace(self.s.tick_s if self.monitor.watching else IDLE_TICK_S)
        now = time.monotonic()
        if not self._hold_over and now - self._started_mono >= STARTUP_HOLD_S:
            self._hold_over = True
            self._dirty = True  # send what was held back
        if self.monitor.judge([(state.req, state.current) for state in self.needs.values()],
                              self.view.index, now):
            self._dirty = True
        self.registrar.expire_pending(now)
        self._start_waiting_fetch()
        if now - self._last_resend >= RESEND_S:
            self._last_resend = now
            self._resync_agent_tokens()
            self.registrar.resync()
            for state in self.needs.values():
                if state.result is not None and state.sent is not None:
                    self._send(state, state.sent, now, state.sent_standby)

    # -- snapshot
    def _on_services_query(self, query: zenoh.Query) -> None:
        """Answer with the current revision, with fresh measured values."""
        try:
            query.reply(keys.agent_services(self.realm, self.agent_id), self._snapshot())
        finally:
            query.drop()

    def _publish_if_dirty(self) -> None:
        """Publish a new revision (structure changed: services, needs' matches)."""
        if not self._snapshot_dirty:
            return
        self._snapshot_dirty = False
        self.revision = next_seq(self.revision, time.monotonic() - self._started_mono)
        assert self.session is not None
        self.session.put(keys.agent_services(self.realm, self.agent_id), self._snapshot(),
                         congestion_control=zenoh.CongestionControl.BLOCK)

    def _snapshot(self) -> bytes:
        me = Identity(self.agent_id, self.realm, self.epoch, self.endpoints)
        return build_snapshot(self.view, me, self.revision, self._need_status,
                              self.monitor.measured)

    def _need_status(self, sid: str, need_name: str) -> NeedStatus:
        state = self.needs.get((sid, need_name))
        if state is None:
            return NeedStatus()
        result = state.result
        return NeedStatus(result.chosen if result else (), bool(result and result.satisfied),
                          self.monitor.excluded((sid, need_name)))


def _match(offer: Offer) -> Match:
    """What a service is told of an ability its need is connected to."""
    return Match.of(offer.key, offer.agent_id, offer.service_id, offer.ability)
