"""The accelerometer rig model, the simulator and the dead reckoner (Hogue 2003, ch. 4).

The thesis' figures 4.12-4.20 become tests: on noise-free data the estimator must follow
the simulator's ground truth (it uses RK4 where the thesis used Euler, so "follows" means
to micrometres and thousandths of a degree, not to plotting accuracy).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from agent import geometry as geo
from services.accel_rig import integrator
from services.accel_rig import rig as rg
from services.accel_rig.integrator import DeadReckoner, dead_reckon_from_truth
from services.accel_rig.motions import AxisRotation, SinusoidalTranslation
from services.accel_rig.sensor import Calibration, NoiseModel
from services.accel_rig.simulator import (
    SensorTruth,
    default_device,
    simulate,
    specific_force_readings,
)
from services.frames import GRAVITY
from services.sim.mounts import HEAD_TO_ACCEL_RIG
from services.sim.trajectory import HeadTrajectory

RATE = 300.0


def _track(layout: rg.RigLayout, motion, seconds: float, mount=None, t0: float = 0.0):
    """Ideal device on ``layout`` (axes exactly known): simulate, then dead-reckon."""
    device = SensorTruth.ideal(layout)
    run = simulate(motion, seconds, RATE, seed=0, t0=t0, sensor=device, mount=mount)
    est = dead_reckon_from_truth(device.calibration(), run.t, run.accel, run.truth, RATE)
    p = np.array([e.position for e in est])
    q = np.array([e.quaternion for e in est])
    dp, dq = geo.pose_error(p, q, run.truth.position, run.truth.quaternion)
    return run, est, dp, np.degrees(dq)


# ---------------------------------------------------------------------- the rig model


def test_marvin_six_readings_match_the_thesis_pair_equations():
    """Eqs. 4.26-4.31 for the ideal MARVIN rig, term by term."""
    d = 0.05
    lay = rg.marvin_six(d)
    rng = np.random.default_rng(3)
    f, w, wd = rng.normal(size=(3, 3))
    a = lay.readings(f, w, wd)
    x, y, z = f
    expected = [z - w[1] * w[2] * d - wd[0] * d, z + w[1] * w[2] * d + wd[0] * d,
                y + w[0] * w[1] * d + wd[2] * d, y - w[0] * w[1] * d - wd[2] * d,
                x - w[2] * w[0] * d - wd[1] * d, x + w[2] * w[0] * d + wd[1] * d]
    np.testing.assert_allclose(a, expected, atol=1e-12)
    # eq. 4.32 (pair sums) and 4.34 (pair differences)
    np.testing.assert_allclose([(a[4] + a[5]) / 2, (a[2] + a[3]) / 2, (a[0] + a[1]) / 2], f,
                               atol=1e-12)
    np.testing.assert_allclose((a[1] - a[0]) / (2 * d) - w[1] * w[2], wd[0], atol=1e-12)


@pytest.mark.parametrize("make", [rg.marvin_six, rg.marvin_six_table_4_1,
                                  rg.nine_accelerometer])
def test_solve_inverts_the_measurement_model(make):
    lay = make()
    rng = np.random.default_rng(4)
    f, w, wd = rng.normal(size=(3, 3)) * [[9.0], [3.0], [20.0]]
    f_est, wd_est = lay.solve(lay.readings(f, w, wd), w)
    np.testing.assert_allclose(f_est, f, atol=1e-9)
    np.testing.assert_allclose(wd_est, wd, atol=1e-9)


def test_nine_accelerometer_rig_needs_no_angular_velocity():
    lay = rg.nine_accelerometer()
    assert lay.omega_free and not rg.marvin_six().omega_free
    rng = np.random.default_rng(5)
    f, w, wd = rng.normal(size=(3, 3)) * 3.0
    a = lay.readings(f, w, wd)
    f_est, wd_est = lay.solve(a, np.zeros(3))  # a wrong omega estimate does not matter
    np.testing.assert_allclose(wd_est, wd, atol=1e-9)
    np.testing.assert_allclose(f_est, f, atol=1e-9)
    # the six-accelerometer rig does need it
    six = rg.marvin_six()
    _, wd6 = six.solve(six.readings(f, w, wd), np.zeros(3))
    assert np.abs(wd6 - wd).max() > 0.1


def test_h_matches_the_simulator_and_its_jacobian_matches_finite_differences():
    rng = np.random.default_rng(6)
    lay = rg.marvin_six_table_4_1()
    acc, w, wd = rng.normal(size=(3, 3))
    q = geo.rotvec_to_quat(rng.normal(size=3))
    y = lay.h(acc, q, w, wd)
    # h through the world frame equals eq. 4.72 with the rig-frame specific force
    f = geo.quat_rotate(geo.quat_conjugate(q), acc - GRAVITY)
    np.testing.assert_allclose(y, lay.readings(f, w, wd), atol=1e-12)
    J = lay.h_jacobian(acc, q, w, wd)
    eps = 1e-6
    for k in range(12):
        d = np.zeros(12)
        d[k] = eps
        qk = geo.quat_multiply(geo.rotvec_to_quat(d[3:6]), q)
        yk = lay.h(acc + d[:3], qk, w + d[6:9], wd + d[9:])
        np.testing.assert_allclose((yk - y) / eps, J[:, k], atol=1e-4, err_msg=f"column {k}")


def test_singular_layouts_are_refused_with_the_reason():
    d = 0.05
    pos = np.array([[0, -d, 0], [0, d, 0], [d, 0, 0], [-d, 0, 0], [0, 0, -d], [0, 0, d]])
    all_z = np.tile([0.0, 0.0, 1.0], (6, 1))
    with pytest.raises(ValueError, match=r"singular accelerometer layout.*rank"):
        rg.RigLayout(pos, all_z)
    with pytest.raises(ValueError, match="at least 6"):
        rg.RigLayout(pos[:5], all_z[:5])
    with pytest.raises(ValueError, match="unit vector"):
        rg.RigLayout(pos, 2.0 * rg.marvin_six().axes)
    with pytest.raises(ValueError, match="non-finite"):
        rg.RigLayout(pos, np.where(np.eye(6, 3) > 0, np.nan, rg.marvin_six().axes))
    with pytest.raises(ValueError, match="positive length"):
        rg.marvin_six(-0.1)
    with pytest.raises(ValueError, match="unknown accelerometer layout"):
        rg.layout_by_name("seven")


# ---------------------------------------------------------------------- simulator


def test_simulator_is_deterministic_and_seeded():
    traj = HeadTrajectory(2)
    a = simulate(traj, 0.2, seed=7)
    b = simulate(traj, 0.2, seed=7)
    c = simulate(traj, 0.2, seed=8)
    np.testing.assert_array_equal(a.counts, b.counts)
    assert np.any(a.counts != c.counts)
    assert a.counts.shape == (60, 6)
    # each reading averages eight whole-count conversions
    np.testing.assert_array_equal(a.counts * 8, np.round(a.counts * 8))
    np.testing.assert_allclose(a.t[1] - a.t[0], 1 / 300)


def test_simulator_applies_appendix_c_electronics():
    """1 g = 400 mV, 1 LSB = 1 mV, a static rig reads its bias + gain * n.f within noise."""
    dev = default_device()
    still = simulate(AxisRotation(amplitude_rad=0.0), 1.0, seed=1, sensor=dev, mount=None)
    f = -GRAVITY  # z up, at rest
    expect = dev.bias_v + dev.gain_v_per_mps2 * (dev.layout.axes @ f)
    np.testing.assert_allclose(still.volts.mean(axis=0), expect, atol=2e-4)
    np.testing.assert_allclose(still.volts, still.counts * 1e-3)  # volts are counts of 1 mV
    # 0.22 mV rms analog, 0.5 LSB converter noise and quantisation over 8 conversions
    assert 0.2e-3 < still.volts.std(axis=0).mean() < 0.4e-3
    # a z-sensing accelerometer at rest reads about 1 g = 400 mV away from its bias
    assert abs(abs(expect[0] - dev.bias_v[0]) - 0.4) < 0.02


@pytest.mark.parametrize("conversions", [1, 2, 8])
def test_simulated_readings_have_the_noise_the_model_reports(conversions):
    """A still rig's readings scatter as ``NoiseModel.per_sample_var_v2`` says, for each number
    of averaged conversions (converter noise only: the analog part's low-frequency power,
    which the model reports, is not its per-sample variance)."""
    dev = replace(default_device(), noise_density_v=0.0, conversions=conversions)
    still = simulate(AxisRotation(amplitude_rad=0.0), 20.0, seed=3, sensor=dev, mount=None)
    expected = math.sqrt(dev.noise_model().per_sample_var_v2(300.0))
    np.testing.assert_allclose(still.volts.std(axis=0), expected, rtol=0.05)
    # and the averaged quantisation leaves no visible error in the mean
    bias_free = dev.bias_v + dev.gain_v_per_mps2 * (dev.layout.axes @ -GRAVITY)
    assert np.abs(still.volts.mean(axis=0) - bias_free).max() < 0.02e-3


def test_device_refuses_conversions_that_do_not_divide_the_analog_steps():
    with pytest.raises(ValueError, match=r"conversions \(3\) must divide"):
        replace(default_device(), conversions=3)


def test_simulator_bandwidth_delays_by_the_reported_latency():
    """The 0-110 Hz response (2 ms) and the averaging of eight conversions over the sample
    period (1.5 ms) delay head motion; ``truth`` accounts for it."""
    lay = rg.marvin_six()
    filtered = SensorTruth(lay, np.zeros(6), np.zeros(6), noise_density_v=0.0, quantise=False)
    run = simulate(SinusoidalTranslation(amplitude_m=0.05, frequency_hz=2.0), 1.0, seed=0,
                   sensor=filtered, mount=None)
    assert 3.4e-3 < run.latency_s < 3.6e-3
    ideal = specific_force_readings(lay, run.truth)  # evaluated at t - latency
    np.testing.assert_allclose(run.accel, ideal, atol=2e-3)


# ---------------------------------------------------------------------- figures 4.12-4.20


@pytest.mark.parametrize("layout", [rg.marvin_six(), rg.marvin_six_table_4_1()],
                         ids=["ideal-fig4.12", "misaligned-fig4.13"])
def test_pure_translation_is_tracked_exactly(layout):
    motion = SinusoidalTranslation(axis="x", amplitude_m=0.5, frequency_hz=0.5)
    run, est, dp, dq = _track(layout, motion, 4.0)
    # the rig really moved a metre, and the estimate follows to micrometres
    assert np.ptp(run.truth.position[:, 0]) > 0.9
    assert dp.max() < 1e-5 and dq.max() < 1e-6
    # no rotation is invented (figure 4.12 c)
    assert max(np.linalg.norm(e.omega) for e in est) < 1e-9


@pytest.mark.parametrize("axis", ["z", "y", "x"], ids=["yaw", "pitch", "roll"])
@pytest.mark.parametrize("layout", [rg.marvin_six(), rg.marvin_six_table_4_1()],
                         ids=["ideal-fig4.15-4.17", "misaligned-fig4.18-4.20"])
def test_pure_rotation_is_tracked_exactly(layout, axis):
    motion = AxisRotation(axis=axis, amplitude_rad=np.pi / 2, frequency_hz=0.25)
    run, est, dp, dq = _track(layout, motion, 4.0)
    theta = np.array([geo.quat_to_rotvec(e.quaternion)["xyz".index(axis)] for e in est])
    np.testing.assert_allclose(theta, motion.angle(run.truth.t), atol=1e-7)
    assert dq.max() < 1e-5
    assert dp.max() < 1e-6  # and no translation is invented (figure 4.16 b)


@pytest.mark.parametrize("make", [rg.marvin_six, rg.marvin_six_table_4_1,
                                  rg.nine_accelerometer])
def test_combined_head_motion_is_tracked_exactly(make):
    run, _, dp, dq = _track(make(), HeadTrajectory(3), 3.0, mount=HEAD_TO_ACCEL_RIG,
                              t0=10.0)
    assert np.linalg.norm(run.truth.omega_body, axis=1).max() > 0.5  # it does turn
    assert dp.max() < 1e-5 and dq.max() < 1e-4


# ---------------------------------------------------------------------- dead reckoner API


def test_dead_reckoner_refuses_bad_samples_without_changing_state():
    dev = SensorTruth.ideal(rg.marvin_six())
    dr = DeadReckoner(dev.calibration(), RATE)
    good = dev.layout.axes @ -GRAVITY  # level and at rest
    assert dr.update(0.0, good) is None  # no pose before a reset
    with pytest.raises(ValueError, match="reset it with an absolute pose"):
        dr.estimate()
    dr.reset(0.0, np.zeros(3), geo.quat_identity())
    dr.update(1 / RATE, good)
    before = dr.estimate()
    bad = good.copy()
    bad[2] = np.nan
    with pytest.raises(ValueError, match="accelerometer 3 is nan"):
        dr.update(2 / RATE, bad)
    with pytest.raises(ValueError, match="expected 6 values"):
        dr.update(2 / RATE, good[:5])
    with pytest.raises(ValueError, match="not after the previous"):
        dr.update(1 / RATE, good)
    with pytest.raises(ValueError, match="not a unit quaternion"):
        dr.reset(0.0, np.zeros(3), [0, 0, 0, 2.0])
    after = dr.estimate()
    assert after.t == before.t
    np.testing.assert_array_equal(after.position, before.position)
    # a rig at rest, level, stays put
    for k in range(2, 300):
        e = dr.update(k / RATE, good)
    assert np.linalg.norm(e.position) < 1e-9 and np.linalg.norm(e.velocity) < 1e-9


def test_reset_keeps_unreset_velocity_and_takes_pose_covariance():
    dev = SensorTruth.ideal(rg.marvin_six())
    dr = DeadReckoner(dev.calibration(), RATE)
    dr.reset(0.0, [1.0, 2.0, 0.0], geo.quat_identity(), velocity=[0.5, 0.0, 0.0])
    cov = geo.covariance_from_std(np.array([1.0, 2.0, 0.0]), 0.01, 0.02)
    dr.reset(0.0, [1.0, 2.0, 0.0], geo.quat_identity(), covariance=cov)
    e = dr.estimate()
    np.testing.assert_allclose(e.velocity, [0.5, 0, 0])
    np.testing.assert_allclose(e.covariance, cov, atol=1e-15)
    with pytest.raises(ValueError, match="positive semi-definite"):
        dr.reset(0.0, np.zeros(3), geo.quat_identity(), covariance=-np.eye(6))


@pytest.mark.slow
@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "python"])
def test_a_tilted_start_leaves_the_height_given_the_rest_honest(compiled, monkeypatch):
    """A rig at rest, its dead reckoning started 1 mm and 30-50 mrad off, as drawn from
    the covariance it is reset with, and fed the rig's noise-free readings.  The estimate
    sinks by g (1 - cos|tilt|) whatever the tilt's sign, and the covariance, linearised at
    the estimate's tilted specific force, ties the height to the horizontal error as if it
    sank by g |tilt|^2: over 200 starts the height's NEES given the other five components
    must still average about 1 (the linear covariance alone gives about 90)."""
    if compiled and integrator.NATIVE is None:
        pytest.skip("the compiled step is not built or is switched off")
    monkeypatch.setattr(integrator, "NATIVE", integrator.NATIVE if compiled else None)
    lay = rg.marvin_six()
    quiet = NoiseModel(density_v=0.0, quantised=False, bandwidth_hz=None,
                       converter_noise_lsb=0.0)
    cal = Calibration(lay, np.zeros(lay.count), np.ones(lay.count), noise=quiet)
    q = geo.rotvec_to_quat(np.array([0.3, -0.2, 1.0]))  # tilted and turned, at rest
    L = np.array([[0.04, 0.0, 0.0], [0.015, 0.03, 0.0], [0.01, -0.02, 0.05]])
    cov = np.zeros((6, 6))
    cov[:3, :3] = 1e-6 * np.eye(3)
    cov[3:, 3:] = L @ L.T
    readings = lay.h(np.zeros(3), q, np.zeros(3), np.zeros(3))
    rate, rest = 20.0, [0, 1, 3, 4, 5]
    rng = np.random.default_rng(3)
    height = []
    for _ in range(200):
        x0 = rng.multivariate_normal(np.zeros(6), cov)  # truth minus estimate, [dp, dtheta]
        dr = DeadReckoner(cal, rate)
        dr.reset(0.0, -x0[:3], geo.quat_multiply(geo.rotvec_to_quat(-x0[3:]), q),
                 covariance=cov, velocity=np.zeros(3), omega=np.zeros(3))
        dr.update(0.0, readings)
        for k in range(1, int(rate) + 1):
            est = dr.update(k / rate, readings)
        x = np.concatenate([-est.position, geo.quat_to_rotvec(
            geo.quat_multiply(q, geo.quat_conjugate(est.quaternion)))])
        P = est.decoupled_covariance
        height.append(x @ np.linalg.solve(P, x)
                      - x[rest] @ np.linalg.solve(P[np.ix_(rest, rest)], x[rest]))
    assert 0.7 < np.mean(height) < 1.4, np.mean(height)


def test_the_second_order_spread_is_the_rotations_and_stays_bounded():
    """The root mean square of the along-u change of a specific force u rotated by
    phi ~ N(0, C), against a Monte Carlo of the rotation: a few percent at 30 mrad and at
    0.4 rad (a start with a large orientation uncertainty), and bounded however large C
    (sqrt(5) |u|: 1 - cos of each of the two tilts, means 1 and variances 1 / 2)."""
    u = np.array([0.5, -1.0, 9.7])
    rng = np.random.default_rng(4)
    for scale in (0.03, 0.4):
        L = scale * np.array([[1.0, 0.0, 0.0], [0.4, 0.8, 0.0], [0.2, -0.5, 1.2]])
        phi = rng.multivariate_normal(np.zeros(3), L @ L.T, 100_000)
        along = geo.quat_rotate(geo.rotvec_to_quat(phi), u) @ u / np.linalg.norm(u)
        rms = np.sqrt(np.mean((along - np.linalg.norm(u)) ** 2))
        spread = np.asarray(integrator._second_order(L @ L.T, u.tolist()))
        assert np.linalg.norm(spread) == pytest.approx(rms, rel=0.05)
        assert np.allclose(np.cross(spread, u), 0.0)
    huge = np.asarray(integrator._second_order(1e6 * np.eye(3), u.tolist()))
    assert np.linalg.norm(huge) == pytest.approx(math.sqrt(5.0) * np.linalg.norm(u))


@pytest.mark.parametrize("history, offset", [(0, 0.0), (2, 0.3)],
                         ids=["first-start", "between-samples"])
def test_the_covariance_after_a_start_is_the_integrators_response_to_the_noise(history,
                                                                             offset):
    """0.1 s of dead reckoning on the head trajectory, started from the true state at a
    sample's time with no earlier samples, or 0.3 of a period after the third sample: the
    pose's covariance must be what the readings' white noise makes of the integration,
    sum over samples of J_k var J_k^T with J_k each sample's effect on the pose (linear,
    by finite differences).  Their ratio, tr(P^-1 C) / 6, is the mean NEES over 6; it was
    1.035 before the samples the first steps use from the start's time counted."""
    device = replace(SensorTruth.draw(7, rg.marvin_six_table_4_1()), bandwidth_hz=None,
                     quantise=False)
    cal = device.calibration(RATE)
    last = history + 30
    run = simulate(HeadTrajectory(2), (last + 3) / RATE, RATE, seed=0, t0=12.0,
                   sensor=replace(device, noise_density_v=0.0))
    t_start = run.t[history] + offset / RATE
    start = HeadTrajectory(2).state(np.array([t_start])).rigid_offset(*HEAD_TO_ACCEL_RIG)

    def pose(accel):
        dr = DeadReckoner(cal, RATE)
        for k in range(history + 1):
            dr.update(run.t[k], accel[k])
        dr.reset(t_start, start.position[0], start.quaternion[0],
                 velocity=start.velocity[0], omega=start.omega_body[0])
        for k in range(history + 1, last + 1):
            est = dr.update(run.t[k], accel[k])
        return est

    base = pose(run.accel)
    var, eps = cal.accel_var(RATE), 1e-5
    C = np.zeros((6, 6))
    for k in range(last + 1):
        for j in range(cal.layout.count):
            accel = run.accel.copy()
            accel[k, j] += eps
            est = pose(accel)
            J = np.concatenate([est.position - base.position, geo.quat_to_rotvec(
                geo.quat_multiply(est.quaternion, geo.quat_conjugate(base.quaternion)))]) / eps
            C += var[j] * np.outer(J, J)
    ratio = np.trace(np.linalg.solve(base.decoupled_covariance, C)) / 6.0
    assert ratio == pytest.approx(1.0, abs=0.004)


def test_a_late_reset_is_applied_at_its_time_and_the_samples_since_replayed():
    device = SensorTruth.ideal(rg.marvin_six_table_4_1())
    run = simulate(HeadTrajectory(4), 1.0, RATE, seed=0, t0=20.0, sensor=device)
    s = run.truth
    dr = DeadReckoner(device.calibration(), RATE)
    for k in range(200):  # samples arrive before any absolute pose
        assert dr.update(run.t[k], run.accel[k]) is None
    k0 = 120  # the pose of sample 120 arrives when sample 199 is already in
    dr.reset(s.t[k0], s.position[k0], s.quaternion[k0], velocity=s.velocity[k0],
             omega=s.omega_body[k0])
    e = dr.estimate()
    assert e.t == pytest.approx(s.t[199])  # replayed up to the newest sample
    dp, dq = geo.pose_error(e.position, e.quaternion, s.position[199], s.quaternion[199])
    assert dp < 1e-6 and np.degrees(dq) < 1e-5
    e = dr.update(run.t[200], run.accel[200])
    dp, _ = geo.pose_error(e.position, e.quaternion, s.position[200], s.quaternion[200])
    assert dp < 1e-6
