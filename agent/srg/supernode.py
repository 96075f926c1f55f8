"""Supernode summaries (Klinker, Bauer 2005, §1.3.3 "Super Nodes"): an agent's SRG condensed.

Other agents need not see every edge of a host, only how well the host can link the frames
that matter across hosts.  A summary lists the agent's frames, its *boundary* frames (those
another agent also knows: a shared frame id is what links two agents' graphs) and, for every
frame and every boundary frame of the same connected part, the attributes of the best local
path between them under each built-in error function.  A planner joins summaries into a
graph whose edges are these links, finds a route, and asks each owning agent for its
segment at the query time.

Cost: a summary grows with frames x boundary frames, so its work must not grow
faster.  No query plan is built: per boundary frame, one shortest-path tree (Dijkstra from
that frame) gives every frame's best path to it, whose attributes are extended by one edge
from those of the path it continues (one composition per frame).  Where a path is made only
of bridges (edges whose removal splits the graph) it is the only simple path, so every
error function picks it: in a tree-shaped SRG one search per boundary frame serves all five.
Only frames whose paths cross a cycle need the other additive trees (latency, confidence,
cost) and, for ``accuracy`` (path-level: the most accurate of the hop-ranked candidates, as
a local query ranks them), a candidate search of their own.  Equally good paths may be
tied differently than a query's search from the other end would; their ranked value is the
same.  A summary reads a :class:`Topology` copied under the graph's lock and is computed
without it.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.attributes import SUMMARY_ERRORS, combine, path_constants
from agent.result import finite_or_none
from agent.srg import paths
from agent.srg.edge import EdgeKey
from agent.srg.errorfn import ErrorFunction, error_function
from agent.srg.graph import PATH_LEVEL_CANDIDATES, Graph
from agent.srg.plan import compose_values, nominal_attributes, oriented

#: the additive ones besides hops: their trees are grown only where a path crosses a cycle
_OTHER_ADDITIVE = ("latency", "confidence", "cost")


@dataclass(frozen=True)
class Topology:
    """What a summary reads of a graph: its adjacency, each edge's attributes (with
    ``static``) and nominal value ``(p, q, covariance)``.  Copied (``of``) under the lock
    that guards the graph, so that the summary itself holds no lock while it is computed."""

    adj: dict[str, list[tuple[str, EdgeKey, bool]]]
    attrs: dict[EdgeKey, dict[str, Any]]
    nominal: dict[EdgeKey, tuple]
    #: how many hop-ranked candidates a path-level error function compares (as a query)
    candidates: int
    #: nominal values as walked, computed once per edge and direction (``walked``)
    _walked: dict[tuple[EdgeKey, bool], tuple] = field(default_factory=dict, repr=False,
                                                       compare=False)

    def walked(self, key: EdgeKey, forward: bool) -> tuple:
        """An edge's nominal ``(p, q, covariance)`` as walked: the trees of every boundary
        frame and error function walk most edges the same way (an inverse costs tens of
        microseconds, a summary walks thousands)."""
        value = self._walked.get((key, forward))
        if value is None:
            value = self._walked[(key, forward)] = oriented(*self.nominal[key], forward)
        return value

    @classmethod
    def of(cls, graph: Graph) -> Topology:
        """A copy of what ``summarize`` needs of ``graph``.  The newest sample of a measured
        edge is its nominal value: copied, as the buffer it lives in keeps changing (a
        static value is replaced, never changed in place)."""
        adj = graph.adjacency()
        attrs: dict[EdgeKey, dict[str, Any]] = {}
        nominal: dict[EdgeKey, tuple] = {}
        for steps in adj.values():
            for _, key, forward in steps:
                if forward:  # every edge is listed once forwards
                    edge = graph.edge(*key)
                    attrs[key] = dict(edge.attrs, static=edge.is_static)
                    nominal[key] = edge.value if edge.is_static else tuple(
                        None if x is None else np.array(x) for x in edge.nominal())
        return cls(adj, attrs, nominal, max(PATH_LEVEL_CANDIDATES, graph.k_paths))


def summarize(graph: Graph | Topology, boundary: Iterable[str]) -> dict[str, Any]:
    """``frames``, ``boundary``, ``components`` and ``links`` of ``graph`` (plain data).

    Each link is ``{"a": frame, "b": boundary frame, "attrs": {error: path attributes}}``;
    infinite attributes (the update rate of an all-static path) are None.
    """
    top = graph if isinstance(graph, Topology) else Topology.of(graph)
    frames = sorted(top.adj)
    ports = set(boundary).intersection(frames)
    components = paths.components(top.adj)
    bridges = paths.bridges(top.adj) if ports else set()
    links = []
    for part in components:
        for b in sorted(ports.intersection(part)):
            best = best_paths_to(top, b, bridges)
            for a in part:
                if a == b or (a in ports and a < b):
                    continue  # two boundary frames are linked once
                finite = {id(x): finite_or_none(x) for x in best[a].values()}  # once a path
                attrs = {e: finite[id(best[a][e])] for e in SUMMARY_ERRORS}
                links.append({"a": a, "b": b, "attrs": attrs})
    return {"frames": frames, "boundary": sorted(ports), "components": components,
            "links": links}


def best_paths_to(top: Topology, root: str, bridges: set[EdgeKey],
                  ) -> dict[str, dict[str, dict[str, Any]]]:
    """Per frame of ``root``'s part, the attributes of its best path to ``root`` under each
    error function of ``SUMMARY_ERRORS`` (module docstring: which searches this takes)."""
    hops = _grow(top, root, error_function("hops"), bridges, None)
    best = {a: dict.fromkeys(SUMMARY_ERRORS, attrs) for a, attrs in hops.attrs.items()}
    crossing = [a for a, unique in hops.unique.items() if not unique]
    if not crossing:
        return best
    for name in _OTHER_ADDITIVE:
        tree = _grow(top, root, error_function(name), bridges, hops)
        for a in crossing:  # a frame no path of finite weight reaches keeps the hop path
            best[a][name] = tree.attrs.get(a, hops.attrs[a])
    for a in crossing:
        best[a]["accuracy"] = _most_accurate(top, a, root)
    return best


@dataclass
class _Tree:
    """Best paths to one root: per frame, its path's composed ``(p, q, covariance)``, its
    attributes, and whether it is the only simple path (bridges all the way)."""

    values: dict[str, tuple] = field(default_factory=dict)
    attrs: dict[str, dict[str, Any]] = field(default_factory=dict)
    unique: dict[str, bool] = field(default_factory=dict)


def _grow(top: Topology, root: str, fn: ErrorFunction, bridges: set[EdgeKey],
          known: _Tree | None) -> _Tree:
    """The shortest-path tree of additive ``fn`` towards ``root``, each frame's path one
    edge more than the path it continues.  A frame whose path is the only one takes its
    value and attributes from ``known`` (any tree holds the same path for it)."""
    tree = _Tree({root: (np.zeros(3), geo.quat_identity(), None)}, {}, {root: True})
    steps = paths.shortest_tree(top.adj, root, lambda key: fn.edge_weight(top.attrs[key]))
    for a, nxt, key, forward in steps:
        unique = key in bridges and tree.unique[nxt]
        tree.unique[a] = unique
        if unique and known is not None:
            tree.values[a], tree.attrs[a] = known.values[a], known.attrs[a]
            continue
        value = compose_values(top.walked(key, forward), tree.values[nxt])
        tree.values[a] = value
        rest = [] if nxt == root else [tree.attrs[nxt]]
        tree.attrs[a] = combine([path_constants([top.attrs[key]]), *rest], value[0], value[2])
    return tree


def _most_accurate(top: Topology, a: str, root: str) -> dict[str, Any]:
    """``accuracy``'s best path from ``a`` to ``root`` as a local query ranks it: the most
    accurate of the hop-ranked candidates (path-level, so no tree can find it)."""
    fn = error_function("accuracy")
    found = paths.k_shortest(top.adj, a, root, lambda _: 1.0, top.candidates)
    ranked = (nominal_attributes([top.attrs[k] for k, _ in p.steps],
                                 [top.walked(k, fwd) for k, fwd in p.steps])
              for p in found)
    return min(ranked, key=fn.path_value)
