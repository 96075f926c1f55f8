"""agent/geometry.py: identities (hypothesis), cross-checks against pytransform3d and
OpenCV, validation messages, and covariance propagation against Monte Carlo sampling."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import pytransform3d.rotations as pr
import pytransform3d.transformations as pt
from hypothesis import given, settings
from hypothesis import strategies as st

from agent import geometry as g

# --------------------------------------------------------------------------- strategies

_coord = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.tuples(_coord, _coord, _coord, _coord).map(np.array).filter(
    lambda q: np.linalg.norm(q) > 0.1).map(lambda q: q / np.linalg.norm(q))
vecs = st.tuples(*[st.floats(-10.0, 10.0, allow_nan=False)] * 3).map(np.array)
axes = st.tuples(_coord, _coord, _coord).map(np.array).filter(
    lambda a: np.linalg.norm(a) > 0.1).map(lambda a: a / np.linalg.norm(a))
#: Rotation vectors with angles from tiny through ordinary to just below pi.
angles = st.one_of(st.floats(1e-12, 1e-5), st.floats(1e-5, math.pi - 1e-3),
                   st.floats(math.pi - 1e-3, math.pi - 1e-9))
rotvecs = st.tuples(axes, angles).map(lambda t: t[0] * t[1])
poses = st.tuples(vecs, quats)
alphas = st.floats(0.0, 1.0)


def same_rotation(a: np.ndarray, b: np.ndarray, atol: float = 1e-9) -> bool:
    """q and -q are the same rotation."""
    return bool(np.allclose(a, b, atol=atol) or np.allclose(a, -b, atol=atol))


def wxyz(q: np.ndarray) -> np.ndarray:
    return np.array([q[3], q[0], q[1], q[2]])


def pq7(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """pytransform3d's pose vector: x, y, z, qw, qx, qy, qz."""
    return np.concatenate([p, wxyz(q)])


# --------------------------------------------------------------------------- identities


@given(poses)
def test_compose_with_inverse_is_identity(pose: tuple[np.ndarray, np.ndarray]) -> None:
    p, q = pose
    for a, b in ((pose, g.inverse(p, q)), (g.inverse(p, q), pose)):
        pc, qc = g.compose(*a, *b)
        np.testing.assert_allclose(pc, 0.0, atol=1e-9)
        assert same_rotation(qc, g.quat_identity())
    pi, qi = g.inverse(*g.inverse(p, q))
    np.testing.assert_allclose(pi, p, atol=1e-9)
    np.testing.assert_allclose(qi, q, atol=1e-12)


@given(poses, poses, poses)
def test_compose_is_associative_and_matches_matrices(a, b, c) -> None:
    left = g.compose(*g.compose(*a, *b), *c)
    right = g.compose(*a, *g.compose(*b, *c))
    np.testing.assert_allclose(left[0], right[0], atol=1e-9)
    assert same_rotation(left[1], right[1])
    Tab = g.to_matrix(*g.compose(*a, *b))
    np.testing.assert_allclose(Tab, g.to_matrix(*a) @ g.to_matrix(*b), atol=1e-9)
    # inverse of a product is the product of inverses, reversed
    inv = g.inverse(*g.compose(*a, *b))
    rev = g.compose(*g.inverse(*b), *g.inverse(*a))
    np.testing.assert_allclose(inv[0], rev[0], atol=1e-9)
    assert same_rotation(inv[1], rev[1])


@given(poses, st.lists(vecs, min_size=1, max_size=5))
def test_transform_points_matches_the_matrix(pose, points) -> None:
    pts = np.array(points)
    T = g.to_matrix(*pose)
    expected = (T @ np.c_[pts, np.ones(len(pts))].T).T[:, :3]
    np.testing.assert_allclose(g.transform_points(*pose, pts), expected, atol=1e-9)
    np.testing.assert_allclose(g.quat_rotate(pose[1], pts), pts @ T[:3, :3].T, atol=1e-9)


@given(poses)
def test_matrix_round_trips(pose) -> None:
    p, q = pose
    T = g.to_matrix(p, q)
    g.check_matrix(T)
    p2, q2 = g.from_matrix(T)
    np.testing.assert_allclose(p2, p, atol=0)
    assert same_rotation(q2, q, atol=1e-12)
    assert q2[3] >= 0  # canonical
    np.testing.assert_allclose(g.quat_to_matrix(g.matrix_to_quat(T[:3, :3])), T[:3, :3],
                               atol=1e-12)


@given(rotvecs)
def test_exp_log_round_trip(r: np.ndarray) -> None:
    q = g.rotvec_to_quat(r)
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)
    back = g.quat_to_rotvec(q)
    theta = np.linalg.norm(r)
    # relative accuracy also for tiny angles; absolute ~1e-9 near pi where w -> 0
    np.testing.assert_allclose(back, r, rtol=1e-9, atol=1e-15 if theta < 1 else 1e-8)
    assert g.quat_angle(g.quat_identity(), q) == pytest.approx(theta, rel=1e-9, abs=1e-15)
    # the single-vector path and the batched one agree (shapes (3,), (1, 3), (2, 3))
    np.testing.assert_allclose(g.rotvec_to_quat(r[None]), q[None], rtol=0, atol=1e-16)
    np.testing.assert_allclose(g.rotvec_to_quat(np.stack([r, r]))[1], q, rtol=0, atol=1e-15)


@given(quats)
def test_log_exp_round_trip(q: np.ndarray) -> None:
    r = g.quat_to_rotvec(q)
    assert np.linalg.norm(r) <= math.pi + 1e-12
    assert same_rotation(g.rotvec_to_quat(r), q, atol=1e-12)


def test_exp_log_at_the_edges() -> None:
    assert same_rotation(g.rotvec_to_quat(np.zeros(3)), g.quat_identity())
    np.testing.assert_array_equal(g.quat_to_rotvec(g.quat_identity()), np.zeros(3))
    half_turn = g.rotvec_to_quat([0.0, 0.0, math.pi])
    np.testing.assert_allclose(half_turn, [0, 0, 1, 0], atol=1e-15)
    assert np.linalg.norm(g.quat_to_rotvec(half_turn)) == pytest.approx(math.pi)
    # the log of -q is the same rotation (angle stays in [0, pi])
    q = g.rotvec_to_quat([0.3, -0.2, 0.1])
    np.testing.assert_allclose(g.quat_to_rotvec(-q), [0.3, -0.2, 0.1], atol=1e-15)
    # a tiny angle keeps its relative precision
    tiny = np.array([1e-13, -2e-13, 3e-13])
    np.testing.assert_allclose(g.quat_to_rotvec(g.rotvec_to_quat(tiny)), tiny, rtol=1e-12)


@given(st.lists(poses, min_size=1, max_size=6))
def test_functions_vectorise_like_a_loop(pose_list) -> None:
    P = np.array([p for p, _ in pose_list])
    Q = np.array([q for _, q in pose_list])
    pc, qc = g.compose(P, Q, P[::-1], Q[::-1])
    T = g.to_matrix(P, Q)
    R = g.rodrigues(g.quat_to_rotvec(Q))
    for i, (p, q) in enumerate(pose_list):
        pi, qi = g.compose(p, q, *pose_list[-1 - i])
        np.testing.assert_allclose(pc[i], pi, atol=1e-12)
        np.testing.assert_allclose(qc[i], qi, atol=1e-12)
        np.testing.assert_allclose(T[i], g.to_matrix(p, q), atol=0)
        np.testing.assert_allclose(R[i], g.quat_to_matrix(q), atol=1e-9)
    Ads = g.adjoint(P, Q)
    assert Ads.shape == (len(P), 6, 6)
    for i, (p, q) in enumerate(pose_list):  # one pose (plain floats) equals the batch
        np.testing.assert_allclose(g.adjoint(p, q), Ads[i], rtol=1e-14, atol=1e-15)
    assert g.adjoint(P[:1], Q[:1]).shape == (1, 6, 6)  # a batch of one stays a batch


# --------------------------------------------------------------------------- interpolation


@given(poses, poses, alphas)
def test_interpolation_endpoints_and_constant_rate(a, b, alpha) -> None:
    (p0, q0), (p1, q1) = a, b
    assert same_rotation(g.slerp(q0, q1, 0.0), q0, atol=1e-12)
    assert same_rotation(g.slerp(q0, q1, 1.0), q1, atol=1e-9)
    total = float(g.quat_angle(q0, q1))
    qa = g.slerp(q0, q1, alpha)
    assert np.linalg.norm(qa) == pytest.approx(1.0, abs=1e-12)
    # constant angular rate along the shortest arc
    assert g.quat_angle(q0, qa) == pytest.approx(alpha * total, abs=1e-9)
    assert g.quat_angle(qa, q1) == pytest.approx((1 - alpha) * total, abs=1e-9)
    pa, qb = g.interpolate(p0, q0, p1, q1, alpha)
    np.testing.assert_allclose(pa, p0 + alpha * (p1 - p0), atol=1e-9)
    np.testing.assert_allclose(qb, qa, atol=1e-12)


def test_slerp_shortest_arc_vectorised_and_extrapolation() -> None:
    q0 = g.rotvec_to_quat([0.0, 0.0, 0.1])
    q1 = -g.rotvec_to_quat([0.0, 0.0, 0.3])  # same rotation, other hemisphere
    mid = g.slerp(q0, q1, 0.5)
    assert same_rotation(mid, g.rotvec_to_quat([0.0, 0.0, 0.2]), atol=1e-12)
    many = g.slerp(q0, g.rotvec_to_quat([0.0, 0.0, 0.3]), np.array([0.0, 0.5, 1.0, 2.0]))
    np.testing.assert_allclose(g.quat_to_rotvec(many)[:, 2], [0.1, 0.2, 0.3, 0.5], atol=1e-12)


@settings(max_examples=50)
@given(quats, quats, alphas)
def test_slerp_matches_pytransform3d(q0, q1, alpha) -> None:
    if g.quat_angle(q0, q1) > math.pi - 1e-3:
        return  # the shortest arc is ill-defined at half a turn
    ref = pr.quaternion_slerp(wxyz(q0), wxyz(q1), alpha, shortest_path=True)
    assert same_rotation(wxyz(g.slerp(q0, q1, alpha)), ref, atol=1e-9)


# --------------------------------------------------------------------------- independent oracles


@given(poses, poses)
def test_against_pytransform3d(a, b) -> None:
    (p1, q1), (p2, q2) = a, b
    T1 = pt.transform_from_pq(pq7(p1, q1))
    T2 = pt.transform_from_pq(pq7(p2, q2))
    np.testing.assert_allclose(g.to_matrix(p1, q1), T1, atol=1e-9)
    np.testing.assert_allclose(g.quat_to_matrix(q1), pr.matrix_from_quaternion(wxyz(q1)),
                               atol=1e-12)
    # T1 is B->A in pytransform3d's words (it maps B coordinates into A): concat(C2B, B2A)
    np.testing.assert_allclose(g.to_matrix(*g.compose(p1, q1, p2, q2)), pt.concat(T2, T1),
                               atol=1e-9)
    np.testing.assert_allclose(g.to_matrix(*g.inverse(p1, q1)), pt.invert_transform(T1),
                               atol=1e-9)
    assert same_rotation(wxyz(g.matrix_to_quat(T1[:3, :3])),
                         pr.quaternion_from_matrix(T1[:3, :3]), atol=1e-9)
    assert same_rotation(wxyz(g.quat_multiply(q1, q2)),
                         pr.concatenate_quaternions(wxyz(q1), wxyz(q2)), atol=1e-12)


def _axis_angle_quat(axis, angle: float) -> np.ndarray:
    """xyzw quaternion of ``angle`` about ``axis``, written out (no geometry call)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[math.sin(angle / 2) * a, math.cos(angle / 2)]


def test_pose_error_position_is_the_euclidean_distance() -> None:
    """Exact values: every accuracy figure of the evals rests on this metric (max-abs
    would give 4, 12, 2 here and the L1 norm 7, 17, 5)."""
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    dp, dr = g.pose_error([3.0, 4.0, 0.0], ident, [0.0, 0.0, 0.0], ident)
    assert dp == 5.0 and dr == 0.0
    truth = np.array([[0.5, -1.0, 2.0]] * 3)
    offsets = np.array([[3.0, 4.0, 0.0], [0.0, -12.0, 5.0], [2.0, -2.0, 1.0]])
    dp, dr = g.pose_error(truth + offsets, np.tile(ident, (3, 1)), truth,
                          np.tile(ident, (3, 1)))
    np.testing.assert_allclose(dp, [5.0, 13.0, 3.0], rtol=1e-15)
    np.testing.assert_array_equal(dr, 0.0)


@pytest.mark.parametrize("angle", [1e-6, 0.3, 1.2, math.pi - 1e-3])
def test_pose_error_orientation_is_the_rotation_angle_between(angle: float) -> None:
    """A known rotation applied on either side of a non-trivial truth reports its angle
    (in radians, [0, pi]); the quaternion's sign does not matter."""
    truth = _axis_angle_quat([1.0, 0.0, 0.0], math.pi / 2)
    turn = _axis_angle_quat([1.0, 2.0, 2.0], angle)
    p = np.zeros(3)
    for est in (g.quat_multiply(turn, truth), g.quat_multiply(truth, turn),
                -g.quat_multiply(turn, truth)):
        dp, dr = g.pose_error(p, est, p, truth)
        assert dp == 0.0 and dr == pytest.approx(angle, rel=1e-9, abs=1e-15)
    # beyond pi the shorter way round is the error
    _, dr = g.pose_error(p, _axis_angle_quat([0.0, 0.0, 1.0], 2 * math.pi - 0.5), p,
                         _axis_angle_quat([0.0, 0.0, 1.0], 0.0))
    assert dr == pytest.approx(0.5, rel=1e-12)


@given(quats, quats)
def test_pose_error_orientation_matches_pytransform3d(a, b) -> None:
    _, dr = g.pose_error(np.zeros(3), a, np.zeros(3), b)
    assert dr == pytest.approx(pr.quaternion_dist(wxyz(a), wxyz(b)), abs=1e-7)


@given(rotvecs)
def test_rodrigues_against_opencv_and_pytransform3d(r: np.ndarray) -> None:
    R = g.rodrigues(r)
    R_cv, _ = cv2.Rodrigues(r.reshape(3, 1))
    np.testing.assert_allclose(R, R_cv, atol=1e-9)
    np.testing.assert_allclose(R, pr.matrix_from_compact_axis_angle(r), atol=1e-9)
    back = g.rodrigues_inverse(R)
    if np.linalg.norm(r) < math.pi - 1e-3:  # near pi only the rotation, not the sign, is fixed
        np.testing.assert_allclose(back, r, atol=1e-8)
    if 1e-4 < np.linalg.norm(r) < math.pi - 1e-3:  # OpenCV rounds smaller angles to zero
        np.testing.assert_allclose(back, cv2.Rodrigues(R)[0].ravel(), atol=1e-6)
    np.testing.assert_allclose(g.rodrigues(back), R, atol=1e-8)


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(("call", "fragment"), [
    (lambda: g.check_quaternion([0, 0, np.nan, 1]), "quaternion: non-finite value nan at "
                                                    "index (2,)"),
    (lambda: g.check_quaternion([0, 0, 0, 1.01]), "not a unit quaternion (norm 1.01"),
    (lambda: g.check_quaternion([0, 0, 0, 0], name="q_wc"), "q_wc: not a unit quaternion"),
    (lambda: g.check_quaternion([0, 0, 1]), "expected shape (..., 4), got (3,)"),
    (lambda: g.check_quaternion([[0, 0, 0, 1], [0, 0, 0, 2]]), "off by 1"),
    (lambda: g.check_vector([1, 2, np.inf]), "position: non-finite value inf"),
    (lambda: g.check_vector(["a", 1, 2]), "position: not a numeric array"),
    (lambda: g.check_vector(3.0), "expected shape (..., 3), got ()"),
    (lambda: g.check_rotation_matrix(np.diag([1.0, 1.0, -1.0])), "reflection"),
    (lambda: g.check_rotation_matrix(np.eye(3) * 1.1), "not orthonormal"),
    (lambda: g.check_rotation_matrix(np.eye(4)), "expected shape (..., 3, 3)"),
    (lambda: g.check_matrix(np.diag([1.0, 1.0, 1.0, 2.0])), "last row must be [0, 0, 0, 1]"),
    (lambda: g.check_matrix(np.diag([1.0, -1.0, 1.0, 1.0])), "rotation block: determinant"),
    (lambda: g.check_covariance(np.triu(np.ones((6, 6)))), "not symmetric"),
    (lambda: g.check_covariance(-np.eye(6)), "not positive semi-definite"),
    (lambda: g.check_covariance(np.eye(3)), "expected shape (..., 6, 6)"),
    (lambda: g.check_covariance(np.stack([np.eye(6)] * 2)), "expected one (6, 6) matrix"),
])
def test_validation_messages(call, fragment: str) -> None:
    with pytest.raises(ValueError) as err:
        call()
    assert fragment in str(err.value)


def test_validation_accepts_and_normalises() -> None:
    q = g.check_quaternion([0, 0, 0, 1.0005])
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)
    assert g.check_quaternion(np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))).shape == (3, 4)
    R = g.rodrigues([0.1, 0.2, 0.3])
    np.testing.assert_array_equal(g.check_rotation_matrix(R), R)
    g.check_covariance(np.zeros((6, 6)))


# --------------------------------------------------------------------------- covariance


def _skew(v: np.ndarray) -> np.ndarray:
    K = np.zeros((*v.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return K - np.swapaxes(K, -1, -2)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Exp of xi = [rho, phi] as (N, 4, 4): written here from the closed form, independently
    of the module under test (checked against pytransform3d below)."""
    rho, phi = xi[:, :3], xi[:, 3:]
    th = np.linalg.norm(phi, axis=1)[:, None, None]
    K = _skew(phi)
    small = th < 1e-9
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0, np.sin(ths) / ths)
    B = np.where(small, 0.5, (1 - np.cos(ths)) / ths**2)
    C = np.where(small, 1 / 6, (ths - np.sin(ths)) / ths**3)
    I = np.eye(3)
    T = np.tile(np.eye(4), (len(xi), 1, 1))
    T[:, :3, :3] = I + A * K + B * K @ K
    T[:, :3, 3] = ((I + B * K + C * K @ K) @ rho[:, :, None])[:, :, 0]
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Inverse of ``se3_exp`` for rotations well below pi (enough for small perturbations)."""
    R = T[:, :3, :3]
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)
    th = np.arccos(cos)
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    s = np.where(th < 1e-9, 1.0, th / (2 * np.sin(np.maximum(th, 1e-9))))
    phi = w * s[:, None]
    thb = th[:, None, None]
    K = _skew(phi)
    ths = np.where(thb < 1e-9, 1.0, thb)
    B = np.where(thb < 1e-9, 0.5, (1 - np.cos(ths)) / ths**2)
    C = np.where(thb < 1e-9, 1 / 6, (ths - np.sin(ths)) / ths**3)
    V = np.eye(3) + B * K + C * K @ K
    rho = np.linalg.solve(V, T[:, :3, 3:])[:, :, 0]
    return np.concatenate([rho, phi], axis=1)


def test_se3_exp_helper_matches_pytransform3d() -> None:
    rng = np.random.default_rng(3)
    xi = rng.normal(size=(5, 6)) * 0.7
    T = se3_exp(xi)
    for i in range(5):
        ref = pt.transform_from_exponential_coordinates(np.r_[xi[i, 3:], xi[i, :3]])
        np.testing.assert_allclose(T[i], ref, atol=1e-12)
    np.testing.assert_allclose(se3_log(T), xi, atol=1e-10)


def _spd(rng: np.random.Generator, scales: np.ndarray) -> np.ndarray:
    A = rng.normal(size=(6, 6)) * 0.3 + np.eye(6)
    C = A @ A.T
    d = np.sqrt(np.diag(C))
    return C / np.outer(d, d) * np.outer(scales, scales)


def _assert_close_in_distribution(C_emp: np.ndarray, C: np.ndarray, tol: float) -> None:
    """Whiten by the predicted covariance: a first-order match gives about the identity."""
    L = np.linalg.cholesky(C)
    M = np.linalg.solve(L, np.linalg.solve(L, C_emp).T)
    assert np.abs(M - np.eye(6)).max() < tol, np.round(M, 3)


N_SAMPLES = 20_000
STD = np.array([0.01, 0.02, 0.015, 0.01, 0.02, 0.015])  # m, m, m, rad, rad, rad


def _random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    q = rng.normal(size=4)
    return rng.normal(size=3), q / np.linalg.norm(q)


def test_compose_covariance_matches_monte_carlo() -> None:
    rng = np.random.default_rng(11)
    (p1, q1), (p2, q2) = _random_pose(rng), _random_pose(rng)
    C1, C2 = _spd(rng, STD), _spd(rng, 1.5 * STD)
    xi1 = rng.multivariate_normal(np.zeros(6), C1, N_SAMPLES)
    xi2 = rng.multivariate_normal(np.zeros(6), C2, N_SAMPLES)
    T1, T2 = g.to_matrix(p1, q1), g.to_matrix(p2, q2)
    T_noisy = se3_exp(xi1) @ T1 @ se3_exp(xi2) @ T2
    xi = se3_log(T_noisy @ np.linalg.inv(T1 @ T2))
    predicted = g.compose_covariance(p1, q1, C1, C2)
    _assert_close_in_distribution(np.cov(xi.T), predicted, tol=0.06)
    # the adjoint matters: ignoring it is clearly wrong here
    with pytest.raises(AssertionError):
        _assert_close_in_distribution(np.cov(xi.T), C1 + C2, tol=0.06)
    # None means exactly known
    assert g.compose_covariance(p1, q1, None, None) is None
    np.testing.assert_array_equal(g.compose_covariance(p1, q1, C1, None), C1)
    Ad = g.adjoint(p1, q1)
    np.testing.assert_allclose(g.compose_covariance(p1, q1, None, C2), Ad @ C2 @ Ad.T)


def test_inverse_covariance_matches_monte_carlo() -> None:
    rng = np.random.default_rng(12)
    p, q = _random_pose(rng)
    C = _spd(rng, STD)
    xi = rng.multivariate_normal(np.zeros(6), C, N_SAMPLES)
    T = g.to_matrix(p, q)
    T_inv_noisy = np.linalg.inv(se3_exp(xi) @ T)
    xi_inv = se3_log(T_inv_noisy @ T)
    _assert_close_in_distribution(np.cov(xi_inv.T), g.inverse_covariance(p, q, C), tol=0.06)
    assert g.inverse_covariance(p, q, None) is None
    # inverting twice gives the covariance back exactly
    pi, qi = g.inverse(p, q)
    np.testing.assert_allclose(g.inverse_covariance(pi, qi, g.inverse_covariance(p, q, C)), C,
                               atol=1e-15)


def test_decoupled_covariance_matches_monte_carlo() -> None:
    """Sensor-style noise (position error, parent-frame rotation error) in xi form."""
    rng = np.random.default_rng(13)
    p, q = _random_pose(rng)
    p = p * 3
    C_dec = _spd(rng, STD)
    e = rng.multivariate_normal(np.zeros(6), C_dec, N_SAMPLES)
    T_noisy = np.tile(np.eye(4), (N_SAMPLES, 1, 1))
    T_noisy[:, :3, :3] = g.rodrigues(e[:, 3:]) @ g.quat_to_matrix(q)
    T_noisy[:, :3, 3] = p + e[:, :3]
    xi = se3_log(T_noisy @ np.linalg.inv(g.to_matrix(p, q)))
    C_se3 = g.decoupled_to_se3(p, C_dec)
    _assert_close_in_distribution(np.cov(xi.T), C_se3, tol=0.06)
    np.testing.assert_allclose(g.se3_to_decoupled(p, C_se3), C_dec, atol=1e-15)
    pos_trace, rot_trace, _ = g.decoupled_traces(p, C_se3)  # without the matrix
    assert pos_trace == pytest.approx(np.trace(C_dec[:3, :3]), rel=1e-12)
    assert rot_trace == pytest.approx(np.trace(C_dec[3:, 3:]), rel=1e-12)
    for C in (C_se3, _spd(rng, STD), np.diag(rng.uniform(0, 1, 6)) * 1e-7):
        assert g.decoupled_traces(p, C)[2] == float(np.trace(C))  # to the bit
    iso = g.covariance_from_std(p, 0.01, 0.002)
    np.testing.assert_allclose(iso, g.decoupled_to_se3(p, np.diag([1e-4] * 3 + [4e-6] * 3)))
    assert g.covariance_from_std(p, None, None) is None


@given(poses, st.tuples(*[st.floats(-0.5, 0.5)] * 6).map(np.array))
def test_adjoint_moves_a_perturbation_across_a_pose(pose, xi) -> None:
    """Exp(Ad(T) xi) T == T Exp(xi), exactly (not only to first order)."""
    T = g.to_matrix(*pose)
    Ad = g.adjoint(*pose)
    left = se3_exp((Ad @ xi)[None])[0] @ T
    right = T @ se3_exp(xi[None])[0]
    np.testing.assert_allclose(left, right, atol=1e-9)


def test_single_vector_hot_path_forms_agree_with_the_broadcasting_ones() -> None:
    rng = np.random.default_rng(7)
    for _ in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3)
        assert np.allclose(g.skew3(a), g.skew(a))
        assert np.allclose(g.cross3(a, b), np.cross(a, b))
