"""The compiled chain kernel against the pure-Python one on random graphs: the same poses,
covariances, sample stamps and extrapolation, and undefined edges left to Python's errors.

The pytransform3d oracle and analytic interpolation tests (``test_srg_graph.py``) run on
both kernels as well; here the two are compared with each other, to float rounding.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent import geometry as geo
from agent.srg import Graph, kernel
from agent.srg.errors import EdgeUndefinedError

COMPILED = kernel.NATIVE
needs_compiled = pytest.mark.skipif(COMPILED is None,
                                    reason="the compiled kernel was not built")
LIMIT_S = 0.05


def _random_chain(seed: int, hops: int) -> list[tuple]:
    """Edges of a path f0 .. f{hops}: static or measured (irregular sample times, some
    with sample covariances), random directions and uncertainty attributes."""
    rng = np.random.default_rng(seed)
    edges = []
    for i in range(hops):
        a, b = f"f{i}", f"f{i + 1}"
        if rng.random() < 0.5:
            a, b = b, a
        attrs = {}
        if rng.random() < 0.4:
            attrs = {"pos_std_m": float(rng.uniform(1e-3, 1e-2)),
                     "rot_std_rad": float(rng.uniform(0, 1e-2))}
        elif rng.random() < 0.2:
            L = rng.normal(size=(6, 6)) * 1e-3
            attrs = {"covariance": L @ L.T}
        if rng.random() < 0.3:
            p = rng.normal(size=3)
            edges.append(("static", a, b, p, geo.rotvec_to_quat(rng.normal(size=3)), attrs))
            continue
        times = np.cumsum(rng.integers(1_000_000, 30_000_000, int(rng.integers(1, 12))))
        samples = []
        for t in times:
            cov = None
            if rng.random() < 0.2:
                L = rng.normal(size=(6, 6)) * 1e-3
                cov = L @ L.T
            samples.append((int(t), rng.normal(size=3),
                            geo.rotvec_to_quat(rng.normal(size=3) * 2.0), cov))
        edges.append(("measured", a, b, samples, None, attrs))
    return edges


def _graph(edges: list[tuple]) -> Graph:
    g = Graph(max_extrapolation_s=LIMIT_S)
    for kind, a, b, value, q, attrs in edges:
        if kind == "static":
            g.add_static(a, b, value, q, **attrs)
        else:
            g.declare_measured(a, b, **attrs)
            for t, p, sq, cov in value:
                g.add_measurement(a, b, t, p, sq, cov)
    return g


def _query(g: Graph, hops: int, t: int, compiled: bool):
    kernel.NATIVE = COMPILED if compiled else None
    try:
        return g.pose("f0", f"f{hops}", at=t)
    except EdgeUndefinedError as exc:
        return exc
    finally:
        kernel.NATIVE = COMPILED


@needs_compiled
@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), hops=st.integers(1, 6))
def test_compiled_and_python_kernels_agree_on_random_chains(seed, hops):
    edges = _random_chain(seed, hops)
    # one graph per kernel: each fills its own cache of slerp logs
    ours, theirs = _graph(edges), _graph(edges)
    times = sorted({s[0] for e in edges if e[0] == "measured" for s in e[3]} or {0})
    rng = np.random.default_rng(seed)
    queries = [times[0], times[-1], times[-1] + 20_000_000, times[-1] + 80_000_000,
               times[0] - 30_000_000, *rng.integers(times[0], times[-1] + 1, 8).tolist()]
    for t in queries:
        a = _query(ours, hops, int(t), compiled=True)
        b = _query(theirs, hops, int(t), compiled=False)
        if isinstance(b, Exception):
            assert type(a) is type(b) and str(a) == str(b)
            continue
        np.testing.assert_allclose(a.position, b.position, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.quaternion, b.quaternion, rtol=0, atol=1e-12)
        assert a.stamps == b.stamps and a.path == b.path
        assert a.extrapolated_s == b.extrapolated_s
        assert (a.covariance is None) == (b.covariance is None)
        if a.covariance is not None:
            np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-12, atol=1e-18)


@needs_compiled
def test_compiled_kernel_leaves_undefined_edges_to_python():
    """Where an edge has no value at t, the compiled kernel answers None (and caches no
    log), so the error is the Python kernel's, naming the edge."""
    g = Graph(max_extrapolation_s=LIMIT_S)
    g.add_measurement("a", "b", 0, [0, 0, 0], [0, 0, 0, 1])
    g.add_measurement("a", "b", 10_000_000, [1, 0, 0], [0, 0, 0, 1])
    g.declare_measured("b", "c")
    g.pose("a", "b", at=5_000_000)
    items = g.best_paths("a", "c")[0]._kernel_items
    assert COMPILED(5_000_000, items, False, np.empty(3), np.empty(4)) is None
    assert COMPILED(None, items, False, np.empty(3), np.empty(4)) is None
    items_ab = g.best_paths("a", "b")[0]._kernel_items
    assert COMPILED(10_000_000 + 10**9, items_ab, False, np.empty(3), np.empty(4)) is None
    with pytest.raises(ValueError, match="float64 arrays"):
        COMPILED(5_000_000, items_ab, False, np.empty(3, np.float32), np.empty(4))
    chain = g.best_paths("a", "c")[0]
    with_cov = kernel.NATIVE_COVARIANCE
    assert with_cov(5_000_000, chain._kernel_items, chain._cov_items, np.empty(3),
                    np.empty(4), np.empty((6, 6))) is None


@needs_compiled
def test_compiled_covariance_is_the_chains_own():
    """An uncertain chain is evaluated with its covariance in one compiled call, to the
    Python path's result; a covariance that is not a 6x6 float64 array leaves it to the
    Python path."""
    g = Graph(max_extrapolation_s=LIMIT_S)
    g.add_static("a", "b", [1.0, 0.0, 0.0], [0, 0, 0, 1], pos_std_m=0.01, rot_std_rad=0.02)
    g.add_measurement("c", "b", 0, [0, 1, 0], [0, 0, 0.6, 0.8], rot_std_rad=0.01)
    g.add_measurement("c", "b", 10_000_000, [0, 2, 0], [0, 0, 0, 1], rot_std_rad=0.01)
    chain = g.best_paths("a", "c")[0]
    p, q, cov = np.empty(3), np.empty(4), np.empty((6, 6))
    got = kernel.NATIVE_COVARIANCE(4_000_000, chain._kernel_items, chain._cov_items, p, q, cov)
    assert got is not None and got[2] is True
    kernel.NATIVE = None
    try:
        want = _graph_of(g).pose("a", "c", at=4_000_000)
    finally:
        kernel.NATIVE = COMPILED
    np.testing.assert_allclose(cov, want.covariance, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(p, want.position, rtol=0, atol=1e-12)
    covs = chain._cov_items[1][0]
    odd = (chain._cov_items[0], (covs, 1, np.eye(6, dtype=np.float32)))
    assert kernel.NATIVE_COVARIANCE(4_000_000, chain._kernel_items, odd, p, q, cov) is None


def _graph_of(g: Graph) -> Graph:
    """The same edges in a new graph (its own plan and slerp-log caches)."""
    copy = Graph(max_extrapolation_s=LIMIT_S)
    for e in g.edges():
        edge = g.edge(e["parent"], e["child"], e["source"])
        if edge.buffer is None:
            p, q, _ = edge.value
            copy.add_static(e["parent"], e["child"], p, q, source=e["source"], **edge.attrs)
            continue
        copy.declare_measured(e["parent"], e["child"], source=e["source"], **edge.attrs)
        buf = edge.buffer
        for t, v, c in zip(buf.times, buf.values, buf.covs, strict=True):
            copy.add_measurement(e["parent"], e["child"], t, v[:3], v[3:], c,
                                 source=e["source"])
    return copy


def test_pure_python_kernel_is_forced_by_the_environment():
    env = dict(os.environ, UMA_SRG_PURE_PYTHON="1")
    out = subprocess.run([sys.executable, "-c",
                          "from agent.srg import kernel; print(kernel.NATIVE is None)"],
                         env=env, capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "True"


def test_the_kernels_quaternion_products_are_geometrys() -> None:
    """The kernel writes its quaternion products out (a call would cost as much); they are
    ``agent.geometry.quat_product`` exactly, in composition and in slerp's log."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        q = rng.normal(size=(2, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        a = (*rng.normal(size=3).tolist(), *q[0].tolist())
        b = (*rng.normal(size=3).tolist(), *q[1].tolist())
        assert kernel.compose(a, b)[3:] == geo.quat_product(a[3:], b[3:])
        conj = (-a[3], -a[4], -a[5], a[6])
        np.testing.assert_allclose(kernel._log_between(a, b),
                                   geo.quat_to_rotvec(np.array(geo.quat_product(conj, b[3:]))),
                                   atol=1e-12)


@needs_compiled
@pytest.mark.parametrize("seed", range(5))
def test_compiled_propagation_equals_the_adjoint_sum(seed: int) -> None:
    """``propagate`` (compiled) is ``sum(Ad C Ad^T)`` with ``geometry.adjoint``, to float
    rounding; covariances that are not 6x6 float64 arrays take the numpy form."""
    rng = np.random.default_rng(seed)
    poses, covs = [], []
    for _ in range(int(rng.integers(1, 5))):
        q = geo.rotvec_to_quat(rng.normal(size=3) * 2.0)
        poses.append(tuple(float(x) for x in np.r_[rng.normal(size=3) * 3.0, q]))
        L = rng.normal(size=(6, 6))
        covs.append(L @ L.T)
    M = np.array(poses)
    Ad = geo.adjoint(M[:, :3], M[:, 3:])
    expected = (Ad @ np.array(covs) @ Ad.transpose(0, 2, 1)).sum(axis=0)
    np.testing.assert_allclose(kernel.propagate(poses, covs), expected, rtol=0,
                               atol=1e-12 * np.abs(expected).max())
    as_lists = [c.tolist() for c in covs]
    np.testing.assert_allclose(kernel.propagate(poses, as_lists), expected, rtol=0,
                               atol=1e-12 * np.abs(expected).max())
