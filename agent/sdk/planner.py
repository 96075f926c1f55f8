"""Cross-agent pose queries: routes over supernode summaries, composed from segments.

Each agent publishes a summary of its SRG (:mod:`agent.srg.supernode`): its frames, its
boundary frames and the attributes of its best local paths between them.  A frame id known
to two agents links them.  The planner joins all summaries into one graph whose edges are
those links (labelled with their agent), ranks routes from source to target for the error
function (Dijkstra/Yen as in the local SRG: additive functions sum the links' values,
path-level ones are evaluated on the joined attributes of k candidate routes), merges
consecutive links of one agent into a single *segment*, and leaves it to the caller
(:class:`agent.sdk.client.Client`) to ask each owning agent for its segment at ``t`` and to
:func:`compose` the answers.

Routes through agents that have left the realm are never tried; when only such routes
exist, :class:`RouteError` names the segments and agents that are missing.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent.srg import geometry as geo
from agent.srg import paths
from agent.srg.attributes import combine
from agent.srg.errorfn import ErrorFunction
from agent.srg.errors import SrgLookupError, UnknownFrameError, UnreachableError, list_names
from agent.srg.result import PoseResult
from agent.srg.supernode import SUMMARY_ERRORS
from schemas import ids
from schemas.models import FRAME_PATTERN, MAX_FRAME_LENGTH, QUAT_NORM_TOL, check_plain

#: candidate routes ranked for path-level error functions
ROUTE_CANDIDATES = 16
_INF_WHEN_NONE = ("frequency_hz", "ttl_s")


class RouteError(SrgLookupError):
    """Every route between the frames needs an agent that is gone or failed."""


class SegmentError(SrgLookupError):
    """One agent could not deliver its segment (no answer, or its own lookup failed)."""

    def __init__(self, segment: Segment, reason: str, missing: bool) -> None:
        self.segment = segment
        self.missing = missing  # the agent did not answer at all
        super().__init__(f"segment {segment} failed: {reason}")


@dataclass(frozen=True)
class Segment:
    """The part of a route one agent computes: ``source -> target`` in its own graph."""

    agent: str
    source: str
    target: str

    def __str__(self) -> str:
        return f"{self.source} -> {self.target} of agent {self.agent!r}"


@dataclass
class Summary:
    """One agent's supernode summary, as received."""

    agent: str
    rev: int
    frames: set[str]
    components: list[set[str]]
    links: list[tuple[str, str, dict[str, dict[str, Any]]]]
    instance: str = ""  # the agent process's run id: revisions restart with it


@dataclass
class Route:
    segments: list[Segment]
    value: float
    attributes: dict[str, Any] = field(default_factory=dict)

    @property
    def agents(self) -> list[str]:
        return list(dict.fromkeys(s.agent for s in self.segments))


def attributes_from_wire(d: Mapping[str, Any]) -> dict[str, Any]:
    """Path attributes as received: None stands for an infinite rate or time to live."""
    out = dict(d)
    for name in _INF_WHEN_NONE:
        if out.get(name) is None:
            out[name] = math.inf
    return out


_WIRE_FIELDS = frozenset(("source", "target", "t_ns", "position", "quaternion", "covariance",
                          "path", "edges", "attributes", "extrapolated_s"))
_EDGE_FIELDS = frozenset(("parent", "child", "inverted", "owner", "t_ns"))


class _IdCheck:
    """One kind of id (frame or agent id): its pattern and length limit.  Answers carry the
    same few ids again and again, so those already found valid are remembered (a set lookup
    costs a tenth of a regex match), at most ``limit`` of them.  ``where % args`` names the
    field in the error; it is only formatted when the id is wrong."""

    def __init__(self, pattern: str, max_length: int, limit: int = 4096) -> None:
        self._regex = re.compile(pattern)
        self._max_length = max_length
        self._limit = limit
        self._valid: set[str] = set()

    def __call__(self, value: Any, where: str, *args: object) -> str:
        if type(value) is str and value in self._valid:
            return value
        if (not isinstance(value, str) or len(value) > self._max_length
                or not self._regex.match(value)):
            raise ValueError(f"{where % args}: {value!r:.60} is not a valid id")
        if len(self._valid) >= self._limit:
            self._valid.clear()
        self._valid.add(value)
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


def pose_from_wire(d: Any, to_local: Callable[[int], int] = lambda t: t) -> PoseResult:
    """A segment answer (a ``schemas.models.PoseResult`` map) as a result, timestamps mapped
    by ``to_local``; ``ValueError`` names the first field that is wrong.

    The hot-path twin of ``PoseResult.model_validate`` (the documented contract; pydantic
    validates descriptors and API results, not per-message hot paths): the same
    fields, shapes, ids, finiteness and unit quaternion (renormalized), at a tenth of the
    cost.  ``tests/test_client_wire.py`` holds the two to the same verdicts.
    """
    if not isinstance(d, dict):
        raise ValueError(f"pose result: expected a map, got {type(d).__name__}")
    if not d.keys() <= _WIRE_FIELDS:
        extra = sorted(map(str, d.keys() - _WIRE_FIELDS))
        raise ValueError(f"pose result: unexpected field(s) {', '.join(extra)}")
    for name in ("source", "target", "t_ns", "position", "quaternion"):
        if name not in d:
            raise ValueError(f"pose result: missing field {name!r}")
    _frame_id(d["source"], "source")
    _frame_id(d["target"], "target")
    t_ns = _wire_int(d["t_ns"], "t_ns")
    position = _wire_floats(d["position"], 3, "position")
    q = _wire_floats(d["quaternion"], 4, "quaternion")
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise ValueError(f"quaternion: norm {norm:.6g} is not 1 (tolerance {QUAT_NORM_TOL:g}); "
                         "quaternions are x, y, z, w")
    cov = d.get("covariance")
    if cov is not None:
        cov = _wire_covariance(cov)
    path = d.get("path", [])
    if not isinstance(path, list):
        raise ValueError(f"path: expected a list of frame ids, got {path!r:.60}")
    for i, frame in enumerate(path):
        _frame_id(frame, "path[%d]", i)
    edges = d.get("edges", [])
    if not isinstance(edges, list):
        raise ValueError(f"edges: expected a list, got {edges!r:.60}")
    edges = [_wire_edge(e, i, to_local) for i, e in enumerate(edges)]
    extrapolated = d.get("extrapolated_s", 0.0)
    if (isinstance(extrapolated, bool) or not isinstance(extrapolated, float | int)
            or not math.isfinite(extrapolated) or extrapolated < 0):
        raise ValueError(f"extrapolated_s: expected a finite number >= 0, got {extrapolated!r}")
    attributes = _wire_attributes(d.get("attributes", {}))
    stamps = [(e["t_ns"], e["t_ns"]) for e in edges]
    return PoseResult(np.array(position), np.array(q) / norm, cov, list(path), edges,
                      to_local(t_ns), float(extrapolated), stamps, attributes)


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


def parse_summary(msg: Mapping[str, Any]) -> Summary:
    """A decoded supernode message as a :class:`Summary`; ``ValueError`` says what is wrong."""
    agent, frames = msg.get("agent"), msg.get("frames")
    if not isinstance(agent, str) or not agent:
        raise ValueError(f"summary: agent must be a non-empty string, got {agent!r}")
    if not isinstance(frames, list) or not all(isinstance(f, str) for f in frames):
        raise ValueError("summary: frames must be a list of strings")
    components = msg.get("components", [])
    links_in = msg.get("links", [])
    if not isinstance(components, list) or not isinstance(links_in, list):
        raise ValueError("summary: components and links must be lists")
    links = []
    for link in links_in:
        if not (isinstance(link, dict) and isinstance(link.get("a"), str)
                and isinstance(link.get("b"), str) and isinstance(link.get("attrs"), dict)):
            raise ValueError(f"summary: malformed link {link!r:.120}")
        attrs = {k: attributes_from_wire(v) for k, v in link["attrs"].items()
                 if k in SUMMARY_ERRORS and isinstance(v, dict)}
        if set(attrs) != set(SUMMARY_ERRORS):
            raise ValueError(f"summary: link {link['a']}-{link['b']} lacks attributes for "
                             f"{', '.join(sorted(set(SUMMARY_ERRORS) - set(attrs)))}")
        links.append((link["a"], link["b"], attrs))
    rev, instance = msg.get("rev", 0), msg.get("instance", "")
    return Summary(agent, rev if isinstance(rev, int) else 0, set(frames),
                   [set(c) for c in components if isinstance(c, list)], links,
                   instance if isinstance(instance, str) else "")


def _link_value(fn: ErrorFunction, attrs: Mapping[str, dict[str, Any]]) -> float:
    """A link's error: its best local path for a built-in; for an expression, the best of the
    paths the summary describes."""
    if fn.key in attrs:
        return fn.path_value(attrs[fn.key])
    return min(fn.path_value(a) for a in attrs.values())


def _link_attrs(fn: ErrorFunction, attrs: Mapping[str, dict[str, Any]]) -> dict[str, Any]:
    if fn.key in attrs:
        return attrs[fn.key]
    return min(attrs.values(), key=fn.path_value)


def joined_attributes(parts: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Attributes of a route from its links' (for ranking; the answer has the exact ones):
    latencies, costs, hops and covariance traces add, standard deviations add in quadrature."""
    out = combine(parts, np.zeros(3), None)
    out["accuracy"] = sum(p.get("accuracy", 0.0) for p in parts)
    out["pos_std_m"] = math.sqrt(sum(p.get("pos_std_m", 0.0) ** 2 for p in parts))
    out["rot_std_rad"] = math.sqrt(sum(p.get("rot_std_rad", 0.0) ** 2 for p in parts))
    return out


def plan_routes(summaries: Mapping[str, Summary], source: str, target: str,
                fn: ErrorFunction, k: int = 8) -> list[Route]:
    """Routes from ``source`` to ``target``, best first, through every known agent (alive or
    not: the caller skips the dead ones but names them when nothing else is left)."""
    known = set().union(*(s.frames for s in summaries.values())) if summaries else set()
    for frame in (source, target):
        if frame not in known:
            raise UnknownFrameError(frame, known)
    routes: list[Route] = []
    adj: dict[str, list] = {}
    link_attrs: dict[tuple, dict] = {}
    for s in summaries.values():
        for a, b, attrs in s.links:
            key = (s.agent, a, b)
            link_attrs[key] = attrs
            adj.setdefault(a, []).append((b, key, True))
            adj.setdefault(b, []).append((a, key, False))
    if source in adj and target in adj:
        if fn.additive:
            found = paths.k_shortest(adj, source, target,
                                     lambda key: _link_value(fn, link_attrs[key]), k)
        else:
            found = paths.k_shortest(adj, source, target, lambda key: 1.0,
                                     max(k, ROUTE_CANDIDATES))
        for path in found:
            parts = [_link_attrs(fn, link_attrs[key]) for key, _ in path.steps]
            joined = joined_attributes(parts)
            segments = _merge(path)
            routes.append(Route(segments, fn.path_value(joined), joined))
    linked = {tuple(r.segments) for r in routes}
    for s in summaries.values():
        # one agent holds both frames but neither is a boundary frame, so no link describes
        # its local path: that agent answers alone, and a local answer is preferred
        if any(source in c and target in c for c in s.components):
            direct = [Segment(s.agent, source, target)]
            if tuple(direct) not in linked:
                routes.append(Route(direct, -math.inf))
    if not routes:
        raise UnreachableError(source, target, _reach(adj, summaries, source),
                               _reach(adj, summaries, target))
    unique: dict[tuple, Route] = {}
    for route in sorted(routes, key=lambda r: r.value):
        unique.setdefault(tuple(route.segments), route)
    return list(unique.values())[: max(k, 1)]


def _reach(adj: Mapping, summaries: Mapping[str, Summary], frame: str) -> set[str]:
    out = paths.reachable(adj, frame) if frame in adj else {frame}
    for s in summaries.values():
        for c in s.components:
            if frame in c:
                out |= c
    return out


def _merge(path: paths.Path) -> list[Segment]:
    """Consecutive links of one agent become one segment (that agent finds its best path)."""
    segments: list[Segment] = []
    for i, (key, _) in enumerate(path.steps):
        agent = key[0]
        a, b = path.frames[i], path.frames[i + 1]
        if segments and segments[-1].agent == agent:
            segments[-1] = Segment(agent, segments[-1].source, b)
        else:
            segments.append(Segment(agent, a, b))
    return segments


def usable_routes(routes: Sequence[Route], alive: set[str], source: str,
                  target: str) -> list[Route]:
    """The routes whose agents are all alive; ``RouteError`` names what is missing if none."""
    ok = [r for r in routes if set(r.agents) <= alive]
    if ok:
        return ok
    best = routes[0]
    missing = [str(s) for s in best.segments if s.agent not in alive]
    gone = sorted({s.agent for s in best.segments if s.agent not in alive})
    raise RouteError(
        f"no route from {source!r} to {target!r}: the best route needs segment(s) "
        f"{'; '.join(missing)}, but agent(s) {list_names(gone)} left the realm, and no "
        f"other route exists ({len(routes)} considered)")


def compose(results: Sequence[PoseResult], t_ns: int | None) -> PoseResult:
    """Chain segment answers source -> target, propagating the covariance (first order)."""
    chain = Composition(len(results))
    for i, r in enumerate(results):
        chain.add(i, r)
    return chain.result(t_ns)


class Composition:
    """Segment answers chained source -> target as they arrive, covariance propagated (first
    order).  Answers of neighbouring segments are merged into runs at once, in whatever
    order they come, so when the slowest agent answers only its own segment is left to
    merge with the runs beside it (the others were composed while it computed).

    Merging run ``X`` with the run ``Y`` right of it uses ``X``'s adjoint: its rotation
    block carries ``Y``'s position into ``X``'s source frame and it maps ``Y``'s covariance
    there (``C = C_X + Ad_X C_Y Ad_X^T``).  A run that ends at the last segment never needs
    its adjoint.
    """

    def __init__(self, n: int) -> None:
        if n < 1:
            raise ValueError("a composition needs at least one segment")
        self._results: list[PoseResult | None] = [None] * n
        self._starting: dict[int, _Run] = {}  # runs by their first segment
        self._ending: dict[int, _Run] = {}  # the same runs by their last segment

    def add(self, i: int, result: PoseResult) -> None:
        """Segment ``i``'s answer (each segment once)."""
        if self._results[i] is not None:
            raise ValueError(f"segment {i} was already added")
        self._results[i] = result
        last = len(self._results) - 1
        run = _Run(i, i, result.position, result.quaternion, result.covariance,
                   None if i == last else geo.adjoint(result.position, result.quaternion))
        left = self._ending.pop(i - 1, None)
        if left is not None:
            del self._starting[left.first]
            run = left.then(run, last)
        right = self._starting.pop(i + 1, None)
        if right is not None:
            del self._ending[right.final]
            run = run.then(right, last)
        self._starting[run.first] = run
        self._ending[run.final] = run

    def result(self, t_ns: int | None) -> PoseResult:
        """The composed pose at ``t_ns``; ``ValueError`` if a segment is still missing."""
        missing = [i for i, r in enumerate(self._results) if r is None]
        if missing:
            raise ValueError(f"segment(s) {missing} missing from the composition")
        results: list[PoseResult] = self._results  # type: ignore[assignment]
        whole = self._starting[0]
        path: list[str] = []
        edges: list[dict[str, Any]] = []
        stamps: list[tuple[int, int]] = []
        for r in results:
            path.extend(r.path if not path else r.path[1:])
            edges.extend(r.edges)
            stamps.extend(r.stamps)
        extrapolated = max(r.extrapolated_s for r in results)
        parts = [r.attributes for r in results]
        # runs start from the segments' own arrays: the result must not alias them
        p, q, cov = whole.p, whole.q, whole.cov
        if len(results) == 1:
            p, q = p.copy(), q.copy()
        if cov is not None and any(cov is r.covariance for r in results):
            cov = cov.copy()
        return PoseResult(p, q, cov, path, edges, t_ns, extrapolated, stamps,
                          lambda: combine(parts, p, cov))


@dataclass
class _Run:
    """Segments ``first..final`` composed: pose, covariance, and adjoint (None when the run
    ends at the last segment: nothing is ever right of it)."""

    first: int
    final: int
    p: np.ndarray
    q: np.ndarray
    cov: np.ndarray | None
    Ad: np.ndarray | None

    def then(self, right: _Run, last: int) -> _Run:
        """This run followed by the one right of it."""
        J = self.Ad
        cov = self.cov
        if right.cov is not None:
            mapped = J @ right.cov @ J.T
            cov = mapped if cov is None else cov + mapped
        return _Run(self.first, right.final, self.p + J[:3, :3] @ right.p,
                    geo.quat_multiply(self.q, right.q), cov,
                    None if right.final == last else J @ right.Ad)
