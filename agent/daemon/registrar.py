"""The agent's registrar: the daemon's side of the registration protocol
(``agent.protocol.registration``, whose docstring specifies it, steps 2 to 4).

- **registration** (``uma/R/agent/A/register``): a valid registration is admitted into the
  agent's ``RealmView`` and the agent is told (:meth:`RegistrarHost.service_admitted`);
  an invalid one is refused, saying why;
- **a lost answer**: a registration of the instance already held but not yet live (no
  token), without its key, is refused with ``retry``: the service may have stopped waiting
  before our answer with the key came; the held one expires without its token and the
  retry is then accepted as new;
- **hijacks**: a registration of a live instance is accepted only with that instance's key.
  Keys live exactly as long as the registration they were given with (nothing evicts the
  key of a held service); an instance held without a key (re-adopted after this agent
  restarted) is refused with ``renew``: the real service then registers as a new
  instance, which passes the duplicate check below because its own queryable answers
  with that new instance, while a stranger's new instance finds the real service
  answering;
- **duplicates**: a second process registering a service id already held by another
  instance is *pending* while the holder is asked on ``uma/R/svc/A/S`` whether it still
  answers (``DUPLICATE_CHECK_S``): refused if anything answers there with another instance
  than the newcomer's, else it replaces the holder.  A
  registration for an id being checked is refused with ``retry``;
- **token watch**: every service token ``uma/R/svc/*/*`` (local and remote): a PUT makes
  the service present; a DELETE is a **departure check** first: the service is asked on
  ``uma/R/svc/A/S`` (``DEPARTURE_CHECK_S``), and only one that does not answer with the
  instance we know is dropped (a killed service has no queryable left: the check costs one
  local lookup and failover stays fast; a spurious DELETE keeps a live one);
- **adoption**: a live local service the agent holds no registration for (dropped
  meanwhile, or the agent restarted before it re-registered) is re-adopted from its own
  answer on ``uma/R/svc/A/S``;
- **anti-entropy** (:meth:`Registrar.resync`, every ``RESEND_S``): the live service tokens
  are asked for; tokens the subscription missed count as PUTs, a service believed alive
  whose token is absent is checked; a registration whose token never came is dropped after
  ``PENDING_TIMEOUT_S`` (:meth:`Registrar.expire_pending`).

- **floods** (:class:`RegistrationGate`): a request larger than ``MAX_REGISTRATION_BYTES``
  is refused unread; the rest are rated per service id before they reach the worker.  A
  re-registration that carries the key of the instance held draws on its own service's
  bucket, which no stranger can drain; every other one (new services, new instances,
  refusals to come) on a smaller bucket per service id and one shared by all of them.
  A refusal says ``retry``: a real service registers again after its back-off.

Everything else runs in the agent's worker: Zenoh callbacks and replies are handed to it
with ``put``.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import logging
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import zenoh

from agent.daemon.realm_view import RealmView
from agent.protocol import keys
from agent.protocol.registration import (
    CHALLENGE_BYTES,
    CHALLENGE_TTL_S,
    CONTROL_KEY_BYTES,
    MAX_REGISTRATION_BYTES,
    Proof,
    Registration,
    parse_descriptor_answer,
    parse_descriptor_reply,
    parse_register_request,
    peek_register,
    reply_error,
    reply_ok,
)
from agent.runtime.limits import Coalescer, SenderLimits, token_limits
from agent.runtime.logs import RateLimitedLog
from agent.runtime.session import ask_all
from schemas.codec import DecodeError

log = logging.getLogger("uma.agent")

#: how long a duplicate-id check waits for the first holder of the id to answer
DUPLICATE_CHECK_S = 0.5
#: how long a departure check waits for a service whose token went to answer on its
#: descriptor queryable (a killed or unreachable one has no queryable: the get ends at once)
DEPARTURE_CHECK_S = 1.0
#: seconds to wait for a service's descriptor answer when adopting it
ADOPT_TIMEOUT_S = 2.0
#: registrations of a held instance with its key, per service id: at once, then per second
PROVEN_BURST, PROVEN_RATE = 20, 5.0
#: other registrations (new services or instances, and would-be hijacks): per service id,
#: and for all service ids together (a host starting a hundred services at once is served
#: in seconds; the refused retry after their back-off)
UNPROVEN_BURST, UNPROVEN_RATE = 5, 1.0
UNPROVEN_TOTAL_BURST, UNPROVEN_TOTAL_RATE = 64, 20.0


class RegistrarHost(Protocol):
    """What the registrar tells the agent."""

    def service_admitted(self, reg: Registration, new_instance: bool) -> None:
        """A local service registered (again; ``new_instance``: by another process)."""

    def service_left(self, service_id: str) -> None:
        """A local service is gone."""

    def realm_changed(self) -> None:
        """The offers or the local needs changed: re-match."""

    def snapshot_changed(self) -> None:
        """The local services changed: publish a new snapshot."""


class Challenges:
    """The challenges an agent gives with its answers to registrations, checked without
    keeping any: the time issued and an HMAC of it with the service id and instance under
    a secret of this agent run, so a stranger can neither make one nor reuse one for
    another instance, and none outlives ``CHALLENGE_TTL_S``."""

    def __init__(self) -> None:
        self._secret = secrets.token_bytes(16)

    def issue(self, sid: str, instance: str) -> bytes:
        issued = int(time.monotonic() * 1000).to_bytes(8, "big")
        return issued + self._tag(issued, sid, instance)

    def fresh(self, sid: str, instance: str, challenge: bytes) -> bool:
        issued = challenge[:8]
        age_ms = int(time.monotonic() * 1000) - int.from_bytes(issued, "big")
        return (0 <= age_ms <= CHALLENGE_TTL_S * 1000
                and hmac.compare_digest(challenge[8:], self._tag(issued, sid, instance)))

    def _tag(self, issued: bytes, sid: str, instance: str) -> bytes:
        return hmac.new(self._secret, issued + f"{sid}/{instance}".encode(),
                        hashlib.sha256).digest()[:CHALLENGE_BYTES - 8]


class RegistrationGate:
    """Size and rate bounds on registrations, checked on Zenoh's thread before any decoding
    of the descriptor (module docstring, "floods"); refusals are counted by reason."""

    def __init__(self, agent_id: str, bad: RateLimitedLog,
                 proven: Callable[[str, str, Proof | None], bool]) -> None:
        self.agent_id = agent_id
        self._bad = bad
        self._proves = proven
        self._proven = SenderLimits(PROVEN_RATE, PROVEN_BURST)
        self._unproven = SenderLimits(UNPROVEN_RATE, UNPROVEN_BURST,
                                      (UNPROVEN_TOTAL_RATE, UNPROVEN_TOTAL_BURST))
        self._count_lock = threading.Lock()
        #: registrations refused here, by reason ("size", "rate")
        self.refused: dict[str, int] = {}

    def refusal(self, data: bytes | None) -> str | None:
        """Why this request is refused unread (None: it goes on to the worker)."""
        if data is not None and len(data) > MAX_REGISTRATION_BYTES:
            return self._count("size", f"{len(data)} bytes, more than "
                               f"{MAX_REGISTRATION_BYTES}")
        claim = peek_register(data) if data is not None else None
        sid = claim.service_id if claim is not None else "?"
        proven = claim is not None and self._proves(*claim)
        over = (self._proven if proven else self._unproven).allow(sid)
        if over is None:
            return None
        return self._count("rate", f"service id {sid!r}: more registrations than "
                           + ("its own bound" if over == "sender" else "the bound of all new "
                              "or unproven registrations together") + "; retry")

    def _count(self, reason: str, detail: str) -> str:
        with self._count_lock:
            n = self.refused[reason] = self.refused.get(reason, 0) + 1
        self._bad.warning(f"agent {self.agent_id} registrations",
                          f"refused ({reason}, {n} so far): {detail}")
        return f"registration refused: {detail}"


@dataclass
class PendingRegistration:
    """A registration waiting for the duplicate check (does the first holder answer?)."""

    query: zenoh.Query
    reg: Registration
    holder_answered: bool = False


class Registrar:
    """Registrations, duplicates, service tokens, departures, adoption (module docstring)."""

    def __init__(self, view: RealmView, epoch: int, put: Callable[..., None],
                 host: RegistrarHost, bad: RateLimitedLog) -> None:
        self.view = view
        self.realm, self.agent_id = view.realm, view.agent_id
        self.epoch = epoch
        self._put = put
        self._host = host
        self._log = bad
        self._session: zenoh.Session | None = None
        self._decls: list[Any] = []
        self._pending: dict[str, PendingRegistration] = {}
        #: services whose token went, being checked: (agent, service) -> check number
        self._checking: dict[tuple[str, str], int] = {}
        self._checks = 0
        #: local services whose descriptor is being re-fetched (their token came back)
        self._adopting: set[str] = set()
        #: service id -> (instance, the key control messages to it are signed with), for
        #: the registrations held (dropped with them: see ``_prune_keys``)
        self._control_keys: dict[str, tuple[str, bytes]] = {}
        #: registrations refused for an instance id without its key
        self.hijacks_refused = 0
        self.challenges = Challenges()
        #: service token events, coalesced per token and rated per agent (token churn)
        self.tokens = Coalescer(put, self._on_service_token, token_limits(),
                                lambda sender, why: token_churn(self._log, sender, why,
                                                                self.tokens.refused))
        self.gate = RegistrationGate(self.agent_id, bad, self._proves)

    def declare(self, session: zenoh.Session) -> None:
        """Answer registrations and watch the service tokens from now on."""
        self._session = session
        self._decls += [
            session.declare_queryable(keys.agent_register(self.realm, self.agent_id),
                                      self._on_register_query),
            session.liveliness().declare_subscriber(
                keys.service_tokens(self.realm), lambda smp: self.tokens.offer(
                    str(smp.key_expr), _token_sender(str(smp.key_expr), self.realm), smp),
                history=True),
        ]

    def close(self) -> None:
        for decl in self._decls:
            with contextlib.suppress(Exception):
                decl.undeclare()
        self._decls = []

    def _get(self, key: str, on_reply: Callable[[zenoh.Reply], None],
             on_done: Callable[[], None], timeout: float, every_reply: bool = False) -> None:
        """Ask ``key``; ``on_reply`` (Zenoh's thread) for each reply, then ``on_done`` in
        the worker.  ``every_reply``: two processes may answer on one key, keep both."""
        assert self._session is not None
        extra = {"consolidation": zenoh.ConsolidationMode.NONE} if every_reply else {}
        self._session.get(key, zenoh.handlers.Callback(on_reply, lambda: self._put(on_done)),
                          timeout=timeout, **extra)

    # -- registrations and duplicates
    def _on_register_query(self, query: zenoh.Query) -> None:
        """Zenoh's thread: refuse a flood here, hand the rest to the worker."""
        data = _payload(query)
        refusal = self.gate.refusal(data)
        if refusal is None:
            self._put(self.on_register, query, data)
        else:
            _refuse(query, refusal, retry=True)

    def on_register(self, query: zenoh.Query, data: bytes | None) -> None:
        try:
            if data is None:
                raise DecodeError("empty registration")
            reg = parse_register_request(data, self.agent_id)
        except DecodeError as exc:
            self._log.warning(f"registration on {query.key_expr}", f"refused: {exc}")
            _refuse(query, f"registration refused: {exc}")
            return
        sid = reg.descriptor.service_id
        if sid in self._pending:
            _refuse(query, f"service id {sid!r}: a registration is being checked; retry",
                    retry=True)
            return
        entry = self.view.local.get(sid)
        if entry is not None and entry.instance == reg.instance and not self._proven(reg):
            self._refuse_unproven(query, reg)
            return
        if entry is not None and entry.instance == reg.instance and reg.revision < entry.revision:
            _refuse(query, f"service id {sid!r}: revision {reg.revision} is older than the "
                    f"one held ({entry.revision}): a replay")
            return
        if entry is None or entry.instance == reg.instance:
            self._accept(query, reg)
            return
        # another process holds this id: refuse if it still answers, else replace it
        self._pending[sid] = PendingRegistration(query, reg)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self._put(self._on_holder_reply, sid, reply.ok.payload.to_bytes())
        self._get(keys.service_token(self.realm, self.agent_id, sid), on_reply,
                  lambda: self._on_holder_done(sid), DUPLICATE_CHECK_S, every_reply=True)

    def _refuse_unproven(self, query: zenoh.Query, reg: Registration) -> None:
        """A registration of the instance held that does not prove the key it was given."""
        sid, instance = reg.descriptor.service_id, reg.instance
        held = self._control_keys.get(sid)
        keyed = held is not None and held[0] == instance
        if keyed and reg.proof is not None and reg.proof.verifies(held[1]):
            # the right key on a challenge too old: the real service, long after its last
            # registration; it signs a fresh one
            _refuse(query, f"service id {sid!r}: the challenge is stale; retry with this one",
                    retry=True, challenge=self.challenges.issue(sid, instance))
            return
        if (self.agent_id, sid) not in self.view.live_services:
            # no token yet: our answer with the key may have come after the service
            # stopped waiting.  Not told from a hijack, so not accepted; but temporary:
            # the registration expires without its token and the next one is new
            _refuse(query, f"service id {sid!r}: instance {instance!r} is registered, "
                    "waiting for its token, and this registration does not carry its key; "
                    "retry", retry=True)
            return
        self.hijacks_refused += 1
        self._log.warning(f"service {sid}", "registration refused: it names the running "
                          "instance's id without that instance's key "
                          f"({self.hijacks_refused} refused so far)")
        _refuse(query, f"service id {sid!r}: instance {instance!r} is registered and this "
                "registration does not carry its key"
                + ("" if keyed else "; register as a new instance"), renew=not keyed)

    def _on_holder_reply(self, sid: str, data: bytes) -> None:
        pending = self._pending.get(sid)
        if pending is None:
            return
        try:
            if parse_descriptor_reply(data) != pending.reg.instance:
                pending.holder_answered = True
        except DecodeError as exc:
            self._log.warning(f"service {sid}", f"bad descriptor reply: {exc}")

    def _on_holder_done(self, sid: str) -> None:
        pending = self._pending.pop(sid, None)
        if pending is None:
            return
        if pending.holder_answered:
            error = (f"duplicate service id {sid!r} on agent {self.agent_id!r} in realm "
                     f"{self.realm!r}: another process already runs it")
            self._log.warning(f"service {sid}", f"second registration refused ({error})")
            _refuse(pending.query, error)
        else:
            log.info("service %s: previous instance does not answer; replaced", sid)
            self._accept(pending.query, pending.reg)

    def _proven(self, reg: Registration) -> bool:
        """Whether a registration of the instance held proves the key it was given (an
        instance held without a key, i.e. re-adopted, cannot prove anything)."""
        return self._proves(reg.descriptor.service_id, reg.instance, reg.proof)

    def _proves(self, sid: str, instance: str, proof: Proof | None) -> bool:
        """Whether ``proof`` signs a fresh challenge of ours with the key of ``instance``,
        the instance of ``sid`` held (also called on Zenoh's threads: reads only)."""
        held = self._control_keys.get(sid)
        return (proof is not None and held is not None and held[0] == instance
                and self.challenges.fresh(sid, instance, proof.challenge)
                and proof.verifies(held[1]))

    def control_key(self, sid: str) -> bytes | None:
        """The key control messages to local service ``sid`` are signed with (None: it
        never registered with this agent, e.g. re-adopted: it registers on the first
        message it cannot verify)."""
        entry, held = self.view.local.get(sid), self._control_keys.get(sid)
        return held[1] if entry and held and held[0] == entry.instance else None

    def _issue_key(self, sid: str, instance: str) -> bytes:
        """The key of the instance held (a new one for a new instance)."""
        held = self._control_keys.get(sid)
        if held is None or held[0] != instance:
            held = self._control_keys[sid] = (instance, secrets.token_bytes(CONTROL_KEY_BYTES))
        return held[1]

    def _prune_keys(self) -> None:
        """Keep a key for each registration held, none for one that ended (as many keys as
        services)."""
        for sid in [s for s in self._control_keys if s not in self.view.local]:
            del self._control_keys[sid]

    def _accept(self, query: zenoh.Query, reg: Registration) -> None:
        self._prune_keys()
        self._admit(reg)
        sid = reg.descriptor.service_id
        key = self._issue_key(sid, reg.instance)
        try:
            query.reply(query.key_expr, reply_ok(self.epoch, key,
                                                 self.challenges.issue(sid, reg.instance)))
        finally:
            query.drop()
        log.info("service %s registered with agent %s (revision %d)",
                 reg.descriptor.service_id, self.agent_id, reg.revision)

    def _admit(self, reg: Registration) -> None:
        """Take a registration into the view, and tell the agent."""
        old = self.view.local.get(reg.descriptor.service_id)
        new_instance = old is None or old.instance != reg.instance
        if self.view.register_local(reg, time.monotonic()):
            self._host.realm_changed()
        self._host.service_admitted(reg, new_instance)
        self._host.snapshot_changed()

    def expire_pending(self, now: float) -> None:
        """Drop registrations whose token never appeared."""
        for sid in self.view.expired_pending(now):
            log.warning("service %s registered but never declared its liveliness token; "
                        "dropped", sid)
            self.view.remove_local(sid)
            self._host.service_left(sid)

    # -- service tokens and departures
    def _on_service_token(self, smp: zenoh.Sample) -> None:
        parsed = keys.parse_service_token(str(smp.key_expr), self.realm)
        if parsed is None:
            self._log.warning(f"liveliness {smp.key_expr}", "not a service token key")
            return
        if smp.kind == zenoh.SampleKind.PUT:
            self._service_token_put(*parsed)
        else:
            self._check_departure(*parsed)

    def _service_token_put(self, agent_id: str, sid: str) -> None:
        self._checking.pop((agent_id, sid), None)  # back: a pending check is moot
        if self.view.service_alive(agent_id, sid):
            self._host.realm_changed()
        if agent_id == self.agent_id:
            self._host.snapshot_changed()
            if sid not in self.view.local:
                self._adopt(sid)  # we dropped it meanwhile: take it back

    def resync(self) -> None:
        """Anti-entropy: ask for the live service tokens and reconcile (a liveliness
        subscription declared before its links were up may not get the tokens that
        existed then; a DELETE and a PUT may have crossed)."""
        assert self._session is not None
        found: list[str] = []

        def on_service(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                found.append(str(reply.ok.key_expr))
        self._session.liveliness().get(keys.service_tokens(self.realm), zenoh.handlers.Callback(
            on_service, lambda: self._put(self._on_resync_service_tokens, found)),
            timeout=1.0)

    def _on_resync_service_tokens(self, token_keys: list[str]) -> None:
        """Tokens we missed count as PUTs; a local service with a live token but no
        registration is re-adopted; a service we believe alive whose token is not there
        is checked (it is dropped only if it does not answer)."""
        live: set[tuple[str, str]] = set()
        for key in token_keys:
            parsed = keys.parse_service_token(key, self.realm)
            if parsed is None:
                self._log.warning(f"liveliness {key}", "not a service token key")
                continue
            live.add(parsed)
        for agent_id, sid in live:
            if (agent_id, sid) not in self.view.live_services:
                self._service_token_put(agent_id, sid)
            elif agent_id == self.agent_id and sid not in self.view.local:
                self._adopt(sid)
        for agent_id, sid in self.view.live_services - live:
            self._check_departure(agent_id, sid)

    def _check_departure(self, agent_id: str, sid: str) -> None:
        """A service token's DELETE: ask the service itself before tearing anything down
        (a DELETE may be spurious)."""
        k = (agent_id, sid)
        if k not in self.view.live_services and not (
                agent_id == self.agent_id and sid in self.view.local):
            return  # nothing to tear down
        if k in self._checking:
            return
        self._checks += 1
        check = self._checking[k] = self._checks
        assert self._session is not None
        ask_all(self._session, keys.service_token(self.realm, agent_id, sid), DEPARTURE_CHECK_S,
                lambda answers: self._put(lambda: self._on_departure_checked(k, check, answers)),
                every_reply=True)

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
                self._log.warning(f"service {agent_id}/{sid}", f"bad descriptor reply: {exc}")
                continue
            if expected is None or instance == expected:
                self._log.warning(f"service {agent_id}/{sid}",
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
        if self.view.service_gone(agent_id, sid):
            self._host.realm_changed()
        if local:
            log.info("service %s left agent %s", sid, self.agent_id)
            self._host.service_left(sid)
        if agent_id == self.agent_id:
            self._host.snapshot_changed()

    # -- adoption
    def _adopt(self, sid: str) -> None:
        """Re-fetch a live local service's descriptor from the service itself."""
        if sid in self._adopting:
            return
        self._adopting.add(sid)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self._put(self._on_adopt_reply, sid, reply.ok.payload.to_bytes())
        self._get(keys.service_token(self.realm, self.agent_id, sid), on_reply,
                  lambda: self._adopting.discard(sid), ADOPT_TIMEOUT_S)

    def _on_adopt_reply(self, sid: str, data: bytes) -> None:
        if sid in self.view.local or (self.agent_id, sid) not in self.view.live_services:
            return  # registered by itself meanwhile, or gone again
        try:
            reg = parse_descriptor_answer(data, self.agent_id)
        except DecodeError as exc:
            self._log.warning(f"service {sid}", f"cannot re-adopt it: {exc}")
            return
        if reg.descriptor.service_id != sid:
            self._log.warning(f"service {sid}", "cannot re-adopt it: it answers as "
                              f"{reg.descriptor.service_id!r}")
            return
        self._admit(reg)
        log.info("service %s re-adopted by agent %s: its token came back (revision %d)",
                 sid, self.agent_id, reg.revision)


def _refuse(query: zenoh.Query, error: str, retry: bool = False, renew: bool = False,
            challenge: bytes | None = None) -> None:
    try:
        query.reply_err(reply_error(error, retry, renew, challenge))
    finally:
        query.drop()


def _payload(query: zenoh.Query) -> bytes | None:
    return None if query.payload is None else query.payload.to_bytes()


def _token_sender(key: str, realm: str) -> str:
    """Who a service token's events are rated as: the agent id in its key."""
    parsed = keys.parse_service_token(key, realm)
    return parsed[0] if parsed else "?"


def token_churn(limited_log: RateLimitedLog, sender: str, why: str, refused: int) -> None:
    """Say that token events of ``sender`` were refused (rate-limited lines)."""
    limited_log.warning(f"liveliness of agent {sender[:64]}",
                        f"token churn: events refused ({why} bound, {refused} so far); the "
                        "periodic resync repairs what they would have told")
