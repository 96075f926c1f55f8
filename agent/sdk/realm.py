"""What a client knows of its realm: the agents' supernode summaries and which agents are
alive, kept true by their tokens and summaries, and by probing agents that missed an answer.

An agent is alive while its token is there, and as soon as it shows life (a new token or
summary).  One that missed an answer counts as gone until it shows life again, or answers
the probe it gets every ``PROBE_S`` while its token is still there (it may only have been
slow).  ``topology`` moves whenever a summary or the set of live agents changes (the
subscriptions re-plan when it does); ``summaries_rev`` only when a summary does (routes
planned before are stale).
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from agent.protocol import keys
from agent.protocol.query import Summary, decode_summary
from agent.runtime.logs import RateLimitedLog
from agent.runtime.payload import payload_bytes
from schemas.codec import DecodeError

log = logging.getLogger("uma.client")

#: how long the first look at the realm waits for the set of agents to settle
SETTLE_S = 0.15
#: how often an agent that missed an answer, its token still there, is asked whether it
#: answers again
PROBE_S = 2.0
#: most agents a client keeps summaries of (a realm of real hosts has tens; a flood of
#: forged summaries must not grow a client without bound)
MAX_AGENTS = 1000
#: how far a published summary's revision may run ahead of the known one
MAX_REVISION_JUMP = 10_000
#: bytes (on the wire) of the summaries a client keeps in all: a realm of a hundred agents
#: with a hundred links each needs about 4 MiB; invented agents (each with a token, on a
#: plain realm) must not grow a client without bound
MAX_SUMMARY_BYTES = 32 * 1024 * 1024


@dataclass(frozen=True)
class RealmView:
    """The summaries and live agents at one moment; ``summaries_rev`` tells whether routes
    planned on them are stale."""

    summaries: dict[str, Summary]
    alive: set[str]
    summaries_rev: int


class RealmTracker:
    """The summaries, live agents and suspects of one realm (module docstring), under one
    lock.  ``probe(agent)`` asks one agent whether it answers (True if it did)."""

    def __init__(self, session: zenoh.Session, realm: str, timeout: float,
                 probe: Callable[[str], bool], settle_s: float = SETTLE_S) -> None:
        self.session = session
        self.realm = realm
        self.timeout = timeout
        self._probe = probe
        #: how long the first look waits for the set of agents to stop growing: a peer's
        #: gossip is still linking it to agents; a client's agent answers for all at once (0)
        self.settle_s = settle_s
        self._lock = threading.Lock()
        self._log = RateLimitedLog(log)
        #: summaries refused: malformed, under another agent's key, or beyond MAX_AGENTS
        self.refused = 0
        self._summaries: dict[str, Summary] = {}
        self._bytes: dict[str, int] = {}  # agent -> its summary's bytes on the wire
        self._alive: set[str] = set()
        #: when each agent last showed life (its token or a summary; monotonic s): a missed
        #: answer marks it gone only if that came before the query went out
        self._heard: dict[str, float] = {}
        #: agents whose token was seen removed (and not declared again)
        self._departed: set[str] = set()
        #: agents whose token was seen at some time, oldest first (an ordered set)
        self._tokens: dict[str, None] = {}
        #: agents marked gone after a missed answer, not by their token: probed every
        #: PROBE_S by a thread that runs while there are any
        self._suspects: set[str] = set()
        self._prober: threading.Thread | None = None
        self._closing = threading.Event()
        self.topology = 0
        self.summaries_rev = 0
        self._looked = False
        self._decls = [
            session.declare_subscriber(keys.all_agent_supernodes(realm), self._on_summary),
            session.liveliness().declare_subscriber(keys.all_agent_tokens(realm),
                                                    self._on_token, history=True),
        ]

    def close(self) -> None:
        """Stop probing and listening (the session stays open)."""
        self._closing.set()
        prober = self._prober
        if prober is not None:
            prober.join(PROBE_S + self.timeout)
        for decl in self._decls:
            with contextlib.suppress(zenoh.ZError):
                decl.undeclare()
        self._decls.clear()

    # ------------------------------------------------------------------ what is known

    def view(self) -> RealmView:
        with self._lock:
            return RealmView(dict(self._summaries), set(self._alive), self.summaries_rev)

    def current(self) -> RealmView:
        """The realm to plan a query on: looked at first if it never was or nobody is
        known, refreshed if an agent appeared whose summary has not come yet."""
        view = self.view()
        if not self._looked or not view.summaries:
            self.look()
        elif view.alive - set(view.summaries):
            self.refresh()
        else:
            return view
        return self.view()

    def is_alive(self, agent: str) -> bool:
        with self._lock:
            return agent in self._alive

    def summary_version(self, agent: str) -> tuple[str, int] | None:
        """``(instance, rev)`` of the agent's summary (any change of its edges or their
        attributes moves it), None if unknown."""
        with self._lock:
            s = self._summaries.get(agent)
            return None if s is None else (s.instance, s.rev)

    def agents(self) -> dict[str, dict[str, Any]]:
        """The agents known: alive or not, and their frames."""
        if not self._looked:
            self.look()
        with self._lock:
            return {a: {"alive": a in self._alive, "frames": sorted(s.frames)}
                    for a, s in self._summaries.items()}

    # ------------------------------------------------------------------ asking the realm

    def refresh(self) -> None:
        """Ask every agent for its summary now (also learns who is alive)."""
        alive = set()
        for reply in self.session.liveliness().get(keys.all_agent_tokens(self.realm),
                                                   timeout=self.timeout):
            if reply.ok is not None:
                agent = keys.parse_agent_token(str(reply.ok.key_expr), self.realm)
                if agent is not None:
                    alive.add(agent)
        with self._lock:
            # a token whose removal was seen can still be in the answer (a peer not yet
            # done with the departure): only a new token brings it back
            for agent in alive - self._departed:
                self._saw_token(agent)
                self._mark_alive(agent, True)
        for reply in self.session.get(keys.all_agent_supernodes(self.realm),
                                      timeout=self.timeout):
            if reply.ok is not None:
                self.take_summary(str(reply.ok.key_expr), reply.ok.payload.to_bytes(),
                                  answered=True)

    def look(self) -> None:
        """The first look at the realm: refresh until the set of agents stops growing
        (peers learn of each other by gossip within tens of ms; ``settle_s`` 0: the first
        answer is the whole realm), bounded by the timeout."""
        deadline = time.monotonic() + self.timeout
        seen: set[str] = set()
        while True:
            self.refresh()
            with self._lock:
                now = set(self._summaries)
            if now and (now == seen or not self.settle_s):
                break
            seen = now
            if time.monotonic() + self.settle_s > deadline:
                break
            time.sleep(self.settle_s)
        self._looked = True

    # ------------------------------------------------------------------ what comes in

    def _on_summary(self, sample: zenoh.Sample) -> None:
        try:
            data = payload_bytes(sample.payload)
        except DecodeError as exc:
            self.refused += 1
            self._log.warning(f"supernode {sample.key_expr}", f"dropped: {exc}")
            return
        self.take_summary(str(sample.key_expr), data)

    def take_summary(self, key: str, data: bytes, answered: bool = False) -> None:
        """A summary published or answered on ``key``: newer ones replace the known one.  A
        published one more than ``MAX_REVISION_JUMP`` revisions ahead is refused (a forged
        revision would outrank every real one); an answer to our own ask is taken.  One
        whose key names an agent without a seen token is refused before it is decoded."""
        named = keys.parse_agent_supernode(key, self.realm)
        if named is not None and named not in self._tokens:
            self._refuse_tokenless(key)
            return
        try:
            summary = decode_summary(data)
            if summary.agent != keys.parse_agent_supernode(key, self.realm):
                raise ValueError(f"it names agent {summary.agent[:64]!r}, not the agent of "
                                 "its key")
        except ValueError as exc:
            self.refused += 1
            self._log.warning(f"supernode {key}", f"dropped a malformed summary: {exc} "
                              f"({self.refused} refused so far)")
            return
        with self._lock:
            if summary.agent not in self._tokens:  # never an agent: not kept
                self._refuse_tokenless(key)
                return
            if not self._room_for(summary.agent, len(data)):
                return
            old = self._summaries.get(summary.agent)
            if (old is not None and not answered and summary.instance == old.instance
                    and summary.rev > old.rev + MAX_REVISION_JUMP):
                self.refused += 1
                self._log.warning(f"supernode {key}", f"revision {summary.rev} jumps from "
                                  f"{old.rev}: refused ({self.refused} refused so far)")
                return
            if (old is None or summary.rev > old.rev or summary.instance != old.instance
                    or (answered and summary.rev != old.rev)):
                self._summaries[summary.agent] = summary
                self._bytes[summary.agent] = len(data)
                self.summaries_rev += 1
                self.topology += 1
            self._mark_alive(summary.agent, True)

    def _room_for(self, agent: str, size: int) -> bool:
        """Whether a summary of ``agent`` of ``size`` bytes may be kept (lock held): within
        ``MAX_SUMMARY_BYTES`` in all, and a known agent always, a new one while fewer than
        ``MAX_AGENTS`` are kept, making room by forgetting one not alive if needed."""
        held = sum(self._bytes.values()) - self._bytes.get(agent, 0)
        if held + size > MAX_SUMMARY_BYTES:
            self.refused += 1
            self._log.warning("supernode", f"summaries of {MAX_SUMMARY_BYTES} bytes kept "
                              f"already; summary of {agent[:64]!r} dropped ({self.refused} "
                              "refused so far)")
            return False
        if agent in self._summaries or len(self._summaries) < MAX_AGENTS:
            return True
        dead = next((a for a in self._summaries if a not in self._alive), None)
        if dead is not None:
            del self._summaries[dead]
            self._bytes.pop(dead, None)
            self._heard.pop(dead, None)
            return True
        self.refused += 1
        self._log.warning("supernode", f"more than {MAX_AGENTS} agents; summary of {agent!r} "
                          f"dropped ({self.refused} refused so far)")
        return False

    def _refuse_tokenless(self, key: str) -> None:
        self.refused += 1
        self._log.warning(f"supernode {key}", "dropped: its agent's liveliness token was "
                          f"never seen ({self.refused} refused so far)")

    def _on_token(self, sample: zenoh.Sample) -> None:
        agent = keys.parse_agent_token(str(sample.key_expr), self.realm)
        if agent is None:
            return
        with self._lock:
            gone = sample.kind == zenoh.SampleKind.DELETE
            if not gone:
                self._saw_token(agent)
            (self._departed.add if gone else self._departed.discard)(agent)
            self._suspects.discard(agent)  # its token says what it is now
            self._mark_alive(agent, not gone)

    def _saw_token(self, agent: str) -> None:
        """Remember that ``agent`` had a token (lock held): only such an agent is made
        alive by its summary; bounded, the oldest agent that is not alive forgotten first,
        so tokens a stranger declares and drops do not push a live agent out."""
        self._tokens.pop(agent, None)
        self._tokens[agent] = None
        while len(self._tokens) > MAX_AGENTS:
            oldest = next((a for a in self._tokens if a not in self._alive),
                          next(iter(self._tokens)))
            del self._tokens[oldest]
            self._departed.discard(oldest)

    def _mark_alive(self, agent: str, alive: bool) -> None:
        """Update the live set (lock held); a change moves ``topology``."""
        if alive and agent not in self._alive and len(self._alive) >= MAX_AGENTS:
            self.refused += 1
            self._log.warning("liveliness", f"more than {MAX_AGENTS} live agents; {agent!r} "
                              f"ignored ({self.refused} refused so far)")
            return
        if alive:
            self._heard[agent] = time.monotonic()
            self._suspects.discard(agent)
        if (agent in self._alive) != alive:
            self.topology += 1
            (self._alive.add if alive else self._alive.discard)(agent)

    # ------------------------------------------------------------------ missed answers

    def missed(self, agent: str, asked: float) -> None:
        """``agent`` did not answer a query sent at ``asked``: count it as gone, unless it
        showed life since (a query that reached a restarting agent's old self gets no
        answer, and marking it gone after its new token and summary came would outlive them:
        nothing else would bring it back).  Unless its token is gone too, it is probed
        until it answers again: it may only have been slow."""
        with self._lock:
            if self._heard.get(agent, -math.inf) >= asked:
                return
            self._mark_alive(agent, False)
            if agent in self._departed:
                return
            self._suspects.add(agent)
            if self._prober is None and not self._closing.is_set():
                self._prober = threading.Thread(target=self._probe_suspects,
                                                name="uma-client-probe", daemon=True)
                self._prober.start()

    def _probe_suspects(self) -> None:
        """Ask the agents that missed an answer whether they answer now; one that does is
        alive again, and subscriptions re-plan (and move back to it if it is on their best
        route).  Runs on its own thread: an agent still too slow costs a query timeout."""
        try:
            while not self._closing.wait(PROBE_S):
                with self._lock:
                    suspects = sorted(self._suspects)
                    if not suspects:  # done, in the lock in which missed would start one
                        self._prober = None
                        return
                for agent in suspects:
                    self._probe_one(agent)
        finally:
            with self._lock:
                if self._prober is threading.current_thread():
                    self._prober = None

    def _probe_one(self, agent: str) -> None:
        if not self._probe(agent):
            return
        with self._lock:
            if agent in self._suspects:
                self._mark_alive(agent, True)
