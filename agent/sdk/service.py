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
attributes) filled in.  ``m.t_ns`` is on this host's clock (``svc.now_ns()``) even when
the sample comes from a service on another host: it is moved by the offset of that host's
agent's clock, measured by round trips as a ``Client`` measures it
(:mod:`agent.sdk.sampleclock`; until it is measured within 2 ms, that agent's samples are
held back and counted in ``svc.links.clocks.unsynced``; ``m.time_error_ns`` is the bound).
Callbacks run on the service's own dispatch thread, one at a time, never on a Zenoh thread;
an exception in a callback is logged, not fatal.

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

``Service`` is a facade over parts with one job each: its presence with the agent and the
registration of its descriptor (:mod:`agent.sdk.presence`), the verification of its
agent's control messages (:mod:`agent.sdk.control`) and the subscriptions of its needs with
the dispatch of their samples (:mod:`agent.sdk.needs`).  It holds what they share: the
declared abilities and needs, their revision, the session and the worker thread.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import zenoh
from pydantic import ValidationError

from agent.errors import InvalidInputError, UmaError, UmaTimeoutError
from agent.protocol import keys
from agent.protocol.query import skew_from_env
from agent.protocol.registration import Match
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
from agent.sdk.control import SEQ_WINDOW, ControlGate
from agent.sdk.needs import NeedHandle, NeedLinks, OnSample
from agent.sdk.presence import Presence
from schemas.codec import (
    Measurement,
    encode_measurement,
    encode_pose,
    peek_time,
    validation_summary,
)
from schemas.models import Ability, Need, ServiceDescriptor

__all__ = ["SEQ_WINDOW", "AbilityHandle", "NeedHandle", "Service"]

log = logging.getLogger("uma.service")

#: how often the worker sees whether to attach, probe for the agent or register again
RETRY_TICK_S = 0.05
#: seconds between attempts to reach an agent that did not answer at start()
OPEN_RETRY_S = 0.25


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
        """Publish one pose (``pose6d`` abilities); ``InvalidInputError`` (a ``ValueError``)
        names a bad field."""
        if self.ability.type != "pose6d":
            raise UmaError(f"ability {self.name!r} is {self.ability.type}; use "
                           "publish_measurement()")
        try:
            data = encode_pose(t_ns, position, quaternion, covariance, seq=self._seq + 1)
        except ValueError as exc:
            raise InvalidInputError(f"ability {self.name!r}: {exc}") from None
        self._seq += 1  # only once the sample is valid: a refused one leaves no gap
        self._put(data)

    def publish_measurement(self, m: Measurement) -> None:
        """Publish a measurement of any type (must be this ability's type);
        ``InvalidInputError`` (a ``ValueError``) names a bad field."""
        if m.type != self.ability.type:
            raise UmaError(f"ability {self.name!r} publishes {self.ability.type}, "
                           f"not {m.type}")
        numbered = m.seq is None
        if numbered:
            m.seq = self._seq + 1
        try:
            data = encode_measurement(m)
        except ValueError as exc:
            if numbered:
                m.seq = None
            raise InvalidInputError(f"ability {self.name!r}: {exc}") from None
        if numbered:
            self._seq += 1  # only once the sample is valid: a refused one leaves no gap
        self._put(data)

    def publish_encoded(self, data: bytes) -> None:
        """Publish a sample that is already encoded, byte for byte (``uma play`` replays a
        recording's exact bytes); ``DecodeError`` if its envelope is not a measurement of
        this ability's type."""
        peek_time(data, self.ability.type)
        self._put(data)

    def update(self, **attributes: Any) -> None:
        """Change advertised attributes at run time (re-advertised, re-matched)."""
        self._svc._update_ability(self, attributes)

    def _put(self, payload: bytes) -> None:
        pub = self._publisher
        if pub is None and self._svc.connecting:
            self.unsent += 1
            return
        if pub is None:  # attached since it was read: the publisher is there before the session
            pub = self._publisher
        if pub is None:
            raise UmaError(f"service {self._svc.service_id!r}: call start() before publishing "
                           f"on {self.name!r}" if not self._svc.closed else
                           f"service {self._svc.service_id!r} is closed")
        pub.put(payload)


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
        try:
            #: how far this host's clock is off the system clock: 0, but for tests that
            #: skew a host (agent.protocol.query.SKEW_ENV, read by its agent too)
            self.clock_skew_ns = skew_from_env()
        except ValueError as exc:
            raise InvalidInputError(str(exc)) from None
        _checked(ServiceDescriptor, f"service {service_id!r}", service_id=service_id,
                 agent_id=self.agent_id, attributes=self.attributes)
        self.session: zenoh.Session | None = None
        self.closed = False
        self._abilities: dict[str, AbilityHandle] = {}
        self._needs: dict[str, NeedHandle] = {}
        self._lock = threading.Lock()          # abilities/needs/revision vs the worker
        self._cond = threading.Condition()     # match changes, registration outcome
        self._revision = 0
        self._next_open = 0.0
        self._attaching = threading.Lock()
        self._decls: list[Any] = []
        self._started = False
        self._log = RateLimitedLog(log)
        #: the parts (module docstring)
        self.presence = Presence(self)
        self.control = ControlGate(self, self._log)
        self.links = NeedLinks(self, self._log)
        #: owns registration and subscriptions; retries every RETRY_TICK_S
        self._worker = Worker(f"uma-service-{self.service_id}-worker",
                              f"service {self.service_id}", log, self._retry, RETRY_TICK_S)

    @property
    def instance(self) -> str:
        """This run's instance id (a new one when the agent must be told apart from an
        adopted one)."""
        return self.presence.instance

    def now_ns(self) -> int:
        """This host's clock, the one its agent keeps and received samples' times are on
        (ns since the epoch); publish samples stamped on it."""
        return time.time_ns() + self.clock_skew_ns

    @property
    def error(self) -> str | None:
        """Why the agent refused this service for good (None: not refused)."""
        return self.presence.error

    @property
    def control_refused(self) -> dict[str, int]:
        """Control messages refused, by reason ("signature", "epoch", "seq", ...)."""
        return self.control.refused

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
            self._enqueue(self.presence.register)
        return handle

    def need(self, name: str, type: str, edge: tuple[str, str],
             where: str | None = None, prefer: str | None = None, min_count: int = 1,
             max_count: int = 1, on_sample: OnSample | None = None,
             standby: int = 0) -> NeedHandle:
        """Declare what this service wants; ``on_sample(m)`` receives each sample.

        ``standby``: how many next-best abilities to keep subscribed as well; a chosen one
        that falls silent is stood in for by them at once (``agent.sdk.needs``)."""
        need = _checked(Need, f"need {name!r}", name=name, type=type, edge=tuple(edge),
                        where=where, prefer=prefer, min_count=min_count, max_count=max_count,
                        standby=standby)
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
            self._enqueue(self.presence.register)
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
            self._enqueue(self.presence.register)

    # -- life cycle
    def start(self) -> Service:
        """Open the session, declare everything, register with the agent.

        Waits up to ``register_timeout`` s for the agent's answer; raises ``UmaError`` if
        it refuses (e.g. a duplicate service id).  If the agent is not there yet, returns
        anyway and registers when it appears.
        """
        if self.closed:
            raise UmaError(f"service {self.service_id!r} is closed; create a new one")
        if self._started:
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
        if not self.presence.outcome.wait(self.register_timeout):
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
        return self._started and self.session is None and not self.closed

    def _start_threads(self) -> None:
        self._started = True
        self._worker.start()
        self.links.start()

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
                for handle in self._abilities.values():
                    handle._publisher = sess.declare_publisher(handle.key)
                # last: a publish that finds no publisher but a session looks again
                # (AbilityHandle._put) and must then find its publisher
                self.session = sess
            self._declare(sess)
            return True

    def _declare(self, sess: zenoh.Session) -> None:
        r, a, s = self.realm, self.agent_id, self.service_id
        put = self._enqueue
        self._decls += [
            sess.declare_subscriber(keys.control(r, a, s), guarded(
                lambda smp: put(self.control.on_control, payload_bytes(smp.payload)),
                keys.control(r, a, s), self._log)),
            sess.declare_queryable(keys.service_token(r, a, s),
                                   lambda q: put(self.presence.on_descriptor_query, q)),
            sess.liveliness().declare_subscriber(
                keys.agent_token(r, a), lambda smp: put(self.presence.on_agent_token, smp.kind),
                history=True),
        ]

    def close(self) -> None:
        """Leave: undeclare the token first (agents re-match at once), then everything."""
        if self.closed:
            return
        self.closed = True
        for obj in [self.presence.token, *self._decls]:
            if obj is not None:
                with contextlib.suppress(Exception):
                    obj.undeclare()
        self.presence.token, self._decls = None, []
        for handle in self._abilities.values():
            if handle._publisher is not None:
                with contextlib.suppress(Exception):
                    handle._publisher.undeclare()
                handle._publisher = None
        self._worker.stop(1.0)
        self.links.close()
        if self.session is not None:
            release_session(self.session)
            self.session = None
        self.presence.outcome.set()
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
            while self.presence.registered_revision != self._revision and not self.closed:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return self.presence.registered_revision == self._revision

    def _need(self, name: str) -> NeedHandle:
        try:
            return self._needs[name]
        except KeyError:
            raise UmaError(f"service {self.service_id!r} has no need {name!r} (has: "
                           f"{', '.join(self._needs) or 'none'})") from None

    # -- the worker (owns registration and subscriptions)
    def _enqueue(self, fn: Callable[..., None], *args: Any) -> None:
        self._worker.put(fn, *args)

    def _retry(self) -> None:
        """The worker's tick: attach while there is no session, else let the presence
        probe and register."""
        if self.session is None:
            now = time.monotonic()
            if now >= self._next_open:
                self._next_open = now + OPEN_RETRY_S
                self._attach()
            return
        self.presence.tick()
