"""A service's standing with its agent: whether the agent is there (its liveliness token,
probed while unseen), registering the current descriptor (retried with back-off, again
whenever the agent restarts or the descriptor changes), the service's own token once
accepted, and the descriptor it answers with when an agent checks on it
(:mod:`agent.protocol.registration`).  Runs on the service's worker thread.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from typing import TYPE_CHECKING, Any

import zenoh

from agent.protocol import keys
from agent.protocol.registration import (
    RegisterReply,
    descriptor_reply,
    parse_reply,
    register_request,
)
from schemas.codec import DecodeError, encode_descriptor

if TYPE_CHECKING:
    from agent.sdk.service import Service

log = logging.getLogger("uma.service")

#: registration query timeout, and the retry back-off bounds
REGISTER_TIMEOUT_S = 2.0
RETRY_MIN_S, RETRY_MAX_S = 0.1, 1.0
#: while the agent's token is not seen, ask for it this often
PROBE_S = 1.0


class Presence:
    """Registration and presence of one service (module docstring)."""

    def __init__(self, svc: Service) -> None:
        self._svc = svc
        self.instance = secrets.token_hex(8)
        #: why the agent refused this service for good (None: not refused)
        self.error: str | None = None
        self.agent_present = False
        self.registered_revision = -1
        self.token: Any = None
        #: set once the agent answered the first registration (accepted or refused)
        self.outcome = threading.Event()
        self._registering = False
        self._next_try = 0.0
        self._next_probe = time.monotonic() + PROBE_S
        self._backoff = RETRY_MIN_S
        #: the challenge the agent's last answer gave (the next registration signs it)
        self._challenge: bytes | None = None

    def tick(self) -> None:
        """Probe for the agent while it is unseen; register what changed since."""
        now = time.monotonic()
        if not self.agent_present and now >= self._next_probe:
            self._probe_agent()
            self._next_probe = now + PROBE_S
        if (self.agent_present and not self._registering and self.error is None
                and self.registered_revision != self._svc._revision
                and now >= self._next_try):
            self.register()

    def on_agent_found(self) -> None:
        if not self.agent_present:
            self.on_agent_token(zenoh.SampleKind.PUT)

    def on_agent_token(self, kind: zenoh.SampleKind) -> None:
        svc = self._svc
        if kind == zenoh.SampleKind.PUT:
            self.agent_present = True
            self._backoff = RETRY_MIN_S
            self.registered_revision = -1  # a (re)started agent needs the registration
            self.register()
        else:
            self.agent_present = False
            self.registered_revision = -1
            log.warning("service %s: agent %s is gone; keeping current connections, will "
                        "register again when it is back", svc.service_id, svc.agent_id)

    def _probe_agent(self) -> None:
        """Ask for the agent's token (a liveliness subscription declared before the links
        were up may never report a token that already existed)."""
        svc = self._svc
        assert svc.session is not None

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                svc._enqueue(self.on_agent_found)
        svc.session.liveliness().get(keys.agent_token(svc.realm, svc.agent_id), on_reply,
                                     timeout=1.0)

    def register(self) -> None:
        svc = self._svc
        if self._registering or self.error is not None or not self.agent_present:
            return
        assert svc.session is not None
        with svc._lock:
            revision = svc._revision
            desc = encode_descriptor(svc._descriptor_locked())
        self._registering = True
        answers: list[tuple[bytes, bool]] = []

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:  # an acceptance is taken at once
                data = reply.ok.payload.to_bytes()
                if not answers or not answers[0][1]:
                    svc._enqueue(self.on_register_reply, revision, data, True)
                answers.insert(0, (data, True))
            else:
                answers.append((reply.err.payload.to_bytes(), False))

        def on_done() -> None:
            svc._enqueue(self._on_register_answers, revision, answers)
        svc.session.get(keys.agent_register(svc.realm, svc.agent_id),
                        zenoh.handlers.Callback(on_reply, on_done),
                        payload=register_request(desc, self.instance, revision,
                                                 self._connected(), svc.control.key,
                                                 self._challenge),
                        consolidation=zenoh.ConsolidationMode.NONE,
                        timeout=REGISTER_TIMEOUT_S)

    def _on_register_answers(self, revision: int, answers: list[tuple[bytes, bool]]) -> None:
        """Every answer to one registration, once its get ended: an acceptance (taken when
        it came) wins over refusals, and a temporary refusal over a final one, so one
        process answering in the agent's place cannot make the service give up (any
        process may declare a queryable on a plain realm; on a secured site only the
        agent's host can)."""
        self._registering = False
        if not answers:
            self._schedule_retry()
            return
        if answers[0][1]:
            return
        parsed = [(_parse_reply(data), data) for data, _ in answers]
        for rank in (lambda r: r.renew, lambda r: r.retry, lambda r: True):
            chosen = next((data for r, data in parsed if rank(r)), None)
            if chosen is not None:
                self.on_register_reply(revision, chosen, False)
                return

    def _connected(self) -> dict[str, list[str]]:
        return {n.name: [m.key for m in n.matches] for n in self._svc._needs.values()}

    def on_register_reply(self, revision: int, data: bytes, ok_reply: bool) -> None:
        svc = self._svc
        reply = _parse_reply(data)
        ok, error, retry = reply.ok, reply.error, reply.retry
        if reply.challenge is not None:
            self._challenge = reply.challenge
        if ok and ok_reply:
            svc.control.trust(reply.epoch, reply.key)
            if self.token is None:
                assert svc.session is not None
                self.token = svc.session.liveliness().declare_token(
                    keys.service_token(svc.realm, svc.agent_id, svc.service_id))
            with svc._cond:
                self.registered_revision = revision
                svc._cond.notify_all()
            self._backoff = RETRY_MIN_S
            self.outcome.set()
            log.info("service %s registered with agent %s (revision %d)", svc.service_id,
                     svc.agent_id, revision)
        elif reply.renew:
            self._renew_instance()
        elif retry or "Timeout" in error:
            self._schedule_retry()
        else:
            self.error = (f"service {svc.service_id!r} refused by agent {svc.agent_id!r}: "
                          f"{error}")
            log.error("%s", self.error)
            self.outcome.set()
            with svc._cond:
                svc._cond.notify_all()

    def _renew_instance(self) -> None:
        """The agent holds this instance without a key it gave (it restarted and adopted
        us): register as a new instance, which the duplicate check lets through because
        our own descriptor queryable answers with it."""
        svc = self._svc
        self.instance = secrets.token_hex(8)
        svc.control.forget_key()
        self._challenge = None
        self._next_try = 0.0
        log.info("service %s: agent %s holds this instance without its key; registering as "
                 "instance %s", svc.service_id, svc.agent_id, self.instance)

    def _schedule_retry(self) -> None:
        self._next_try = time.monotonic() + self._backoff
        self._backoff = min(RETRY_MAX_S, self._backoff * 2)

    def on_descriptor_query(self, query: zenoh.Query) -> None:
        """An agent checks on this service (duplicate id, departure): answer with what is
        advertised now."""
        svc = self._svc
        try:
            with svc._lock:
                desc = encode_descriptor(svc._descriptor_locked())
            query.reply(query.key_expr, descriptor_reply(desc, self.instance, svc._revision,
                                                         self._connected()))
        finally:
            query.drop()


def _parse_reply(data: bytes) -> RegisterReply:
    """A register reply; an unreadable one counts as a temporary refusal."""
    try:
        return parse_reply(data)
    except DecodeError as exc:
        return RegisterReply(False, f"unreadable reply from agent ({exc})", True)
