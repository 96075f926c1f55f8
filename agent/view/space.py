"""The realm's frames in space: every edge the view knows, placed in one root frame.

Pure numpy, no I/O.  The frames reachable from the root form a breadth-first tree over the
edges that have a value (static ones always; measured ones once a sample came), a static
edge winning where two could place a frame; the tree is rebuilt only when that set
changes, and the poses are composed level by level, each level in one vectorised call, so
1,000 frames cost a handful of numpy calls per redraw.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent import geometry as geo


@dataclass(frozen=True)
class EdgeView:
    """One edge as the view shows it: who owns it, whether it is static, where its samples
    come from (``key``: the data key of a measured edge) and its attributes."""

    parent: str
    child: str
    owner: str
    static: bool
    source: str
    key: str | None = None
    type: str = "pose6d"
    attributes: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.parent} -> {self.child} [{self.owner}/{self.source}]"


@dataclass
class Placed:
    """The frames reachable from the root: names, positions (N, 3), quaternions (N, 4,
    x y z w), and for each frame the edge that placed it (the root has none)."""

    frames: list[str]
    positions: np.ndarray
    quaternions: np.ndarray
    via: dict[str, str]

    def index(self) -> dict[str, int]:
        return {f: i for i, f in enumerate(self.frames)}


class Space:
    """Places frames in a root frame from edges' latest values (module docstring)."""

    def __init__(self) -> None:
        self._signature: tuple[str, frozenset[str]] | None = None
        #: per level of the tree: (child indices, parent indices, edge names, inverted)
        self._levels: list[tuple[np.ndarray, np.ndarray, list[str], np.ndarray]] = []
        self._frames: list[str] = []
        self._via: dict[str, str] = {}

    def place(self, root: str, edges: Mapping[str, EdgeView],
              values: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> Placed:
        """Every frame reachable from ``root`` over edges with a value (``values``: edge
        name -> (position, quaternion) of child in parent)."""
        usable = frozenset(n for n in edges if n in values)
        if self._signature != (root, usable):
            self._build(root, {n: edges[n] for n in usable})
            self._signature = (root, usable)
        n = len(self._frames)
        P = np.zeros((n, 3))
        Q = np.tile(geo.quat_identity(), (n, 1)) if n else np.zeros((0, 4))
        for child, parent, names, inverted in self._levels:
            pe = np.array([values[k][0] for k in names], float)
            qe = np.array([values[k][1] for k in names], float)
            if inverted.any():
                pi, qi = geo.inverse(pe[inverted], qe[inverted])
                pe[inverted], qe[inverted] = pi, qi
            P[child], Q[child] = geo.compose(P[parent], Q[parent], pe, qe)
        return Placed(list(self._frames), P, Q, dict(self._via))

    def _build(self, root: str, edges: Mapping[str, EdgeView]) -> None:
        """The breadth-first tree from ``root``, stored level by level; of two edges that
        could place a frame, a static one (a calibration) wins over a measured one."""
        adjacent: dict[str, list[tuple[str, str, bool]]] = {}
        for name in sorted(edges, key=lambda n: (not edges[n].static, n)):
            e = edges[name]
            adjacent.setdefault(e.parent, []).append((e.child, name, False))
            adjacent.setdefault(e.child, []).append((e.parent, name, True))
        index = {root: 0}
        self._frames, self._via, self._levels = [root], {}, []
        level = deque([root]) if root in adjacent else deque()
        while level:
            children, parents, names, inverted = [], [], [], []
            for frame in level:
                for other, name, inv in adjacent[frame]:
                    if other in index:
                        continue
                    index[other] = len(self._frames)
                    self._frames.append(other)
                    self._via[other] = name
                    children.append(index[other])
                    parents.append(index[frame])
                    names.append(name)
                    inverted.append(inv)
            if children:
                self._levels.append((np.array(children), np.array(parents), names,
                                     np.array(inverted, bool)))
            level = deque(self._frames[i] for i in children)


class Trails:
    """The positions of moving frames over the last ``seconds`` (sampled at each call of
    :meth:`add`), as line segments."""

    def __init__(self, seconds: float, min_travel_m: float = 0.001) -> None:
        self.seconds = seconds
        self.min_travel_m = min_travel_m
        self._points: dict[str, deque[tuple[float, np.ndarray]]] = {}

    def add(self, t: float, placed: Placed) -> None:
        for frame, p in zip(placed.frames, placed.positions, strict=True):
            trail = self._points.setdefault(frame, deque())
            trail.append((t, p.copy()))
            while trail and trail[0][0] < t - self.seconds:
                trail.popleft()
        for frame in set(self._points) - set(placed.frames):
            del self._points[frame]

    def segments(self) -> np.ndarray:
        """(M, 2, 3): consecutive positions of every frame that moved."""
        out = []
        for trail in self._points.values():
            if len(trail) < 2:
                continue
            pts = np.array([p for _, p in trail])
            if np.ptp(pts, axis=0).max() < self.min_travel_m:
                continue
            out.append(np.stack([pts[:-1], pts[1:]], axis=1))
        return np.concatenate(out) if out else np.zeros((0, 2, 3))


def ellipsoid(cov_parent: np.ndarray, q_root_parent: np.ndarray,
              sigmas: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Radii (3,) and orientation (x y z w) of the ``sigmas`` ellipsoid of a position
    covariance given in the parent's axes, turned into the root's axes."""
    w, v = np.linalg.eigh(0.5 * (cov_parent + cov_parent.T))
    if np.linalg.det(v) < 0:
        v[:, 2] = -v[:, 2]
    q_axes = geo.matrix_to_quat(v)
    return sigmas * np.sqrt(np.clip(w, 0.0, None)), geo.quat_multiply(q_root_parent, q_axes)
