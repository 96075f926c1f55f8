"""The realm's static edges and the agents' clock offsets, for a recording to explain itself.

An agent's static edges (its configured calibration, e.g. the rig mountings) are not on any
data key, and its summary lists only frames.  So the recorder asks, as a client would: at
the start and whenever an agent's summary changes, one ``hops`` pose query per ordered pair
of that agent's frames (at most ``MAX_FRAMES`` of them), keeping the answers that are one
static edge owned by that agent in its stored direction.  The clock offset to the agent
comes from the same round trips (:mod:`agent.sdk.clock`).  Each agent's edges go into the
recording as one msgpack message on ``uma/R/agent/A/static`` (recorder-made, not a Zenoh
key): ``{v: 1, agent, edges: [{parent, child, p, q}], clock_offset_ns}``, written when they
change, and on ``/tf_static`` when ROS channels are on.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

import msgpack
import zenoh

from agent.errors import InvalidInputError, UmaError
from agent.runtime import RateLimitedLog, WakeLoop

log = logging.getLogger("uma.record")

#: an agent with more frames than this has its static edges looked up among the first ones
MAX_FRAMES = 24
#: look again this often even without a summary change (a clock offset drifts)
RECHECK_S = 30.0


def static_topic(realm: str, agent_id: str) -> str:
    return f"uma/{realm}/agent/{agent_id}/static"


def encode_statics(agent_id: str, edges: list[dict[str, Any]], offset_ns: int | None) -> bytes:
    return msgpack.packb({"v": 1, "agent": agent_id, "edges": edges,
                          "clock_offset_ns": offset_ns}, use_bin_type=True)


def decode_statics(data: bytes) -> dict[str, Any]:
    """A static-edges message; ``InvalidInputError`` (a ``ValueError``) says what is wrong."""
    try:
        msg = msgpack.unpackb(data, raw=False)
    except Exception as exc:  # msgpack raises many kinds
        raise InvalidInputError(f"static edges: not msgpack ({exc})") from None
    if not isinstance(msg, dict) or msg.get("v") != 1 or not isinstance(msg.get("edges"), list):
        raise InvalidInputError("static edges: expected {v: 1, agent, edges: [...]}")
    return msg


class StaticEdges:
    """Looks the static edges up on its own thread; :meth:`changed` asks it to look again."""

    def __init__(self, session: zenoh.Session, realm: str,
                 offer: Callable[[str, bytes, int], None]) -> None:
        from agent import Client

        self._client = Client(realm, session=session, timeout=1.0)
        self._realm = realm
        self._offer = offer
        self._last: dict[str, list[dict[str, Any]]] = {}
        self._loop = WakeLoop("uma-record-statics", self._run, RateLimitedLog(log),
                              "looking up static edges", period_s=RECHECK_S)
        self._loop.start()
        self._loop.wake()

    def changed(self) -> None:
        self._loop.wake()

    def close(self) -> None:
        self._loop.close(5.0)
        with contextlib.suppress(Exception):
            self._client.close()

    def _run(self) -> None:
        """Look at every live agent's frames; a realm in flux fails a look, logged, and the
        next change or recheck tries again."""
        self._client.refresh()
        for agent_id, info in sorted(self._client.agents().items()):
            if info["alive"]:
                self._look(agent_id, info["frames"][:MAX_FRAMES])

    def _look(self, agent_id: str, frames: list[str]) -> None:
        edges = []
        for parent in frames:
            for child in frames:
                if parent == child or self._loop.stopping:
                    continue
                with contextlib.suppress(UmaError):
                    r = self._client.pose(parent, child, error="hops")
                    e = r.edges[0] if len(r.edges) == 1 else {}
                    if (r.attributes.get("static") and e.get("forward")
                            and e.get("owner") == agent_id):
                        edges.append({"parent": parent, "child": child,
                                      "p": [float(v) for v in r.position],
                                      "q": [float(v) for v in r.quaternion]})
        if edges != self._last.get(agent_id):
            self._last[agent_id] = edges
            offset = self._client.clock.offset(agent_id)
            self._offer(static_topic(self._realm, agent_id),
                        encode_statics(agent_id, edges, offset), time.time_ns())
