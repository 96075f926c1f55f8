"""Composing a pose from its segments: the answers of a route's agents chained source ->
target, the covariance propagated to first order (``C = C_X + Ad_X C_Y Ad_X^T`` for run
``X`` followed by run ``Y``).  Pure: no I/O; a client composes a remote query with it
(:mod:`agent.sdk.query`), in whatever order the answers arrive.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.attributes import combine
from agent.result import PoseResult
from agent.srg import kernel


def compose(results: Sequence[PoseResult], t_ns: int | None) -> PoseResult:
    """Chain segment answers source -> target, propagating the covariance (first order).

    All answers are in (an agent composing a route it holds, a client's second round), so
    the chain is composed in one pass on floats and every covariance mapped by the pose
    before it in one compiled call (:func:`agent.srg.kernel.propagate`), rather than run by
    run in numpy as :class:`Composition` must while answers arrive."""
    if not results:
        raise ValueError("a composition needs at least one segment")
    before: list[kernel.Pose] = []
    covs: list[np.ndarray] = []
    pose = _IDENTITY
    for r in results:
        if r.covariance is not None:
            before.append(pose)
            covs.append(r.covariance)
        pose = kernel.compose(pose, (*r.position.tolist(), *r.quaternion.tolist()))
    cov = kernel.propagate(before, covs) if covs else None
    return _chained(results, np.array(pose[:3]), np.array(pose[3:]), cov, t_ns)


_IDENTITY: kernel.Pose = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def _chained(results: Sequence[PoseResult], p: np.ndarray, q: np.ndarray,
             cov: np.ndarray | None, t_ns: int | None) -> PoseResult:
    """The composed result of ``results`` with its pose and covariance: their paths, edges
    and stamps joined, the largest extrapolation, the attributes combined when read."""
    path: list[str] = []
    edges: list[dict[str, Any]] = []
    stamps: list[tuple[int, int]] = []
    for r in results:
        path.extend(r.path if not path else r.path[1:])
        edges.extend(r.edges)
        stamps.extend(r.stamps)
    extrapolated = max(r.extrapolated_s for r in results)
    parts = [r.attributes for r in results]
    return PoseResult(p, q, cov, path, edges, t_ns, extrapolated, stamps,
                      lambda: combine(parts, p, cov))


class Composition:
    """Segment answers chained source -> target as they arrive, covariance propagated (first
    order).  Answers of neighbouring segments are merged into runs at once, in whatever
    order they come, so when the slowest agent answers only its own segment is left to
    merge with the runs beside it (the others were composed while it computed).

    Merging run ``X`` with the run ``Y`` right of it carries ``Y``'s position into ``X``'s
    source frame by ``X``'s rotation and maps ``Y``'s covariance there by ``X``'s adjoint
    (``C = C_X + Ad_X C_Y Ad_X^T``).  Poses are composed on plain floats (numpy's per-call
    overhead on 3- and 4-vectors was most of a query's composing time); only covariances,
    6x6, go through numpy.
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
        q = tuple(result.quaternion.tolist())
        run = _Run(i, i, tuple(result.position.tolist()), q, geo.rotation_rows(q),
                   result.covariance)
        left = self._ending.pop(i - 1, None)
        if left is not None:
            del self._starting[left.first]
            run = left.then(run)
        right = self._starting.pop(i + 1, None)
        if right is not None:
            del self._ending[right.final]
            run = run.then(right)
        self._starting[run.first] = run
        self._ending[run.final] = run

    def result(self, t_ns: int | None) -> PoseResult:
        """The composed pose at ``t_ns``; ``ValueError`` if a segment is still missing."""
        missing = [i for i, r in enumerate(self._results) if r is None]
        if missing:
            raise ValueError(f"segment(s) {missing} missing from the composition")
        results: list[PoseResult] = self._results  # type: ignore[assignment]
        whole = self._starting[0]
        cov = whole.cov
        # a run starts from a segment's own covariance: the result must not alias it
        if cov is not None and any(cov is r.covariance for r in results):
            cov = cov.copy()
        return _chained(results, np.array(whole.p), np.array(whole.q), cov, t_ns)


Vec = tuple[float, ...]
Rot = tuple[Vec, Vec, Vec]


@dataclass
class _Run:
    """Segments ``first..final`` composed: position, quaternion and rotation on floats, and
    the covariance (None: exactly known)."""

    first: int
    final: int
    p: Vec
    q: Vec
    R: Rot
    cov: np.ndarray | None

    def then(self, right: _Run) -> _Run:
        """This run followed by the one right of it."""
        R, (rx, ry, rz) = self.R, right.p
        cov = self.cov
        if right.cov is not None:
            J = geo.adjoint_of_rows(self.p, R)
            mapped = J @ right.cov @ J.T
            cov = mapped if cov is None else cov + mapped
        p = tuple(pi + row[0] * rx + row[1] * ry + row[2] * rz
                  for pi, row in zip(self.p, R, strict=True))
        q = geo.quat_product(self.q, right.q)
        cols = tuple(zip(*right.R, strict=True))
        rot = tuple(tuple(row[0] * col[0] + row[1] * col[1] + row[2] * col[2] for col in cols)
                    for row in R)
        return _Run(self.first, right.final, p, q, rot, cov)  # type: ignore[arg-type]
