"""The pure SRG: poses against pytransform3d, interpolation against analytic motion,
errors that name what is missing, error functions, covariance propagation, plan caching."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pytransform3d.transform_manager import TransformManager

from agent import geometry as geo
from agent.srg import Graph, kernel
from agent.srg.errors import (
    BadErrorFunctionError,
    DataNotYetArrivedError,
    DataTooOldError,
    NoSamplesError,
    NoValidPathError,
    UnknownEdgeError,
    UnknownFrameError,
    UnreachableError,
)

S = 1_000_000_000  # ns per second
COMPILED = kernel.NATIVE


@pytest.fixture(scope="module", autouse=True, params=["compiled", "python"])
def chain_kernel(request):
    """Every test here runs on both chain kernels: the compiled one (when it was built) and
    the pure-Python one, which must give the same answers and errors."""
    if request.param == "compiled" and COMPILED is None:
        pytest.skip("the compiled kernel was not built (agent/srg/_kernel.c)")
    kernel.NATIVE = COMPILED if request.param == "compiled" else None
    yield request.param
    kernel.NATIVE = COMPILED


def random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    q = rng.normal(size=4)
    return rng.normal(size=3) * 2.0, q / np.linalg.norm(q)


def assert_same_pose(p, q, T, tol=1e-9):
    np.testing.assert_allclose(geo.to_matrix(p, q), T, atol=tol)


# ------------------------------------------------------------------ oracle: pytransform3d


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 9), extra=st.integers(0, 5))
def test_random_static_graphs_match_pytransform3d(seed, n, extra):
    """A random connected graph (a tree plus extra edges closing cycles, random directions)
    of consistent static edges gives pytransform3d's transform for every pair."""
    rng = np.random.default_rng(seed)
    world = [random_pose(rng) for _ in range(n)]  # ground truth pose of each frame
    names = [f"f{i}" for i in range(n)]
    pairs = [(int(rng.integers(0, i)), i) for i in range(1, n)]
    pairs += [tuple(rng.choice(n, 2, replace=False)) for _ in range(extra)]
    g = Graph()
    tm = TransformManager()
    for a, b in pairs:
        if rng.random() < 0.5:
            a, b = b, a
        # pose of b in a = inv(W_a) W_b
        p, q = geo.compose(*geo.inverse(*world[a]), *world[b])
        g.add_static(names[a], names[b], p, q, source=f"s{len(g.edges())}")
        tm.add_transform(names[b], names[a], geo.to_matrix(p, q))
    for _ in range(6):
        a, b = rng.choice(n, 2, replace=False)
        r = g.pose(names[a], names[b])
        assert_same_pose(r.position, r.quaternion, tm.get_transform(names[b], names[a]), 1e-8)
        assert r.path[0] == names[a] and r.path[-1] == names[b]
        assert r.covariance is None and r.extrapolated_s == 0.0


# ------------------------------------------------------------------ time: analytic motion


def motion(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant linear velocity and constant body angular velocity: the model that lerp +
    slerp reproduce exactly (and that constant-velocity extrapolation continues)."""
    p0, v = np.array([0.3, -0.2, 1.5]), np.array([0.4, 0.1, -0.2])
    q0 = geo.rotvec_to_quat(np.array([0.2, -0.1, 0.5]))
    w = np.array([0.3, 1.1, -0.7])
    return p0 + v * t_s, geo.quat_multiply(q0, geo.rotvec_to_quat(w * t_s))


def feed(g: Graph, parent: str, child: str, times_s, **attrs) -> None:
    for t in times_s:
        p, q = motion(t)
        g.add_measurement(parent, child, round(t * S), p, q, **attrs)


def test_interpolated_queries_match_analytic_trajectory_through_static_and_inverse_edges():
    g = Graph(max_extrapolation_s=0.05)
    feed(g, "ivy/world", "alice/head", np.arange(0.0, 2.0, 1 / 60), frequency_hz=60.0)
    cam_p, cam_q = np.array([1.2, 0.0, 2.0]), geo.rotvec_to_quat(np.array([0.0, 2.5, 0.0]))
    g.add_static("cam/nw", "ivy/world", cam_p, cam_q)  # walked backwards from ivy/world
    rng = np.random.default_rng(7)
    for t in rng.uniform(0.01, 1.95, 20):
        r = g.pose("ivy/world", "alice/head", at=round(t * S))
        p, q = motion(t)
        assert_same_pose(r.position, r.quaternion, geo.to_matrix(p, q), 1e-7)
        assert r.extrapolated_s == 0.0
        r2 = g.pose("alice/head", "cam/nw", at=round(t * S))
        expect = np.linalg.inv(geo.to_matrix(cam_p, cam_q) @ geo.to_matrix(p, q))
        assert_same_pose(r2.position, r2.quaternion, expect, 1e-7)
        assert r2.path == ["alice/head", "ivy/world", "cam/nw"]
        assert [e["forward"] for e in r2.edges] == [False, False]


def test_extrapolation_is_bounded_reported_and_follows_constant_velocity():
    g = Graph(max_extrapolation_s=0.05)
    feed(g, "a", "b", [0.0, 0.01, 0.02])
    r = g.pose("a", "b", at=round(0.05 * S))
    assert r.extrapolated_s == pytest.approx(0.03)
    p, q = motion(0.05)
    assert_same_pose(r.position, r.quaternion, geo.to_matrix(p, q), 1e-9)
    with pytest.raises(DataNotYetArrivedError, match=r"a->b \[measured\].*not yet arrived"):
        g.pose("a", "b", at=round(0.08 * S))
    # before the first sample, within the limit: extrapolated backwards
    r = g.pose("a", "b", at=-round(0.02 * S))
    assert r.extrapolated_s == pytest.approx(0.02)
    assert_same_pose(r.position, r.quaternion, geo.to_matrix(*motion(-0.02)), 1e-9)


def test_ttl_lowers_the_extrapolation_limit():
    g = Graph(max_extrapolation_s=1.0)
    feed(g, "a", "b", [0.0, 0.01], ttl_s=0.02)
    g.pose("a", "b", at=round(0.03 * S))
    with pytest.raises(DataNotYetArrivedError, match=r"limit of 0\.02 s"):
        g.pose("a", "b", at=round(0.04 * S))


def test_too_old_and_no_samples_are_distinguished():
    g = Graph(buffer_s=1.0, max_extrapolation_s=0.01)
    feed(g, "a", "b", np.arange(0.0, 3.0, 0.1))
    with pytest.raises(DataTooOldError, match=r"data too old.*buffer keeps 1 s"):
        g.pose("a", "b", at=round(0.5 * S))
    assert len(g.edge("a", "b").buffer) <= 14  # ~1 s of 10 Hz plus the batch slack
    g.declare_measured("b", "c", source="cam", frequency_hz=30.0)
    with pytest.raises(NoSamplesError, match=r"b->c \[cam\].*no sample has arrived"):
        g.pose("a", "c", at=round(2.9 * S))
    with pytest.raises(NoSamplesError, match=r"b->c \[cam\]"):
        g.pose("a", "c")


def test_a_frame_in_itself_is_the_identity():
    g = Graph()
    g.add_static("a", "b", [1, 2, 3], [0, 0, 0, 1])
    r = g.pose("b", "b", at=5)
    assert r.path == ["b"] and r.t_ns == 5 and r.covariance is None
    np.testing.assert_array_equal(r.matrix, np.eye(4))
    with pytest.raises(UnknownFrameError):
        g.pose("z", "z")


def test_buffers_are_bounded_in_length():
    g = Graph(max_samples=10)
    feed(g, "a", "b", np.arange(0.0, 1.0, 0.01))
    buf = g.edge("a", "b").buffer
    assert len(buf) == 10 and buf.times[0] == round(0.9 * S)
    with pytest.raises(DataTooOldError):
        g.pose("a", "b", at=round(0.5 * S))


def test_at_none_is_the_latest_common_time():
    g = Graph()
    feed(g, "a", "b", [0.0, 0.1, 0.2, 0.3])
    feed(g, "b", "c", [0.0, 0.1, 0.2])
    r = g.pose("a", "c")
    assert r.t_ns == round(0.2 * S) and r.extrapolated_s == 0.0


def test_out_of_order_and_repeated_samples():
    g = Graph()
    feed(g, "a", "b", [0.0, 0.2, 0.1, 0.3])
    g.pose("a", "b", at=round(0.15 * S))  # caches the slerp log between 0.1 and 0.2
    feed(g, "a", "b", [0.15])  # inserted between: the cached logs must not be reused
    r = g.pose("a", "b", at=round(0.12 * S))
    assert_same_pose(r.position, r.quaternion, geo.to_matrix(*motion(0.12)), 1e-9)
    assert r.stamps == [(round(0.1 * S), round(0.15 * S))]


# ------------------------------------------------------------------ errors that name things


def test_unknown_frame_and_unreachable_name_what_exists():
    g = Graph()
    g.add_static("a", "b", [0, 0, 0], [0, 0, 0, 1])
    g.add_static("x", "y", [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(UnknownFrameError, match=r"unknown frame 'zz'; known frames: a, b, x, y"):
        g.pose("a", "zz")
    with pytest.raises(UnreachableError, match=r"no path from 'a' to 'y'.*'a' reaches a, b"):
        g.pose("a", "y")
    with pytest.raises(UnknownEdgeError, match=r"b->a"):
        g.remove_edge("b", "a")
    assert isinstance(UnknownFrameError("q", []), LookupError)


@pytest.mark.parametrize("bad", [
    dict(position=[0, float("nan"), 0]),
    dict(quaternion=[0, 0, 0, 2.0]),
    dict(position=[1, 2]),
    dict(t_ns=1.5),
    dict(latency_s=-1.0),
    dict(confidence=1.5),
    dict(latency=0.1),  # misspelled attribute
])
def test_bad_measurements_are_refused_with_a_reason(bad):
    g = Graph()
    args = dict(t_ns=0, position=[0, 0, 0], quaternion=[0, 0, 0, 1])
    attrs = {k: v for k, v in bad.items() if k not in args}
    args.update({k: v for k, v in bad.items() if k in args})
    with pytest.raises(ValueError):
        g.add_measurement("a", "b", args["t_ns"], args["position"], args["quaternion"], **attrs)


def test_bad_error_function():
    g = Graph()
    g.add_static("a", "b", [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(BadErrorFunctionError, match="nor a valid expression"):
        g.pose("a", "b", error="latency_s +")
    with pytest.raises(BadErrorFunctionError, match="condition"):
        g.pose("a", "b", error="latency_s < 1")
    with pytest.raises(BadErrorFunctionError):
        g.pose("a", "b", error="bogus_attribute * 2")


# ------------------------------------------------------------------ error functions


def diamond() -> Graph:
    """a -> b -> d (fast, low confidence, cheap) and a -> c -> d (slow, confident, dear),
    plus a direct, very uncertain a -> d."""
    g = Graph()
    z, i = [0.1, 0.0, 0.0], [0, 0, 0, 1]
    g.add_static("a", "b", z, i, latency_s=0.001, confidence=0.5, cost=1.0, pos_std_m=0.01)
    g.add_static("b", "d", z, i, latency_s=0.001, confidence=0.5, cost=1.0, pos_std_m=0.01)
    g.add_static("a", "c", z, i, latency_s=0.01, confidence=0.99, cost=5.0, pos_std_m=0.001)
    g.add_static("c", "d", z, i, latency_s=0.01, confidence=0.99, cost=5.0, pos_std_m=0.001)
    g.add_static("a", "d", [0.2, 0, 0], i, latency_s=0.05, confidence=0.9, cost=20.0,
                 pos_std_m=0.5)
    return g


@pytest.mark.parametrize("error, path", [
    ("hops", ["a", "d"]),
    ("latency", ["a", "b", "d"]),
    ("cost", ["a", "b", "d"]),
    ("confidence", ["a", "c", "d"]),
    ("accuracy", ["a", "c", "d"]),
    ("latency_s * 1000 + cost", ["a", "b", "d"]),
    ("pos_std_m * 100 + hops", ["a", "c", "d"]),
    ("pos_std_m + hops", ["a", "d"]),
])
def test_error_functions_pick_their_best_path(error, path):
    r = diamond().pose("a", "d", error=error)
    assert r.path == path
    np.testing.assert_allclose(r.position, [0.2, 0, 0], atol=1e-12)


def test_path_attributes_aggregate():
    r = diamond().pose("a", "d", error="latency")
    a = r.attributes
    assert a["hops"] == 2 and a["latency_s"] == pytest.approx(0.002)
    assert a["confidence"] == pytest.approx(0.25) and a["cost"] == 2.0
    assert a["static"] is True and math.isinf(a["frequency_hz"])
    assert a["pos_std_m"] == pytest.approx(0.01 * math.sqrt(2), rel=1e-9)
    assert a["accuracy"] == pytest.approx(np.trace(r.covariance))


def test_parallel_edges_from_different_sources_are_distinct():
    g = Graph()
    g.add_measurement("w", "h", 0, [0, 0, 0], [0, 0, 0, 1], source="cam", latency_s=0.02)
    g.add_measurement("w", "h", 0, [1, 0, 0], [0, 0, 0, 1], source="imu", latency_s=0.001)
    r = g.pose("w", "h", at=0, error="latency")
    assert r.edges[0]["source"] == "imu" and r.position[0] == 1.0
    g.set_attributes("w", "h", "imu", latency_s=0.5)
    r = g.pose("w", "h", at=0, error="latency")
    assert r.edges[0]["source"] == "cam" and r.position[0] == 0.0
    with pytest.raises(ValueError, match="2 parallel edges"):
        g.set_attributes("w", "h", latency_s=0.1)


# ------------------------------------------------------------------ covariance


def test_covariance_matches_sequential_geometry_propagation():
    """Batched propagation equals composing edge by edge with geometry's functions,
    including backward edges, sample covariances and std attributes."""
    rng = np.random.default_rng(3)
    g = Graph()
    values = [random_pose(rng) for _ in range(4)]
    C = np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5])
    g.add_static("a", "b", *values[0], pos_std_m=0.01, rot_std_rad=0.02)
    g.add_measurement("c", "b", 0, *values[1], covariance=C)  # walked backwards
    g.add_measurement("c", "d", 0, *values[2], pos_std_m=0.003, rot_std_rad=0.004)
    g.add_static("d", "e", *values[3], covariance=2 * C)
    r = g.pose("a", "e", at=0)
    steps = [(values[0], geo.covariance_from_std(values[0][0], 0.01, 0.02), True),
             (values[1], C, False),
             (values[2], geo.covariance_from_std(values[2][0], 0.003, 0.004), True),
             (values[3], 2 * C, True)]
    p, q, cov = np.zeros(3), geo.quat_identity(), None
    for (ep, eq), ec, fwd in steps:
        if not fwd:
            ec = geo.inverse_covariance(ep, eq, ec)
            ep, eq = geo.inverse(ep, eq)
        cov = geo.compose_covariance(p, q, cov, ec)
        p, q = geo.compose(p, q, ep, eq)
    np.testing.assert_allclose(r.covariance, cov, rtol=1e-9, atol=1e-15)
    assert_same_pose(r.position, r.quaternion, geo.to_matrix(p, q))


def test_single_measured_edge_covariance_in_both_directions():
    """The one-edge fast path (a tracker's own segment) agrees with geometry, walked
    forwards and backwards, with std attributes and with a sample covariance."""
    rng = np.random.default_rng(4)
    (p1, q1), (p2, q2) = random_pose(rng), random_pose(rng)
    C = np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5])
    g = Graph()
    g.add_measurement("a", "b", 0, p1, q1, pos_std_m=0.003, rot_std_rad=0.004)
    g.add_measurement("c", "d", 0, p2, q2, covariance=C)
    std = geo.covariance_from_std(p1, 0.003, 0.004)
    np.testing.assert_allclose(g.pose("a", "b", at=0).covariance, std, rtol=1e-12)
    np.testing.assert_allclose(g.pose("b", "a", at=0).covariance,
                               geo.inverse_covariance(p1, q1, std), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(g.pose("c", "d", at=0).covariance, C, rtol=1e-12)


# ------------------------------------------------------------------ plans


def chain_graph() -> Graph:
    g = Graph()
    feed(g, "w", "x", [0.0, 0.1], latency_s=0.01)
    g.add_static("x", "y", [0, 1, 0], [0, 0, 0, 1])
    g.add_static("p", "q", [0, 0, 1], [0, 0, 0, 1])  # another component
    return g


def test_new_sample_does_not_invalidate_a_plan():
    g = chain_graph()
    g.pose("w", "y", at=round(0.05 * S), error="latency")
    built = g.plans_built
    feed(g, "w", "x", [0.2, 0.3], latency_s=0.01)  # same attributes: just samples
    r = g.pose("w", "y", at=round(0.25 * S), error="latency")
    assert g.plans_built == built and g.has_plan("w", "y", "latency")
    assert r.stamps == [(round(0.2 * S), round(0.3 * S))]


def test_a_kept_plan_answers_as_pose_until_the_graph_changes():
    """``plan()`` is the plan ``pose()`` evaluates: the same answers while ``version`` stays,
    new samples included; an edge change moves ``version`` and gives a new plan."""
    g = chain_graph()
    plan, version = g.plan("w", "y", "latency"), g.version
    feed(g, "w", "x", [0.2, 0.3], latency_s=0.01)
    for at in (round(0.05 * S), round(0.25 * S), None):
        kept, asked = plan.evaluate(at), g.pose("w", "y", at=at, error="latency")
        np.testing.assert_array_equal(kept.position, asked.position)
        assert kept.stamps == asked.stamps and kept.t_ns == asked.t_ns
    assert g.version == version and g.plan("w", "y", "latency") is plan
    g.add_static("w", "y", [5, 0, 0], [0, 0, 0, 1], source="survey")
    assert g.version != version and g.plan("w", "y", "latency") is not plan


def test_attribute_change_invalidates_plans_that_use_the_edge_only():
    g = chain_graph()
    g.pose("w", "y", at=0, error="latency")
    g.pose("p", "q", error="latency")
    g.set_attributes("w", "x", latency_s=0.02)
    assert not g.has_plan("w", "y", "latency")
    assert g.has_plan("p", "q", "latency")  # unrelated component
    g.pose("w", "y", at=0, error="latency")
    feed(g, "w", "x", [0.4], latency_s=0.03)  # an attribute change carried by a sample
    assert not g.has_plan("w", "y", "latency")
    g.set_attributes("w", "x", latency_s=0.5)
    feed(g, "w", "x", [0.5], latency_s=0.03)  # the sample's attributes win again
    assert g.edge("w", "x").attrs["latency_s"] == 0.03


def test_added_and_removed_edges_invalidate_and_reroute():
    g = chain_graph()
    g.pose("w", "y", at=0, error="hops")
    g.add_static("p", "z", [0, 0, 0], [0, 0, 0, 1])  # unrelated addition
    assert g.has_plan("w", "y", "hops")
    g.add_static("w", "y", [5, 0, 0], [0, 0, 0, 1], source="survey")  # shortcut
    assert not g.has_plan("w", "y", "hops")
    assert g.pose("w", "y", at=0).path == ["w", "y"]
    g.remove_edge("w", "y", "survey")
    assert not g.has_plan("w", "y", "hops")
    assert g.pose("w", "y", at=0).path == ["w", "x", "y"]
    g.remove_source("measured")
    with pytest.raises(UnknownFrameError, match="'w'"):
        g.pose("w", "y", at=0)


def test_falls_back_to_the_next_path_when_the_best_has_no_data_at_t():
    g = Graph(max_extrapolation_s=0.01)
    feed(g, "a", "b", [0.0, 0.1], latency_s=0.001, source="fast")
    feed(g, "a", "b", [0.0, 0.1, 0.2, 0.3], latency_s=0.01, source="slow")
    assert g.pose("a", "b", at=round(0.05 * S), error="latency").edges[0]["source"] == "fast"
    assert g.pose("a", "b", at=round(0.25 * S), error="latency").edges[0]["source"] == "slow"
    with pytest.raises(NoValidPathError, match=r"2 candidates tried.*\[fast\].*\[slow\]"):
        g.pose("a", "b", at=round(0.5 * S), error="latency")


def test_an_all_static_path_answers_alike_at_every_time_with_arrays_of_its_own():
    from agent.srg import Graph

    g = Graph()
    g.add_static("a", "b", [1.0, 0.0, 0.0], [0, 0, 0, 1], pos_std_m=0.01)
    g.add_static("b", "c", [0.0, 2.0, 0.0], [0, 0, 0.38268343, 0.92387953], rot_std_rad=0.02)
    first, second = g.pose("a", "c", at=5), g.pose("a", "c", at=9)
    assert (first.t_ns, second.t_ns) == (5, 9) and second.stamps == []
    np.testing.assert_array_equal(first.position, second.position)
    np.testing.assert_array_equal(first.covariance, second.covariance)
    assert first.attributes == second.attributes
    first.position[0] = 99.0  # a caller's change stays in its own result
    first.covariance[0, 0] = 99.0
    third = g.pose("a", "c", at=1)
    assert third.position[0] == 1.0 and third.covariance[0, 0] != 99.0
    g.add_static("b", "c", [0.0, 3.0, 0.0], [0, 0, 0, 1])  # a new value: a new answer
    assert g.pose("a", "c", at=1).position[1] == 3.0
