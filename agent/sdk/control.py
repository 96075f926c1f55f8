"""What a service accepts of the control messages on its key: only those of its own agent,
signed with the key the agent gave this instance, of the agent's current epoch and the next
in sequence (``agent.protocol.registration``, "Agent -> its local services"); each accepted
one goes to :meth:`agent.sdk.needs.NeedLinks.apply`, each refused one is counted by reason.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from agent.protocol import keys
from agent.protocol.registration import UnverifiedControlError, control_need, parse_control
from agent.runtime.logs import RateLimitedLog
from schemas.codec import DecodeError

if TYPE_CHECKING:
    from agent.sdk.service import Service

#: how far a control message's seq (the agent's milliseconds, ``next_seq``) may run ahead
#: of the last one applied plus the milliseconds passed since: a forged jump holds the
#: agent's real messages back this long at most
SEQ_WINDOW = 2000
#: seconds between registrations prompted by control messages that do not verify
REVERIFY_S = 1.0


class ControlGate:
    """Verifies control messages before they are applied (module docstring)."""

    def __init__(self, svc: Service, limited_log: RateLimitedLog) -> None:
        self._svc = svc
        self._log = limited_log
        #: the agent's epoch and the key it signs control messages with (register reply)
        self.epoch: int | None = None
        self.key: bytes | None = None
        #: the newest control message per own need that did not verify yet (kept until
        #: the next registration gives a key: the agent may have sent it first)
        self._unverified: dict[str, bytes] = {}
        self._next_reverify = 0.0
        #: control messages refused, by reason ("signature", "epoch", "seq")
        self.refused: dict[str, int] = {}

    def trust(self, epoch: int | None, key: bytes | None) -> None:
        """The agent accepted a registration: its epoch and key from now on; the messages
        kept for want of a key are tried again."""
        self.epoch, self.key = epoch, key
        pending, self._unverified = self._unverified, {}
        for kept in pending.values():
            self.on_control(kept)

    def forget_key(self) -> None:
        self.key = None

    def on_control(self, data: bytes) -> None:
        """Apply a control message that comes from this service's agent (module
        docstring)."""
        svc = self._svc
        try:
            ctl = parse_control(data, svc.realm, self.key)
        except UnverifiedControlError as exc:
            self._unverified_control(data, str(exc))
            return
        except DecodeError as exc:
            self._refuse("malformed", f"dropped: {exc}")
            return
        if ctl.epoch != self.epoch:
            self._refuse("epoch", f"epoch {ctl.epoch} is not agent {svc.agent_id}'s "
                         f"current one ({self.epoch})")
            return
        need = svc._needs.get(ctl.need)
        if need is None:
            self._refuse("need", f"names unknown need {ctl.need!r}")
            return
        now = time.monotonic()
        if ctl.epoch == need.last[0]:
            if ctl.seq <= need.last[1]:
                return  # older than what was applied
            if ctl.seq > need.last[1] + int((now - need.last_at) * 1000) + SEQ_WINDOW:
                self._refuse("seq", f"seq {ctl.seq} jumps ahead of {need.last[1]} "
                             "by more than the time passed")
                return
        need.last, need.last_at = (ctl.epoch, ctl.seq), now
        svc.links.apply(need, ctl.matches, ctl.satisfied, ctl.standby)

    def _unverified_control(self, data: bytes, reason: str) -> None:
        """Keep it until the next registration gives a key (the agent may have signed it
        with a key whose reply has not arrived), and register again to get one."""
        svc = self._svc
        need = control_need(data)
        if need in svc._needs:
            self._unverified[need] = data
        if self.key is None:  # the usual race with the register reply: no warning
            self.refused["no key yet"] = self.refused.get("no key yet", 0) + 1
        else:
            self._refuse("signature", reason)
        now = time.monotonic()
        if now >= self._next_reverify and svc.presence.agent_present:
            self._next_reverify = now + REVERIFY_S
            svc.presence.registered_revision = -1

    def _refuse(self, reason: str, detail: str) -> None:
        svc = self._svc
        n = self.refused[reason] = self.refused.get(reason, 0) + 1
        self._log.warning(f"control {keys.control(svc.realm, svc.agent_id, svc.service_id)}",
                          f"refused ({reason}, {n} so far): {detail}")
