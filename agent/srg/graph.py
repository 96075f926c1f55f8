"""The spatial relationship graph of Klinker, Bauer 2005, §1.3: frames, edges, and pose queries.

A general directed multigraph: cycles, several parents and parallel edges between the same
frames (distinguished by their ``source``, e.g. the service and ability that measure them)
are all fine, unlike tf2's tree.  Edges are walked both ways (inverse pose and covariance).
Static edges hold one value; measured edges hold a bounded time buffer that is
interpolated (lerp + slerp) at the query time and extrapolated, boundedly and visibly, past
its ends.  Queries compile to cached plans (:mod:`agent.srg.plan`).  A new sample never
invalidates a plan.  Removing an edge invalidates the plans whose candidate paths use it.
Adding an edge, or changing an edge's attributes or static value, invalidates the plans
whose searched component contains it: the plans that use it, and those for which it might
now be part of a better path; plans of other components are kept (nothing there can change
their best path).

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

import math
import numbers
from collections import OrderedDict
from collections.abc import Iterable
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.attributes import aggregate, check_attributes, same_attributes
from agent.errors import InvalidInputError
from agent.result import PoseResult
from agent.srg import paths
from agent.srg.edge import Edge, EdgeKey, edge_name
from agent.srg.errorfn import ErrorFunction, error_function
from agent.srg.errors import UnknownEdgeError, UnknownFrameError, UnreachableError
from agent.srg.plan import Chain, Plan

DEFAULT_STATIC_SOURCE = "static"
DEFAULT_MEASURED_SOURCE = "measured"
#: candidate paths a path-level error function evaluates (ranked by hops first)
PATH_LEVEL_CANDIDATES = 16
#: query plans kept (least recently used dropped first): every distinct error expression of
#: a query is a plan, so a peer sending distinct expressions must not grow the cache
MAX_PLANS = 1024

PlanKey = tuple[str, str, str]


def _frame(name: str, value: Any) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InvalidInputError(f"{name} frame must be a non-empty string, got {value!r}")
    return value


def _time(t_ns: Any) -> int:
    if type(t_ns) is int:  # the common case, before the slower abstract check
        return t_ns
    if isinstance(t_ns, bool) or not isinstance(t_ns, numbers.Integral):
        raise InvalidInputError(f"time must be integer nanoseconds since the epoch, got {t_ns!r}")
    return int(t_ns)


def _same_kwargs(a: dict[str, Any], b: dict[str, Any] | None) -> bool:
    """Whether a sample repeats the attributes of the previous one (the common case:
    checking them again per sample would cost more than the sample)."""
    if b is None or a.keys() != b.keys():
        return False
    try:
        return all(a[k] is b[k] or bool(a[k] == b[k]) for k in a)
    except ValueError:  # arrays (a covariance): compare properly
        return same_attributes(a, b)


def identity(frame: str, t_ns: int | None) -> PoseResult:
    """The pose of a frame in itself (as tf2 answers it): exact, no edges."""
    p = np.zeros(3)
    return PoseResult(p, geo.quat_identity(), None, [frame], [], t_ns, 0.0, [],
                      aggregate([], p, None))


class Graph:
    """An SRG with per-edge time buffers and cached query plans (no I/O, numpy only).

    ``buffer_s`` and ``max_samples`` bound each measured edge's history;
    ``max_extrapolation_s`` bounds how far past its samples an edge is extrapolated (an
    edge's ``ttl_s`` lowers it); ``k_paths`` is how many ranked candidates a plan keeps
    to fall back on when the best path is undefined at the query time; ``max_plans`` how
    many plans are cached (least recently used evicted first, counted in
    ``plans_evicted``).
    """

    def __init__(self, buffer_s: float = 10.0, max_extrapolation_s: float = 0.1,
                 max_samples: int = 1000, k_paths: int = 4,
                 max_plans: int = MAX_PLANS) -> None:
        if not buffer_s > 0:
            raise InvalidInputError(f"buffer_s must be > 0, got {buffer_s!r}")
        if not max_extrapolation_s >= 0:
            raise InvalidInputError(
                f"max_extrapolation_s must be >= 0, got {max_extrapolation_s!r}")
        if k_paths < 1:
            raise InvalidInputError(f"k_paths must be >= 1, got {k_paths!r}")
        if max_plans < 1:
            raise InvalidInputError(f"max_plans must be >= 1, got {max_plans!r}")
        self.buffer_s = float(buffer_s)
        self.max_extrapolation_s = float(max_extrapolation_s)
        self.max_samples = int(max_samples)
        self.k_paths = int(k_paths)
        self.max_plans = int(max_plans)
        self._edges: dict[EdgeKey, Edge] = {}
        self._adj: dict[str, list[tuple[str, EdgeKey, bool]]] = {}
        self._plans: OrderedDict[PlanKey, Plan] = OrderedDict()
        self._plans_by_frame: dict[str, set[PlanKey]] = {}
        self._plans_by_edge: dict[EdgeKey, set[PlanKey]] = {}
        #: how many plans were compiled (tests and benchmarks watch the cache with it)
        self.plans_built = 0
        #: how many plans were dropped to keep at most ``max_plans``
        self.plans_evicted = 0
        #: incremented on every structural or attribute change (summaries watch it)
        self.version = 0
        #: samples ever added: with ``version``, what an answer at the latest time depends on
        self.samples = 0

    # ------------------------------------------------------------------ edges

    def add_static(self, parent: str, child: str, position: Any, quaternion: Any,
                   covariance: Any = None, *, source: str = DEFAULT_STATIC_SOURCE,
                   **attributes: Any) -> EdgeKey:
        """Add or replace a static edge (a calibration: one value valid at all times)."""
        key = self._key(parent, child, source)
        p = geo.check_vector(position, "position").reshape(3)
        q = geo.check_quaternion(quaternion, "quaternion").reshape(4)
        attrs = check_attributes(attributes)
        attrs.pop("static", None)
        cov = None if covariance is None else geo.check_covariance(covariance)
        old = self._edges.get(key)
        if old is not None and not old.is_static:
            raise InvalidInputError(f"edge {edge_name(key)} is measured; remove it before adding a "
                                    "static edge with the same source")
        edge = Edge(key, attrs, static_value=(p, q, cov if cov is not None
                                              else self._nominal_cov(attrs, p)))
        if old is None:
            self._link(edge)
        else:
            self._edges[key] = edge
            self._changed(key)
        return key

    @staticmethod
    def _nominal_cov(attrs: dict, p: np.ndarray) -> np.ndarray | None:
        if "covariance" in attrs:
            return attrs["covariance"]
        return geo.covariance_from_std(p, attrs.get("pos_std_m"), attrs.get("rot_std_rad"))

    def add_measurement(self, parent: str, child: str, t_ns: int, position: Any,
                        quaternion: Any, covariance: Any = None, *,
                        source: str = DEFAULT_MEASURED_SOURCE, **attributes: Any) -> EdgeKey:
        """Append a sample to a measured edge, creating the edge on its first sample.

        Attributes given here update the edge's attributes (and invalidate plans) only
        when they differ from the stored ones; a plain new sample never invalidates.
        """
        key = (parent, child, source)
        edge = self._edges.get(key)
        if edge is None or (attributes and not _same_kwargs(attributes, edge.last_kwargs)):
            edge = self._edges[self.declare_measured(parent, child, source=source,
                                                     **attributes)]
            edge.last_kwargs = attributes
        elif edge.buffer is None:
            raise InvalidInputError(f"edge {edge.name} is static; it takes no measurements")
        t = _time(t_ns)
        p = geo.check_vector(position, "position").reshape(3)
        q = geo.check_quaternion(quaternion, "quaternion").reshape(4)
        cov = None if covariance is None else geo.check_covariance(covariance)
        edge.buffer.add(t, p, q, cov)
        self.samples += 1
        return key

    def add_decoded(self, parent: str, child: str, t_ns: int,
                    position: tuple[float, float, float],
                    quaternion: tuple[float, float, float, float],
                    covariance: np.ndarray | None = None, *,
                    source: str = DEFAULT_MEASURED_SOURCE) -> EdgeKey:
        """:meth:`add_measurement` of a sample as ``schemas.codec.decode_pose`` gives it:
        its values were checked there (finite, a unit quaternion, a checked covariance), so
        they go into the buffer as they are, the quaternion renormalised as
        ``add_measurement`` does (the agent and the SDK put every received sample here)."""
        key = (parent, child, source)
        edge = self._edges.get(key)
        if edge is None:
            edge = self._edges[self.declare_measured(parent, child, source=source)]
            edge.last_kwargs = {}
        elif edge.buffer is None:
            raise InvalidInputError(f"edge {edge.name} is static; it takes no measurements")
        x, y, z, w = quaternion
        n = math.sqrt(x * x + y * y + z * z + w * w)
        edge.buffer.add_value(t_ns, (*position, x / n, y / n, z / n, w / n), covariance)
        self.samples += 1
        return key

    def declare_measured(self, parent: str, child: str, *,
                         source: str = DEFAULT_MEASURED_SOURCE, **attributes: Any) -> EdgeKey:
        """Create a measured edge without samples yet (an ability was declared), or update
        its attributes; the edge is then known to path searches."""
        key = self._key(parent, child, source)
        attrs = check_attributes(attributes)
        attrs.pop("static", None)
        edge = self._edges.get(key)
        if edge is None:
            self._link(Edge(key, attrs, buffer_s=self.buffer_s, max_samples=self.max_samples))
        elif edge.buffer is None:
            raise InvalidInputError(f"edge {edge.name} is static; it takes no measurements")
        else:
            merged = dict(edge.attrs, **attrs)
            if not same_attributes(merged, edge.attrs):
                edge.set_attributes(merged)
                self._changed(key)
        return key

    def set_attributes(self, parent: str, child: str, source: str | None = None,
                       **attributes: Any) -> None:
        """Change attributes of an edge (``None`` removes one); invalidates affected plans."""
        edge = self._edge(parent, child, source)
        merged = dict(edge.attrs)
        for name, value in attributes.items():
            if value is None:
                merged.pop(name, None)
        merged.update(check_attributes(attributes))
        merged.pop("static", None)
        if same_attributes(merged, edge.attrs):
            return
        edge.set_attributes(merged)
        if edge.is_static and "covariance" not in merged:
            p, q, _ = edge.value
            edge.value = (p, q, self._nominal_cov(merged, p))
        self._changed(edge.key)

    def remove_edge(self, parent: str, child: str, source: str | None = None) -> int:
        """Remove the edge from ``parent`` to ``child`` of ``source`` (None: every one).

        Returns how many edges were removed; ``UnknownEdgeError`` if none matched.
        """
        keys = [k for k in self._edges if k[0] == parent and k[1] == child
                and (source is None or k[2] == source)]
        if not keys:
            raise UnknownEdgeError(f"{parent}->{child}" + (f" [{source}]" if source else ""),
                              self._between(parent, child))
        for key in keys:
            self._unlink(key)
        return len(keys)

    def remove_source(self, source: str) -> int:
        """Remove every edge of one source (a service or ability that went away)."""
        keys = [k for k in self._edges if k[2] == source]
        for key in keys:
            self._unlink(key)
        return len(keys)

    # ------------------------------------------------------------------ inspection

    def frames(self) -> list[str]:
        return sorted(self._adj)

    def edges(self) -> list[dict[str, Any]]:
        """Every edge with its attributes and, for measured ones, its sample count and span."""
        out = []
        for edge in self._edges.values():
            info = edge.info()
            info["attributes"] = {k: v for k, v in edge.attrs.items() if k != "covariance"}
            if edge.buffer is not None:
                buf = edge.buffer
                info["samples"] = len(buf)
                info["newest_ns"] = buf.newest_ns
            out.append(info)
        return out

    def edge(self, parent: str, child: str, source: str | None = None) -> Edge:
        """The edge object (read-only use: its attributes, buffer or static value)."""
        return self._edge(parent, child, source)

    def has_plan(self, source: str, target: str, error: str | ErrorFunction = "hops") -> bool:
        """Whether a query plan for this triple is cached (tests observe invalidation)."""
        return (source, target, error_function(error).key) in self._plans

    def components(self) -> list[list[str]]:
        """The connected parts of the graph (frames linked by any chain of edges)."""
        return paths.components(self._adj)

    def adjacency(self) -> dict[str, list[tuple[str, EdgeKey, bool]]]:
        """A copy of frame -> [(neighbour, edge key, walked forwards?)]: what a path search
        over a snapshot of the graph needs (a summary is computed off the graph's lock)."""
        return {frame: list(steps) for frame, steps in self._adj.items()}

    # ------------------------------------------------------------------ queries

    def pose(self, source: str, target: str, at: int | None = None,
             error: str | ErrorFunction = "hops") -> PoseResult:
        """The pose of ``target`` in ``source``'s frame at ``at`` (ns; None: the latest time
        at which every measured edge of the path has data), along the best path for
        ``error`` among those defined at that time."""
        fn = error_function(error)
        plan = self._cached_plan((source, target, fn.key))
        if plan is None:
            if source == target and source in self._adj:
                return identity(source, None if at is None else _time(at))
            plan = self._build_plan(source, target, fn)
        return plan.evaluate(None if at is None else _time(at))

    def plan(self, source: str, target: str, error: str | ErrorFunction = "hops") -> Plan:
        """The compiled query of :meth:`pose` (``source`` != ``target``): its ``evaluate(at)``
        answers as :meth:`pose` does, for as long as :attr:`version` is unchanged.  A caller
        that asks the same route again and again (a kept route) keeps it."""
        fn = error_function(error)
        return self._cached_plan((source, target, fn.key)) or self._build_plan(source, target,
                                                                                fn)

    def _cached_plan(self, key: PlanKey) -> Plan | None:
        """The cached plan of a query, marked as the most recently used."""
        plan = self._plans.get(key)
        if plan is not None:
            self._plans.move_to_end(key)
        return plan

    def best_paths(self, source: str, target: str, error: str | ErrorFunction = "hops",
                   ) -> list[Chain]:
        """The ranked candidate paths (with their attributes) a query would try, best first."""
        return list(self.plan(source, target, error).chains)

    def _build_plan(self, source: str, target: str, fn: ErrorFunction) -> Plan:
        for frame in (source, target):
            if frame not in self._adj:
                raise UnknownFrameError(frame, self._adj)
        component = paths.reachable(self._adj, source)
        if target not in component:
            raise UnreachableError(source, target, component, paths.reachable(self._adj, target))
        edges = self._edges
        if fn.additive:
            found = paths.k_shortest(self._adj, source, target,
                                     lambda k: fn.edge_weight(edges[k].attrs), self.k_paths)
        else:
            found = paths.k_shortest(self._adj, source, target, lambda k: 1.0,
                                     max(PATH_LEVEL_CANDIDATES, self.k_paths))
        chains = [Chain(path.frames, [(edges[k], fwd) for k, fwd in path.steps],
                        self.max_extrapolation_s) for path in found]
        if not fn.additive:
            chains.sort(key=lambda c: fn.path_value(c.attributes))
            chains = chains[: self.k_paths]
        if not chains:
            raise UnreachableError(source, target, component, component)
        key = (source, target, fn.key)
        plan = Plan(source, target, chains, component)
        self._plans[key] = plan
        for frame in component:
            self._plans_by_frame.setdefault(frame, set()).add(key)
        for ek in plan.edge_keys:
            self._plans_by_edge.setdefault(ek, set()).add(key)
        self.plans_built += 1
        if len(self._plans) > self.max_plans:
            self._invalidate([next(iter(self._plans))])  # the least recently used
            self.plans_evicted += 1
        return plan

    # ------------------------------------------------------------------ internals

    def _key(self, parent: str, child: str, source: str) -> EdgeKey:
        _frame("parent", parent)
        _frame("child", child)
        if parent == child:
            raise InvalidInputError(f"an edge needs two different frames, got {parent!r} twice")
        if not isinstance(source, str) or not source:
            raise InvalidInputError(f"edge source must be a non-empty string, got {source!r}")
        return (parent, child, source)

    def _between(self, a: str, b: str) -> list[str]:
        return [edge_name(k) for k in self._edges if {k[0], k[1]} == {a, b}]

    def _edge(self, parent: str, child: str, source: str | None) -> Edge:
        if source is not None:
            edge = self._edges.get((parent, child, source))
            if edge is None:
                raise UnknownEdgeError(f"{parent}->{child} [{source}]",
                                       self._between(parent, child))
            return edge
        found = [e for k, e in self._edges.items() if k[0] == parent and k[1] == child]
        if len(found) != 1:
            if not found:
                raise UnknownEdgeError(f"{parent}->{child}", self._between(parent, child))
            raise InvalidInputError(f"{len(found)} parallel edges {parent}->{child}: name the "
                                    f"source ({', '.join(e.source for e in found)})")
        return found[0]

    def _link(self, edge: Edge) -> None:
        key = edge.key
        self._edges[key] = edge
        self._adj.setdefault(key[0], []).append((key[1], key, True))
        self._adj.setdefault(key[1], []).append((key[0], key, False))
        self._changed(key)

    def _unlink(self, key: EdgeKey) -> None:
        self._invalidate(self._plans_by_edge.get(key, set()))
        del self._edges[key]
        for frame in key[:2]:
            rest = [a for a in self._adj[frame] if a[1] != key]
            if rest:
                self._adj[frame] = rest
            else:
                del self._adj[frame]
        self.version += 1

    def _changed(self, key: EdgeKey) -> None:
        """An edge appeared or its attributes changed: any plan over its component may now
        have a better path (a plan elsewhere cannot)."""
        affected: set[PlanKey] = set()
        for frame in key[:2]:
            affected |= self._plans_by_frame.get(frame, set())
        self._invalidate(affected)
        self.version += 1

    def _invalidate(self, keys: Iterable[PlanKey]) -> None:
        for pk in list(keys):
            plan = self._plans.pop(pk, None)
            if plan is None:
                continue
            for frame in plan.frames:
                _discard(self._plans_by_frame, frame, pk)
            for ek in plan.edge_keys:
                _discard(self._plans_by_edge, ek, pk)


def _discard(index: dict[Any, set[PlanKey]], key: Any, pk: PlanKey) -> None:
    """Take a plan out of an index entry, and the entry out when it is empty (an index of
    a removed edge or frame must not stay behind)."""
    s = index.get(key)
    if s is not None:
        s.discard(pk)
        if not s:
            del index[key]
