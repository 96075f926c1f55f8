"""The pose-query protocol: every message on an agent's query and supernode keys, built and
checked here (``R`` = realm, ``A`` = agent id; all messages are ``schemas.codec`` msgpack
maps).  A client asks, an agent answers; both sides import this module and nothing of the
other's.

**Queries** (``uma/R/agent/A/query``, a queryable of every agent)

======================================  ==============================================
request                                 reply
======================================  ==============================================
``{"op": "clock"}``                     ``{"ok": true, "t2": recv ns, "t3": reply ns}``
``{"op": "segment", "source": S,        ``{"ok": true, "result": PoseResult, "t2", "t3"``
"target": T, "t": ns or nil,            ``[, "edges": [edge details]]}`` where result
"error": E[, "details": true]}``        is a ``schemas.models.PoseResultMessage`` as a map;
(``"op": "pose"`` is the same)          ``details`` adds each edge's data key (measured)
                                        or value (static), for streaming clients
``{"op": "segments", "parts":           the same answer to this agent's part; no answer
{agent id: segment request}}``          at all if there is none (one query sent to
                                        ``uma/R/agent/*/query`` asks every agent
                                        of a route at once)
``{"op": "route", "parts":              ``{"ok": true, "parts": {agent id: answer},
{agent id: segment request}}``          "t2", "t3"}``: a whole route asked of one
                                        agent, which answers every part it can (its
                                        own, its cache of other agents' segments) and
                                        asks the other agents for the rest; each
                                        answer is that agent's reply without its
                                        ``agent``, ``t2`` and ``t3`` (``"cached":
                                        true`` if from the cache); a part whose
                                        agent did not answer is left out
``{"op": "route", "parts": {...},       when every part is there (its own, its
"compose": true}``                      cache's): ``{"ok": true, "route": {"result":
                                        PoseResult of the whole route, "times":
                                        {agent id: its part's time or nil when
                                        static}}, "cached": n, "t2", "t3"}``, each
                                        edge's ``t_ns`` on its owner's clock; else
                                        the ``parts`` answer above
anything malformed or failing           ``{"ok": false, "error": message, "kind":
                                        exception class, "t2", "t3"}``
======================================  ==============================================

``t2``/``t3`` are the agent's clock when the request arrived and when the reply left, for
the caller's clock-offset estimate (:mod:`agent.sdk.clock`).  An edge detail is ``{parent,
child, source, static, attributes}`` plus ``key`` (the data key) and maybe ``covariance``
for a measured edge, ``position``, ``quaternion``, ``covariance`` for a static one.

**Summaries** (``uma/R/agent/A/supernode``, a queryable and a publication on change)

``{"agent": A, "rev": n, "instance": run id, "frames": [...], "boundary": [...],
"components": [[frame index...]...], "paths": [path attributes...], "links": [[a, b, p]...]}``:
the agent's supernode summary (:mod:`agent.srg.supernode`) as :func:`summary_to_wire` sends
it.  Frames are named once: components and links refer to them by their index in
``frames``.  Each distinct map of path attributes is sent once, in ``paths``; a link
``[a, b, p]`` refers to the best local path ``a -> b`` under each error function of
``SUMMARY_ERRORS`` by index in ``paths`` (``p``: one index when every error function finds
the same path, as in a tree, else a list of one per error function).  ``rev`` counts its
revisions within one run (``instance``), and a path attribute that is infinite travels as
nil.  :func:`parse_summary` also reads a summary spelt out as ``summarize`` builds it
(``components`` of frame ids, ``links`` of ``{"a", "b", "attrs": {error: path
attributes}}``, no ``paths``): the same content, five to twenty times the bytes
(``bench/bench_scale.py``).

A segment answer is read by :func:`pose_from_wire`, the hot-path form of
``schemas.models.PoseResultMessage.model_validate``: answers arrive at tracking rates, and the
model costs ten times as much (pydantic validates descriptors and API results, not
per-message hot paths).  The model stays the one definition of the answer's fields: the
fast reader takes their names, which are required and their defaults from it, and has one
check per field, which it refuses to import without.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent.attributes import EDGE_ATTRIBUTES, SUMMARY_ERRORS, check_attributes
from agent.result import PoseResult, finite_or_none
from schemas import ids
from schemas.codec import DecodeError, decode_message, encode_message
from schemas.models import (
    FRAME_PATTERN,
    MAX_FRAME_LENGTH,
    EdgeUse,
    PoseResultMessage,
    check_plain,
)
from schemas.native import compiled_twin
from schemas.quaternion import QUAT_NORM_TOL, unit_norm

#: environment variable that skews an agent's clock, as its ``t2``/``t3`` show it: the agent
#: then stamps as if its clock were that many ns ahead (tests only: it exists to test the
#: clients' offset estimate end to end)
SKEW_ENV = "UMA_CLOCK_SKEW_NS"


def skew_from_env() -> int:
    """The test-only clock skew in ns (0 when unset); ``ValueError`` if it is not an int."""
    raw = os.environ.get(SKEW_ENV, "").strip()
    if not raw:
        return 0
    try:
        return int(raw)
    except ValueError:
        raise ValueError(f"{SKEW_ENV}={raw!r} is not an integer number of nanoseconds") from None


# ---------------------------------------------------------------------- requests

@dataclass(frozen=True)
class ClockRequest:
    """``{"op": "clock"}``: only the timestamps of the reply are wanted."""


#: parts one ``route`` request may have (an agent asks the others for each one it lacks)
MAX_ROUTE_PARTS = 16


@dataclass(frozen=True)
class SegmentRequest:
    """One agent's segment: ``source -> target`` in its graph at ``t`` (its clock; None:
    the latest time), ranked by ``error``; ``details`` asks for every edge's details."""

    source: str
    target: str
    error: str
    t: int | None = None
    details: bool = False

    def to_wire(self) -> dict[str, Any]:
        part: dict[str, Any] = {"source": self.source, "target": self.target,
                                "error": self.error, "t": self.t}
        if self.details:
            part["details"] = True
        return part


@dataclass(frozen=True)
class RouteRequest:
    """``{"op": "route"}``: the segments of a route by agent id (in route order), asked of
    one agent; ``compose``: the whole route, composed there, when it can."""

    parts: dict[str, SegmentRequest]
    compose: bool = False


def clock_request() -> bytes:
    return encode_message({"op": "clock"})


def segments_request(parts: Mapping[str, SegmentRequest], op: str = "segments",
                     compose: bool = False) -> bytes:
    """One request for several agents' segments (one per agent id): to every agent at once
    (``segments``) or to one agent that answers the whole route (``route``, composed there
    if ``compose``)."""
    msg: dict[str, Any] = {"op": op,
                           "parts": {agent: p.to_wire() for agent, p in parts.items()}}
    if compose:
        msg["compose"] = True
    return encode_message(msg)


def decode_request(data: bytes) -> dict[str, Any]:
    """A request's map; ``DecodeError`` if it is not a message with an ``op``."""
    return decode_message(data, required=("op",))


def parse_request(msg: Mapping[str, Any], agent_id: str,
                  ) -> ClockRequest | SegmentRequest | RouteRequest | None:
    """What a decoded request asks of agent ``agent_id`` (None: a ``segments`` request with
    no part for it); ``ValueError`` names what is wrong."""
    op = msg["op"]
    if op == "clock":
        return ClockRequest()
    if op == "route":
        parts = msg.get("parts")
        if not isinstance(parts, dict) or not 0 < len(parts) <= MAX_ROUTE_PARTS:
            raise ValueError(f"route request: parts must be a map agent id -> request of 1 "
                             f"to {MAX_ROUTE_PARTS} entries")
        for agent, part in parts.items():
            if not isinstance(agent, str) or not isinstance(part, dict):
                raise ValueError(f"route request: the part for {agent!r:.64} is not a map")
        return RouteRequest({agent: _segment_request(part, "segment")
                             for agent, part in parts.items()}, msg.get("compose") is True)
    if op == "segments":
        parts = msg.get("parts")
        if not isinstance(parts, dict):
            raise ValueError("segments request: parts must be a map agent id -> request")
        part = parts.get(agent_id)
        if part is None:
            return None
        if not isinstance(part, dict):
            raise ValueError(f"segments request: the part for {agent_id!r} is not a map")
        msg, op = part, "segment"
    if op not in ("segment", "pose"):
        raise ValueError(f"unknown op {op!r} (expected clock, segment, segments, route or "
                         "pose)")
    return _segment_request(msg, op)


def _segment_request(msg: Mapping[str, Any], op: str) -> SegmentRequest:
    """One segment's request; ``ValueError`` names what is wrong."""
    source, target, error = msg.get("source"), msg.get("target"), msg.get("error", "hops")
    for name, value in (("source", source), ("target", target), ("error", error)):
        if not isinstance(value, str) or not value:
            raise ValueError(f"{op} request: {name} must be a non-empty string, got "
                             f"{value!r}")
    t = msg.get("t")
    if t is not None and (isinstance(t, bool) or not isinstance(t, int)):
        raise ValueError(f"{op} request: t must be integer ns or nil, got {t!r}")
    return SegmentRequest(source, target, error, t, bool(msg.get("details")))


# ---------------------------------------------------------------------- replies (agent side)

def clock_reply() -> dict[str, Any]:
    return {"ok": True}


def segment_reply(result: dict[str, Any],
                  edges: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """A segment's answer: ``result`` from :func:`result_to_wire`, ``edges`` from
    :func:`edge_details` when details were asked for."""
    reply = {"ok": True, "result": result}
    if edges is not None:
        reply["edges"] = edges
    return reply


def error_reply(exc: Exception) -> dict[str, Any]:
    """A request that was malformed or whose lookup failed."""
    return {"ok": False, "error": str(exc), "kind": type(exc).__name__}


def internal_error_reply(exc: Exception) -> dict[str, Any]:
    """A request that hit a bug of the agent's: the caller still gets an answer."""
    return {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}",
            "kind": "InternalError"}


def stamped(reply: dict[str, Any], agent: str, t2: int, t3: int) -> bytes:
    """A reply as sent, naming the agent that answers (the client checks it against the
    key the reply came on) and its receive and send times."""
    return encode_message({**reply, "agent": agent, "t2": t2, "t3": t3})


def wire_edges(r: PoseResult, owner: str, t_ns: int) -> list[dict[str, Any]]:
    """A local result's edges as sent: each with its owner and the time of its sample (a
    static edge: ``t_ns``)."""
    stamps = iter(r.stamps)
    edges = []
    for e in r.edges:
        t_edge = t_ns if e["static"] else next(stamps)[1]
        edges.append({"parent": e["parent"], "child": e["child"], "inverted": not e["forward"],
                      "owner": owner, "t_ns": int(t_edge)})
    return edges


def result_to_wire(r: PoseResult, source: str, target: str, owner: str,
                   t_ns: int, edges: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """A local result as a ``schemas.models.PoseResultMessage`` map (checked by the
    receiver); ``edges`` as sent when they are not all ``owner``'s (:func:`wire_edges`)."""
    if edges is None:
        edges = wire_edges(r, owner, t_ns)
    return {
        "source": source, "target": target, "t_ns": int(t_ns),
        "position": r.position.tolist(),  # numpy float64 -> Python floats in one call
        "quaternion": r.quaternion.tolist(),
        "covariance": None if r.covariance is None else r.covariance.ravel().tolist(),
        "path": list(r.path), "edges": edges,
        "attributes": finite_or_none(r.attributes),
        "extrapolated_s": float(r.extrapolated_s),
    }


def at_time(result: dict[str, Any], t_ns: int) -> dict[str, Any]:
    """A wire answer of an all-static path restamped at ``t_ns`` (a static edge is used at
    the query's time); the cached original is not modified."""
    out = dict(result)
    out["t_ns"] = t_ns
    out["edges"] = [{**e, "t_ns": t_ns} for e in result["edges"]]
    return out


def edge_details(e: Mapping[str, Any], edge: Any, data_key: str | None) -> dict[str, Any]:
    """What a streaming client needs to rebuild an edge of a path (``e``, an entry of a
    result's ``edges``; ``edge``, the graph's edge): its data key or its value."""
    attrs = {k: v for k, v in edge.attrs.items() if k != "covariance"}
    out = {"parent": e["parent"], "child": e["child"], "source": e["source"],
           "static": e["static"], "attributes": attrs}
    if edge.is_static:
        p, q, cov = edge.value
        out.update(position=p.tolist(), quaternion=q.tolist(),
                   covariance=None if cov is None else cov.ravel().tolist())
    else:
        out["key"] = data_key
        if "covariance" in edge.attrs:
            out["covariance"] = edge.attrs["covariance"].ravel().tolist()
    return out


# ---------------------------------------------------------------------- replies (client side)

class RefusedError(Exception):
    """The agent answered, but with ``ok: false`` (its lookup failed, or the request)."""


def decode_reply(data: bytes) -> dict[str, Any]:
    """A reply's map; an unreadable one reads as a refusal saying so."""
    try:
        return decode_message(data)
    except DecodeError as exc:
        return {"ok": False, "error": f"unreadable answer: {exc}"}


def route_result(reply: Mapping[str, Any],
                 ) -> tuple[dict[str, Any], dict[str, int | None]] | None:
    """A composed ``route`` reply's result (as sent: :func:`pose_from_wire` reads it) and
    each agent's part's time (None: static); None if the reply has the parts instead.
    ``ValueError`` if it is malformed."""
    route = reply.get("route") if reply.get("ok") else None
    if route is None:
        return None
    if not isinstance(route, dict) or not isinstance(route.get("result"), dict):
        raise ValueError("route reply: route must be a map with a result")
    times = route.get("times")
    if not isinstance(times, dict) or not all(
            isinstance(a, str) and (t is None or (isinstance(t, int) and not isinstance(t, bool)))
            for a, t in times.items()):
        raise ValueError("route reply: times must be a map agent id -> integer ns or nil")
    return route["result"], times


def route_parts(reply: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """The answers of a ``route`` reply by agent id; ``RefusedError`` if the agent refused
    the whole request, ``ValueError`` if the reply is malformed."""
    if not reply.get("ok"):
        raise RefusedError(str(reply.get("error", "no reason given")))
    parts = reply.get("parts")
    if not isinstance(parts, dict) or not all(
            isinstance(k, str) and isinstance(v, dict) for k, v in parts.items()):
        raise ValueError("route reply: parts must be a map agent id -> answer")
    return parts


def reply_times(reply: Mapping[str, Any]) -> tuple[int, int] | None:
    """The agent's ``(t2, t3)`` of a reply, or None if it has none."""
    t2, t3 = reply.get("t2"), reply.get("t3")
    return (t2, t3) if isinstance(t2, int) and isinstance(t3, int) else None


def read_segment_reply(reply: Mapping[str, Any], to_local: Callable[[int], int],
                       ) -> tuple[PoseResult, list[dict[str, Any]]]:
    """A segment's answer on the caller's clock (``to_local``) and its edge details (as
    sent; :func:`edge_from_wire` reads each); ``RefusedError`` if the agent could not answer,
    ``ValueError`` if the answer is malformed."""
    if not reply.get("ok"):
        raise RefusedError(str(reply.get("error", "no reason given")))
    if "result" not in reply:
        raise ValueError("no result")
    return pose_from_wire(reply["result"], to_local), reply.get("edges") or []


_INF_WHEN_NONE = ("frequency_hz", "ttl_s")
_WIRE_FIELDS = frozenset(PoseResultMessage.model_fields)
_EDGE_FIELDS = frozenset(EdgeUse.model_fields)


#: most frames (and links) one agent's summary may carry: a host's SRG has tens to
#: hundreds; a forged summary of many more would make every client's planning slow
MAX_SUMMARY_FRAMES = 5000


def _link_attributes(link: Mapping[str, Any], d: Mapping[str, Any]) -> dict[str, Any]:
    """A summary link's path attributes: numbers >= 0 (None: an infinite rate or time to
    live), a confidence in [0, 1]; a negative latency or a string would otherwise fail deep
    inside a client's planning.  The few non-numbers go through ``check_attributes``."""
    for k, v in d.items():
        if type(v) in (int, float) and v >= 0 and (k != "confidence" or v <= 1):
            continue  # the common case, checked inline: a summary has thousands of these
        if v is None and k in _INF_WHEN_NONE:
            continue
        try:
            if k not in EDGE_ATTRIBUTES or type(v) in (int, float):
                raise ValueError(f"attribute {k}: expected a number >= 0, got {v!r:.40}")
            check_attributes({k: v})
        except (TypeError, ValueError) as exc:
            raise ValueError(f"summary: link {link['a']}-{link['b']}: {exc}") from None
    return attributes_from_wire(d)


def attributes_from_wire(d: Mapping[str, Any]) -> dict[str, Any]:
    """Path attributes as received: None stands for an infinite rate or time to live."""
    out = dict(d)
    for name in _INF_WHEN_NONE:
        if out.get(name) is None:
            out[name] = math.inf
    return out


class _IdCheck:
    """One kind of id (frame or agent id): its pattern and length limit.  Answers carry the
    same few ids again and again, so those already found valid are remembered (a set lookup
    costs a tenth of a regex match), at most ``limit`` of them.  ``where % args`` names the
    field in the error; it is only formatted when the id is wrong."""

    def __init__(self, pattern: str, max_length: int, limit: int = 4096) -> None:
        self._regex = re.compile(pattern)
        self._max_length = max_length
        self._limit = limit
        #: the ids found valid (the compiled reader takes those as valid)
        self.valid: set[str] = set()

    def __call__(self, value: Any, where: str, *args: object) -> str:
        if type(value) is str and value in self.valid:
            return value
        if (not isinstance(value, str) or len(value) > self._max_length
                or not self._regex.match(value)):
            raise ValueError(f"{where % args}: {value!r:.60} is not a valid id")
        if len(self.valid) >= self._limit:
            self.valid.clear()
        self.valid.add(value)
        return value


_frame_id = _IdCheck(FRAME_PATTERN, MAX_FRAME_LENGTH)
_agent_id = _IdCheck(ids.ID_PATTERN, ids.MAX_LENGTH)  # the rule of schemas.ids, cached


def _wire_int(value: Any, where: str, *args: object) -> int:
    if type(value) is not int and (isinstance(value, bool) or not isinstance(value, int)):
        raise ValueError(f"{where % args}: expected integer ns, got {value!r:.60}")
    return value


def _wire_floats(value: Any, n: int, where: str) -> list[float]:
    """``n`` finite numbers (a list or tuple, as msgpack gives them)."""
    if not isinstance(value, list | tuple) or len(value) != n:
        raise ValueError(f"{where}: expected {n} numbers, got {value!r:.80}")
    for x in value:
        if ((type(x) is not float and (isinstance(x, bool) or not isinstance(x, float | int)))
                or not math.isfinite(x)):
            raise ValueError(f"{where}: {x!r:.40} is not a finite number")
    return [float(x) for x in value]


def _wire_covariance(value: Any) -> np.ndarray:
    """36 finite numbers as a 6x6 matrix.  Numpy converts and checks them (36 is too many
    for a Python loop); like the model's lax floats it takes bools and numeric strings."""
    if not isinstance(value, list | tuple) or len(value) != 36:
        raise ValueError(f"covariance: expected 36 numbers or null, got {value!r:.80}")
    try:
        cov = np.array(value, dtype=float)
    except (TypeError, ValueError):
        cov = None
    if cov is None or cov.shape != (36,) or not np.isfinite(cov).all():
        raise ValueError(f"covariance: expected 36 finite numbers, got {value!r:.80}")
    return cov.reshape(6, 6)


def _wire_attributes(value: Any) -> dict[str, Any]:
    """A flat map of plain values (anything nested goes through ``check_plain``), as
    :func:`attributes_from_wire` reads it."""
    if not isinstance(value, dict):
        raise ValueError(f"attributes: expected a map, got {value!r:.60}")
    for k, v in value.items():
        if not isinstance(k, str):
            raise ValueError(f"attributes: key {k!r:.40} is not a string")
        if type(v) is float:
            if not math.isfinite(v):
                raise ValueError(f"attributes.{k}: non-finite value {v!r}")
        elif v is not None and type(v) not in (int, bool, str):
            check_plain(v, f"attributes.{k}", 1)
    return attributes_from_wire(value)


def _wire_quaternion(value: Any) -> np.ndarray:
    """Four finite numbers of unit norm within the tolerance, renormalized (as the model)."""
    q = _wire_floats(value, 4, "quaternion")
    return np.array(q) / unit_norm(*q)


def _wire_path(value: Any) -> list[str]:
    if not isinstance(value, list):
        raise ValueError(f"path: expected a list of frame ids, got {value!r:.60}")
    for i, frame in enumerate(value):
        _frame_id(frame, "path[%d]", i)
    return list(value)


def _wire_edges(value: Any, to_local: Callable[[int], int]) -> list[dict[str, Any]]:
    if not isinstance(value, list):
        raise ValueError(f"edges: expected a list, got {value!r:.60}")
    return [_wire_edge(e, i, to_local) for i, e in enumerate(value)]


def _wire_extrapolated(value: Any) -> float:
    if (isinstance(value, bool) or not isinstance(value, float | int)
            or not math.isfinite(value) or value < 0):
        raise ValueError(f"extrapolated_s: expected a finite number >= 0, got {value!r}")
    return float(value)


Reader = Callable[[Any, Callable[[int], int]], Any]

#: the fast check of each field of ``PoseResultMessage``, with its value as
#: :class:`PoseResult` takes it.  The model is the one definition of the fields: which
#: exist, which are required and their defaults are read from it, and importing this
#: module fails if the model has a field this table does not check.
_READERS: dict[str, Reader] = {
    "source": lambda v, _: _frame_id(v, "source"),
    "target": lambda v, _: _frame_id(v, "target"),
    "t_ns": lambda v, to_local: to_local(_wire_int(v, "t_ns")),
    "position": lambda v, _: np.array(_wire_floats(v, 3, "position")),
    "quaternion": lambda v, _: _wire_quaternion(v),
    "covariance": lambda v, _: None if v is None else _wire_covariance(v),
    "path": lambda v, _: _wire_path(v),
    "edges": _wire_edges,
    "attributes": lambda v, _: _wire_attributes(v),
    "extrapolated_s": lambda v, _: _wire_extrapolated(v),
}
if _READERS.keys() != PoseResultMessage.model_fields.keys():
    raise ImportError("agent.protocol.query checks the fields "
                      f"{sorted(_READERS)} but PoseResultMessage has "
                      f"{sorted(PoseResultMessage.model_fields)}: give each field its check")
_REQUIRED = tuple(n for n, f in PoseResultMessage.model_fields.items() if f.is_required())
_DEFAULTS = {n: f.get_default(call_default_factory=True)
             for n, f in PoseResultMessage.model_fields.items() if not f.is_required()}


def _same_time(t: int) -> int:
    return t


def pose_from_wire(d: Any, to_local: Callable[[int], int] = _same_time) -> PoseResult:
    """A segment answer (a ``schemas.models.PoseResultMessage`` map) as a result, timestamps mapped
    by ``to_local``; ``ValueError`` names the first field that is wrong.

    The model's fields, required fields and defaults, each checked by its entry of
    ``_READERS`` (shapes, ids, finiteness, unit quaternion renormalized) at a tenth of the
    model's cost (module docstring).  ``tests/test_client_wire.py`` holds the two to the
    same verdicts, field by field.  An answer as agents write it is read by the compiled
    twin ``agent/protocol/_wire.c`` where it was built (a fifth of this reader's time); it
    leaves everything else, and every error, to this one.
    """
    if _NATIVE_RESULT is not None:
        p, q, cov = np.empty(3), np.empty(4), np.empty((6, 6))
        got = _NATIVE_RESULT(d, _frame_id.valid, _agent_id.valid,
                             None if to_local is _same_time else to_local, p, q, cov)
        if got is not None:
            path, edges, t_ns, extrapolated, attributes, has_cov = got
            return PoseResult(p, q, cov if has_cov else None, path, edges, t_ns, extrapolated,
                              [(e["t_ns"], e["t_ns"]) for e in edges], attributes)
    if not isinstance(d, dict):
        raise ValueError(f"pose result: expected a map, got {type(d).__name__}")
    if not d.keys() <= _WIRE_FIELDS:
        extra = sorted(map(str, d.keys() - _WIRE_FIELDS))
        raise ValueError(f"pose result: unexpected field(s) {', '.join(extra)}")
    for name in _REQUIRED:
        if name not in d:
            raise ValueError(f"pose result: missing field {name!r}")
    v = {name: read(d[name] if name in d else _DEFAULTS[name], to_local)
         for name, read in _READERS.items()}
    edges = v["edges"]
    return PoseResult(v["position"], v["quaternion"], v["covariance"], v["path"], edges,
                      v["t_ns"], v["extrapolated_s"], [(e["t_ns"], e["t_ns"]) for e in edges],
                      v["attributes"])


def _native_result() -> Callable[..., Any] | None:
    """The compiled twin of :func:`pose_from_wire` (``agent/protocol/_wire.c``), or None (not
    built, built from older source, or ``UMA_CODEC_PURE_PYTHON=1``)."""
    _wire = compiled_twin("agent.protocol._wire", "UMA_CODEC_PURE_PYTHON")
    if _wire is None:
        return None
    _wire.configure(QUAT_NORM_TOL, _INF_WHEN_NONE)
    return _wire.pose_result


_NATIVE_RESULT = _native_result()


def _wire_edge(e: Any, i: int, to_local: Callable[[int], int]) -> dict[str, Any]:
    if not isinstance(e, dict) or e.keys() != _EDGE_FIELDS:
        raise ValueError(f"edges[{i}]: expected a map with exactly "
                         f"{', '.join(sorted(_EDGE_FIELDS))}, got {e!r:.100}")
    if not isinstance(e["inverted"], bool):
        raise ValueError(f"edges[{i}].inverted: expected a bool, got {e['inverted']!r:.40}")
    return {"parent": _frame_id(e["parent"], "edges[%d].parent", i),
            "child": _frame_id(e["child"], "edges[%d].child", i),
            "forward": not e["inverted"],
            "owner": _agent_id(e["owner"], "edges[%d].owner", i),
            "t_ns": to_local(_wire_int(e["t_ns"], "edges[%d].t_ns", i))}


@dataclass(frozen=True)
class EdgeDetail:
    """One edge of a route as a streaming client mirrors it (:func:`edge_details`)."""

    parent: str
    child: str
    source: str
    static: bool
    attributes: dict[str, Any]
    covariance: np.ndarray | None
    position: list[float] | None = None  # static edges only
    quaternion: list[float] | None = None
    key: str | None = None  # measured edges only (None: the agent gave none)


def edge_from_wire(e: Any) -> EdgeDetail:
    """An edge detail as received; ``ValueError`` names what is wrong."""
    if not isinstance(e, dict):
        raise ValueError(f"edge details: expected a map, got {e!r:.60}")
    parent = _frame_id(e.get("parent"), "edge details: parent")
    child = _frame_id(e.get("child"), "edge details: child")
    source, attrs = e.get("source"), e.get("attributes") or {}
    if not isinstance(source, str) or not isinstance(attrs, dict):
        raise ValueError(f"edge details of {parent}->{child}: source must be a string and "
                         "attributes a map")
    cov = e.get("covariance")
    cov = None if cov is None else _wire_covariance(cov)
    if e.get("static"):
        return EdgeDetail(parent, child, source, True, attrs, cov,
                          _wire_floats(e.get("position"), 3, "position"),
                          _wire_floats(e.get("quaternion"), 4, "quaternion"))
    key = e.get("key")
    return EdgeDetail(parent, child, source, False, attrs, cov,
                      key=key if isinstance(key, str) and key else None)


# ---------------------------------------------------------------------- summaries

@dataclass
class Summary:
    """One agent's supernode summary, as received."""

    agent: str
    rev: int
    frames: set[str]
    components: list[set[str]]
    links: list[tuple[str, str, dict[str, dict[str, Any]]]]
    instance: str = ""  # the agent process's run id: revisions restart with it


def decode_summary(data: bytes) -> Summary:
    """A summary as published; ``ValueError`` (``DecodeError`` included) says what is
    wrong."""
    return parse_summary(decode_message(data, required=("agent", "frames")))


def parse_summary(msg: Mapping[str, Any]) -> Summary:
    """A decoded supernode message as a :class:`Summary`; ``ValueError`` says what is wrong."""
    msg = spelt_out(msg)
    agent, frames = msg.get("agent"), msg.get("frames")
    _agent_id(agent, "summary: agent")
    if not isinstance(frames, list) or not all(isinstance(f, str) for f in frames):
        raise ValueError("summary: frames must be a list of strings")
    components = msg.get("components", [])
    links_in = msg.get("links", [])
    if not isinstance(components, list) or not isinstance(links_in, list):
        raise ValueError("summary: components and links must be lists")
    if len(frames) > MAX_SUMMARY_FRAMES or len(links_in) > MAX_SUMMARY_FRAMES:
        raise ValueError(f"summary: {len(frames)} frames and {len(links_in)} links, more "
                         f"than {MAX_SUMMARY_FRAMES}")
    for i, frame in enumerate(frames):
        _frame_id(frame, "summary: frames[%d]", i)
    links = []
    for link in links_in:
        if not (isinstance(link, dict) and isinstance(link.get("a"), str)
                and isinstance(link.get("b"), str) and isinstance(link.get("attrs"), dict)):
            raise ValueError(f"summary: malformed link {link!r:.120}")
        attrs = {k: _link_attributes(link, v) for k, v in link["attrs"].items()
                 if k in SUMMARY_ERRORS and isinstance(v, dict)}
        if set(attrs) != set(SUMMARY_ERRORS):
            raise ValueError(f"summary: link {link['a']}-{link['b']} lacks attributes for "
                             f"{', '.join(sorted(set(SUMMARY_ERRORS) - set(attrs)))}")
        links.append((link["a"], link["b"], attrs))
    rev, instance = msg.get("rev", 0), msg.get("instance", "")
    return Summary(agent, rev if isinstance(rev, int) else 0, set(frames),
                   [set(c) for c in components if isinstance(c, list)], links,
                   instance if isinstance(instance, str) else "")


def summary_to_wire(summary: Mapping[str, Any]) -> dict[str, Any]:
    """A summary as ``agent.srg.supernode.summarize`` builds it, in its compact wire form
    (module docstring).  Spelt out, a summary repeats each frame id in every link and
    component and each path's attributes once per error function: its size grows with
    frames x boundary frames x error functions; compact, a link costs a few
    bytes and only distinct paths carry attributes."""
    index = {frame: i for i, frame in enumerate(summary["frames"])}
    paths: list[dict[str, Any]] = []
    known: dict[tuple, int] = {}

    def path_ref(attrs: Mapping[str, Any]) -> int:
        # the value's type is part of the key: an int and an equal float stay apart
        key = tuple((k, type(v), v) for k, v in sorted(attrs.items()))
        ref = known.get(key)
        if ref is None:
            ref = known[key] = len(paths)
            paths.append(dict(attrs))
        return ref

    links = []
    for link in summary["links"]:
        refs = [path_ref(link["attrs"][e]) for e in SUMMARY_ERRORS]
        same = all(r == refs[0] for r in refs)
        links.append([index[link["a"]], index[link["b"]], refs[0] if same else refs])
    return {**summary, "components": [[index[f] for f in c] for c in summary["components"]],
            "paths": paths, "links": links}


def spelt_out(msg: Mapping[str, Any]) -> Mapping[str, Any]:
    """A summary in its compact wire form (it has ``paths``) with its components and links
    spelt out as ``summarize`` builds them; any other message as it is.  ``ValueError`` if
    an index or a link is malformed (what they refer to is checked by the caller)."""
    if "paths" not in msg:
        return msg
    frames, paths = msg.get("frames"), msg.get("paths")
    links, components = msg.get("links", []), msg.get("components", [])
    if not all(isinstance(x, list) for x in (frames, paths, links, components)):
        raise ValueError("summary: frames, paths, links and components must be lists")

    def pick(table: list, i: Any, what: str) -> Any:
        if type(i) is not int or not 0 <= i < len(table):
            raise ValueError(f"summary: {what} index {i!r:.40} out of range")
        return table[i]

    spelt = []
    for link in links:
        if not isinstance(link, list) or len(link) != 3:
            raise ValueError(f"summary: malformed link {link!r:.120}")
        a, b, refs = link
        refs = refs if isinstance(refs, list) else [refs] * len(SUMMARY_ERRORS)
        if len(refs) != len(SUMMARY_ERRORS):
            raise ValueError(f"summary: link {link!r:.120} needs one path per error function")
        spelt.append({"a": pick(frames, a, "frame"), "b": pick(frames, b, "frame"),
                      "attrs": {e: pick(paths, r, "path")
                                for e, r in zip(SUMMARY_ERRORS, refs, strict=True)}})
    parts = [[pick(frames, i, "frame") for i in c] if isinstance(c, list) else c
             for c in components]
    out = {k: v for k, v in msg.items() if k != "paths"}
    return out | {"components": parts, "links": spelt}
