"""What crosses a process boundary: the key space and every message of uma's protocols.

One module per protocol; each builds and checks its own messages and says in its
docstring who sends what to whom.  Nothing here opens a session or keeps state.

The names below are what a realm tool (``uma view``, ``uma record``, a service that keeps
its own key) reads off the wire: :mod:`agent.protocol.keys`, the key space; an agent's
services snapshot (:func:`parse_snapshot`); a pose query's ``segments`` request and its
answer (:class:`SegmentRequest`, :func:`segments_request`, :func:`decode_reply`,
:func:`edge_from_wire`); a supernode summary (:class:`Summary`); an agent's stream digest
(:func:`read_digest`); the environment variable that skews a simulated host's clock, agent
and services alike (:data:`SKEW_ENV`, for demos and tests).  The rest is internal.
"""

from __future__ import annotations

from agent._lazy import lazy_attributes

__all__ = ["SKEW_ENV", "EdgeDetail", "SegmentRequest", "Snapshot", "Summary", "decode_reply",
           "edge_from_wire", "keys", "parse_snapshot", "read_digest", "segments_request"]

__getattr__ = lazy_attributes(__name__, {
    "keys": "agent.protocol.keys",
    "Snapshot": "agent.protocol.registration",
    "parse_snapshot": "agent.protocol.registration",
    "SKEW_ENV": "agent.protocol.query",
    "EdgeDetail": "agent.protocol.query",
    "SegmentRequest": "agent.protocol.query",
    "Summary": "agent.protocol.query",
    "decode_reply": "agent.protocol.query",
    "edge_from_wire": "agent.protocol.query",
    "segments_request": "agent.protocol.query",
    "read_digest": "agent.protocol.digest",
})
