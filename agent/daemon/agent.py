"""The agent daemon: one per host (DWARF's service manager, Ubitrack's UMA).

What it does, in one Zenoh peer session:

- **registry** (``agent.registry``, whose docstring specifies the protocol): accepts its local
  services' registrations on ``uma/R/agent/A/register``, refuses duplicates, advertises them
  through its snapshot ``uma/R/agent/A/services`` (queryable + publication on change), and
  learns every other agent's services through their tokens and snapshots;
- **matching** (``agent.daemon.matching``): re-matches all local needs whenever the realm changes
  and tells each service, on ``uma/R/ctl/A/S``, the complete set of data keys each need
  must subscribe to.  Data then flows service to service;
- **measuring and re-matching**: it subscribes to every stream its local needs are
  connected to and measures rate (arrivals in the last ``rate_window_s``, once the stream
  has been watched that long) and latency (median of receive time minus sample time).
  When the measured values fail a need's predicate continuously for ``grace_s`` the ability
  is *excluded* for that need and the need re-matched to the next best; the agent keeps
  watching the excluded stream, and once it satisfies the predicate again for ``grace_s``
  the exclusion is lifted (so the need moves back if it ranks better).  Disappearance
  (token DELETE of the service or of its agent) re-matches at once, once a service whose
  token went has been asked whether it still answers (``agent.registry`` step 4: a killed
  service has no queryable left, so the check costs one local lookup; one that answers is
  kept, and a local service whose token comes back after it was dropped is re-adopted);
- **SRG hook**: after opening its session it creates
  ``agent.daemon.srg_node.SrgNode(session, realm, agent_id, static_edges)`` (``static_edges``: the
  config file's ``[[static]]`` tables as dicts with ``parent``, ``child``, ``position``
  [3], ``quaternion`` [4] xyzw and optional ``pos_std_m``, ``rot_std_rad``).  For every
  local ``pose6d`` ability it subscribes to the data key and calls
  ``node.on_local_sample(service_id, ability, measurement)`` (``schemas.models.Ability``,
  ``schemas.codec.Measurement``) from its own feed thread; when a local ability goes away
  (service gone or ability dropped by a re-registration) it calls
  ``node.on_ability_removed(service_id, ability)``; at shutdown ``node.close()`` before the
  session closes.  If ``agent.daemon.srg_node`` cannot be imported the agent runs without an SRG
  and says so once;
- **hosted services**: ``--service NAME`` runs the ``uma.services`` plug-in NAME in a thread
  with the plug-in's default options and ``realm``/``agent``/``connect`` pointing at this
  agent's own listening endpoints; stopped (their ``stop`` event set) at shutdown.

Threads: Zenoh callbacks only enqueue; one worker thread owns all state (no locks), does
the matching and all Zenoh calls; a feed thread decodes local pose samples for the SRG.

Robustness: every ``RESEND_S`` (5 s) the agent re-sends each need's set (idempotent) and
asks for all live tokens: tokens its liveliness subscriptions missed count as PUTs, a live
local service it holds no registration for is re-adopted, and a service it believes alive
whose token is absent is checked (dropped only if it does not answer).  After a
restart it holds back changes to the connections its services report for
``STARTUP_HOLD_S`` (2 s), while its view of the realm fills up, so restarting an agent
never interrupts data; what vanished meanwhile is disconnected after that.

Timing defaults (``[matching]`` / ``[zenoh]`` in the TOML config): ``grace_s`` 0.5,
``rate_window_s`` 0.5, lease 1000 ms (``agent.runtime.session``).  A SIGKILLed service is noticed in
~2 ms (its sockets close), a frozen one after the lease; a rate drop after about
``rate_window_s`` (for the window to reflect it) + ``grace_s``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import queue
import re
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import zenoh

from agent.daemon.matching import Choice, MatchResult, Offer, Requirement, judge, match
from agent.daemon.realm_view import RealmView
from agent.errors import UmaError
from agent.protocol import keys
from agent.protocol.registration import (
    RESEND_S,
    Match,
    Registration,
    Snapshot,
    control_message,
    parse_descriptor_answer,
    parse_descriptor_reply,
    parse_register_request,
    parse_snapshot,
    reply_error,
    reply_ok,
    snapshot_message,
)
from agent.runtime import plugins
from agent.runtime.logs import RateLimitedLog
from agent.runtime.session import listening_endpoints, open_session, query
from agent.srg.geometry import check_quaternion, check_vector
from schemas.codec import DecodeError, decode_measurement, encode_descriptor
from schemas.models import Ability, AgentInfo

log = logging.getLogger("uma.agent")

#: while the agent's view of the realm may be incomplete (just started), it does not tear
#: down connections its services report (an agent restart must not interrupt data)
STARTUP_HOLD_S = 2.0
#: how long a duplicate-id check waits for the first holder of the id to answer
DUPLICATE_CHECK_S = 0.5
#: how long start() waits for a first link to its connect endpoints
LINK_WAIT_S = 1.0
#: seconds to wait for a snapshot query's replies
FETCH_TIMEOUT_S = 2.0
#: how long a departure check waits for a service whose token went to answer on its
#: descriptor queryable (a killed or unreachable one has no queryable: the get ends at once)
DEPARTURE_CHECK_S = 1.0
#: bound on queued local pose samples for the SRG
FEED_QUEUE = 10_000


@dataclass
class AgentSettings:
    """Everything ``uma agent`` can be told (command line and/or TOML config)."""

    realm: str = "default"
    agent_id: str = field(default_factory=keys.default_agent_id)
    mode: str = "peer"
    listen: list[str] | None = None
    connect: list[str] = field(default_factory=list)
    services: list[str] = field(default_factory=list)
    static_edges: list[dict[str, Any]] = field(default_factory=list)
    grace_s: float = 0.5
    rate_window_s: float = 0.5
    lease_ms: int | None = None
    tick_s: float = 0.05

    def check(self) -> AgentSettings:
        """Validate; ``UmaError`` names the setting that is wrong."""
        keys.check_name("realm", self.realm)
        keys.check_name("agent id", self.agent_id)
        if self.mode not in ("peer", "client"):
            raise UmaError(f"mode {self.mode!r}: an agent runs as 'peer' or 'client'")
        for name in ("grace_s", "rate_window_s", "tick_s"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not 0 < value <= 60:
                raise UmaError(f"{name} must be a number of seconds in (0, 60], got {value!r}")
        self.static_edges = [check_static_edge(e, i) for i, e in enumerate(self.static_edges)]
        return self


def check_static_edge(edge: Any, i: int) -> dict[str, Any]:
    """A ``[[static]]`` table, checked and normalised (lists of floats, unit quaternion)."""
    where = f"static edge #{i + 1}"
    if not isinstance(edge, Mapping):
        raise UmaError(f"{where}: expected a table, got {type(edge).__name__}")
    allowed = {"parent", "child", "position", "quaternion", "pos_std_m", "rot_std_rad"}
    unknown = set(edge) - allowed
    if unknown:
        raise UmaError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} "
                       f"(allowed: {', '.join(sorted(allowed))})")
    out: dict[str, Any] = {}
    for k in ("parent", "child"):
        v = edge.get(k)
        if not isinstance(v, str) or not re.fullmatch(r"[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*", v):
            raise UmaError(f"{where}: {k} must be a frame id like 'ivy/world', got {v!r}")
        out[k] = v
    if out["parent"] == out["child"]:
        raise UmaError(f"{where}: parent and child are both {out['parent']!r}")
    try:
        out["position"] = check_vector(edge.get("position"), f"{where} position").tolist()
        out["quaternion"] = check_quaternion(edge.get("quaternion"),
                                             f"{where} quaternion").tolist()
    except ValueError as exc:
        raise UmaError(str(exc)) from None
    if len(out["position"]) != 3 or len(out["quaternion"]) != 4:
        raise UmaError(f"{where}: position needs 3 numbers and quaternion 4 (x, y, z, w)")
    for k in ("pos_std_m", "rot_std_rad"):
        if k in edge:
            v = edge[k]
            if isinstance(v, bool) or not isinstance(v, int | float) or not (
                    math.isfinite(v) and v >= 0):
                raise UmaError(f"{where}: {k} must be a finite number >= 0, got {v!r}")
            out[k] = float(v)
    return out


# --------------------------------------------------------------------------- measuring


class StreamMonitor:
    """Rate and latency of one data stream as this host receives it.

    The Zenoh callback only appends (arrival, payload); ``measure`` (worker thread) decodes
    the sample times and keeps a sliding window.
    """

    def __init__(self, key: str, type_: str, window_s: float, now: float,
                 bad: RateLimitedLog) -> None:
        self.key = key
        self.type = type_
        self.window_s = window_s
        self.started = now
        self.inbox: deque[tuple[float, int, bytes]] = deque(maxlen=20_000)
        self.window: deque[tuple[float, float]] = deque()  # (arrival mono, latency s)
        self.subscriber: Any = None
        self._bad = bad

    def on_sample(self, sample: zenoh.Sample) -> None:
        self.inbox.append((time.monotonic(), time.time_ns(), sample.payload.to_bytes()))

    def measure(self, now: float) -> dict[str, float] | None:
        """Measured values, or ``None`` until the stream was watched for a full window."""
        while self.inbox:
            mono, wall_ns, data = self.inbox.popleft()
            try:
                t_ns = decode_measurement(data, expected_type=self.type).t_ns
            except DecodeError as exc:
                self._bad.warning(f"data {self.key}", f"dropped a malformed sample: {exc}")
                continue
            self.window.append((mono, (wall_ns - t_ns) / 1e9))
        while self.window and self.window[0][0] <= now - self.window_s:
            self.window.popleft()
        if now - self.started < self.window_s:
            return None
        out = {"measured_frequency_hz": len(self.window) / self.window_s}
        if self.window:
            out["measured_latency_s"] = statistics.median(lat for _, lat in self.window)
        return out


@dataclass
class NeedState:
    """The matching state of one local need."""

    req: Requirement
    result: MatchResult | None = None
    sent: tuple[Match, ...] | None = None     # the set last sent to the service
    sent_at: float = 0.0
    seq: int = 0
    failing: dict[str, float] = field(default_factory=dict)    # key -> failing since
    excluded: dict[str, str] = field(default_factory=dict)     # key -> reason
    recovering: dict[str, float] = field(default_factory=dict)  # excluded key -> passing since

    @property
    def current(self) -> set[str]:
        return {m.key for m in self.sent or ()}


@dataclass
class PendingRegistration:
    """A registration waiting for the duplicate check (does the first holder answer?)."""

    query: zenoh.Query
    reg: Registration
    old_instance: str
    holder_answered: bool = False


# --------------------------------------------------------------------------- the agent


class Agent:
    """The per-host daemon (see the module docstring): ``start()``, then ``close()``."""

    def __init__(self, settings: AgentSettings) -> None:
        self.s = settings.check()
        self.realm, self.agent_id = self.s.realm, self.s.agent_id
        self.epoch = time.time_ns()
        self.view = RealmView(self.realm, self.agent_id)
        self.needs: dict[tuple[str, str], NeedState] = {}
        self.monitors: dict[str, StreamMonitor] = {}
        self.endpoints: list[str] = []
        self.revision = 0
        self.session: zenoh.Session | None = None
        self.srg: Any = None
        self._q: queue.Queue[tuple[Callable[..., None], tuple[Any, ...]]] = queue.Queue()
        self._feed_q: queue.Queue[tuple[tuple[str, str], bytes, str] | None] = queue.Queue(
            FEED_QUEUE)
        # (service id, ability name) -> (subscriber, ability, its attributes as a dict)
        self._feeds: dict[tuple[str, str], tuple[Any, Ability, dict[str, Any]]] = {}
        self._decls: list[Any] = []
        self._token: Any = None
        self._pending: dict[str, PendingRegistration] = {}
        #: services whose token went, being checked: (agent, service) -> check number
        self._checking: dict[tuple[str, str], int] = {}
        self._checks = 0
        #: local services whose descriptor is being re-fetched (their token came back)
        self._adopting: set[str] = set()
        self._desc_bytes: dict[str, bytes] = {}
        self._dirty = False           # re-match needed
        self._snapshot_dirty = False  # publish a new snapshot
        self._stopping = threading.Event()
        self._worker: threading.Thread | None = None
        self._feeder: threading.Thread | None = None
        self._hosted: list[tuple[str, threading.Thread, threading.Event]] = []
        self._bad = RateLimitedLog(log)
        self._started_mono = time.monotonic()
        self._last_resend = time.monotonic()
        self._measured: dict[str, dict[str, float]] = {}
        self._hold_over = False

    # -- life cycle
    def start(self) -> None:
        """Open the session, join the realm, start the worker, the SRG and hosted services."""
        s = self.s
        hosted = [(name, plugins.load(plugins.SERVICE_GROUP, name)) for name in s.services]
        self.session = open_session(s.mode, s.listen, s.connect, self.realm,
                                    lease_ms=s.lease_ms)
        try:
            self._join()
            if s.mode == "peer" or s.listen:  # a client without listeners has none
                self.endpoints = listening_endpoints(self.session)
            self._start_srg()
            # last: the token tells clients and agents this one is here, so its query
            # handlers must already be up (a query between the two would go unanswered)
            self._token = self.session.liveliness().declare_token(
                keys.agent_token(self.realm, self.agent_id))
            self._worker = threading.Thread(target=self._work, name="uma-agent", daemon=True)
            self._worker.start()
            self._feeder = threading.Thread(target=self._feed, name="uma-agent-srg",
                                            daemon=True)
            self._feeder.start()
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
        put = self._enqueue
        self._decls += [
            sess.declare_queryable(keys.agent_register(r, a),
                                   lambda q: put(self._on_register, q, _payload(q))),
            sess.declare_queryable(keys.agent_services(r, a),
                                   lambda q: put(self._on_services_query, q)),
            sess.declare_subscriber(keys.all_agent_services(r),
                                    lambda smp: put(self._on_snapshot, str(smp.key_expr),
                                                    smp.payload.to_bytes())),
            sess.liveliness().declare_subscriber(
                keys.all_agent_tokens(r), lambda smp: put(self._on_agent_token, smp),
                history=True),
            sess.liveliness().declare_subscriber(
                keys.service_tokens(r), lambda smp: put(self._on_service_token, smp),
                history=True),
        ]

    def _start_srg(self) -> None:
        try:
            from agent.daemon.srg_node import SrgNode
        except ImportError as exc:
            log.warning("agent %s runs without a spatial relationship graph: agent.daemon.srg_node "
                        "is not available (%s)", self.agent_id, exc)
            return
        self.srg = SrgNode(self.session, self.realm, self.agent_id, self.s.static_edges)

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

        def run() -> None:
            try:
                code = plugin.run(args, stop)
                if code and not stop.is_set():
                    log.error("hosted service %s exited with code %s", name, code)
            except Exception:
                log.exception("hosted service %s failed", name)

        t = threading.Thread(target=run, name=f"uma-service-{name}", daemon=True)
        t.start()
        self._hosted.append((name, t, stop))

    def alive(self) -> bool:
        """Whether the worker runs (it only stops on close, or on a bug)."""
        return self._worker is not None and self._worker.is_alive()

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
        self._stopping.set()
        if self._worker is not None:
            self._worker.join(max(0.1, deadline - time.monotonic() - 0.3))
        with contextlib.suppress(queue.Full):
            self._feed_q.put_nowait(None)
        if self._feeder is not None:
            self._feeder.join(0.2)
        if self.srg is not None:
            try:
                self.srg.close()
            except Exception:
                log.exception("closing the SRG node failed")
            self.srg = None
        for obj in [self._token, *self._decls, *(m.subscriber for m in self.monitors.values()),
                    *(feed[0] for feed in self._feeds.values())]:
            if obj is not None:
                with contextlib.suppress(Exception):
                    obj.undeclare()
        self._token, self._decls = None, []
        self.monitors.clear()
        self._feeds.clear()
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
            self.session = None
        # a worker still inside a blocking put returns once the session is closed; let it
        # leave Zenoh before the interpreter finalises (else the process may abort)
        if self._worker is not None:
            self._worker.join(0.5)

    # -- the worker
    def _enqueue(self, fn: Callable[..., None], *args: Any) -> None:
        self._q.put((fn, args))

    def _work(self) -> None:
        next_tick = time.monotonic()
        while not self._stopping.is_set():
            try:
                fn, args = self._q.get(timeout=max(0.0, next_tick - time.monotonic()))
                self._call(fn, args)
                for _ in range(1000):  # drain what arrived meanwhile, then re-match once
                    fn, args = self._q.get_nowait()
                    self._call(fn, args)
            except queue.Empty:
                pass
            now = time.monotonic()
            if now >= next_tick:
                self._call(self._tick, (now,))
                next_tick = now + self.s.tick_s
            if self._dirty:
                self._call(self._rematch, ())
            if self._snapshot_dirty:
                self._call(self._publish_snapshot, ())

    def _call(self, fn: Callable[..., None], args: tuple[Any, ...]) -> None:
        try:
            fn(*args)
        except zenoh.ZError as exc:
            if not self._stopping.is_set():
                self._bad.warning(f"agent {self.agent_id}", f"{fn.__name__}: Zenoh: {exc}")
        except Exception:  # a bug must not stop the agent; log it with its traceback
            log.exception("agent %s: %s failed", self.agent_id, fn.__name__)

    # -- registry events
    def _on_agent_token(self, smp: zenoh.Sample) -> None:
        agent_id = keys.parse_agent_token(str(smp.key_expr), self.realm)
        if agent_id is None:
            self._bad.warning(f"liveliness {smp.key_expr}", "not an agent token key")
            return
        if agent_id == self.agent_id:
            return
        if smp.kind == zenoh.SampleKind.PUT:
            self.view.agent_alive(agent_id)
            self._fetch_snapshot(agent_id)
        elif self.view.agent_gone(agent_id):
            log.info("agent %s left realm %s", agent_id, self.realm)
            self._dirty = True

    def _fetch_snapshot(self, agent_id: str) -> None:
        assert self.session is not None
        key = keys.agent_services(self.realm, agent_id)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self._enqueue(self._on_snapshot, key, reply.ok.payload.to_bytes())
        self.session.get(key, on_reply, timeout=FETCH_TIMEOUT_S)

    def _resync_tokens(self) -> None:
        """Anti-entropy: ask for the live agent and service tokens and reconcile (a
        liveliness subscription declared before its links were up may not get the tokens
        that existed then; a DELETE and a PUT may have crossed)."""
        assert self.session is not None

        def on_agent(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self._enqueue(self._on_resync_agent_token, reply.ok)
        liveliness = self.session.liveliness()
        liveliness.get(keys.all_agent_tokens(self.realm), on_agent, timeout=1.0)
        found: list[str] = []

        def on_service(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                found.append(str(reply.ok.key_expr))
        liveliness.get(keys.service_tokens(self.realm), zenoh.handlers.Callback(
            on_service, lambda: self._enqueue(self._on_resync_service_tokens, found)),
            timeout=1.0)

    def _on_resync_agent_token(self, smp: zenoh.Sample) -> None:
        agent_id = keys.parse_agent_token(str(smp.key_expr), self.realm)
        if agent_id is not None and agent_id != self.agent_id and (
                agent_id not in self.view.live_agents):
            self._on_agent_token(smp)

    def _on_resync_service_tokens(self, token_keys: list[str]) -> None:
        """Tokens we missed count as PUTs; a local service with a live token but no
        registration is re-adopted; a service we believe alive whose token is not there
        is checked (it is dropped only if it does not answer)."""
        live: set[tuple[str, str]] = set()
        for key in token_keys:
            parsed = keys.parse_service_token(key, self.realm)
            if parsed is None:
                self._bad.warning(f"liveliness {key}", "not a service token key")
                continue
            live.add(parsed)
        for agent_id, sid in live:
            if (agent_id, sid) not in self.view.live_services:
                self._service_token_put(agent_id, sid)
            elif agent_id == self.agent_id and sid not in self.view.local:
                self._adopt(sid)
        for agent_id, sid in self.view.live_services - live:
            self._check_departure(agent_id, sid)

    def _on_snapshot(self, key: str, data: bytes) -> None:
        agent_id = keys.parse_agent_services(key, self.realm)
        if agent_id is None:
            self._bad.warning(key, "not an agent services key")
            return
        try:
            snap: Snapshot = parse_snapshot(data, agent_id)
        except DecodeError as exc:
            self._bad.warning(f"snapshot {key}", f"dropped: {exc}")
            return
        if agent_id == self.agent_id:
            if snap.epoch != self.epoch:
                self._bad.warning(f"agent {agent_id}", "another agent with this id runs in "
                                  f"realm {self.realm} (epoch {snap.epoch}); give each agent "
                                  "its own --id")
            return
        for err in snap.errors:
            self._bad.warning(f"snapshot {key}", f"service dropped: {err}")
        if self.view.apply_snapshot(snap):
            self._dirty = True

    def _on_service_token(self, smp: zenoh.Sample) -> None:
        parsed = keys.parse_service_token(str(smp.key_expr), self.realm)
        if parsed is None:
            self._bad.warning(f"liveliness {smp.key_expr}", "not a service token key")
            return
        agent_id, sid = parsed
        if smp.kind == zenoh.SampleKind.PUT:
            self._service_token_put(agent_id, sid)
        else:
            self._check_departure(agent_id, sid)

    def _service_token_put(self, agent_id: str, sid: str) -> None:
        self._checking.pop((agent_id, sid), None)  # back: a pending check is moot
        if self.view.service_alive(agent_id, sid):
            self._dirty = True
        if agent_id == self.agent_id:
            self._snapshot_dirty = True
            if sid not in self.view.local:
                self._adopt(sid)  # we dropped it meanwhile: take it back

    def _check_departure(self, agent_id: str, sid: str) -> None:
        """A service token's DELETE: ask the service itself before tearing anything down
        (see ``agent.registry``, step 4: a DELETE may be spurious)."""
        k = (agent_id, sid)
        if k not in self.view.live_services and not (
                agent_id == self.agent_id and sid in self.view.local):
            return  # nothing to tear down
        if k in self._checking:
            return
        assert self.session is not None
        self._checks += 1
        check, answers = self._checks, []
        self._checking[k] = check

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                answers.append(reply.ok.payload.to_bytes())
        self.session.get(keys.service_token(self.realm, agent_id, sid), zenoh.handlers.Callback(
            on_reply, lambda: self._enqueue(self._on_departure_checked, k, check, answers)),
            timeout=DEPARTURE_CHECK_S, consolidation=zenoh.ConsolidationMode.NONE)

    def _on_departure_checked(self, k: tuple[str, str], check: int,
                              answers: list[bytes]) -> None:
        if self._checking.get(k) != check:
            return  # the token came back meanwhile, or a newer check runs
        del self._checking[k]
        agent_id, sid = k
        expected = self._instance_of(agent_id, sid)
        for data in answers:
            try:
                instance = parse_descriptor_reply(data)
            except DecodeError as exc:
                self._bad.warning(f"service {agent_id}/{sid}", f"bad descriptor reply: {exc}")
                continue
            if expected is None or instance == expected:
                self._bad.warning(f"service {agent_id}/{sid}",
                                  "its liveliness token went but it still answers; kept")
                return
        self._service_gone(agent_id, sid)

    def _instance_of(self, agent_id: str, sid: str) -> str | None:
        """The process instance this agent knows for a service (None: unknown)."""
        if agent_id == self.agent_id:
            entry = self.view.local.get(sid)
            return entry.instance if entry else None
        snap = self.view.remote.get(agent_id)
        instance = snap.status.get(sid, {}).get("instance") if snap else None
        return instance if isinstance(instance, str) else None

    def _service_gone(self, agent_id: str, sid: str) -> None:
        local = agent_id == self.agent_id and sid in self.view.local
        if local:
            self._local_abilities_changed(sid, [])
        changed = self.view.service_gone(agent_id, sid)
        if local:
            log.info("service %s left agent %s", sid, self.agent_id)
            self._drop_needs(sid)
        if changed:
            self._dirty = True
        if agent_id == self.agent_id:
            self._snapshot_dirty = True

    def _adopt(self, sid: str) -> None:
        """Re-fetch a live local service's descriptor from the service itself."""
        if sid in self._adopting:
            return
        assert self.session is not None
        self._adopting.add(sid)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self._enqueue(self._on_adopt_reply, sid, reply.ok.payload.to_bytes())
        self.session.get(keys.service_token(self.realm, self.agent_id, sid),
                         zenoh.handlers.Callback(
                             on_reply, lambda: self._enqueue(self._adopting.discard, sid)),
                         timeout=FETCH_TIMEOUT_S)

    def _on_adopt_reply(self, sid: str, data: bytes) -> None:
        if sid in self.view.local or (self.agent_id, sid) not in self.view.live_services:
            return  # registered by itself meanwhile, or gone again
        try:
            reg = parse_descriptor_answer(data, self.agent_id)
        except DecodeError as exc:
            self._bad.warning(f"service {sid}", f"cannot re-adopt it: {exc}")
            return
        if reg.descriptor.service_id != sid:
            self._bad.warning(f"service {sid}", "cannot re-adopt it: it answers as "
                              f"{reg.descriptor.service_id!r}")
            return
        self._admit(reg)
        log.info("service %s re-adopted by agent %s: its token came back (revision %d)",
                 sid, self.agent_id, reg.revision)

    def _on_register(self, query: zenoh.Query, data: bytes | None) -> None:
        try:
            if data is None:
                raise DecodeError("empty registration")
            reg = parse_register_request(data, self.agent_id)
        except DecodeError as exc:
            self._bad.warning(f"registration on {query.key_expr}", f"refused: {exc}")
            self._refuse(query, f"registration refused: {exc}")
            return
        sid = reg.descriptor.service_id
        if sid in self._pending:
            self._refuse(query, f"service id {sid!r}: a registration is being checked; "
                                "retry", retry=True)
            return
        entry = self.view.local.get(sid)
        if entry is None or entry.instance == reg.instance:
            self._accept(query, reg)
            return
        # another process holds this id: refuse if it still answers, else replace it
        pending = PendingRegistration(query, reg, entry.instance)
        self._pending[sid] = pending
        assert self.session is not None

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self._enqueue(self._on_holder_reply, sid, reply.ok.payload.to_bytes())
        self.session.get(keys.service_token(self.realm, self.agent_id, sid),
                         zenoh.handlers.Callback(
                             on_reply, lambda: self._enqueue(self._on_holder_done, sid)),
                         timeout=DUPLICATE_CHECK_S,
                         # both holders answer on the same key: keep every reply
                         consolidation=zenoh.ConsolidationMode.NONE)

    def _on_holder_reply(self, sid: str, data: bytes) -> None:
        pending = self._pending.get(sid)
        if pending is None:
            return
        try:
            if parse_descriptor_reply(data) == pending.old_instance:
                pending.holder_answered = True
        except DecodeError as exc:
            self._bad.warning(f"service {sid}", f"bad descriptor reply: {exc}")

    def _on_holder_done(self, sid: str) -> None:
        pending = self._pending.pop(sid, None)
        if pending is None:
            return
        if pending.holder_answered:
            error = (f"duplicate service id {sid!r} on agent {self.agent_id!r} in realm "
                     f"{self.realm!r}: another process already runs it")
            self._bad.warning(f"service {sid}", f"second registration refused ({error})")
            self._refuse(pending.query, error)
        else:
            log.info("service %s: previous instance does not answer; replaced", sid)
            self._accept(pending.query, pending.reg)

    def _refuse(self, query: zenoh.Query, error: str, retry: bool = False) -> None:
        try:
            query.reply_err(reply_error(error, retry))
        finally:
            query.drop()

    def _accept(self, query: zenoh.Query, reg: Registration) -> None:
        self._admit(reg)
        try:
            query.reply(query.key_expr, reply_ok(self.epoch))
        finally:
            query.drop()
        log.info("service %s registered with agent %s (revision %d)",
                 reg.descriptor.service_id, self.agent_id, reg.revision)

    def _admit(self, reg: Registration) -> None:
        """Take a registration in: the view, the SRG feed, the needs."""
        sid = reg.descriptor.service_id
        old = self.view.local.get(sid)
        new_instance = old is None or old.instance != reg.instance
        if old is not None and new_instance:
            self._drop_needs(sid)
        if self.view.register_local(reg, time.monotonic()):
            self._dirty = True
        self._desc_bytes[sid] = encode_descriptor(reg.descriptor)
        self._local_abilities_changed(sid, reg.descriptor.abilities)
        for need in reg.descriptor.needs:
            state = self.needs.get((sid, need.name))
            if state is None or state.req.need != need:
                self.needs[(sid, need.name)] = NeedState(self._requirement(sid, need.name))
                self._dirty = True
            if new_instance:
                # what the service is subscribed to right now (agent restart): keep it
                self.needs[(sid, need.name)].sent = tuple(
                    _match(offer) if offer else Match.unknown(k, need.type, self.realm)
                    for k in reg.connected.get(need.name, ())
                    for offer in [self.view.index.by_key.get(k)])
        for (s, name) in [k for k in self.needs if k[0] == sid]:
            if name not in {n.name for n in reg.descriptor.needs}:
                del self.needs[(s, name)]
        self._snapshot_dirty = True

    def _requirement(self, sid: str, need_name: str) -> Requirement:
        for req in self.view.requirements():
            if req.service_id == sid and req.name == need_name:
                return req
        raise KeyError((sid, need_name))

    def _drop_needs(self, sid: str) -> None:
        for k in [k for k in self.needs if k[0] == sid]:
            del self.needs[k]
        self._desc_bytes.pop(sid, None)
        self._dirty = True

    def _on_services_query(self, query: zenoh.Query) -> None:
        """Answer with the current revision, with fresh measured values."""
        try:
            query.reply(keys.agent_services(self.realm, self.agent_id), self._build_snapshot())
        finally:
            query.drop()

    # -- SRG feed of local pose abilities
    def _local_abilities_changed(self, sid: str, abilities: list[Ability]) -> None:
        """Subscribe the SRG to new local pose6d abilities, tell it about removed ones; an
        ability whose attributes changed keeps its subscription (the SRG gets the new
        ``Ability`` with the next sample)."""
        if self.srg is None or self.session is None:
            return
        wanted = {a.name: a for a in abilities if a.type == "pose6d"}
        for (s, name), (sub, ability, _) in list(self._feeds.items()):
            if s != sid:
                continue
            if name in wanted:
                self._feeds[(s, name)] = (sub, wanted[name], _attributes(wanted[name]))
                continue
            sub.undeclare()
            del self._feeds[(s, name)]
            self._srg_call("on_ability_removed", sid, ability)
        for name in wanted:
            if (sid, name) in self._feeds:
                continue
            key = keys.data(self.realm, self.agent_id, sid, name)

            def on_sample(smp: zenoh.Sample, feed: tuple[str, str] = (sid, name),
                          k: str = key) -> None:
                try:
                    self._feed_q.put_nowait((feed, smp.payload.to_bytes(), k))
                except queue.Full:
                    self._bad.warning(f"data {k}", "SRG feed queue full; sample dropped")
            self._feeds[(sid, name)] = (self.session.declare_subscriber(key, on_sample),
                                        wanted[name], _attributes(wanted[name]))

    def _feed(self) -> None:
        while True:
            item = self._feed_q.get()
            if item is None or self._stopping.is_set():
                return
            feed, data, key = item
            entry = self._feeds.get(feed)
            if entry is None:
                continue  # the ability went away meanwhile
            _, ability, attributes = entry
            try:
                m = decode_measurement(data, expected_type="pose6d")
            except DecodeError as exc:
                self._bad.warning(f"data {key}", f"dropped a malformed sample: {exc}")
                continue
            m.edge, m.source = ability.edge, feed[0]
            m.attributes = attributes
            self._srg_call("on_local_sample", feed[0], ability, m)

    def _srg_call(self, method: str, *args: Any) -> None:
        node = self.srg
        if node is None:
            return
        try:
            getattr(node, method)(*args)
        except Exception as exc:
            self._bad.warning(f"SRG {method}", f"{type(exc).__name__}: {exc}")

    # -- matching
    def _rematch(self) -> None:
        self._dirty = False
        now = time.monotonic()
        for state in list(self.needs.values()):
            gone = [k for k in state.excluded if k not in self.view.index.by_key]
            for k in gone:
                state.excluded.pop(k, None)
                state.recovering.pop(k, None)
            before = state.result
            state.result = match(state.req, self.view.index, self.agent_id,
                                 excluded=state.excluded.keys(), current=state.current)
            if (before is None or before.chosen != state.result.chosen
                    or before.satisfied != state.result.satisfied):
                self._snapshot_dirty = True
            self._send_if_changed(state, now)
        self._sync_monitors(now)

    def _send_if_changed(self, state: NeedState, now: float) -> None:
        assert state.result is not None
        matches = tuple(_match(c.offer) for c in state.result.chosen)
        if state.sent is not None and matches == state.sent:
            return
        if state.sent and now - self._started_mono < STARTUP_HOLD_S:
            return  # the view may still be filling up: keep what the service has
        self._send(state, matches, now)

    def _send(self, state: NeedState, matches: tuple[Match, ...], now: float) -> None:
        assert self.session is not None and state.result is not None
        state.seq += 1
        sid = state.req.service_id
        payload = control_message(self.epoch, state.seq, state.req.name, matches,
                                  state.result.satisfied)
        self.session.put(keys.control(self.realm, self.agent_id, sid), payload,
                         congestion_control=zenoh.CongestionControl.BLOCK)
        if matches != state.sent:
            log.info("need %s/%s -> %s", sid, state.req.name,
                     ", ".join(f"{m.agent_id}/{m.service_id}/{m.ability}" for m in matches)
                     or "nothing")
        state.sent, state.sent_at = matches, now

    # -- measuring
    def _sync_monitors(self, now: float) -> None:
        wanted: dict[str, str] = {}
        for state in self.needs.values():
            for k in state.current | state.excluded.keys():
                offer = self.view.index.by_key.get(k)
                if offer is not None:
                    wanted[k] = offer.type
        for k in self.monitors.keys() - wanted.keys():
            mon = self.monitors.pop(k)
            with contextlib.suppress(Exception):
                mon.subscriber.undeclare()
        assert self.session is not None
        for k, type_ in wanted.items():
            if k not in self.monitors:
                mon = StreamMonitor(k, type_, self.s.rate_window_s, now, self._bad)
                mon.subscriber = self.session.declare_subscriber(k, mon.on_sample)
                self.monitors[k] = mon

    def _tick(self, now: float) -> None:
        measured = {k: m for k, m in ((k, mon.measure(now)) for k, mon in self.monitors.items())
                    if m is not None}
        self._measured = measured  # shown in snapshots (uma services)
        if not self._hold_over and now - self._started_mono >= STARTUP_HOLD_S:
            self._hold_over = True
            self._dirty = True  # send what was held back
        for state in self.needs.values():
            self._judge(state, measured, now)
        for sid in self.view.expired_pending(now):
            log.warning("service %s registered but never declared its liveliness token; "
                        "dropped", sid)
            self._local_abilities_changed(sid, [])
            self.view.remove_local(sid)
            self._drop_needs(sid)
        if now - self._last_resend >= RESEND_S:
            self._last_resend = now
            self._resync_tokens()
            for state in self.needs.values():
                if state.result is not None and state.sent is not None:
                    self._send(state, state.sent, now)

    def _judge(self, state: NeedState, measured: dict[str, dict[str, float]],
               now: float) -> None:
        """Exclude connected streams failing the predicate for ``grace_s``; readmit
        excluded ones passing it for ``grace_s``."""
        grace = self.s.grace_s
        for k in state.current:
            offer = self.view.index.by_key.get(k)
            values = measured.get(k)
            if offer is None or values is None:
                state.failing.pop(k, None)
                continue
            ok, reason = judge(state.req, offer, values)
            if ok:
                state.failing.pop(k, None)
                continue
            since = state.failing.setdefault(k, now)
            if now - since >= grace:
                state.failing.pop(k)
                state.excluded[k] = f"{reason} for {now - since:.2f} s: " + _fmt(values)
                log.info("need %s/%s: %s fails its predicate as measured (%s); re-matching",
                         state.req.service_id, state.req.name, k, state.excluded[k])
                self._dirty = True
        for k in list(state.excluded):
            offer = self.view.index.by_key.get(k)
            values = measured.get(k)
            if offer is None or values is None or not judge(state.req, offer, values)[0]:
                state.recovering.pop(k, None)
                continue
            since = state.recovering.setdefault(k, now)
            if now - since >= grace:
                del state.excluded[k]
                state.recovering.pop(k)
                log.info("need %s/%s: %s satisfies its predicate again (%s)",
                         state.req.service_id, state.req.name, k, _fmt(values))
                self._dirty = True

    # -- snapshot
    def _build_snapshot(self) -> bytes:
        measured = self._measured
        services = []
        for sid, entry in sorted(self.view.local.items()):
            if not self.view.present(self.agent_id, sid):
                continue
            matches, satisfied, excluded = {}, {}, {}
            for need in entry.descriptor.needs:
                state = self.needs.get((sid, need.name))
                chosen: tuple[Choice, ...] = state.result.chosen if state and state.result else ()
                matches[need.name] = [_choice_status(c, measured.get(c.offer.key))
                                      for c in chosen]
                satisfied[need.name] = bool(state and state.result and state.result.satisfied)
                excluded[need.name] = dict(state.excluded) if state else {}
            services.append({"descriptor": self._desc_bytes.get(sid)
                             or encode_descriptor(entry.descriptor),
                             "instance": entry.instance, "matches": matches,
                             "satisfied": satisfied, "excluded": excluded})
        info = AgentInfo(agent_id=self.agent_id, realm=self.realm, version=_version(),
                         started_ns=self.epoch, endpoints=self.endpoints,
                         services=[sid for sid in sorted(self.view.local)
                                   if self.view.present(self.agent_id, sid)])
        return snapshot_message(info.model_dump(mode="json"), self.epoch, self.revision,
                                services)

    def _publish_snapshot(self) -> None:
        """Publish a new revision (structure changed: services, needs' matches)."""
        self._snapshot_dirty = False
        self.revision += 1
        assert self.session is not None
        self.session.put(keys.agent_services(self.realm, self.agent_id), self._build_snapshot(),
                         congestion_control=zenoh.CongestionControl.BLOCK)


def _match(offer: Offer) -> Match:
    """What a service is told of an ability its need is connected to."""
    return Match.of(offer.key, offer.agent_id, offer.service_id, offer.ability)


def _payload(query: zenoh.Query) -> bytes | None:
    return None if query.payload is None else query.payload.to_bytes()


def _choice_status(c: Choice, measured: dict[str, float] | None) -> dict[str, Any]:
    o: Offer = c.offer
    return {"key": o.key, "agent_id": o.agent_id, "service_id": o.service_id,
            "ability": o.ability.name, "score": c.score if math.isfinite(c.score) else None,
            "local": c.local, "measured": dict(measured or {})}


def _attributes(ability: Ability) -> dict[str, Any]:
    """An ability's attributes as the plain dict samples carry (as in the service SDK)."""
    return ability.attributes.model_dump(mode="json", exclude_none=True)


def _fmt(values: Mapping[str, float]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in sorted(values.items()))


def _version() -> str:
    try:
        return version("uma-tracking")
    except PackageNotFoundError:
        return "unknown"
