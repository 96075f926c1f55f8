"""Dorfmüller-Ulhaas's predictor: Jacobians, ω -> 0 limits, the §3.3 experiments.

Dorfmüller-Ulhaas: Dorfmüller-Ulhaas, *Robust Optical User Motion Tracking Using a Kalman
Filter*.
"""

from __future__ import annotations

import numpy as np
import pytest

from agent import geometry as geo
from services.fusion import evaluate_predictor as ep
from services.fusion import predictor as pr


def _fd_jacobian(omega, P, v, a, dt, h=1e-6):
    def f(w):
        W, V, A = pr.motion_matrices(w, dt)
        return W @ P + V @ v + A @ a
    return np.column_stack([(f(omega + h * e) - f(omega - h * e)) / (2 * h) for e in np.eye(3)])


@pytest.mark.parametrize("scale", [0.0, 1e-12, 1e-6, 1e-3, 0.5, 3.0, 20.0])
@pytest.mark.parametrize("dt", [0.02, 0.25])
def test_eq16_jacobian_matches_finite_differences(scale, dt):
    rng = np.random.default_rng(int(scale * 1000) + int(dt * 100))
    omega = rng.normal(size=3) * scale
    P, v, a = rng.normal(size=(3, 3))
    J = pr.point_motion_jacobian(omega, P, v, a, dt)
    assert np.allclose(J, _fd_jacobian(omega, P, v, a, dt), atol=1e-8)


def test_limits_at_zero_angular_velocity_are_the_papers():
    rng = np.random.default_rng(3)
    P, v, a = rng.normal(size=(3, 3))
    dt = 0.02
    J = pr.point_motion_jacobian(np.zeros(3), P, v, a, dt)
    paper = (-dt * geo.skew(P) - dt**2 / 2 * geo.skew(v) - dt**3 / 6 * geo.skew(a))
    assert np.allclose(J, paper, atol=1e-15)


def test_printed_omega_squared_term_is_a_typo():
    """Eq. 16 as printed has (omega^T P) I where omega P^T belongs: it fails the check."""
    rng = np.random.default_rng(4)
    omega, P = rng.normal(size=3), rng.normal(size=3)
    Om, Pt = geo.skew(omega), geo.skew(P)
    printed = -Om @ Pt + (omega @ P) * np.eye(3) - np.outer(P, omega)
    corrected = -Om @ Pt + np.outer(omega, P) - np.outer(P, omega)
    h = 1e-6
    fd = np.column_stack([(geo.skew(omega + h * e) @ geo.skew(omega + h * e) @ P
                           - geo.skew(omega - h * e) @ geo.skew(omega - h * e) @ P) / (2 * h)
                          for e in np.eye(3)])
    assert np.allclose(corrected, fd, atol=1e-7)
    assert not np.allclose(printed, fd, atol=1e-3)


@pytest.mark.parametrize("theta_dt", [0.1999999, 0.2000001])
def test_series_and_closed_form_agree_at_the_switch(theta_dt):
    dt = 0.02
    lo = pr.coefficients(theta_dt / dt * (1 - 1e-6), dt)
    hi = pr.coefficients(theta_dt / dt * (1 + 1e-6), dt)
    for name in ("c1", "c2", "c3", "c4", "d1", "d2", "d3", "d4"):
        a, b = getattr(lo, name), getattr(hi, name)
        assert a == pytest.approx(b, rel=1e-5), name


def test_theorem1_matrices_are_the_integrals_of_the_rotation():
    omega, dt = np.array([0.4, -1.2, 2.0]), 0.3
    W, V, A = pr.motion_matrices(omega, dt)
    assert np.allclose(W, geo.rodrigues(omega * dt), atol=1e-14)
    s = np.linspace(0, dt, 2001)
    R = geo.rodrigues(omega[None] * s[:, None])
    w = np.full(s.size, 1.0)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0          # Simpson weights
    integral = np.einsum("n,nij->ij", w, R) * (s[1] - s[0]) / 3
    weighted = np.einsum("n,nij->ij", w * (dt - s), R) * (s[1] - s[0]) / 3
    assert np.allclose(V, integral, atol=1e-10)
    assert np.allclose(A, weighted, atol=1e-10)


def test_ideal_experiment_converges_within_three_iterations():
    fig = ep.experiment("ideal", [ep.FIRST], False, seed=1)
    conv = fig["convergence"]
    assert conv["omega_iterations"] <= 3 and conv["v_iterations"] <= 3
    assert conv["a_iterations"] <= 3


@pytest.mark.parametrize("perturb", [False, True])
def test_abrupt_change_reconverges_within_four_iterations(perturb):
    fig = ep.experiment("abrupt", [ep.FIRST, ep.CHANGE], perturb, seed=2)
    re = fig["reconvergence_after_frame_10"]
    judged = re if not perturb else {k: v for k, v in re.items() if not k.startswith("a_")}
    assert all(v is not None and v <= 4 for v in judged.values()), re
    assert fig["manoeuvre_resets"] >= 1


def test_corrupted_omega_and_v_stay_within_the_perturbation():
    for seed in (1, 2, 3):
        fig = ep.experiment("corrupted", [ep.FIRST], True, seed=seed)
        assert fig["convergence"]["omega_iterations"] <= 3
        assert fig["convergence"]["v_iterations"] <= 3


def test_predicts_a_screw_motion_exactly():
    omega, v, a, dt = np.array([0.3, -0.2, 1.0]), np.array([0.1, 0.4, -0.2]), \
        np.array([0.5, 0.0, -0.3]), 1 / 60
    f = pr.DorfmullerPredictor(pr.PredictorConfig(point_std_m=1e-6, omega_walk=0,
                                                  velocity_walk=0, accel_walk=0))
    p, q = np.array([0.2, 0.1, 1.5]), geo.rotvec_to_quat([0.1, 0.2, 0.3])
    vel = v.copy()
    poses = []
    for k in range(8):
        poses.append((k * dt, p, q))
        vel = vel + a * dt
        W, V, A = pr.motion_matrices(omega, dt)
        p, q = p + V @ vel + A @ a, geo.quat_multiply(geo.matrix_to_quat(W), q)
    for t, pk, qk in poses[:-1]:
        f.update(t, pk, qk)
    pp, qp = f.predict(dt)
    e_p, e_r = geo.pose_error(pp, qp, poses[-1][1], poses[-1][2])
    assert e_p < 1e-6 and e_r < 1e-6
    assert np.allclose(f.omega, omega, atol=1e-5)


@pytest.mark.slow
def test_prediction_beats_holding_the_last_pose_on_head_motion():
    fig = ep.head_trajectory_prediction(6.0, seed=3)
    assert fig["predicted_position_rmse_mm"] < 0.8 * fig["hold_last_position_rmse_mm"]
    assert fig["predicted_orientation_rmse_deg"] < 0.8 * fig["hold_last_orientation_rmse_deg"]


def test_bad_input_is_refused_with_a_reason():
    f = pr.DorfmullerPredictor()
    with pytest.raises(ValueError, match="no pose"):
        f.predict(0.01)
    f.update(0.0, [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(ValueError, match="non-finite"):
        f.update(0.1, [np.nan, 0, 0], [0, 0, 0, 1])
    with pytest.raises(ValueError, match="unit quaternion"):
        f.update(0.1, [0, 0, 0], [0, 0, 0, 2])
    with pytest.raises(ValueError, match="does not increase"):
        f.update(0.0, [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(ValueError, match="horizon"):
        f.predict(-0.1)
    with pytest.raises(ValueError, match="point_std_m"):
        pr.PredictorConfig(point_std_m=0.0)


def test_a_long_silence_restarts_the_motion_estimate():
    f = pr.DorfmullerPredictor(pr.PredictorConfig(max_gap_s=0.2))
    for k in range(5):
        f.update(k * 0.02, [0.01 * k, 0, 0], [0, 0, 0, 1])
    assert f.ready and abs(f.velocity[0] - 0.5) < 0.05
    f.update(2.0, [0.0, 0.0, 0.0], [0, 0, 0, 1])
    assert f.stats.restarts == 1 and not f.ready


def test_live_predictor_publishes_ahead_and_refuses_bad_samples():
    from types import SimpleNamespace

    from services.fusion.predictor_service import LivePredictor

    out = []
    live = LivePredictor(0.02, None, publish=lambda *a: out.append(a))
    for k in range(6):
        live.on_pose(SimpleNamespace(t_ns=10**9 + k * 10**7, position=[0.01 * k, 0, 0],
                                     quaternion=[0, 0, 0, 1], attributes={"pos_std_m": 1e-3}))
    assert len(out) == 5
    t_ns, p, _, cov = out[-1]
    assert t_ns == 10**9 + 5 * 10**7 + 2 * 10**7 and cov is None
    assert p[0] == pytest.approx(0.07, abs=2e-3)      # 1 m/s, 20 ms past 0.05 m
    live.on_pose(SimpleNamespace(t_ns=10**9, position=[0, 0, 0], quaternion=[0, 0, 0, 1],
                                 attributes=None))   # older than the last: refused
    assert live.refused == 1 and len(out) == 5
