"""The dead reckoner's per-sample path on Python floats equals the numpy computation it
replaced (the same figures within float rounding).

The reference below is the previous numpy implementation of one RK4 step and its error
propagation (Hogue 2003, §4.3), kept here unchanged in its mathematics; the fast path must
agree with it to 1e-12 on random states, samples and layouts, in both of its forms: the
compiled step (when built) and the pure-Python one.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agent import geometry as geo
from services.accel_rig import integrator
from services.accel_rig import rig as rg
from services.accel_rig.integrator import DeadReckoner, _State
from services.accel_rig.sensor import Calibration, check_volts
from services.accel_rig.simulator import DEFAULT_RATE_HZ, default_device

TOL = 1e-12
LAYOUTS = [rg.marvin_six, rg.marvin_six_table_4_1, rg.nine_accelerometer]
COMPILED = integrator.NATIVE


@pytest.fixture(params=["compiled", "python"])
def step_path(request, monkeypatch):
    """Run the test on the compiled step and on the pure-Python one."""
    if request.param == "compiled" and COMPILED is None:
        pytest.skip("the compiled step is not built or is switched off")
    monkeypatch.setattr(integrator, "NATIVE", COMPILED if request.param == "compiled" else None)
    return request.param


def _close(a, b) -> None:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    assert np.abs(a - b).max() <= TOL * max(1.0, np.abs(b).max())


# ---------------------------------------------------------------------- the previous numpy path

_HALF_RIGHT_PRODUCT = 0.5 * np.stack(
    [geo.quat_multiply(np.eye(4), np.eye(4)[i]).T for i in range(3)]).reshape(3, 16)


def _rotation_quadratic() -> np.ndarray:
    e = np.eye(4)
    T = np.zeros((4, 4, 3, 3))
    for i in range(4):
        for j in range(4):
            for col in range(3):
                T[i, j, :, col] = geo.quat_multiply(geo.quat_multiply(e[i], np.eye(4)[col]),
                                                    geo.quat_conjugate(e[j]))[:3]
    return T.reshape(16, 9)


_ROTATION_QUADRATIC = _rotation_quadratic()
_W = np.array([1.0, 2.0, 2.0, 1.0])
_WP = np.array([1.0, 1.0, 1.0, 0.0])


def _corr_jacobian(layout: rg.RigLayout, w: np.ndarray) -> np.ndarray:
    """d(correction)/d(omega) as the previous code built it: per output k a symmetric
    (3, 3) form D_k of vec(omega omega^T), Jacobian D_k @ omega."""
    quad = np.zeros((6, 3, 3))
    quad[:, rg._W_ROWS, rg._W_COLS] = layout._corr
    return (quad + quad.transpose(0, 2, 1)) @ w


def _reference_step(dr: DeadReckoner, x: _State, samples, t1: float):
    """The previous ``DeadReckoner._step`` and ``_propagate``, on numpy arrays."""
    lay = dr.layout
    t0, h = x.t, t1 - x.t
    ts = [t for t, _ in samples]
    W = [[np.prod([(tau - tj) / (ti - tj) for j, tj in enumerate(ts) if j != i])
          for i, ti in enumerate(ts)] for tau in (t0, t0 + 0.5 * h, t1)]
    x0, xm, x1 = np.array(W) @ np.array([s for _, s in samples])
    w0 = np.array(x.w)
    s1 = x0 + lay.correction(w0)
    w2 = w0 + 0.5 * h * s1[3:]
    s2 = xm + lay.correction(w2)
    w3 = w0 + 0.5 * h * s2[3:]
    s3 = xm + lay.correction(w3)
    w4 = w0 + h * s3[3:]
    s4 = x1 + lay.correction(w4)
    ws, xs = np.array([w0, w2, w3, w4]), np.array([s1, s2, s3, s4])
    M = (ws @ _HALF_RIGHT_PRODUCT).reshape(4, 4, 4)
    q0 = np.array(x.q)
    kq1 = M[0] @ q0
    q2 = q0 + 0.5 * h * kq1
    kq2 = M[1] @ q2
    q3 = q0 + 0.5 * h * kq2
    kq3 = M[2] @ q3
    q4 = q0 + h * kq3
    kq4 = M[3] @ q4
    q1 = q0 + h / 6.0 * (_W @ np.array([kq1, kq2, kq3, kq4]))
    qs = np.array([q0, q2, q3, q4])
    Rs = (((qs[:, :, None] * qs[:, None, :]).reshape(4, 16) @ _ROTATION_QUADRATIC)
          / (qs * qs).sum(axis=1)[:, None]).reshape(4, 3, 3)
    spread = _reference_second_order(dr, x, Rs[1] @ s2[:3])
    acc = (Rs @ xs[:, :3, None])[:, :, 0] + dr.gravity
    v0, p0 = np.array(x.v), np.array(x.p)
    p1 = p0 + h * v0 + h * h / 6.0 * (_WP @ acc)
    v1 = v0 + h / 6.0 * (_W @ acc)
    w1 = w0 + h / 6.0 * (_W @ xs[:, 3:])
    R, f, p, v = Rs[1], s2[:3], 0.5 * (p1 + p0), 0.5 * (v1 + v0)
    G, Jw = lay._proj, _corr_jacobian(lay, w2)
    A = np.zeros((12, 12))
    A[0:3, 9:12] = R
    A[3:6, 6:9] = np.eye(3)
    A[3:6, 0:3] = geo.skew(v)
    A[3:6, 9:12] = geo.skew(p) @ R
    A[6:9, 0:3] = geo.skew(-(R @ f))
    A[6:9, 9:12] = R @ Jw[:3]
    A[9:12, 9:12] = Jw[3:]
    Ah = A * h
    F = np.eye(12) + Ah + 0.5 * (Ah @ Ah)
    B = np.zeros((12, G.shape[1]))
    B[6:9] = R @ G[:3]
    B[9:12] = G[3:]
    Bs = B * np.sqrt(dr.calibration.accel_var(dr.rate_hz))
    P = F @ x.P @ F.T + (h / dr.rate_hz) * (Bs @ Bs.T)
    c = np.ones((G.shape[1], 4)) / dr.calibration.gain_v_per_mps2[:, None]
    c[:, 1:] *= f
    S = F @ x.S + h * (B[:, :, None] * c[None, :, :]).reshape(12, -1)
    D = F @ x.D + h * np.concatenate([np.zeros(6), spread, np.zeros(3)])
    return p1, q1 / np.linalg.norm(q1), v1, w1, P, S, D


def _reference_second_order(dr: DeadReckoner, x: _State, u: np.ndarray):
    """The root mean square of the orientation error's second-order effect along ``u``
    times ``u``: for the tilt about each principal axis of C_perp (the orientation error's
    covariance projected across ``u``, eigenvalue l), 1 - cos of it has mean
    1 - exp(-l / 2) and variance (1 - exp(-l))^2 / 2."""
    cal = integrator.calibration_covariance(dr.calibration)
    C = x.P[:3, :3] + (0.0 if cal is None else x.S[:3] @ cal @ x.S[:3].T)
    n = u / np.linalg.norm(u)
    basis = np.linalg.svd(np.eye(3) - np.outer(n, n))[0][:, :2]  # two axes across u
    lam = np.clip(np.linalg.eigvalsh(basis.T @ C @ basis), 0.0, None)
    mean = np.sum(1.0 - np.exp(-lam / 2))
    var = np.sum(0.5 * (1.0 - np.exp(-lam)) ** 2)
    return np.sqrt(mean**2 + var) * u


# ---------------------------------------------------------------------- the comparisons


def _random_state(rng, n: int) -> _State:
    L = rng.normal(size=(12, 12)) * 1e-3
    q = rng.normal(size=4)
    return _State(float(rng.uniform(0, 10)), rng.normal(size=3).tolist(),
                  (q / np.linalg.norm(q)).tolist(),
                  rng.normal(size=3).tolist(), rng.uniform(-4, 4, size=3).tolist(),
                  L @ L.T, rng.normal(size=(12, 4 * n)) * 1e-3, rng.normal(size=12) * 1e-3)


@pytest.mark.parametrize("make", LAYOUTS)
def test_float_solve_equals_numpy(make):
    lay = make()
    rng = np.random.default_rng(19)
    for _ in range(50):
        a, w = rng.normal(size=lay.count) * 20, rng.uniform(-6, 6, size=3)
        _close(lay.project_floats(a.tolist()), lay.project(a))
        _close(lay.solve_floats(lay.project_floats(a.tolist()), w.tolist()),
               np.concatenate(lay.solve(a, w)))
        _close(lay.omega_jacobian_floats(w.tolist()), _corr_jacobian(lay, w))


def test_float_conversion_equals_numpy_and_refuses_alike():
    cal = default_device().calibration(DEFAULT_RATE_HZ)
    rng = np.random.default_rng(7)
    for _ in range(50):
        v = rng.uniform(-1.99, 1.99, size=cal.layout.count)
        _close(cal.to_accel_floats(v), cal.to_accel(v))
    for bad in (np.nan, np.inf, -9.0, 2.0, -1.9999):
        v = np.full(cal.layout.count, 0.1)
        v[3] = bad
        with pytest.raises(ValueError) as numpy_error:
            cal.to_accel(v)
        with pytest.raises(ValueError) as float_error:
            cal.to_accel_floats(v)
        assert str(float_error.value) == str(numpy_error.value)
    with pytest.raises(ValueError, match="expected 6 values"):
        cal.to_accel_floats(np.full(5, 0.1))
    assert check_volts(np.full((4, 6), 0.1)).shape == (4, 6)  # batches: unchanged


@pytest.mark.parametrize("make", LAYOUTS)
@pytest.mark.parametrize("samples_before", [1, 2, 3])
def test_step_equals_the_previous_numpy_step(make, samples_before, step_path):
    """Random states, readings and step lengths, the first samples' shorter parabolas
    included; with a calibration covariance (the sensitivity S is propagated too)."""
    lay = make()
    n = lay.count
    rng = np.random.default_rng(samples_before)
    cal = Calibration(lay, rng.uniform(-0.05, 0.05, n), rng.uniform(0.3, 0.5, n),
                      param_cov=np.stack([np.eye(4) * 1e-6] * n))
    dr = DeadReckoner(cal, 300.0)
    for _ in range(20):
        x = _random_state(rng, n)
        t1 = x.t + float(rng.uniform(1e-3, 5e-3))
        before = [x.t - i * float(rng.uniform(2e-3, 4e-3)) for i in range(samples_before - 1)]
        samples = [(t, (rng.normal(size=6) * 5).tolist()) for t in [*before[::-1], t1]]
        got = dr._step(x, samples, t1)
        want = _reference_step(dr, x, samples, t1)
        for g, w in zip((got.p, got.q, got.v, got.w, got.P, got.S, got.D), want, strict=True):
            _close(g, w)


@pytest.mark.parametrize("calibration_covariance", [False, True])
def test_estimate_takes_the_pose_block_of_the_full_covariance(calibration_covariance,
                                                              step_path):
    cal = default_device().calibration(DEFAULT_RATE_HZ)
    if calibration_covariance:  # full 4x4 blocks, one per accelerometer
        L = np.random.default_rng(6).normal(size=(cal.layout.count, 4, 4)) * 1e-3
        cal = dataclasses.replace(cal, param_cov=L @ L.transpose(0, 2, 1))
    dr = DeadReckoner(cal, DEFAULT_RATE_HZ)
    rng = np.random.default_rng(5)
    dr._x = _random_state(rng, cal.layout.count)
    full = dr.state_covariance()
    order = [3, 4, 5, 0, 1, 2]
    _close(dr.estimate().covariance, full[np.ix_(order, order)])
