"""The dead reckoner's compiled step (``services/accel_rig/_step.c``) against its pure-Python
path on the same samples: the same states, covariances, calibration sensitivities and
divergences, to float rounding.

Issue 19 allows a compiled helper only as an optional accelerator, with the pure-Python path
kept, tested and equal; ``tests/test_accel_fast_path.py`` checks both paths against the
previous numpy step as well.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from services.accel_rig import integrator
from services.accel_rig import rig as rg
from services.accel_rig.integrator import MAX_OMEGA_RAD_S, DeadReckoner, _State
from services.accel_rig.sensor import Calibration
from services.accel_rig.simulator import DEFAULT_RATE_HZ, default_device, simulate
from services.sim.trajectory import HeadTrajectory

COMPILED = integrator.NATIVE
needs_compiled = pytest.mark.skipif(COMPILED is None,
                                    reason="the compiled step is not built or is switched off")
REL = 1e-12


@contextmanager
def _path(compiled: bool) -> Iterator[None]:
    integrator.NATIVE = COMPILED if compiled else None
    try:
        yield
    finally:
        integrator.NATIVE = COMPILED


def _close(a, b) -> None:
    """Equal to ``REL`` of the largest magnitude (exactly equal when that is zero)."""
    if a is None or b is None:
        assert a is None and b is None
        return
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    assert np.abs(a - b).max(initial=0.0) <= REL * np.abs(b).max(initial=0.0)


def _with_calibration_covariance(cal: Calibration, seed: int) -> Calibration:
    """``cal`` with full (not diagonal) 4x4 blocks of calibration covariance."""
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(cal.layout.count, 4, 4)) * 1e-4
    return dataclasses.replace(cal, param_cov=L @ L.transpose(0, 2, 1))


def _dead_reckon(compiled: bool, cal: Calibration, seconds: float) -> list:
    """Estimates and full state covariances of a simulated run, with a late reset (a
    pose with covariance 40 samples back, replayed) two thirds of the way."""
    device = default_device()
    sim = simulate(HeadTrajectory(3), seconds, DEFAULT_RATE_HZ, seed=2, t0=7.0, sensor=device)
    s = sim.truth
    out = []
    with _path(compiled):
        dr = DeadReckoner(cal, DEFAULT_RATE_HZ)
        dr.reset(s.t[0], s.position[0], s.quaternion[0], velocity=s.velocity[0],
                 omega=s.omega_body[0])
        late = 2 * len(sim.t) // 3
        for k in range(len(sim.t)):
            est = dr.update_volts(sim.t[k], sim.volts[k])
            out.append((est, dr.state_covariance()))
            if k == late:
                back = out[k - 40][0]
                dr.reset(back.t, back.position, back.quaternion, covariance=np.eye(6) * 1e-6)
                out.append((dr.estimate(), dr.state_covariance()))
    return out


@needs_compiled
@pytest.mark.parametrize("calibration_covariance", [False, True])
def test_compiled_and_python_steps_agree_on_a_run(calibration_covariance):
    cal = default_device().calibration(DEFAULT_RATE_HZ)
    if calibration_covariance:
        cal = _with_calibration_covariance(cal, 1)
    ours = _dead_reckon(True, cal, 1.5)
    theirs = _dead_reckon(False, cal, 1.5)
    assert len(ours) == len(theirs)
    for (a, full_a), (b, full_b) in zip(ours, theirs, strict=True):
        assert a.t == b.t
        for name in ("position", "quaternion", "velocity", "omega", "covariance",
                     "calibration_sensitivity"):
            _close(getattr(a, name), getattr(b, name))
        _close(full_a, full_b)
    assert (ours[-1][0].calibration_sensitivity is not None) == calibration_covariance


@needs_compiled
@pytest.mark.parametrize("make", [rg.marvin_six, rg.marvin_six_table_4_1, rg.nine_accelerometer])
def test_compiled_and_python_estimates_agree_on_every_layout(make):
    """The estimate's arrays from random states of six- and nine-accelerometer rigs."""
    lay = make()
    n = lay.count
    rng = np.random.default_rng(n)
    cal = _with_calibration_covariance(
        Calibration(lay, rng.uniform(-0.05, 0.05, n), rng.uniform(0.3, 0.5, n)), n)
    dr = DeadReckoner(cal, DEFAULT_RATE_HZ)
    for _ in range(10):
        L = rng.normal(size=(12, 12)) * 1e-3
        q = rng.normal(size=4)
        dr._x = _State(1.0, rng.normal(size=3).tolist(), (q / np.linalg.norm(q)).tolist(),
                       rng.normal(size=3).tolist(), rng.normal(size=3).tolist(), L @ L.T,
                       rng.normal(size=(12, 4 * n)) * 1e-3, rng.normal(size=12) * 1e-3)
        with _path(True):
            a = dr.estimate()
        with _path(False):
            b = dr.estimate()
        for name in ("position", "quaternion", "velocity", "omega", "covariance",
                     "calibration_sensitivity"):
            _close(getattr(a, name), getattr(b, name))


def _diverge(compiled: bool, accel: np.ndarray, omega: np.ndarray) -> tuple[str, list]:
    """The error of the first diverging update from a reset with ``omega``, the dead reckoner
    fed ``accel`` at every sample, and the estimates before it."""
    cal = _with_calibration_covariance(default_device().calibration(DEFAULT_RATE_HZ), 2)
    with _path(compiled):
        dr = DeadReckoner(cal, DEFAULT_RATE_HZ)
        dr.reset(0.0, np.zeros(3), [0.0, 0.0, 0.0, 1.0], omega=omega)
        estimates = []
        for k in range(1, 3000):
            try:
                estimates.append(dr.update(k / DEFAULT_RATE_HZ, accel))
            except ValueError as exc:
                assert not dr.initialised
                return str(exc), estimates
    raise AssertionError("the dead reckoning did not diverge")


@needs_compiled
@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # numpy on the overflow
@pytest.mark.parametrize("case", ["spin", "overflow"])
def test_compiled_and_python_steps_diverge_alike(case):
    """The same sample diverges for the same reason: a growing spin beyond
    ``MAX_OMEGA_RAD_S``, and readings so large that the step overflows to NaN."""
    n = default_device().calibration(DEFAULT_RATE_HZ).layout.count
    if case == "spin":
        spin = np.array([1.0, -0.5, 0.3])  # 30 % of the limit: 30 samples to diverge
        accel, omega = np.full(n, 9.81), spin * 0.3 * MAX_OMEGA_RAD_S / np.linalg.norm(spin)
    else:
        accel, omega = np.linspace(-1.0, 1.0, n) * 1e200, np.zeros(3)
    ours, before_ours = _diverge(True, accel, omega)
    theirs, before_theirs = _diverge(False, accel, omega)
    assert ours == theirs
    assert ("non-finite" in ours) == (case == "overflow"), ours
    assert len(before_ours) == len(before_theirs) > (20 if case == "spin" else 0)
    for a, b in zip(before_ours, before_theirs, strict=True):
        _close(a.position, b.position)
        _close(a.covariance, b.covariance)
        _close(a.calibration_sensitivity, b.calibration_sensitivity)


@needs_compiled
def test_compiled_step_refuses_malformed_constants():
    dr = DeadReckoner(default_device().calibration(DEFAULT_RATE_HZ), DEFAULT_RATE_HZ)
    dr.reset(0.0, np.zeros(3), [0.0, 0.0, 0.0, 1.0])
    x = dr._x
    P, S, D = np.empty((12, 12)), np.empty_like(x.S), np.empty(12)
    with pytest.raises(ValueError, match="constants"):
        COMPILED.step(dr._consts[:-1], x, [(0.1, [0.0] * 6)], 0.1, P, S, D)
    with pytest.raises(ValueError, match="P_out"):
        COMPILED.step(dr._consts, x, [(0.1, [0.0] * 6)], 0.1, np.empty((12, 11)), S, D)
    with pytest.raises(ValueError, match="D_out"):
        COMPILED.step(dr._consts, x, [(0.1, [0.0] * 6)], 0.1, P, S, np.empty(11))


def test_pure_python_step_is_forced_by_the_environment():
    env = dict(os.environ, UMA_ACCEL_PURE_PYTHON="1")
    out = subprocess.run([sys.executable, "-c", "from services.accel_rig import integrator; "
                          "print(integrator.NATIVE is None)"],
                         env=env, capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "True"
