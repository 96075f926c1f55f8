"""What this agent learns of the others' summaries: the frames each knows, which decide this
agent's boundary (the frames its summary describes paths between).

Summaries arrive from any peer (published on change, or asked for): each is checked (it
names the agent of its key, every frame is a valid frame id) and bounded
(``MAX_REMOTE_AGENTS`` agents, ``MAX_REMOTE_FRAMES`` frames and ``MAX_AGENT_FRAME_BYTES``
each, ``MAX_FRAME_BYTES`` in all); only agents whose liveliness token was seen are kept
(a summary of one that never had a token is not: a flood of invented agents holds
nothing); an agent that appears is asked for its summary (it may
have published before this agent was linked), one that leaves is forgotten, and every
agent is asked again every ``RESYNC_S`` (a summary put before this agent's subscription
reached its author is never sent again).  ``changed()`` is called when the frames known
elsewhere change.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Callable

import zenoh

from agent.protocol import keys
from agent.runtime.callbacks import guarded
from agent.runtime.logs import RateLimitedLog
from agent.runtime.payload import payload_bytes
from schemas.codec import DecodeError, decode_message
from schemas.models import FRAME_PATTERN, MAX_FRAME_LENGTH

log = logging.getLogger("uma.srg")

#: how often every agent is asked for its summary again (see ``resync_if_due``)
RESYNC_S = 2.0
#: other agents whose frames are remembered, and frames remembered per agent: summaries
#: arrive from any peer, so what they make this agent hold is bounded
MAX_REMOTE_AGENTS = 1024
MAX_REMOTE_FRAMES = 4096
#: bytes of frame ids remembered per agent and in all (a frame id has up to 200)
MAX_AGENT_FRAME_BYTES = 256 * 1024
MAX_FRAME_BYTES = 16 * 1024 * 1024


_FRAME = re.compile(FRAME_PATTERN)


def _is_frame(value: object) -> bool:
    return (isinstance(value, str) and len(value) <= MAX_FRAME_LENGTH
            and _FRAME.match(value) is not None)


class PeerFrames:
    """The frames other agents know, from their summaries (module docstring)."""

    def __init__(self, session: zenoh.Session, realm: str, agent_id: str,
                 lock: threading.Lock, changed: Callable[[], None],
                 limited_log: RateLimitedLog) -> None:
        self._session = session
        self.realm = realm
        self.agent_id = agent_id
        #: the graph's lock: the summary publisher reads ``frames`` under it
        self._lock = lock
        self._changed = changed
        self._log = limited_log
        #: frames by agent, as its latest summary named them, and their bytes
        self.frames: dict[str, set[str]] = {}
        self._bytes: dict[str, int] = {}
        #: agents whose token was seen (and not removed since): only theirs are kept
        self._live: set[str] = set()
        #: every frame another agent knows, and what ``frames`` was when it was built
        #: (its identity and size; ``learn`` and tokens clear it on a change)
        self._union: frozenset[str] | None = None
        self._union_of: tuple[int, int] = (0, 0)
        #: summaries refused: malformed, or beyond the bounds above
        self.refused = 0
        self._to_fetch: set[str] = set()  # agents whose summary to ask for
        self._next_resync = time.monotonic() + RESYNC_S
        self._on_reply = guarded(self.on_summary_reply, "supernode reply", limited_log)

    def ask_all(self) -> None:
        """Ask every agent for its summary."""
        self._session.get(keys.all_agent_supernodes(self.realm), self._on_reply, timeout=2.0)

    def known_elsewhere(self) -> frozenset[str]:
        """Every frame another agent knows (rebuilt only after a change).  Lock held."""
        of = (id(self.frames), len(self.frames))
        if self._union is None or of != self._union_of:
            self._union, self._union_of = frozenset().union(*self.frames.values()), of
        return self._union

    def on_summary(self, sample: zenoh.Sample) -> None:
        self.learn(str(sample.key_expr), sample.payload)

    def on_summary_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self.learn(str(reply.ok.key_expr), reply.ok.payload)

    def learn(self, key: str, payload: zenoh.ZBytes | bytes) -> None:
        """Record the frames another agent knows (they decide our boundary).  A summary
        whose key names an agent without a seen token is refused before it is decoded:
        decoding and checking a stranger's thousands of frame ids was the flood's cost."""
        named = keys.parse_agent_supernode(key, self.realm)
        if named is not None and named != self.agent_id and named not in self._live:
            self.refused += 1
            self._log.warning(f"supernode {key}", "summary refused: its agent's liveliness "
                              f"token was never seen ({self.refused} refused so far)")
            return
        try:
            data = payload if isinstance(payload, bytes) else payload_bytes(payload)
            msg = decode_message(data, required=("agent", "frames"))
            agent, frames = msg["agent"], msg["frames"]
            if not isinstance(agent, str) or not isinstance(frames, list):
                raise DecodeError("agent must be a string and frames a list of frame ids")
            bad = next((f for f in frames if not _is_frame(f)), None)
            if bad is not None:
                raise DecodeError(f"frame {str(bad)[:64]!r} is not a frame id")
            if agent != keys.parse_agent_supernode(key, self.realm):
                raise DecodeError(f"it names agent {agent[:64]!r}, not the agent of its key")
        except DecodeError as exc:
            self.refused += 1
            self._log.warning(f"supernode {key}", f"dropped a malformed summary: {exc}")
            return
        if agent == self.agent_id:
            return
        size = sum(len(f) for f in frames)
        with self._lock:
            refused = self._refusal(agent, frames, size)
            if refused is None:
                kept = set(frames)
                if self.frames.get(agent) == kept:
                    return
                self.frames[agent], self._bytes[agent] = kept, size
                self._union = None
        if refused is not None:
            self.refused += 1
            self._log.warning(f"supernode {key}", f"summary refused: {refused} "
                              f"({self.refused} refused so far)")
            return
        self._changed()

    def _refusal(self, agent: str, frames: list[str], size: int) -> str | None:
        """Why a summary is not kept, or None.  Lock held."""
        if agent not in self._live:
            return "its agent's liveliness token was never seen"
        if len(frames) > MAX_REMOTE_FRAMES:
            return f"{len(frames)} frames, more than {MAX_REMOTE_FRAMES}"
        if size > MAX_AGENT_FRAME_BYTES:
            return f"{size} bytes of frame ids, more than {MAX_AGENT_FRAME_BYTES}"
        if agent not in self.frames and len(self.frames) >= MAX_REMOTE_AGENTS:
            return f"frames of {MAX_REMOTE_AGENTS} agents kept already"
        total = sum(self._bytes.values()) - self._bytes.get(agent, 0) + size
        if total > MAX_FRAME_BYTES:
            return f"{MAX_FRAME_BYTES} bytes of other agents' frame ids kept already"
        return None

    def on_agent_token(self, sample: zenoh.Sample) -> None:
        """An agent appeared (fetch its summary: it may have published before we were
        linked) or left (forget its frames)."""
        agent = keys.parse_agent_token(str(sample.key_expr), self.realm)
        if agent is None or agent == self.agent_id:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._live.discard(agent)
                if self.frames.pop(agent, None) is not None:
                    self._union = None
                self._bytes.pop(agent, None)
                self._to_fetch.discard(agent)
            elif agent in self._live or len(self._live) < MAX_REMOTE_AGENTS:
                self._live.add(agent)
                self._to_fetch.add(agent)
        self._changed()

    def resync_if_due(self) -> None:
        """Ask every agent for its summary every ``RESYNC_S``: a summary put before this
        agent's subscription reached its author is not sent again, and a boundary that
        misses it hides a link from every planner (bench setups were seen stuck on it)."""
        now = time.monotonic()
        if now < self._next_resync:
            return
        self._next_resync = now + RESYNC_S
        self.ask_all()

    def fetch_new(self) -> None:
        with self._lock:
            agents, self._to_fetch = self._to_fetch, set()
        for agent in sorted(agents):
            self._session.get(keys.agent_supernode(self.realm, agent), self._on_reply,
                              timeout=2.0)
