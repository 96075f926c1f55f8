"""Query plans as data-flow graphs (Klinker, Bauer 2005, §1.3.3 "Data flow graphs").

A plan is what a query compiles to once: the ranked candidate paths between two frames for
one error function, each a chain whose leaves are edges and whose root is the inferred
relation.  Runs of static edges are folded into one constant when the plan is built, so
evaluating a plan at ``t`` only touches measured edges: find each one's samples around
``t``, interpolate them all in one batched call, and compose (with first-order covariance
propagation).  The graph caches plans and drops exactly those an edge change can affect.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from agent.srg import geometry as geo
from agent.srg.attributes import aggregate, path_constants, uncertainty
from agent.srg.edge import Edge, EdgeKey
from agent.srg.errors import EdgeUndefinedError, NoSamplesError, NoValidPathError
from agent.srg.result import PoseResult

_EYE6 = np.eye(6)


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

    Evaluation cost is a handful of batched geometry calls whatever the path length:
    interpolation of every measured edge at once (slerp as ``q0 Exp(a Log(q0^-1 q1))``
    with the log cached per sample pair in the buffer), one ``to_matrix`` for the chain,
    a pairwise product tree for the quaternion, and, when any edge is uncertain, one
    batched ``adjoint`` whose prefix products map each edge's covariance to the source.
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
        self._backward = np.array([not fwd for _, fwd, _ in self._measured], dtype=bool)
        self._any_backward = bool(self._backward.any())
        # constants of the static runs: matrix, quaternion, adjoint, covariance
        self._const = {i: (geo.to_matrix(it[1], it[2]), it[2], geo.adjoint(it[1], it[2]), it[3])
                       for i, it in enumerate(items) if it[0] == "c"}
        self._uncertain = any(it[3] is not None for it in items if it[0] == "c") or any(
            e.attrs.get("covariance") is not None or e.std_cov is not None
            for e, _, _ in self._measured)
        self.attributes = nominal_attributes(
            self.edge_attrs, [oriented(*edge.nominal(), fwd) for edge, fwd in steps])
        self._constant_attrs = path_constants(self.edge_attrs)

    def latest_time(self) -> int | None:
        """The latest time at which every measured edge has data without extrapolating."""
        newest = [e.buffer.newest_ns for e, _, _ in self._measured]
        if not newest or any(t is None for t in newest):
            return None
        return min(newest)

    def evaluate(self, t_ns: int | None) -> PoseResult:
        """The composed pose at ``t_ns``; ``EdgeUndefinedError`` names the edge without data."""
        measured = self._measured
        m = len(measured)
        extrapolated = 0.0
        stamps: list[tuple[int, int]] = []
        P = Q = P_edge = None
        covs: list = []
        uncertain = self._uncertain
        if m:
            if t_ns is None:  # latest_time() found an edge without samples
                empty = next(e for e, _, _ in measured if not len(e.buffer))
                raise NoSamplesError(empty.name, None)
            P0 = np.empty((m, 3))
            P1 = np.empty((m, 3))
            Q0 = np.empty((m, 4))
            D = np.zeros((m, 3))
            A = np.empty((m, 1))
            missing = []
            brackets = []
            exact = True  # every edge has a sample at t: nothing to interpolate
            for j, (edge, _, limit) in enumerate(measured):
                buf = edge.buffer
                i0, i1, a, ex = buf.bracket(t_ns, limit)
                brackets.append((buf, i0, i1, a))
                P0[j] = buf.positions[i0]
                P1[j] = buf.positions[i1]
                Q0[j] = buf.quats[i0]
                A[j, 0] = a
                if i0 != i1:
                    exact = False
                    d = buf.deltas[i0]
                    if d is None:
                        missing.append(j)
                    else:
                        D[j] = d
                if ex > extrapolated:
                    extrapolated = ex
                stamps.append((buf.times[i0], buf.times[i1]))
            if missing:
                self._fill_deltas(brackets, missing, D)
            if exact:
                P, Q = P0, Q0
            else:
                P = P0 + (P1 - P0) * A
                Q = geo.quat_multiply(Q0, geo.rotvec_to_quat(D * A))
            P_edge = P
            # samples may carry covariances the edge's attributes did not announce
            uncertain = uncertain or any(
                buf.covs[i0] is not None or buf.covs[i1] is not None
                for buf, i0, i1, _ in brackets)
            if uncertain:
                covs = [self._edge_cov(edge, br) for (edge, _, _), br in zip(measured, brackets,
                                                                               strict=True)]
            if self._any_backward:
                bw = self._backward
                P = P.copy()
                P[bw], Q[bw] = geo.inverse(P[bw], Q[bw])
        p, q, cov = self._compose_items(P, Q, P_edge, covs if uncertain else None)
        constant = self._constant_attrs
        return PoseResult(p, q, cov, self.frames, self.edge_infos, t_ns, extrapolated, stamps,
                          lambda: {**constant, **uncertainty(p, cov)})

    @staticmethod
    def _fill_deltas(brackets: list, missing: list[int], D: np.ndarray) -> None:
        """Compute (batched) and cache slerp's log between the bracketing samples."""
        Qa = np.array([brackets[j][0].quats[brackets[j][1]] for j in missing])
        Qb = np.array([brackets[j][0].quats[brackets[j][2]] for j in missing])
        R = geo.quat_to_rotvec(geo.quat_multiply(geo.quat_conjugate(Qa), Qb))
        for n, j in enumerate(missing):
            buf, i0, _, _ = brackets[j]
            buf.deltas[i0] = R[n]
            D[j] = R[n]

    @staticmethod
    def _edge_cov(edge: Edge, bracket: tuple) -> tuple[str, np.ndarray] | None:
        """The edge's covariance at the bracket: ("se3", C) ready to map, ("std", D) the
        decoupled form still to be moved to the interpolated translation, or None."""
        buf, i0, i1, a = bracket
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

    def _compose_items(self, P: np.ndarray | None, Q: np.ndarray | None,
                       P_edge: np.ndarray | None, covs: list | None,
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Compose the items in order; covariance by the adjoint of each prefix (None:
        nothing on the path is uncertain).

        The position only needs the rotation matrices of the items before the last one,
        so the last measured edge (often the only one) costs no matrix conversion.
        """
        items = self._items
        need = [it[1] for it in items[:-1] if it[0] == "m"]
        Tm = dict(zip(need, geo.to_matrix(P[need], Q[need]), strict=True)) if need else {}
        M = None
        for i, it in enumerate(items[:-1]):
            T = self._const[i][0] if it[0] == "c" else Tm[it[1]]
            M = T if M is None else M @ T
        last = items[-1]
        p = self._const[len(items) - 1][0][:3, 3] if last[0] == "c" else P[last[1]]
        p = p.copy() if M is None else M[:3, :3] @ p + M[:3, 3]
        quats = [self._const[i][1] if it[0] == "c" else Q[it[1]] for i, it in enumerate(items)]
        q = quat_product(np.array(quats))
        cov = None if covs is None else self._propagate(P, Q, P_edge, covs)
        return p, q, cov

    def _propagate(self, P: np.ndarray | None, Q: np.ndarray | None,
                   P_edge: np.ndarray | None, covs: list) -> np.ndarray | None:
        """``sum(Ad(prefix_i) C_i Ad(prefix_i)^T)`` with every adjoint from one batched call.

        An edge walked forwards is mapped by the prefix before it, one walked backwards by
        the prefix after it (its inverse is part of the prefix: T^-1 Exp(-xi) =
        Exp(-Ad(T^-1) xi) T^-1).  A "std" covariance is first moved to the edge's
        translation by the adjoint of that pure translation (``decoupled_to_se3``).
        """
        m = 0 if P is None else len(P)
        if m == 1 and len(self._items) == 1 and not self._backward[0]:
            # one measured edge walked forwards (a tracker's own segment, the most frequent
            # query): its covariance needs no prefix, only the "std" translation
            if covs[0] is None:
                return None
            kind, c = covs[0]
            return c if kind == "se3" else geo.decoupled_to_se3(P_edge[0], c)
        std_rows = [j for j in range(m) if covs[j] is not None and covs[j][0] == "std"]
        if m:
            Pa = P if not std_rows else np.concatenate([P, P_edge[std_rows]])
            Qa = Q if not std_rows else np.concatenate([Q, np.tile(_QUAT_ID, (len(std_rows),
                                                                               1))])
            Ads = geo.adjoint(Pa, Qa)
        maps, mats = [], []
        prefix = _EYE6
        for i, it in enumerate(self._items):
            if it[0] == "c":
                _, Ad, c = self._const[i][1:]
                if c is not None:
                    maps.append(prefix)
                    mats.append(c)
                prefix = prefix @ Ad
                continue
            j = it[1]
            before = prefix
            prefix = prefix @ Ads[j]
            entry = covs[j]
            if entry is None:
                continue
            kind, c = entry
            mapped = before if not self._backward[j] else prefix
            if kind == "std":
                mapped = mapped @ Ads[m + std_rows.index(j)]
            maps.append(mapped)
            mats.append(c)
        if not mats:
            return None
        Mp = np.array(maps)
        return (Mp @ np.array(mats) @ Mp.transpose(0, 2, 1)).sum(axis=0)


_QUAT_ID = np.array([0.0, 0.0, 0.0, 1.0])


def quat_product(Qs: np.ndarray) -> np.ndarray:
    """``Qs[0] * Qs[1] * ... * Qs[-1]`` by a pairwise tree: log2(n) batched multiplies."""
    while len(Qs) > 1:
        half = len(Qs) // 2
        paired = geo.quat_multiply(Qs[0 : 2 * half : 2], Qs[1 : 2 * half : 2])
        Qs = paired if len(Qs) % 2 == 0 else np.concatenate([paired, Qs[-1:]])
    return Qs[0]


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
