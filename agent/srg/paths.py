"""Shortest and k-shortest simple paths over a multigraph walked in both directions.

The SRG and the planner's graph of supernode summaries both use these: nodes are frame
ids, each edge has a key (parallel edges between the same frames are distinct keys) and
may be walked forwards or backwards.  Additive error functions rank paths by the sum of
per-edge weights (Dijkstra); path-level ones (Klinker, Bauer 2005: e : A* -> R) are
evaluated on the k shortest simple paths found by Yen's algorithm.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from agent.errors import InvalidInputError

#: frame -> [(neighbour frame, edge key, walked forwards?)]
Adjacency = Mapping[str, Sequence[tuple[str, Hashable, bool]]]
Weight = Callable[[Hashable], float]


@dataclass(frozen=True)
class Path:
    """A simple path: ``frames[i] -> frames[i + 1]`` over ``steps[i] = (edge key, forward)``."""

    frames: tuple[str, ...]
    steps: tuple[tuple[Hashable, bool], ...]
    weight: float

    @property
    def edge_keys(self) -> tuple[Hashable, ...]:
        return tuple(k for k, _ in self.steps)


def reachable(adj: Adjacency, start: str) -> set[str]:
    """Every frame connected to ``start`` (edges walked both ways)."""
    seen = {start}
    todo = [start]
    while todo:
        for nxt, _, _ in adj.get(todo.pop(), ()):
            if nxt not in seen:
                seen.add(nxt)
                todo.append(nxt)
    return seen


def _settle(adj: Adjacency, source: str, target: str | None, weight: Weight,
            banned_e: set[Hashable], banned_f: set[str],
            ) -> tuple[dict[str, float], dict[str, tuple[str, Hashable, bool]], list[str]]:
    """Dijkstra from ``source`` until ``target`` is reached (None: every reachable frame):
    each frame's distance, the step that reached it (from frame, edge key, walked forwards?)
    and the frames in the order they were settled (a frame after the one it was reached
    from)."""
    best = {source: 0.0}
    back: dict[str, tuple[str, Hashable, bool]] = {}
    heap = [(0.0, 0, source)]
    counter = 1
    done: set[str] = set()
    order: list[str] = []
    while heap:
        d, _, u = heapq.heappop(heap)
        if u in done:
            continue
        order.append(u)
        if u == target:
            break
        done.add(u)
        for v, key, fwd in adj.get(u, ()):
            if v in done or v in banned_f or key in banned_e:
                continue
            w = weight(key)
            if w < 0 or math.isnan(w):
                raise InvalidInputError(f"error function gave edge {key} the weight {w!r}; "
                                        "additive error functions need weights >= 0")
            nd = d + w
            if nd < best.get(v, math.inf):
                best[v] = nd
                back[v] = (u, key, fwd)
                heapq.heappush(heap, (nd, counter, v))
                counter += 1
    return best, back, order


def dijkstra(adj: Adjacency, source: str, target: str, weight: Weight,
             banned_edges: Iterable[Hashable] = (), banned_frames: Iterable[str] = (),
             ) -> Path | None:
    """The lightest path (weights must be >= 0; ``inf`` edges are never used), or None."""
    banned_f = set(banned_frames)
    if source in banned_f:
        return None
    best, back, _ = _settle(adj, source, target, weight, set(banned_edges), banned_f)
    if target not in best or best[target] == math.inf:
        return None
    frames = [target]
    steps = []
    while frames[-1] != source:
        u, key, fwd = back[frames[-1]]
        steps.append((key, fwd))
        frames.append(u)
    return Path(tuple(reversed(frames)), tuple(reversed(steps)), best[target])


def shortest_tree(adj: Adjacency, root: str, weight: Weight,
                  ) -> list[tuple[str, str, Hashable, bool]]:
    """The lightest paths from every frame to ``root`` at once (one Dijkstra from the root:
    a path's reverse is a path, and weights do not depend on the direction walked).

    Each reachable frame other than the root as ``(frame, next frame towards the root,
    edge key, walked forwards from frame to next?)``, a frame always after its next one, so
    a caller can extend each path by one step from the one it continues.
    """
    _, back, order = _settle(adj, root, None, weight, set(), set())
    return [(v, back[v][0], back[v][1], not back[v][2]) for v in order[1:]]


def components(adj: Adjacency) -> list[list[str]]:
    """The connected parts (frames linked by any chain of edges), each sorted, in the
    order of their first frame."""
    seen: set[str] = set()
    out = []
    for frame in sorted(adj):
        if frame not in seen:
            part = reachable(adj, frame)
            seen |= part
            out.append(sorted(part))
    return out


def bridges(adj: Adjacency) -> set[Hashable]:
    """The keys of the edges whose removal disconnects their two frames (Tarjan's bridges,
    iterative: a chain of thousands of frames must not hit Python's recursion limit).

    A path made only of bridges is the only simple path between its ends (any other would
    have to cross each of them too), so every error function picks it.  Parallel edges are
    never bridges: the walk back to the parent is refused by edge key, not by frame.
    """
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    out: set[Hashable] = set()
    for root in adj:
        if root in index:
            continue
        index[root] = low[root] = len(index)
        stack = [(root, None, iter(adj[root]))]
        while stack:
            node, via, todo = stack[-1]
            for nxt, key, _ in todo:
                if key == via:
                    continue
                if nxt in index:
                    low[node] = min(low[node], index[nxt])
                    continue
                index[nxt] = low[nxt] = len(index)
                stack.append((nxt, key, iter(adj[nxt])))
                break
            else:
                stack.pop()
                if stack:
                    parent = stack[-1][0]
                    low[parent] = min(low[parent], low[node])
                    if low[node] > index[parent]:
                        out.add(via)
    return out


def k_shortest(adj: Adjacency, source: str, target: str, weight: Weight, k: int) -> list[Path]:
    """Up to ``k`` lightest simple paths, lightest first (Yen's algorithm)."""
    first = dijkstra(adj, source, target, weight)
    if first is None:
        return []
    found = [first]
    seen = {first.steps}
    candidates: list[tuple[float, int, Path]] = []
    counter = 0
    while len(found) < k:
        prev = found[-1]
        for i in range(len(prev.steps)):
            root_frames = prev.frames[: i + 1]
            root_steps = prev.steps[:i]
            banned = {p.steps[i][0] for p in found
                      if len(p.steps) > i and p.frames[: i + 1] == root_frames}
            spur = dijkstra(adj, root_frames[-1], target, weight, banned, root_frames[:-1])
            if spur is None:
                continue
            steps = root_steps + spur.steps
            if steps in seen:
                continue
            seen.add(steps)
            w = sum(weight(key) for key, _ in root_steps) + spur.weight
            heapq.heappush(candidates, (w, counter, Path(root_frames[:-1] + spur.frames,
                                                         steps, w)))
            counter += 1
        if not candidates:
            break
        found.append(heapq.heappop(candidates)[2])
    return found
