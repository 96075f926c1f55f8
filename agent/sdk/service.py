"""The service SDK: declare abilities and needs, publish, receive matched streams.

::

    from agent import Service
    with Service("cam-nw", realm="lab", agent="hostA", connect=["tcp/127.0.0.1:7447"]) as svc:
        out = svc.ability("pose", type="pose6d", edge=("ivy/world", "alice/head"),
                          frequency_hz=60, latency_s=0.005, pos_std_m=0.01)
        svc.need("head", type="pose6d", edge=("ivy/world", "*/head"),
                 where="frequency_hz >= 30", prefer="latency_s", on_sample=handle)
        svc.start()
        out.publish(t_ns, position, quaternion, covariance=None)

``handle(m)`` receives a ``schemas.codec.Measurement`` (``m.t_ns``, ``m.position``,
``m.quaternion``, ``m.covariance``, the other fields for other types) with ``m.edge``,
``m.source`` (the publishing service's id) and ``m.attributes`` (the ability's advertised
attributes) filled in.  Callbacks run on the service's own dispatch thread, one at a time,
never on a Zenoh thread; an exception in a callback is logged, not fatal.

The service registers with its local agent (:mod:`agent.protocol.registration`): if
the agent is not running yet, ``start()`` waits ``register_timeout`` seconds, then returns
and the service registers as soon as the agent appears (and again whenever the agent
restarts).  A duplicate service id is refused: ``start()`` raises ``UmaError`` (a refusal
that arrives after ``start()`` returned, because the agent appeared later, is logged and
kept in ``svc.error``).  The agent
then tells the service which data keys each need subscribes to; the service subscribes
and follows every re-match without any action by the code using it.

A service that names its agent's endpoint (``connect``) is a Zenoh *client* of that agent,
which routes its samples (``docs/ARCHITECTURE.md``, "Topology"); every ``Service`` and
``Client`` of one process shares one session (``shared=False`` opts out, ``mode="peer"``
makes the service a listening peer of its own).  When the agent is not
reachable yet, the service connects as soon as it is; samples published meanwhile have no
receiver and are counted in ``handle.unsent``.  ``svc.matches(name)`` and
``svc.wait_matched(name)`` expose the matches.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import secrets
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh
from pydantic import ValidationError

from agent.errors import InvalidInputError, UmaError, UmaTimeoutError
from agent.protocol import keys
from agent.protocol.registration import (
    Match,
    RegisterReply,
    UnverifiedControlError,
    control_need,
    descriptor_reply,
    parse_control,
    parse_reply,
    register_request,
)
from agent.runtime.callbacks import guarded
from agent.runtime.logs import RateLimitedLog
from agent.runtime.payload import payload_bytes
from agent.runtime.session import (
    UnreachableEndpointError,
    acquire_session,
    release_session,
    sdk_mode,
)
from agent.runtime.worker import Worker
from schemas.codec import (
    MAX_IMAGE_BYTES,
    MAX_MESSAGE_BYTES,
    DecodeError,
    Measurement,
    decode_measurement,
    encode_descriptor,
    encode_measurement,
    encode_pose,
    peek_time,
    validation_summary,
)
from schemas.models import Ability, Need, ServiceDescriptor

log = logging.getLogger("uma.service")

#: bound on received samples waiting for the dispatch thread (oldest data is worth least)
SAMPLE_QUEUE = 10_000
#: registration query timeout, and the retry back-off bounds
REGISTER_TIMEOUT_S = 2.0
RETRY_MIN_S, RETRY_MAX_S = 0.1, 1.0
#: while the agent's token is not seen, ask for it this often
PROBE_S = 1.0
#: how often the worker sees whether to probe for the agent or register again
RETRY_TICK_S = 0.05
#: seconds between attempts to reach an agent that did not answer at start()
OPEN_RETRY_S = 0.25
#: how far a control message's seq (the agent's milliseconds, ``next_seq``) may run ahead
#: of the last one applied plus the milliseconds passed since: a forged jump holds the
#: agent's real messages back this long at most
SEQ_WINDOW = 2000
#: seconds between registrations prompted by control messages that do not verify
REVERIFY_S = 1.0

OnSample = Callable[[Measurement], Any]


def _checked(model: type, what: str, **fields: Any) -> Any:
    """Build a pydantic model; a ``ValueError`` with a one-line reason if invalid."""
    try:
        return model(**fields)
    except ValidationError as exc:
        raise InvalidInputError(f"{what}: {validation_summary(exc)}") from None


class AbilityHandle:
    """What ``Service.ability`` returns: publish samples, change attributes."""

    def __init__(self, svc: Service, ability: Ability) -> None:
        self._svc = svc
        self.ability = ability
        self.key = keys.data(svc.realm, svc.agent_id, svc.service_id, ability.name)
        self._publisher: Any = None
        self._seq = 0
        #: samples published while the service had no session (its agent unreachable)
        self.unsent = 0

    @property
    def name(self) -> str:
        return self.ability.name

    def publish(self, t_ns: int, position: Any, quaternion: Any, covariance: Any = None) -> None:
        """Publish one pose (``pose6d`` abilities); ``ValueError`` names a bad field."""
        if self.ability.type != "pose6d":
            raise UmaError(f"ability {self.name!r} is {self.ability.type}; use "
                           "publish_measurement()")
        self._put(encode_pose(t_ns, position, quaternion, covariance, seq=self._next_seq()))

    def publish_measurement(self, m: Measurement) -> None:
        """Publish a measurement of any type (must be this ability's type)."""
        if m.type != self.ability.type:
            raise UmaError(f"ability {self.name!r} publishes {self.ability.type}, "
                           f"not {m.type}")
        if m.seq is None:
            m.seq = self._next_seq()
        self._put(encode_measurement(m))

    def publish_encoded(self, data: bytes) -> None:
        """Publish a sample that is already encoded, byte for byte (``uma play`` replays a
        recording's exact bytes); ``DecodeError`` if its envelope is not a measurement of
        this ability's type."""
        peek_time(data, self.ability.type)
        self._put(data)

    def update(self, **attributes: Any) -> None:
        """Change advertised attributes at run time (re-advertised, re-matched)."""
        self._svc._update_ability(self, attributes)

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _put(self, payload: bytes) -> None:
        pub = self._publisher
        if pub is None and self._svc.connecting:
            self.unsent += 1
            return
        if pub is None:
            raise UmaError(f"service {self._svc.service_id!r}: call start() before publishing "
                           f"on {self.name!r}" if not self._svc.closed else
                           f"service {self._svc.service_id!r} is closed")
        pub.put(payload)


@dataclass
class _Link:
    """One subscription of a need to a matched ability (the callback reads ``match``)."""

    match: Match
    subscriber: Any = None


@dataclass
class NeedHandle:
    """What ``Service.need`` returns; ``matches`` is the current set, best first."""

    need: Need
    on_sample: OnSample | None
    matches: tuple[Match, ...] = ()
    satisfied: bool = False
    links: dict[str, _Link] = field(default_factory=dict)
    last: tuple[int, int] = (-1, -1)  # (agent epoch, seq) of the last control applied
    last_at: float = 0.0  # when it was applied (monotonic s)

    @property
    def name(self) -> str:
        return self.need.name


class Service:
    """A uma service (see the module docstring)."""

    def __init__(self, service_id: str, realm: str = "default", agent: str | None = None,
                 connect: Iterable[str] = (), listen: Sequence[str] | None = None, *,
                 attributes: dict[str, Any] | None = None,
                 register_timeout: float = 3.0, mode: str | None = None,
                 shared: bool = True, zenoh_config: str | None = None) -> None:
        self.service_id = keys.check_name("service id", service_id)
        self.realm = keys.check_name("realm", realm)
        self.agent_id = keys.check_name("agent id", agent or keys.default_agent_id())
        self.connect = list(connect)
        self.listen = None if listen is None else list(listen)
        self.mode = sdk_mode(mode, self.connect)
        self.shared = shared
        #: Zenoh configuration file to start from (a secured site's TLS; UMA_ZENOH_CONFIG)
        self.zenoh_config = zenoh_config
        self.attributes = dict(attributes or {})
        self.register_timeout = register_timeout
        _checked(ServiceDescriptor, f"service {service_id!r}", service_id=service_id,
                 agent_id=self.agent_id, attributes=self.attributes)
        self.instance = secrets.token_hex(8)
        self.session: zenoh.Session | None = None
        self.closed = False
        self.error: str | None = None
        self._abilities: dict[str, AbilityHandle] = {}
        self._needs: dict[str, NeedHandle] = {}
        self._lock = threading.Lock()          # abilities/needs/revision vs the worker
        self._cond = threading.Condition()     # match changes, registration outcome
        self._revision = 0
        self._registered_revision = -1
        self._agent_present = False
        self._registering = False
        self._next_try = 0.0
        self._next_probe = time.monotonic() + PROBE_S
        self._next_open = 0.0
        self._attaching = threading.Lock()
        self._backoff = RETRY_MIN_S
        self._outcome = threading.Event()
        self._token: Any = None
        self._decls: list[Any] = []
        #: owns registration and subscriptions; retries every RETRY_TICK_S
        self._worker = Worker(f"uma-service-{self.service_id}-worker",
                              f"service {self.service_id}", log, self._retry, RETRY_TICK_S)
        self._samples: queue.Queue[tuple[NeedHandle, _Link, bytes] | None] = queue.Queue(
            SAMPLE_QUEUE)
        self._threads: list[threading.Thread] = []
        self._log = RateLimitedLog(log)
        #: the agent's epoch and the key it signs control messages with (register reply)
        self._agent_epoch: int | None = None
        self._control_key: bytes | None = None
        #: the challenge the agent's last answer gave (the next registration signs it)
        self._challenge: bytes | None = None
        #: the newest control message per own need that did not verify yet (kept until
        #: the next registration gives a key: the agent may have sent it first)
        self._unverified: dict[str, bytes] = {}
        self._next_reverify = 0.0
        #: control messages refused, by reason ("signature", "epoch", "seq")
        self.control_refused: dict[str, int] = {}

    # -- declaring
    def ability(self, name: str, type: str, edge: tuple[str, str] | None = None,
                key: str | None = None, **attributes: Any) -> AbilityHandle:
        """Declare a stream this service publishes; returns its handle."""
        ab = _checked(Ability, f"ability {name!r}", name=name, type=type,
                      edge=None if edge is None else tuple(edge), key=key,
                      attributes=attributes)
        with self._lock:
            if name in self._abilities:
                raise InvalidInputError(f"service {self.service_id!r} already has an ability "
                                        f"named {name!r}")
            handle = AbilityHandle(self, ab)
            self._abilities[name] = handle
            self._revision += 1
            if self.session is not None:
                handle._publisher = self.session.declare_publisher(handle.key)
        if self.session is not None:
            self._enqueue(self._register)
        return handle

    def need(self, name: str, type: str, edge: tuple[str, str],
             where: str | None = None, prefer: str | None = None, min_count: int = 1,
             max_count: int = 1, on_sample: OnSample | None = None) -> NeedHandle:
        """Declare what this service wants; ``on_sample(m)`` receives each sample."""
        need = _checked(Need, f"need {name!r}", name=name, type=type, edge=tuple(edge),
                        where=where, prefer=prefer, min_count=min_count, max_count=max_count)
        if on_sample is not None and not callable(on_sample):
            raise InvalidInputError(f"need {name!r}: on_sample must be callable")
        with self._lock:
            if name in self._needs:
                raise InvalidInputError(f"service {self.service_id!r} already has a need named "
                                        f"{name!r}")
            handle = NeedHandle(need, on_sample)
            self._needs[name] = handle
            self._revision += 1
        if self.session is not None:
            self._enqueue(self._register)
        return handle

    def descriptor(self) -> ServiceDescriptor:
        """What is advertised now."""
        with self._lock:
            return self._descriptor_locked()

    def _descriptor_locked(self) -> ServiceDescriptor:
        return _checked(ServiceDescriptor, f"service {self.service_id!r}",
                        service_id=self.service_id, agent_id=self.agent_id,
                        needs=[n.need for n in self._needs.values()],
                        abilities=[a.ability for a in self._abilities.values()],
                        attributes=self.attributes)

    def _update_ability(self, handle: AbilityHandle, attributes: dict[str, Any]) -> None:
        with self._lock:
            merged = {**handle.ability.attributes.model_dump(exclude_none=True,
                                                             exclude_defaults=True),
                      **attributes}
            handle.ability = _checked(Ability, f"ability {handle.name!r}",
                                      **{**handle.ability.model_dump(exclude={"attributes"}),
                                         "attributes": merged})
            self._revision += 1
        if self.session is not None:
            self._enqueue(self._register)

    # -- life cycle
    def start(self) -> Service:
        """Open the session, declare everything, register with the agent.

        Waits up to ``register_timeout`` s for the agent's answer; raises ``UmaError`` if
        it refuses (e.g. a duplicate service id).  If the agent is not there yet, returns
        anyway and registers when it appears.
        """
        if self.closed:
            raise UmaError(f"service {self.service_id!r} is closed; create a new one")
        if self._threads:
            return self
        if not self.connect:
            log.warning("service %s: no connect endpoint given; it will only find agent %s "
                        "if that agent connects to it", self.service_id, self.agent_id)
        self._start_threads()
        try:
            if not self._attach():
                log.warning("service %s: nothing answers at %s yet; connecting as soon as "
                            "agent %s is there", self.service_id, ", ".join(self.connect),
                            self.agent_id)
        except BaseException:
            self.close()
            raise
        if not self._outcome.wait(self.register_timeout):
            log.warning("service %s: agent %s of realm %s not reachable yet; will register "
                        "when it appears", self.service_id, self.agent_id, self.realm)
        elif self.error is not None:
            error = self.error
            self.close()
            raise UmaError(error)
        return self

    @property
    def connecting(self) -> bool:
        """Started, but not attached to a session yet (its agent was unreachable)."""
        return bool(self._threads) and self.session is None and not self.closed

    def _start_threads(self) -> None:
        self._worker.start()
        t = threading.Thread(target=self._dispatch, name=f"uma-service-{self.service_id}-"
                             "dispatch", daemon=True)
        t.start()
        self._threads.append(t)

    def _attach(self) -> bool:
        """Take this process's session and declare everything on it; False if a client's
        agent does not answer yet (the worker tries again every ``OPEN_RETRY_S``).  Both
        ``start()`` and the worker call it, so it holds its own lock: one session each."""
        with self._attaching:
            if self.session is not None:
                return True
            try:
                sess = acquire_session(self.mode, self.listen, self.connect, self.realm,
                                       shared=self.shared, base_file=self.zenoh_config)
            except UnreachableEndpointError:
                if self.mode != "client":
                    raise
                return False
            with self._lock:
                if self.closed:
                    release_session(sess)
                    return False
                self.session = sess
                for handle in self._abilities.values():
                    handle._publisher = sess.declare_publisher(handle.key)
            self._declare(sess)
            return True

    def _declare(self, sess: zenoh.Session) -> None:
        r, a, s = self.realm, self.agent_id, self.service_id
        put = self._enqueue
        self._decls += [
            sess.declare_subscriber(keys.control(r, a, s), guarded(
                lambda smp: put(self._on_control, payload_bytes(smp.payload)),
                keys.control(r, a, s), self._log)),
            sess.declare_queryable(keys.service_token(r, a, s),
                                   lambda q: put(self._on_descriptor_query, q)),
            sess.liveliness().declare_subscriber(
                keys.agent_token(r, a), lambda smp: put(self._on_agent_token, smp.kind),
                history=True),
        ]

    def close(self) -> None:
        """Leave: undeclare the token first (agents re-match at once), then everything."""
        if self.closed:
            return
        self.closed = True
        for obj in [self._token, *self._decls]:
            if obj is not None:
                with contextlib.suppress(Exception):
                    obj.undeclare()
        self._token, self._decls = None, []
        for need in self._needs.values():
            for link in need.links.values():
                with contextlib.suppress(Exception):
                    link.subscriber.undeclare()
            need.links.clear()
        for handle in self._abilities.values():
            if handle._publisher is not None:
                with contextlib.suppress(Exception):
                    handle._publisher.undeclare()
                handle._publisher = None
        self._worker.stop(1.0)
        with contextlib.suppress(queue.Full):
            self._samples.put_nowait(None)
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(1.0)
        if self.session is not None:
            release_session(self.session)
            self.session = None
        self._outcome.set()
        with self._cond:
            self._cond.notify_all()

    def __enter__(self) -> Service:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- matches
    def matches(self, need: str) -> list[Match]:
        """The abilities need ``need`` is connected to now, best first."""
        return list(self._need(need).matches)

    def wait_matched(self, need: str, count: int = 1, timeout: float = 5.0,
                     until: Callable[[list[Match]], bool] | None = None) -> list[Match]:
        """Wait until ``need`` has ``count`` matches (or ``until(matches)`` is true);
        ``TimeoutError`` saying what it has instead."""
        handle = self._need(need)
        test = until or (lambda ms: len(ms) >= count)
        deadline = time.monotonic() + timeout
        with self._cond:
            while not test(list(handle.matches)):
                left = deadline - time.monotonic()
                if left <= 0 or self.closed:
                    have = ", ".join(m.key for m in handle.matches) or "nothing"
                    raise UmaTimeoutError(f"service {self.service_id!r}: need {need!r} not matched "
                                          f"as wanted within {timeout:g} s (connected to {have})")
                self._cond.wait(left)
            return list(handle.matches)

    def wait_registered(self, timeout: float = 5.0) -> bool:
        """Whether the agent accepted the current descriptor within ``timeout`` s."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._registered_revision != self._revision and not self.closed:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return self._registered_revision == self._revision

    def _need(self, name: str) -> NeedHandle:
        try:
            return self._needs[name]
        except KeyError:
            raise UmaError(f"service {self.service_id!r} has no need {name!r} (has: "
                           f"{', '.join(self._needs) or 'none'})") from None

    # -- the worker (owns registration and subscriptions)
    def _enqueue(self, fn: Callable[..., None], *args: Any) -> None:
        self._worker.put(fn, *args)

    def _on_agent_found(self) -> None:
        if not self._agent_present:
            self._on_agent_token(zenoh.SampleKind.PUT)

    def _on_agent_token(self, kind: zenoh.SampleKind) -> None:
        if kind == zenoh.SampleKind.PUT:
            self._agent_present = True
            self._backoff = RETRY_MIN_S
            self._registered_revision = -1  # a (re)started agent needs the registration
            self._register()
        else:
            self._agent_present = False
            self._registered_revision = -1
            log.warning("service %s: agent %s is gone; keeping current connections, will "
                        "register again when it is back", self.service_id, self.agent_id)

    def _retry(self) -> None:
        now = time.monotonic()
        if self.session is None:
            if now >= self._next_open:
                self._next_open = now + OPEN_RETRY_S
                self._attach()
            return
        if not self._agent_present and now >= self._next_probe:
            self._probe_agent()
            self._next_probe = now + PROBE_S
        if (self._agent_present and not self._registering and self.error is None
                and self._registered_revision != self._revision and now >= self._next_try):
            self._register()

    def _probe_agent(self) -> None:
        """Ask for the agent's token (a liveliness subscription declared before the links
        were up may never report a token that already existed)."""
        assert self.session is not None

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self._enqueue(self._on_agent_found)
        self.session.liveliness().get(keys.agent_token(self.realm, self.agent_id), on_reply,
                                      timeout=1.0)

    def _register(self) -> None:
        if self._registering or self.error is not None or not self._agent_present:
            return
        assert self.session is not None
        with self._lock:
            revision = self._revision
            desc = encode_descriptor(self._descriptor_locked())
        connected = {n.name: [m.key for m in n.matches] for n in self._needs.values()}
        self._registering = True
        answered: list[bool] = []

        def on_reply(reply: zenoh.Reply) -> None:
            answered.append(True)
            ok, data = (True, reply.ok.payload.to_bytes()) if reply.ok is not None else (
                False, reply.err.payload.to_bytes())
            self._enqueue(self._on_register_reply, revision, data, ok)

        def on_done() -> None:
            self._enqueue(self._on_register_done, bool(answered))
        self.session.get(keys.agent_register(self.realm, self.agent_id),
                         zenoh.handlers.Callback(on_reply, on_done),
                         payload=register_request(desc, self.instance, revision, connected,
                                                  self._control_key, self._challenge),
                         timeout=REGISTER_TIMEOUT_S)

    def _on_register_reply(self, revision: int, data: bytes, ok_reply: bool) -> None:
        try:
            reply = parse_reply(data)
        except DecodeError as exc:
            reply = RegisterReply(False, f"unreadable reply from agent ({exc})", True)
        ok, error, retry = reply.ok, reply.error, reply.retry
        if reply.challenge is not None:
            self._challenge = reply.challenge
        if ok and ok_reply:
            self._agent_epoch, self._control_key = reply.epoch, reply.key
            pending, self._unverified = self._unverified, {}
            for kept in pending.values():
                self._on_control(kept)
            first = self._token is None
            if first:
                assert self.session is not None
                self._token = self.session.liveliness().declare_token(
                    keys.service_token(self.realm, self.agent_id, self.service_id))
            with self._cond:
                self._registered_revision = revision
                self._cond.notify_all()
            self._backoff = RETRY_MIN_S
            self._outcome.set()
            log.info("service %s registered with agent %s (revision %d)", self.service_id,
                     self.agent_id, revision)
        elif reply.renew:
            self._renew_instance()
        elif retry or "Timeout" in error:
            self._schedule_retry()
        else:
            self.error = (f"service {self.service_id!r} refused by agent {self.agent_id!r}: "
                          f"{error}")
            log.error("%s", self.error)
            self._outcome.set()
            with self._cond:
                self._cond.notify_all()

    def _renew_instance(self) -> None:
        """The agent holds this instance without a key it gave (it restarted and adopted
        us): register as a new instance, which the duplicate check lets through because
        our own descriptor queryable answers with it."""
        self.instance = secrets.token_hex(8)
        self._control_key = self._challenge = None
        self._next_try = 0.0
        log.info("service %s: agent %s holds this instance without its key; registering as "
                 "instance %s", self.service_id, self.agent_id, self.instance)

    def _on_register_done(self, answered: bool) -> None:
        self._registering = False
        if not answered:
            self._schedule_retry()

    def _schedule_retry(self) -> None:
        self._next_try = time.monotonic() + self._backoff
        self._backoff = min(RETRY_MAX_S, self._backoff * 2)

    def _on_descriptor_query(self, query: zenoh.Query) -> None:
        try:
            with self._lock:
                desc = encode_descriptor(self._descriptor_locked())
            connected = {n.name: [m.key for m in n.matches] for n in self._needs.values()}
            query.reply(query.key_expr, descriptor_reply(desc, self.instance,
                                                         self._revision, connected))
        finally:
            query.drop()

    def _on_control(self, data: bytes) -> None:
        """Apply a control message that comes from this service's agent: signed with the key
        it gave us, of its current epoch, the next in sequence (``agent.protocol.
        registration``, "Agent -> its local services")."""
        try:
            ctl = parse_control(data, self.realm, self._control_key)
        except UnverifiedControlError as exc:
            self._unverified_control(data, str(exc))
            return
        except DecodeError as exc:
            self._refuse_control("malformed", f"dropped: {exc}")
            return
        if ctl.epoch != self._agent_epoch:
            self._refuse_control("epoch", f"epoch {ctl.epoch} is not agent {self.agent_id}'s "
                                 f"current one ({self._agent_epoch})")
            return
        need = self._needs.get(ctl.need)
        if need is None:
            self._refuse_control("need", f"names unknown need {ctl.need!r}")
            return
        now = time.monotonic()
        if ctl.epoch == need.last[0]:
            if ctl.seq <= need.last[1]:
                return  # older than what was applied
            if ctl.seq > need.last[1] + int((now - need.last_at) * 1000) + SEQ_WINDOW:
                self._refuse_control("seq", f"seq {ctl.seq} jumps ahead of {need.last[1]} "
                                     "by more than the time passed")
                return
        need.last, need.last_at = (ctl.epoch, ctl.seq), now
        self._apply(need, ctl.matches, ctl.satisfied)

    def _unverified_control(self, data: bytes, reason: str) -> None:
        """Keep it until the next registration gives a key (the agent may have signed it
        with a key whose reply has not arrived), and register again to get one."""
        need = control_need(data)
        if need in self._needs:
            self._unverified[need] = data
        if self._control_key is None:  # the usual race with the register reply: no warning
            self.control_refused["no key yet"] = self.control_refused.get("no key yet", 0) + 1
        else:
            self._refuse_control("signature", reason)
        now = time.monotonic()
        if now >= self._next_reverify and self._agent_present:
            self._next_reverify = now + REVERIFY_S
            self._registered_revision = -1

    def _refuse_control(self, reason: str, detail: str) -> None:
        n = self.control_refused[reason] = self.control_refused.get(reason, 0) + 1
        self._log.warning(f"control {keys.control(self.realm, self.agent_id, self.service_id)}",
                          f"refused ({reason}, {n} so far): {detail}")

    def _apply(self, need: NeedHandle, matches: tuple[Match, ...], satisfied: bool) -> None:
        """Subscribe to exactly ``matches`` (keeping links that stay)."""
        assert self.session is not None
        wanted = {m.key: m for m in matches}
        for key in list(need.links):
            if key not in wanted:
                with contextlib.suppress(Exception):
                    need.links.pop(key).subscriber.undeclare()
        for key, m in wanted.items():
            link = need.links.get(key)
            if link is not None:
                link.match = m  # attributes may have changed
                continue
            link = _Link(m)
            link.subscriber = self.session.declare_subscriber(
                key, lambda smp, n=need, ln=link: self._on_data(n, ln, smp))
            need.links[key] = link
        with self._cond:
            if need.matches != matches:
                log.info("service %s: need %s -> %s", self.service_id, need.name,
                         ", ".join(m.key for m in matches) or "nothing")
            need.matches, need.satisfied = matches, satisfied
            self._cond.notify_all()

    # -- data
    def _on_data(self, need: NeedHandle, link: _Link, smp: zenoh.Sample) -> None:
        limit = MAX_IMAGE_BYTES if need.need.type == "image" else MAX_MESSAGE_BYTES
        try:
            self._samples.put_nowait((need, link, payload_bytes(smp.payload, limit)))
        except DecodeError as exc:
            self._log.warning(f"data {link.match.key}", f"dropped: {exc}")
        except queue.Full:
            self._log.warning(f"service {self.service_id} need {need.name}",
                              "callback queue full (on_sample too slow); samples dropped")

    def _dispatch(self) -> None:
        while True:
            item = self._samples.get()
            if item is None or self.closed:
                return
            need, link, data = item
            if link.match.key not in need.links:
                continue  # disconnected meanwhile
            try:
                m = decode_measurement(data, expected_type=need.need.type)
            except DecodeError as exc:
                self._log.warning(f"data {link.match.key}", f"dropped: {exc}")
                continue
            m.edge, m.source, m.attributes = (link.match.edge, link.match.service_id,
                                              link.match.attributes)
            if need.on_sample is None:
                continue
            try:
                need.on_sample(m)
            except Exception as exc:
                if self._log.warning(f"service {self.service_id} need {need.name}",
                                     f"on_sample raised {type(exc).__name__}: {exc}"):
                    log.debug("on_sample traceback", exc_info=True)
