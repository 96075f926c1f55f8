"""Query plans as data-flow graphs (Klinker, Bauer 2005, §1.3.3 "Data flow graphs").

A plan is what a query compiles to once: the ranked candidate paths between two frames for
one error function, each a chain whose leaves are edges and whose root is the inferred
relation.  Runs of static edges are folded into one constant when the plan is built, so
evaluating a plan at ``t`` only touches measured edges: find each one's samples around
``t``, interpolate and compose on plain floats (:mod:`agent.srg.kernel`), and propagate
covariance to first order.  The graph caches plans and drops exactly those an edge change
can affect.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.attributes import aggregate, path_constants, uncertainty
from agent.result import PoseResult
from agent.srg import kernel
from agent.srg.buffer import SampleBuffer
from agent.srg.edge import Edge, EdgeKey
from agent.srg.errors import EdgeUndefinedError, NoSamplesError, NoValidPathError


def oriented(p: np.ndarray, q: np.ndarray, cov: np.ndarray | None, forward: bool,
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """An edge value as walked: itself forwards, its inverse backwards."""
    if forward:
        return p, q, cov
    pi, qi = geo.inverse(p, q)
    return pi, qi, geo.inverse_covariance(p, q, cov)


def compose_values(a: tuple, b: tuple) -> tuple:
    """``(p, q, covariance)`` of ``a`` followed by ``b`` (first-order covariance)."""
    p, q = geo.compose(a[0], a[1], b[0], b[1])
    return p, q, geo.compose_covariance(a[0], a[1], a[2], b[2])


def nominal_attributes(edge_attrs: Sequence[dict[str, Any]], values: Sequence[tuple],
                       ) -> dict[str, Any]:
    """A path's attributes for ranking: the covariance propagated through its edges'
    nominal values (``(p, q, covariance)`` as walked, see :func:`oriented`)."""
    acc = (np.zeros(3), geo.quat_identity(), None)
    for value in values:
        acc = compose_values(acc, value)
    return aggregate(edge_attrs, acc[0], acc[2])


class Chain:
    """One candidate path compiled for evaluation at any time.

    Evaluation interpolates every measured edge and composes the path on plain floats in
    :mod:`agent.srg.kernel` (compiled when available): for a handful of edges numpy's
    per-call overhead costs more than the arithmetic.  Covariance, when any edge is
    uncertain, is propagated with one batched ``adjoint`` of the composed poses the kernel
    passed through, which map each edge's covariance to the source.
    """

    def __init__(self, frames: Sequence[str], steps: Sequence[tuple[Edge, bool]],
                 max_extrapolation_s: float) -> None:
        self.frames = list(frames)
        self.edge_keys: frozenset[EdgeKey] = frozenset(e.key for e, _ in steps)
        self.edge_infos = [e.info(fwd) for e, fwd in steps]
        self.edge_attrs = [dict(e.attrs, static=e.is_static) for e, _ in steps]
        # items: ("c", p, q, cov) folded static runs, ("m", j) the j-th measured edge
        items: list[tuple] = []
        self._measured: list[tuple[Edge, bool, float]] = []
        for edge, fwd in steps:
            if edge.is_static:
                value = oriented(*edge.value, fwd)
                if items and items[-1][0] == "c":
                    items[-1] = ("c", *compose_values(items[-1][1:], value))
                else:
                    items.append(("c", *value))
            else:
                limit = min(max_extrapolation_s, edge.attrs.get("ttl_s", max_extrapolation_s))
                items.append(("m", len(self._measured)))
                self._measured.append((edge, fwd, limit))
        self._items = items
        self._kernel_items = tuple(self._kernel_item(it) for it in items)
        self._cov_items = tuple(self._cov_item(it) for it in items)
        self._buffers = tuple(e.buffer for e, _, _ in self._measured)
        self._backward = [not fwd for _, fwd, _ in self._measured]
        self._uncertain = any(it[3] is not None for it in items if it[0] == "c") or any(
            e.attrs.get("covariance") is not None or e.std_cov is not None
            for e, _, _ in self._measured)
        self.attributes = nominal_attributes(
            self.edge_attrs, [oriented(*edge.nominal(), fwd) for edge, fwd in steps])
        self._constant_attrs = path_constants(self.edge_attrs)
        #: an all-static chain's value, covariance and attributes, computed once (the same
        #: at every time; a change of its edges builds a new chain)
        self._static: tuple[np.ndarray, np.ndarray, np.ndarray | None, dict[str, Any]] | None
        self._static = None

    def _kernel_item(self, item: tuple) -> tuple:
        """An item as :mod:`agent.srg.kernel` takes it."""
        if item[0] == "c":
            return (tuple(item[1].tolist() + item[2].tolist()),)
        edge, fwd, limit = self._measured[item[1]]
        buf = edge.buffer
        return buf, buf.times, buf.values, buf.deltas, buf.buffer_ns, limit, fwd

    def _cov_item(self, item: tuple) -> tuple:
        """An item's covariance as the compiled kernel's ``evaluate_covariance`` takes it:
        a constant's, or a measured edge's samples with its own covariance as
        :meth:`_edge_cov` falls back to it (0: none, 1: SE(3), 2: decoupled)."""
        if item[0] == "c":
            return (item[3],)
        edge = self._measured[item[1]][0]
        covs = edge.buffer.covs
        if "covariance" in edge.attrs:
            return covs, 1, edge.attrs["covariance"]
        if edge.std_cov is None:
            return covs, 0, None
        cov, rotates = edge.std_cov
        return covs, 2 if rotates else 1, cov

    def latest_time(self) -> int | None:
        """The latest time at which every measured edge has data without extrapolating."""
        newest = [e.buffer.newest_ns for e, _, _ in self._measured]
        if not newest or any(t is None for t in newest):
            return None
        return min(newest)

    def evaluate(self, t_ns: int | None) -> PoseResult:
        """The composed pose at ``t_ns``; ``EdgeUndefinedError`` names the edge without data."""
        if t_ns is None and self._measured:  # latest_time() found an edge without samples
            empty = next(e for e, _, _ in self._measured if not len(e.buffer))
            raise NoSamplesError(empty.name, None)
        if not self._measured:
            return self._static_result(t_ns)
        return self._evaluate_items(t_ns)

    def _evaluate_items(self, t_ns: int | None) -> PoseResult:
        """:meth:`evaluate`'s work: the kernel over the items, then the covariance."""
        uncertain = self._uncertain
        if not uncertain:  # samples may carry covariances the attributes did not announce
            for buf in self._buffers:
                if buf.with_cov:
                    uncertain = True
                    break
        items = self._kernel_items
        p, q = np.empty(3), np.empty(4)
        if uncertain and kernel.NATIVE is not None and kernel.NATIVE_COVARIANCE is not None:
            # pose and covariance in one compiled call
            cov = np.empty((6, 6))
            got = kernel.NATIVE_COVARIANCE(t_ns, items, self._cov_items, p, q, cov)
            if got is not None:
                return self._result(p, q, cov if got[2] else None, t_ns, got[0], got[1])
        native = kernel.NATIVE
        out = None if native is None else native(t_ns, items, uncertain, p, q)
        if out is None:  # the Python kernel: also the one that raises for undefined edges
            out = kernel.evaluate(t_ns, items, uncertain, p, q)
        extrapolated, stamps, edges, prefixes = out
        cov = None if edges is None else self._covariance(edges, prefixes)
        return self._result(p, q, cov, t_ns, extrapolated, stamps)

    def _result(self, p: np.ndarray, q: np.ndarray, cov: np.ndarray | None,
                t_ns: int | None, extrapolated: float,
                stamps: list[tuple[int, int]]) -> PoseResult:
        constant = self._constant_attrs
        return PoseResult(p, q, cov, self.frames, self.edge_infos, t_ns, extrapolated, stamps,
                          lambda: {**constant, **uncertainty(p, cov)})

    def _static_result(self, t_ns: int | None) -> PoseResult:
        """An all-static chain's result at ``t_ns``: computed on the first call, copied
        after (agents answer static segments at every query)."""
        if self._static is None:
            r = self._evaluate_items(t_ns)
            self._static = (r.position, r.quaternion, r.covariance, r.attributes)
        p, q, cov, attrs = self._static
        return PoseResult(p.copy(), q.copy(), None if cov is None else cov.copy(), self.frames,
                          self.edge_infos, t_ns, 0.0, [], dict(attrs))

    def _covariance(self, edges: list[kernel.EdgeValue], prefixes: list[kernel.Pose],
                    ) -> np.ndarray | None:
        """The path's covariance from the interpolated edge values and the composed poses
        after each item that the kernel returned."""
        covs = [self._edge_cov(edge, buf, i0, i1, a)
                for (edge, _, _), buf, (i0, i1, a, _) in zip(self._measured, self._buffers,
                                                              edges, strict=True)]
        if len(self._items) == 1 and edges and not self._backward[0]:
            # one measured edge walked forwards (a tracker's own segment, the most frequent
            # query): its covariance needs no prefix, only the "std" translation
            if covs[0] is None:
                return None
            kind, c = covs[0]
            return c if kind == "se3" else geo.decoupled_to_se3(np.array(edges[0][3][:3]), c)
        return self._propagate(edges, prefixes, covs)

    @staticmethod
    def _edge_cov(edge: Edge, buf: SampleBuffer, i0: int, i1: int, a: float,
                  ) -> tuple[str, np.ndarray] | None:
        """The edge's covariance at the bracket: ("se3", C) ready to map, ("std", D) the
        decoupled form still to be moved to the interpolated translation, or None."""
        c0, c1 = buf.covs[i0], buf.covs[i1]
        if c0 is not None and c1 is not None:
            a = min(max(a, 0.0), 1.0)  # never extrapolate a covariance (it could lose PSD)
            return "se3", c0 if c0 is c1 or a == 0.0 else c0 + (c1 - c0) * a
        if c0 is not None or c1 is not None:
            return "se3", c0 if c0 is not None else c1
        if "covariance" in edge.attrs:
            return "se3", edge.attrs["covariance"]
        if edge.std_cov is None:
            return None
        cov, rotates = edge.std_cov
        return ("std", cov) if rotates else ("se3", cov)

    def _propagate(self, edges: list[kernel.EdgeValue], prefixes: list[kernel.Pose],
                   covs: list) -> np.ndarray | None:
        """``sum(Ad(M_i) C_i Ad(M_i)^T)`` over the uncertain items, every adjoint from one
        batched call.

        ``M_i`` maps item i's covariance to the source: the composed path before it for a
        constant or an edge walked forwards; the path through it for an edge walked
        backwards (its inverse is part of that prefix: T^-1 Exp(-xi) = Exp(-Ad(T^-1) xi)
        T^-1); followed, for a "std" covariance, by the pure translation of the edge
        (``decoupled_to_se3``).  ``Ad(A) Ad(B) = Ad(AB)``, so the kernel's composed poses
        give each map directly, without a chain of 6x6 products.
        """
        poses, mats = [], []
        for i, it in enumerate(self._items):
            before = prefixes[i - 1] if i else _IDENTITY
            if it[0] == "c":
                if it[3] is not None:
                    poses.append(before)
                    mats.append(it[3])
                continue
            j = it[1]
            if covs[j] is None:
                continue
            kind, c = covs[j]
            pose = prefixes[i] if self._backward[j] else before
            if kind == "std":
                pose = kernel.compose(pose, (*edges[j][3][:3], 0.0, 0.0, 0.0, 1.0))
            poses.append(pose)
            mats.append(c)
        return kernel.propagate(poses, mats) if mats else None


_IDENTITY = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


class Plan:
    """The ranked candidate chains of one (source, target, error function)."""

    def __init__(self, source: str, target: str, chains: list[Chain],
                 frames: set[str]) -> None:
        self.source = source
        self.target = target
        self.chains = chains
        self.frames = frames  # the component searched: edge changes there may change the plan
        self.edge_keys: frozenset[EdgeKey] = frozenset().union(*(c.edge_keys for c in chains))

    def evaluate(self, at: int | None) -> PoseResult:
        """The best candidate defined at ``at`` (None: each candidate's latest common time)."""
        causes: list[EdgeUndefinedError] = []
        for chain in self.chains:
            try:
                return chain.evaluate(at if at is not None else chain.latest_time())
            except EdgeUndefinedError as exc:
                causes.append(exc)
        if len(causes) == 1:
            raise causes[0]
        raise NoValidPathError(self.source, self.target, at, causes)
