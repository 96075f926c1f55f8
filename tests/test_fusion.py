"""The fusion EKF (Hogue 2003, ch. 6): measurement model, Jacobians, gating, gaps, honesty,
late optical poses, the eval's helpers and the live service logic (no network).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.accel_rig import simulator as accel_sim
from services.accel_rig.device_options import device_figures, device_from_args
from services.accel_rig.rig import marvin_six, marvin_six_table_4_1
from services.consistency import mean_nees_band_95
from services.fusion import evaluate as fe
from services.fusion.ekf import FusionEKF, FusionStats
from services.fusion.service import LiveFusion, accel_model_from_attributes
from services.fusion.state import MODEL_FLOOR, AccelModel, FusionConfig
from services.fusion.tracker import FusionTracker
from services.sim.mounts import HEAD_TO_ACCEL_RIG, HEAD_TO_LASER_RIG
from services.sim.trajectory import HeadTrajectory
from services.sim.world import IvyWorld

OPT_STD = (3e-4, np.radians(0.02))


def _model(layout=None, var=3e-4):
    layout = layout or marvin_six_table_4_1()
    return AccelModel.from_layout(layout.positions, layout.axes, HEAD_TO_ACCEL_RIG, var)


def _set_true_state(ekf: FusionEKF, traj: HeadTrajectory, t: float) -> None:
    s = traj.state(t)
    ekf.initialise(t, s.position[0], s.quaternion[0], np.eye(6) * 1e-8)
    ekf.x[3:6], ekf.x[6:9] = s.omega_body[0], s.alpha_body[0]
    ekf.x[12:15], ekf.x[15:18] = s.velocity[0], s.acceleration[0]


def _start(f: FusionEKF | FusionTracker, t: float, p, q, cov, **kw) -> None:
    """Start a filter (or tracker, of rig poses) at ``t``, the head still: two poses."""
    for ti in (t - 1 / 15, t):
        if isinstance(f, FusionTracker):
            assert f.add_rig_pose(ti, p, q, cov, HEAD_TO_LASER_RIG, **kw)
        else:
            f.update_pose(ti, p, q, cov)
    assert (f.ekf if isinstance(f, FusionTracker) else f).start_t == t


def _still_rig(config: FusionConfig | None = None, now: float | None = None, **tracker_kw):
    """A tracker started at t = 0 on a head at rest at the origin: the tracker, the rig pose
    (p, q) and covariance its optics report, and the accelerometer readings at rest."""
    model = _model()
    tracker = FusionTracker(FusionEKF(model, config), **tracker_kw)
    cov = geo.covariance_from_std(np.zeros(3), 1e-3, 1e-3)
    p, q = geo.compose(np.zeros(3), np.array([0, 0, 0, 1.0]), *HEAD_TO_LASER_RIG)
    _start(tracker, 0.0, p, q, cov, **({} if now is None else {"now": now}))
    return tracker, p, q, cov, [float(n @ [0, 0, 9.80665]) for n in model.axes]


def test_eq613_matches_the_accelerometer_rigs_own_model():
    """Cross-check with services.accel_rig: the same readings from the rig's kinematics."""
    layout = marvin_six_table_4_1()
    traj = HeadTrajectory(4)
    ekf = FusionEKF(_model(layout))
    for t in (0.3, 2.0, 7.7):
        _set_true_state(ekf, traj, t)
        rig = traj.state(t).rigid_offset(*HEAD_TO_ACCEL_RIG)
        expected = layout.h(rig.acceleration[0], rig.quaternion[0], rig.omega_body[0],
                            rig.alpha_body[0])
        ours = [ekf.predict_reading(j)[0] for j in range(layout.count)]
        assert np.allclose(ours, expected, atol=1e-10)


def test_accelerometer_jacobian_matches_finite_differences():
    traj = HeadTrajectory(5)
    ekf = FusionEKF(_model())
    _set_true_state(ekf, traj, 1.3)
    ekf.x[18:24] = 0.01 * np.arange(6)  # the accelerometer biases
    for j in range(6):
        h0, H = ekf.predict_reading(j)
        num = np.zeros(ekf.dim)
        for k in range(ekf.dim):
            snap = ekf.snapshot()
            d = np.zeros(ekf.dim)
            d[k] = 1e-7
            ekf._inject(d)
            num[k] = (ekf.predict_reading(j)[0] - h0) / 1e-7
            ekf.restore(snap)
        assert np.allclose(H, num, atol=2e-5), j


def _simulate(seconds, seed, gaps=(), optical_noise=OPT_STD, config=None, claimed=None,
              optical_offset=(0.0, 0.0, 0.0), systematic=None):
    """The real accelerometer simulator + optical stand-in (truth + offset + noise) at 15 Hz;
    the optical covariance says ``claimed`` (default: the true ``optical_noise``) plus
    ``systematic`` (6x6), which each pose reports as its systematic part unless
    ``systematic`` is None."""
    traj = HeadTrajectory(seed)
    device, cal = fe.calibrated_accelerometers(300.0, seed)
    run = accel_sim.simulate(traj, seconds, seed=seed, sensor=device, calibration=cal)
    ekf = FusionEKF(fe.accel_model(cal, HEAD_TO_ACCEL_RIG, 300.0, 0.005), config)
    rng = np.random.default_rng(seed)
    ps, rs = optical_noise
    cps, crs = claimed or optical_noise
    cov = np.diag([cps**2] * 3 + [crs**2] * 3)
    if systematic is not None:
        cov = cov + systematic
    frames = [k / 15 for k in range(int(seconds * 15))
              if not any(a <= k / 15 < b for a, b in gaps)]
    out_t, out_p, out_q, nees = [], [], [], []
    k = 0
    for i, t_motion in enumerate(run.t - cal.latency_s):
        while k < len(frames) and frames[k] <= t_motion:
            p, q = traj.pose(frames[k])
            ekf.update_pose(frames[k], p[0] + np.asarray(optical_offset) + rng.normal(0, ps, 3),
                            geo.quat_multiply(geo.rotvec_to_quat(rng.normal(0, rs, 3)), q[0]),
                            cov, systematic)
            k += 1
        if ekf.initialised:
            ekf.update_accel_sample(run.t[i], run.accel[i])
            p, q = ekf.pose()
            pt, qt = traj.pose(ekf.t)
            e = np.concatenate([pt[0] - p, geo.quat_to_rotvec(
                geo.quat_multiply(qt[0], geo.quat_conjugate(q)))])
            C = ekf.pose_covariance_decoupled()
            nees.append(float(e @ np.linalg.solve(C, e)))
            out_t.append(ekf.t)
            out_p.append(p)
            out_q.append(q)
    t = np.array(out_t)
    pt, qt = traj.pose(t)
    ep, er = geo.pose_error(np.array(out_p), np.array(out_q), pt, qt)
    return t, ep, er, np.array(nees), ekf


@pytest.mark.slow
def test_fusion_tracks_through_a_gap_and_beats_the_optical_rate():
    t, ep, er, nees, ekf = _simulate(9.0, seed=2, gaps=[(5.0, 5.5)])
    normal = (t > 2.0) & ((t < 5.0) | (t > 5.8))
    gap = (t >= 5.0) & (t < 5.55)
    assert np.sqrt(np.mean(ep[normal] ** 2)) < 2e-3
    assert np.degrees(np.sqrt(np.mean(er[normal] ** 2))) < 0.1
    assert ep[gap].max() < 0.02 and np.degrees(er[gap].max()) < 1.0
    assert ekf.stats.accel_rejected < 0.01 * ekf.stats.accel_updates
    # honest enough: the mean NEES of the 6-D pose error within a factor of two of 6
    assert 3.0 < float(np.mean(nees[t > 2.0])) < 12.0
    assert np.all(np.linalg.eigvalsh(ekf.P) > -1e-12)


def test_outlier_poses_are_gated_and_persistent_ones_reinitialise():
    ekf = FusionEKF(_model(), FusionConfig(max_rejected_poses=3))
    q = np.array([0.0, 0.0, 0.0, 1.0])
    cov = np.diag([1e-6] * 3 + [1e-6] * 3)
    for k in range(30):
        t = k / 15
        ekf.update_pose(t, np.zeros(3), q, cov)
        assert ekf.initialised == (k > 0)           # two poses start the filter
        for i in range(20 if k else 0):
            reading = [float(ekf.accel.axes[j] @ -np.array([0, 0, -9.80665]))
                       for j in range(6)]
            ekf.update_accel_sample(t + (i + 1) / 300, reading)
    assert ekf.stats.pose_rejected == 0
    far = np.array([1.0, 0.0, 0.0])
    assert not ekf.update_pose(2.1, far, q, cov)
    assert not ekf.update_pose(2.2, far, q, cov)
    assert ekf.update_pose(2.3, far, q, cov)       # third in a row: the optics win
    # restarted from the last two of them: there, and not moving
    assert np.allclose(ekf.position, far) and ekf.stats.reinitialised == 2
    assert ekf.start_t == 2.3 and np.allclose(ekf.velocity, 0.0, atol=1e-9)


def test_two_poses_start_the_filter_with_their_motion_and_an_honest_covariance():
    """The difference of two optical poses gives v and omega; what it misses (the rate
    changes within the interval, the poses' own noise) is in the covariance.  Carried from
    the interval's midpoint to the second pose the rates also carry the unknown
    accelerations times dt / 2, which the first accelerometer samples measure: given the
    true accelerations (the covariance conditioned on them), over many starts on a moving
    head the NEES of [omega, v] stays below its 6 dimensions -- about 5: the start takes
    the prior's jerk, larger than these heads' -- never overconfident, and not so
    pessimistic that the first accelerometer samples are ignored."""
    traj = HeadTrajectory(7)
    rng = np.random.default_rng(7)
    ps, rs = 3e-4, np.radians(0.02)
    cov = np.diag([ps**2] * 3 + [rs**2] * 3)
    nees = []
    for t in np.linspace(1.0, 40.0, 120):
        ekf = FusionEKF(_model())
        for ti in (t - 1 / 15, t):
            p, q = traj.pose(ti)
            ekf.update_pose(ti, p[0] + rng.normal(0, ps, 3),
                            geo.quat_multiply(geo.rotvec_to_quat(rng.normal(0, rs, 3)), q[0]),
                            cov)
        s = traj.state(t)
        e = np.concatenate([ekf.omega - s.omega_body[0], ekf.velocity - s.velocity[0]])
        e_acc = np.concatenate([ekf.omega_dot - s.alpha_body[0],
                                ekf.acceleration - s.acceleration[0]])
        rates, accs = np.r_[3:6, 12:15], np.r_[6:9, 15:18]
        gain = ekf.P[np.ix_(rates, accs)] @ np.linalg.inv(ekf.P[np.ix_(accs, accs)])
        e_given = e - gain @ e_acc
        P_given = ekf.P[np.ix_(rates, rates)] - gain @ ekf.P[np.ix_(accs, rates)]
        nees.append(float(e_given @ np.linalg.solve(P_given, e_given)))
    assert 2.0 < np.mean(nees) < 9.0


def test_a_start_claims_the_error_of_the_pose_it_stands_on():
    """The start from two poses is carried to the second: the estimate there is that
    pose, and so is its error, so the covariance is that pose's, its systematic part
    counted once (a laser pose's is most of it).  Applying the second pose again as an
    update would count its error twice and claim 0.88 of its std (1 mm and 0.05 deg per
    axis: the midpoint's acceleration offset, uncorrelated with the acceleration state,
    kept it from half the variance)."""
    traj = HeadTrajectory(4)
    rng = np.random.default_rng(4)
    ps, rs = 1e-3, np.radians(0.05)
    cov = np.diag([ps**2] * 3 + [rs**2] * 3)
    for t, systematic in ((2.0, None), (9.0, None), (17.0, None), (9.0, 0.9 * cov)):
        ekf = FusionEKF(_model())
        for ti in (t - 1 / 15, t):
            p, q = traj.pose(ti)
            p_b = p[0] + rng.normal(0, ps, 3)
            q_b = geo.quat_multiply(geo.rotvec_to_quat(rng.normal(0, rs, 3)), q[0])
            ekf.update_pose(ti, p_b, q_b, cov, systematic)
        assert ekf.t == t and ekf.start_t == t
        assert np.allclose(ekf.position, p_b, atol=1e-9)
        assert geo.quat_angle(ekf.q, q_b) < 1e-6
        assert np.allclose(np.diag(ekf.pose_covariance_decoupled()), np.diag(cov), rtol=0.02)


@pytest.mark.slow
def test_reading_spread_is_the_variance_the_linearisation_leaves_out():
    """Monte Carlo over the rotation error and angular velocity: the exact reading minus
    its linearisation at the estimate varies as ``reading_spreads`` says (centripetal and
    gravity terms): at a start's 0.5 rad/s some 0.05 m/s^2 (std), more than twice the
    readings' noise here."""
    ekf = FusionEKF(_model())
    _set_true_state(ekf, HeadTrajectory(5), 2.1)
    C = np.diag([0.03**2] * 3 + [0.5**2] * 3)
    C[0:3, 3:6] = C[3:6, 0:3] = np.eye(3) * 0.3 * 0.03 * 0.5
    ekf.P[:6, :6] = C
    spreads = ekf.reading_spreads()
    rng = np.random.default_rng(3)
    errors = rng.multivariate_normal(np.zeros(6), C, 4000)
    for j in range(ekf.accel.count):
        h0, H = ekf.predict_reading(j)
        left = []
        for e in errors:
            snap = ekf.snapshot()
            d = np.zeros(ekf.dim)
            d[:6] = e
            ekf._inject(d)
            left.append(ekf.predict_reading(j)[0] - h0 - H[:6] @ e)
            ekf.restore(snap)
        assert np.var(left) == pytest.approx(spreads[j], rel=0.15), j
    assert spreads.max() > 5 * ekf.accel.variance.max()


@pytest.mark.slow
def test_a_start_from_poses_far_apart_coasts_within_its_covariance():
    """Two poses 0.3 s apart (a lone pose, then frame sets without one) give a rate that is
    off by tenths of a rad/s: the accelerometers alone over the next 0.5 s must not make
    the filter surer of it than it is.  Linearised without its spread, the centripetal
    term shrank the covariance about a rate the filter never measured, and half such
    starts turned further than the starting pose's error plus three of the filter's own
    standard deviations (seeds 3-8, 72 starts)."""
    traj = HeadTrajectory(4)
    device, cal = fe.calibrated_accelerometers(300.0, 4)
    run = accel_sim.simulate(traj, 20.0, seed=4, sensor=device, calibration=cal)
    model = fe.accel_model(cal, HEAD_TO_ACCEL_RIG, 300.0, MODEL_FLOOR)
    motion_t = run.t - cal.latency_s
    rng = np.random.default_rng(4)
    ps, rs = 1e-3, np.radians(0.05)
    cov = np.diag([ps**2] * 3 + [rs**2] * 3)
    ratios = []
    for t0 in np.linspace(2.0, 18.0, 8):
        ekf = FusionEKF(model)
        for ti in (t0 - 0.3, t0):
            p, q = traj.pose(ti)
            ekf.update_pose(ti, p[0] + rng.normal(0, ps, 3),
                            geo.quat_multiply(geo.rotvec_to_quat(rng.normal(0, rs, 3)), q[0]),
                            cov)
        p, q = traj.pose(t0)
        e0 = geo.pose_error(ekf.position[None], ekf.q[None], p, q)
        for i in range(np.searchsorted(motion_t, t0, "right"), np.searchsorted(motion_t, t0 + 0.5)):
            ekf.update_accel_sample(run.t[i], run.accel[i])
            p, q = traj.pose(ekf.t)
            ep, er = geo.pose_error(ekf.position[None], ekf.q[None], p, q)
            C = ekf.pose_covariance_decoupled()
            ratios.append(max(ep[0] / (e0[0][0] + 3 * np.sqrt(np.linalg.eigvalsh(C[:3, :3])[-1])),
                              er[0] / (e0[1][0] + 3 * np.sqrt(np.linalg.eigvalsh(C[3:, 3:])[-1]))))
    assert max(ratios) < 1.0


def test_poses_too_far_apart_do_not_start_the_filter():
    ekf = FusionEKF(_model(), FusionConfig(start_max_gap_s=0.2))
    cov = np.eye(6) * 1e-6
    ekf.update_pose(0.0, np.zeros(3), [0, 0, 0, 1], cov)
    ekf.update_pose(0.5, np.ones(3), [0, 0, 0, 1], cov)       # 0.5 s later: too far
    assert not ekf.initialised
    ekf.update_pose(0.6, np.ones(3), [0, 0, 0, 1], cov)       # pairs with the newer one
    assert ekf.initialised and ekf.start_t == 0.6 and np.allclose(ekf.velocity, 0.0)
    with pytest.raises(ValueError, match="start_max_gap_s"):
        FusionConfig(start_max_gap_s=0.0)


def test_a_restart_from_rejected_poses_scales_their_systematic_part_with_them():
    """The poses a restart starts from are kept with the covariance the filter weighed them
    by, scaled by the optics' matched noise (``pose_noise_scale``); their systematic part
    scales with it, or a scale under 1 leaves it larger than the whole and the random
    part of the fused covariance negative."""
    ekf = FusionEKF(_model(), FusionConfig(max_rejected_poses=2))
    cov = np.eye(6) * 1e-6
    systematic = np.eye(6) * 0.8e-6
    ekf.update_pose(0.0, np.zeros(3), [0, 0, 0, 1], cov, systematic)
    ekf.update_pose(0.05, np.zeros(3), [0, 0, 0, 1], cov, systematic)
    ekf.stats.pose_noise_scale = (0.5, 0.5)    # the optics' noise matched at half of it
    far = np.array([0.5, 0.0, 0.0])
    assert not ekf.update_pose(0.10, far, [0, 0, 0, 1], cov, systematic)
    assert ekf.update_pose(0.15, far, [0, 0, 0, 1], cov, systematic)   # the optics win
    assert ekf.start_t == 0.15
    assert np.linalg.eigvalsh(ekf.P_random).min() > 0
    assert np.linalg.eigvalsh(ekf.pose_covariance_decoupled()).min() > 0


def test_a_restart_cuts_the_history_a_late_pose_cannot_reach_behind_it():
    tracker, p, q, cov, rest = _still_rig(FusionConfig(max_rejected_poses=2))
    for i in range(1, 60):
        tracker.add_accel(i / 300, rest)
    far = p + np.array([0.5, 0.0, 0.0])
    assert not tracker.add_rig_pose(0.1, far, q, cov, HEAD_TO_LASER_RIG)
    assert tracker.add_rig_pose(0.15, far, q, cov, HEAD_TO_LASER_RIG)  # the optics win
    assert tracker.ekf.start_t == 0.15
    for i in range(46, 90):
        tracker.add_accel(i / 300, rest)
    # a pose from before the restart would rewind into the state the filter gave up on
    assert not tracker.add_rig_pose(0.12, p, q, cov, HEAD_TO_LASER_RIG)
    assert tracker.stats.optical_too_old == 1
    assert np.linalg.norm(tracker.pose()[0] - far) < 0.5


def test_without_optics_the_output_stops_after_max_coast_and_the_optics_restart_it():
    """Inertial-only poses for ``max_coast_s`` after the last optical pose, then none (the
    sample says why) until two optical poses start the filter again."""
    tracker, p, q, cov, rest = _still_rig(max_coast_s=0.5)
    published = [tracker.add_accel(i / 300, rest) for i in range(1, 300)]
    assert all(published[:150]) and not any(published[152:])   # 0.5 s, then nothing
    assert "no optical measurement for over 0.5 s" in tracker.refusal
    assert tracker.stats.coast_stops == 1 and not tracker.ekf.initialised
    _start(tracker, 1.05, p, q, cov)
    assert tracker.add_accel(1.06, rest) and tracker.stats.coast_stops == 1
    assert np.linalg.norm(tracker.pose()[0]) < 1e-3
    # poses that wait for a lagging inertial stream when it runs out of coast start it again
    for t_opt in (5.0, 5.05):
        tracker.add_rig_pose(t_opt, p, q, cov, HEAD_TO_LASER_RIG, now=0.0)
    assert not tracker.add_accel(4.0, rest, now=0.0)       # 3 s of coast: stop
    assert tracker.stats.coast_stops == 2 and tracker.ekf.start_t == 5.05
    assert tracker.add_accel(5.06, rest, now=0.0)
    with pytest.raises(ValueError, match="max_coast_s"):
        FusionTracker(tracker.ekf, max_coast_s=float("nan"))


@pytest.mark.slow
def test_a_busy_host_slow_late_optics_and_bursty_accelerometers_stay_on_track():
    """What ``uma demo`` met on an overloaded CI machine: the laser tracker at 4 Hz, its
    poses 0.3 s late, the accelerometer samples in bursts up to 0.3 s apart.  A filter
    started from one pose used to dead-reckon into tens of degrees before the next
    correction, refuse it at the gate and restart, again and again; and once started it
    must end up where the same data in time order takes it."""
    traj = HeadTrajectory(3)
    device, cal = fe.calibrated_accelerometers(300.0, 3)
    run = accel_sim.simulate(traj, 8.0, seed=3, sensor=device, calibration=cal)
    rng = np.random.default_rng(3)
    cov = geo.covariance_from_std(np.zeros(3), 3e-4, np.radians(0.02))
    frames = np.arange(0.0, 8.0, 0.25) + rng.uniform(0, 0.05, 32)
    bursts = np.cumsum(rng.uniform(0.02, 0.3, 100))      # when the host lets samples out
    released = bursts[np.searchsorted(bursts, run.t)]

    def run_with(optical_delay, accel_arrival):
        tracker = FusionTracker(FusionEKF(fe.accel_model(cal, HEAD_TO_ACCEL_RIG, 300.0, 0.005)))
        arrivals = sorted([(f + optical_delay, 0, f) for f in frames]
                          + [(accel_arrival[i] + 1e-6, 1, i) for i in range(run.t.size)])
        errors = []
        for now, kind, x in arrivals:
            if kind == 0:
                p, q = geo.compose(*[a[0] for a in traj.pose(x)], *HEAD_TO_LASER_RIG)
                tracker.add_rig_pose(x, p, q, cov, HEAD_TO_LASER_RIG, now=now)
            elif tracker.add_accel(run.t[x], run.accel[x], now=now):
                pt, qt = traj.pose(tracker.ekf.t)
                errors.append(geo.pose_error(*tracker.pose(), pt[0], qt[0]))
        return tracker, np.array(errors).T

    in_order, (ep, er) = run_with(0.0, run.t)
    assert in_order.ekf.stats.reinitialised == 1 and in_order.ekf.stats.pose_updates > 25
    assert np.median(ep) < 1e-3 and np.degrees(np.median(er)) < 0.1
    busy, (ep, er) = run_with(0.3, released)
    assert busy.ekf.stats.reinitialised == 1 and busy.stats.optical_late > 25
    assert np.median(ep) < 2e-3 and np.degrees(np.median(er)) < 0.3
    e_p, e_r = geo.pose_error(*in_order.pose(), *busy.pose())
    assert e_p < 1e-6 and e_r < 1e-6


def test_late_optical_poses_give_the_same_result_as_in_order():
    traj = HeadTrajectory(6)
    device = accel_sim.SensorTruth.ideal(marvin_six())
    run = accel_sim.simulate(traj, 2.0, seed=6, sensor=device)
    cal = device.calibration()
    model = fe.accel_model(cal, HEAD_TO_ACCEL_RIG, 300.0, 0.005)
    in_order, late = FusionTracker(FusionEKF(model)), FusionTracker(FusionEKF(model))
    frames = [k / 15 + 0.001 for k in range(30)]   # never at a sample's instant
    cov = geo.covariance_from_std(np.zeros(3), 3e-4, 3e-4)

    def optical(t):
        p, q = geo.compose(*[a[0] for a in traj.pose(t)], *HEAD_TO_LASER_RIG)
        return p, q

    pending = []
    k = 0
    for i, t in enumerate(run.t):
        while k < len(frames) and frames[k] <= t:
            p, q = optical(frames[k])
            in_order.add_rig_pose(frames[k], p, q, cov, HEAD_TO_LASER_RIG)
            if k <= 1:   # the first two poses start both filters at the same instant
                late.add_rig_pose(frames[k], p, q, cov, HEAD_TO_LASER_RIG)
            else:
                pending.append((t + 0.04, frames[k], p, q))   # arrives 40 ms late
            k += 1
        in_order.add_accel(t, run.accel[i])
        while pending and pending[0][0] <= t:
            _, tf, p, q = pending.pop(0)
            late.add_rig_pose(tf, p, q, cov, HEAD_TO_LASER_RIG)
        late.add_accel(t, run.accel[i])
    assert late.stats.optical_late > 20
    p1, q1 = in_order.pose()
    p2, q2 = late.pose()
    e_p, e_r = geo.pose_error(p1, q1, p2, q2)
    assert e_p < 1e-6 and e_r < 1e-6


def test_bad_input_is_refused_with_a_reason():
    ekf = FusionEKF(_model())
    with pytest.raises(ValueError, match="no pose yet"):
        ekf.pose()
    with pytest.raises(ValueError, match="before initialisation"):
        ekf.predict_to(1.0)
    _start(ekf, 1.0, np.zeros(3), [0, 0, 0, 1], np.eye(6) * 1e-6)
    with pytest.raises(ValueError, match="not all finite"):
        ekf.update_accel_sample(1.01, [0, 0, np.nan, 0, 0, 0])
    with pytest.raises(ValueError, match="the model has 6"):
        ekf.update_accel_sample(1.01, [0, 0, 0])
    with pytest.raises(ValueError, match="before the filter time"):
        ekf.update_pose(0.5, np.zeros(3), [0, 0, 0, 1], np.eye(6) * 1e-6)
    with pytest.raises(ValueError, match="unit quaternion"):
        ekf.update_pose(1.1, np.zeros(3), [0, 0, 0, 3], np.eye(6) * 1e-6)
    with pytest.raises(ValueError, match="positive semi-definite"):
        ekf.update_pose(1.1, np.zeros(3), [0, 0, 0, 1], -np.eye(6))
    with pytest.raises(ValueError, match="angular_jerk_psd"):
        FusionConfig(angular_jerk_psd=-1.0)


def test_pose_covariance_is_symmetric_positive_and_in_xi_form():
    ekf = FusionEKF(_model())
    p = np.array([0.5, -0.2, 0.4])
    C = np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5])
    _start(ekf, 0.0, p, [0, 0, 0, 1], C)
    out = ekf.pose_covariance()
    assert np.allclose(out, out.T) and np.all(np.linalg.eigvalsh(out) > 0)
    idx = np.r_[9:12, 0:3]
    assert np.allclose(geo.se3_to_decoupled(p, out), ekf.P[np.ix_(idx, idx)], atol=1e-12)
    # the start stands on the second pose: its covariance, grown by half an interval's
    # process noise (the second pose is not applied again)
    diag = np.diag(ekf.P[np.ix_(idx, idx)])
    assert np.all(diag >= np.diag(C)) and np.allclose(diag, np.diag(C), rtol=1e-3)


def test_gap_schedule_and_baselines():
    gaps = fe.gap_schedule(30.0, [0.25, 0.5, 1.0])
    pattern = [0.25, 0.5, 1.0]
    assert len(gaps) >= 3
    assert [round(b - a, 3) for a, b in gaps] == [pattern[i % 3] for i in range(len(gaps))]
    assert gaps[0][0] >= fe.WARMUP_S and gaps[-1][1] < 29.0
    rec = SimpleNamespace(
        t=np.array([0.05, 0.1, 0.15]), optical_t=np.array([0.0, 0.1]),
        optical_p=np.array([[0.0, 0, 0], [0.1, 0, 0]]),
        optical_q=np.tile([0.0, 0, 0, 1], (2, 1)))
    b = fe.optical_baselines(rec)
    assert np.allclose(b["hold_last"][0][:, 0], [0.0, 0.1, 0.1])
    assert np.allclose(b["constant_velocity"][0][:, 0], [0.0, 0.1, 0.15])
    # the extrapolation stops one optical frame past the last pose (1 m/s here)
    rec.t = np.array([0.1 + 0.5 / fe.OPTICAL_HZ, 0.1 + 1 / fe.OPTICAL_HZ, 0.9])
    b = fe.optical_baselines(rec)
    assert np.allclose(b["constant_velocity"][0][:, 0],
                       [0.1 + 0.5 / fe.OPTICAL_HZ, 0.1 + 1 / fe.OPTICAL_HZ,
                        0.1 + 1 / fe.OPTICAL_HZ])
    rec.t = np.array([-0.01])
    with pytest.raises(ValueError, match="before the first optical pose"):
        fe.optical_baselines(rec)


def _recording_off_by(traj: HeadTrajectory, dp, angle: float, horizon_s: float,
                      gap: tuple[float, float]) -> fe.Recording:
    """A run whose outputs are the truth moved by ``dp`` (world) and turned by ``angle``
    about a fixed axis, with a covariance that makes each part's NEES exactly 3; its
    predictions are off by 2 mm; its optical poses are the truth at 15 Hz, none in
    ``gap``; 30 inertial samples came before the filter started."""
    t = np.arange(600, 2400) / 300.0
    p, q = traj.pose(t)
    turn = geo.rotvec_to_quat(angle * np.array([2.0, -1.0, 2.0]) / 3.0)
    p_f, q_f = traj.pose(t + horizon_s)
    opt_t = np.array([k / fe.OPTICAL_HZ for k in range(int(8 * fe.OPTICAL_HZ))
                      if not gap[0] <= k / fe.OPTICAL_HZ < gap[1]])
    opt_p, opt_q = traj.pose(opt_t)
    var = np.r_[[float(np.dot(dp, dp)) / 3] * 3, [angle**2 / 3] * 3]
    return fe.Recording(t, p + dp, geo.quat_multiply(turn, q),
                        np.tile(np.diag(var), (t.size, 1, 1)),
                        p_f + np.array([0.0, 0.0, 2e-3]), q_f, opt_t, opt_p, opt_q,
                        cpu_s=1.0, stats=FusionStats(reinitialised=2),
                        optical_failures={}, uninitialised_t=np.linspace(0.0, 0.1, 30))


def test_eval_figures_report_a_known_injected_error():
    """The fusion eval's figures of a run whose error is known: 5 mm (3, 4, 0) and 0.01 rad
    everywhere, 2 mm for the prediction, NEES 6; one NaN output makes the RMSE NaN and is
    counted, not skipped."""
    traj = HeadTrajectory(2)
    gap = (5.0, 6.0)
    rec = _recording_off_by(traj, np.array([3e-3, 4e-3, 0.0]), 0.01, 0.02, gap)
    f = fe.figures_of(rec, traj, [gap], 0.02)
    for key in ("fused", "fused_inside_gaps", "fused_outside_gaps"):
        fig = f[key]
        assert fig["position_rmse_mm"] == pytest.approx(5.0, rel=1e-9)
        assert fig["position_max_mm"] == pytest.approx(5.0, rel=1e-9)
        assert fig["orientation_rmse_deg"] == pytest.approx(np.degrees(0.01), rel=1e-9)
        assert fig["orientation_max_deg"] == pytest.approx(np.degrees(0.01), rel=1e-9)
    assert f["prediction_20ms"]["position_rmse_mm"] == pytest.approx(2.0, rel=1e-9)
    assert f["prediction_20ms"]["orientation_max_deg"] < 1e-6
    assert f["nees"]["mean"] == pytest.approx(6.0, rel=1e-9)
    for part in ("position_mean", "rotation_mean"):
        assert f["nees"]["by_regime"]["optical_gap"][part] == pytest.approx(3.0, rel=1e-9)
    inside = int(np.sum((rec.t >= 5.0) & (rec.t < 6.0 + fe.RECOVERY_FRAMES / fe.OPTICAL_HZ)))
    assert f["samples"] == {"inertial": 1830, "filter_not_running": 30,
                            "filter_not_running_after_warmup": 0, "warmup": 300,
                            "scored": 1500, "scored_inside_gaps": inside,
                            "scored_outside_gaps": 1500 - inside, "non_finite_outputs": 0}
    assert f["fused_inside_gaps"]["samples"] == inside
    assert f["filter_events"]["starts"] == 2 and f["filter_events"]["restarts"] == 1
    # the baselines of exact optical poses: the hold is off by the motion since the last
    # pose, worst inside the gap; the capped extrapolation is better outside it
    hold, cv = f["baseline_hold_last"], f["baseline_constant_velocity"]
    assert hold["inside_gaps"]["position_max_mm"] > 10 * hold["outside_gaps"][
        "position_rmse_mm"]
    assert cv["outside_gaps"]["position_rmse_mm"] < 0.5 * hold["outside_gaps"][
        "position_rmse_mm"]
    # 5 mm is a quarter of the baselines' RMSE over all samples, but not half of the
    # extrapolation's outside the gaps: the goal asks for each region
    assert f["fused"]["position_rmse_mm"] < 0.25 * min(
        hold["all"]["position_rmse_mm"], cv["all"]["position_rmse_mm"])
    assert fe.goals({**f, "output_rate_hz": 300.0})["rmse_le_half_best_baseline"] is False

    rec.p[1000] = np.nan
    f = fe.figures_of(rec, traj, [gap], 0.02)
    assert f["samples"]["non_finite_outputs"] == 1
    assert np.isnan(f["fused"]["position_rmse_mm"]) and np.isnan(f["fused"]["position_max_mm"])


def test_live_fusion_builds_from_attributes_and_publishes():
    cal = accel_sim.default_device().calibration()
    published = []
    live = LiveFusion(0.02, MODEL_FLOOR, publish=lambda *a: published.append(a))
    attrs = {**cal.to_dict(), "frequency_hz": 300.0}
    accel = SimpleNamespace(t_ns=1_000_000_000, values=np.zeros(6), attributes=attrs)
    live.on_accel(accel)
    assert live.tracker is None and "not known yet" in next(iter(live.dropped))
    live.on_accel_mount(SimpleNamespace(position=HEAD_TO_ACCEL_RIG[0],
                                        quaternion=HEAD_TO_ACCEL_RIG[1]))
    live.on_optical_mount(SimpleNamespace(position=HEAD_TO_LASER_RIG[0],
                                          quaternion=HEAD_TO_LASER_RIG[1]))
    live.on_accel(accel)
    assert live.tracker is not None and not published   # waits for the optics
    p, q = geo.compose(np.zeros(3), np.array([0, 0, 0, 1.0]), *HEAD_TO_LASER_RIG)
    for t_ns in (1_001_000_000, 1_002_000_000):     # two poses start the filter
        live.on_optical(SimpleNamespace(t_ns=t_ns, position=p, quaternion=q, covariance=None))
    reading = [float(n @ [0, 0, 9.80665]) for n in live.tracker.ekf.accel.axes]
    for i in range(10):
        live.on_accel(SimpleNamespace(t_ns=1_010_000_000 + i * 3_333_333,
                                      values=np.array(reading), attributes=attrs))
    assert len(published) == 10
    _, pos, _, cov = published[-1]
    assert np.linalg.norm(pos) < 1e-3 and cov.shape == (6, 6)


def _live_at_rest(walls=None):
    """A ``LiveFusion`` (dot mode if ``walls``) started by two poses of a head at rest at
    the origin: it, the rig pose, the accelerometer attributes and readings at rest."""
    cal = accel_sim.default_device().calibration()
    live = LiveFusion(0.0, MODEL_FLOOR, publish=lambda *a: None, walls=walls)
    attrs = {**cal.to_dict(), "frequency_hz": 300.0}
    live.on_accel_mount(SimpleNamespace(position=HEAD_TO_ACCEL_RIG[0],
                                        quaternion=HEAD_TO_ACCEL_RIG[1]))
    live.on_optical_mount(SimpleNamespace(position=HEAD_TO_LASER_RIG[0],
                                          quaternion=HEAD_TO_LASER_RIG[1]))
    live.on_accel(SimpleNamespace(t_ns=1_000_000_000, values=np.zeros(6), attributes=attrs))
    p, q = geo.compose(np.zeros(3), np.array([0, 0, 0, 1.0]), *HEAD_TO_LASER_RIG)
    for t_ns in (1_001_000_000, 1_002_000_000):
        live.on_optical(SimpleNamespace(t_ns=t_ns, position=p, quaternion=q, covariance=None))
    reading = [float(n @ [0, 0, 9.80665]) for n in live.tracker.ekf.accel.axes]
    return live, (p, q), attrs, np.array(reading)


def test_live_fusion_drops_a_pose_whose_systematic_covariance_is_malformed():
    """A NaN in a pose's systematic part (its ``c_sys`` extra, which the decoder leaves to
    its readers) is dropped and counted by name, not raised into the subscriber."""
    from schemas.codec import SYSTEMATIC_COVARIANCE, pack_covariance

    live, (p, q), _, _ = _live_at_rest()
    bad = [float("nan"), *pack_covariance(np.eye(6) * 1e-6)[1:]]
    live.on_optical(SimpleNamespace(t_ns=1_003_000_000, position=p, quaternion=q,
                                    covariance=None, extra={SYSTEMATIC_COVARIANCE: bad}))
    assert [n for why, n in live.dropped.items() if "non-finite" in why] == [1]


def _dots_message(t_ns, points, ids, std=1e-3, sys_std=5e-4):
    from schemas.codec import DOT_STD, DOT_SYSTEMATIC_STD, Measurement

    n = len(points)
    return Measurement(type="points3d", t_ns=t_ns, points=np.asarray(points, float),
                       ids=ids, extra={DOT_STD: [std] * n, DOT_SYSTEMATIC_STD: [sys_std] * n})


def test_live_fusion_in_dot_mode_drops_bad_dots_with_a_reason():
    from services.fusion.dots import display_walls
    from services.installation.ivy import intersect_beam, make_walls
    from services.installation.laser_housing import BEAM_DIRECTIONS

    walls = list(make_walls().values())
    live, (p, q), attrs, rest = _live_at_rest(walls)
    R = geo.quat_to_matrix(q)
    hit = {k: intersect_beam(make_walls(), p, R @ d).point for k, d in BEAM_DIRECTIONS.items()}
    bad_point = hit[3].copy()
    bad_point[1] = np.nan
    t_ns = 1_010_000_000
    live.on_dots(_dots_message(t_ns, [hit[1], hit[4]], [1, 4]))            # good
    live.on_dots(_dots_message(t_ns + 1, [hit[2], bad_point], [2, 3]))      # one NaN
    live.on_dots(_dots_message(t_ns + 2, [hit[2], hit[1]], [7, 1]))         # unknown label
    live.on_dots(_dots_message(t_ns + 3, [hit[2], hit[1]], [2]))            # ids mismatch
    live.on_dots(_dots_message(t_ns + 4, [hit[2]], [2], std=-1.0))          # bad std
    no_std = _dots_message(t_ns + 5, [hit[2]], [2])
    no_std.extra = {}
    live.on_dots(no_std)
    for i in range(30):  # the accelerometers reach the dots' time: they are applied
        live.on_accel(SimpleNamespace(t_ns=1_005_000_000 + i * 3_333_333, values=rest,
                                      attributes=attrs))
    stats = live.tracker.ekf.stats
    assert stats.dot_updates == 4 and stats.dot_rejected == 0  # the 2 + 1 + 1 good dots
    assert live.dropped["laser dot with a non-finite point or a non-positive std"] == 2
    assert live.dropped["laser dot with unknown label 7"] == 1
    assert live.dropped["laser dots refused: 1 labels for 2 points"] == 1
    assert live.dropped["laser dots refused: extra 'std_m': expected 1 numbers"] == 1
    assert np.linalg.norm(live.tracker.pose()[0]) < 1e-3
    pose_mode, *_ = _live_at_rest()
    pose_mode.on_dots(_dots_message(t_ns, [hit[1]], [1]))
    assert pose_mode.dropped["laser dots while not in dot mode"] == 1
    assert len(display_walls(fe.laser_calibration(IvyWorld(), cache=True))) == 6


def test_live_fusion_in_dot_mode_consumes_the_laser_services_dots_and_tracks_the_truth():
    """Seed 7, 5 s: the laser tracker on rendered frames at 15 Hz publishes as the laser
    service does (``_publish``, through the wire codec), the simulated accelerometers at
    300 Hz; the live fusion in dot mode takes every dot, also those of frame sets without a
    pose, and follows the truth."""
    from schemas.codec import decode_measurement, encode_measurement
    from services.fusion.dots import display_walls
    from services.laser_camera import service as laser_service
    from services.laser_camera.tracker import LaserTracker
    from services.sim.world import SIM_EPOCH_NS, sim_time_s

    seconds, rate = 5.0, accel_sim.DEFAULT_RATE_HZ
    world = IvyWorld(seed=7)
    cal = fe.laser_calibration(world, cache=True)
    device, accel_cal = fe.calibrated_accelerometers(rate, 7)
    accel = accel_sim.simulate(world.trajectory, seconds, rate, seed=7, sensor=device,
                               calibration=accel_cal)
    fused = []
    live = LiveFusion(0.0, MODEL_FLOOR, publish=lambda t, p, q, c: fused.append((t, p)),
                      walls=display_walls(cal))
    live.on_accel_mount(SimpleNamespace(position=HEAD_TO_ACCEL_RIG[0],
                                        quaternion=HEAD_TO_ACCEL_RIG[1]))
    live.on_optical_mount(SimpleNamespace(position=HEAD_TO_LASER_RIG[0],
                                          quaternion=HEAD_TO_LASER_RIG[1]))
    attrs = {**accel_cal.to_dict(), "frequency_hz": rate}

    class Stream:
        def __init__(self, on_sample) -> None:
            self.on_sample = on_sample

        def publish_measurement(self, m) -> None:
            self.on_sample(decode_measurement(encode_measurement(m)))

    out = laser_service._Outputs(Stream(live.on_optical), Stream(live.on_dots), {}, {})
    tracker = LaserTracker(cal)
    frames = [k / 15 for k in range(int(seconds * 15))]
    predicted = sent = 0  # dots sent after the filter started: of frame sets without a pose, all
    for t_a, a in zip(accel.t, accel.accel, strict=True):
        while frames and frames[0] <= t_a - accel_cal.latency_s:
            t_f = frames.pop(0)
            result = tracker.process(world.render(t_f).images, t_f)
            dots = tracker.label_dots(result)
            started = live.tracker is not None and live.tracker.ekf.initialised
            predicted += len(dots.labels) if dots.predicted and started else 0
            sent += len(dots.labels) if started else 0
            laser_service._publish(out, SIM_EPOCH_NS + round(t_f * 1e9), result, dots)
        live.on_accel(SimpleNamespace(t_ns=SIM_EPOCH_NS + round(t_a * 1e9), values=a,
                                      attributes=attrs))
    stats, ekf = live.tracker.stats, live.tracker.ekf.stats
    assert predicted >= 10  # seed 7 has frame sets of fewer than four dots: 27 dots
    # the poses only started it (the second is where it starts, not an update); of 75
    # frame sets the first, a start, was held (no dots)
    assert ekf.pose_updates == 0 and stats.dot_frames == 74
    assert ekf.dot_updates + ekf.dot_rejected == sent and ekf.dot_rejected <= 2
    # nothing dropped but what came before the start: the two poses' frame sets' dots
    assert live.dropped.pop("laser dots before the filter runs (or of the frame set that "
                            "started it)") == 2
    assert set(live.dropped) == {"waiting for two optical poses to start"}
    t = np.array([sim_time_s(t_ns) for t_ns, _ in fused])
    p_true, _ = world.trajectory.pose(t)
    err = np.linalg.norm(np.array([p for _, p in fused]) - p_true, axis=1)[t > 1.0]
    # measured: 1.25 mm RMS, 2.0 mm at most after the first second
    assert np.sqrt(np.mean(err ** 2)) < 0.0025 and err.max() < 0.005


def test_accel_model_from_bad_attributes_names_the_problem():
    with pytest.raises(ValueError, match="format"):
        accel_model_from_attributes({"frequency_hz": 300.0}, HEAD_TO_ACCEL_RIG, 0.0)


def test_optical_pose_older_than_the_history_is_dropped_not_applied():
    tracker, p, q, cov, rest = _still_rig(history_s=0.1)
    for i in range(1, 120):
        tracker.add_accel(i / 300, rest)
    before = tracker.ekf.snapshot()
    assert not tracker.add_rig_pose(0.05, p + 0.5, q, cov, HEAD_TO_LASER_RIG)
    assert tracker.stats.optical_too_old == 1
    assert np.array_equal(tracker.ekf.x, before.x)


def test_a_lagging_inertial_stream_stays_the_clock_and_a_stalled_one_is_bypassed():
    tracker, p, q, cov, rest = _still_rig(now=0.0, max_wait_s=0.1)
    accepted = 0
    for i in range(1, 300):              # accelerometers arrive 0.3 s behind the optics
        wall = i / 300 + 0.3
        if i % 20 == 0:
            tracker.add_rig_pose(wall, p, q, cov, HEAD_TO_LASER_RIG, now=wall)
        accepted += tracker.add_accel(i / 300, rest, now=wall)
    assert accepted == 299 and tracker.stats.optical_waited_out == 0
    assert tracker.ekf.stats.pose_updates > 5          # applied when the stream got there
    tracker.add_rig_pose(1.5, p, q, cov, HEAD_TO_LASER_RIG, now=5.0)   # no accel for 4 s
    assert tracker.stats.optical_waited_out >= 1 and tracker.ekf.t == pytest.approx(1.5)


def test_laser_dot_prediction_and_jacobian_match_the_simulated_world():
    from services.installation.laser_housing import BEAM_DIRECTIONS
    from services.sim.world import IvyWorld

    world = IvyWorld(seed=3, ideal=True)  # the filter models the ideal housing
    traj = world.trajectory
    ekf = FusionEKF(_model())
    _set_true_state(ekf, traj, 2.0)
    p_rig, q_rig = world.rig_pose(2.0)
    hits = world.laser_hits(p_rig[0], q_rig[0])
    for label, hit in hits.items():
        wall = world.walls[hit.wall]
        plane = (wall.normal, float(wall.normal @ hit.point))
        pred, J = ekf.predict_dot(BEAM_DIRECTIONS[label], plane, HEAD_TO_LASER_RIG)
        assert np.allclose(pred, hit.point, atol=1e-9)
        num = np.zeros((3, ekf.dim))
        for k in list(range(0, 3)) + list(range(9, 12)):
            snap = ekf.snapshot()
            d = np.zeros(ekf.dim)
            d[k] = 1e-7
            ekf._inject(d)
            num[:, k] = (ekf.predict_dot(BEAM_DIRECTIONS[label], plane, HEAD_TO_LASER_RIG)[0]
                         - pred) / 1e-7
            ekf.restore(snap)
        assert np.allclose(J, num, atol=1e-5), label


def test_the_nees_band_counts_the_samples_of_the_whitened_errors():
    """An error that lasts the run (1 mm, honestly claimed) with short outages where it is
    ten times larger and new each time, also honestly claimed: the NEES is made of the one
    lasting error, so its band is that of one sample.  Unwhitened, the outages (94 % of
    the squared error) made it 16 samples, [4.42, 7.82], which this honest run's mean NEES,
    10.5, lies above."""
    n, outage = 6000, 60
    t = np.arange(n) / 300.0
    std = np.full(n, 1e-3)
    gaps = np.zeros(n, bool)
    for start in range(150, n, 300):
        gaps[start:start + outage] = True
    std[gaps] = 1e-2
    rng = np.random.default_rng(3)
    e = np.tile(rng.standard_normal(6), (n, 1))
    e[gaps] = np.repeat(rng.standard_normal((gaps.sum() // outage, 6)), outage, axis=0)
    e *= std[:, None]
    rec = SimpleNamespace(t=t, p=np.zeros((n, 3)), q=np.tile([0, 0, 0, 1.0], (n, 1)),
                          cov=np.eye(6) * (std**2)[:, None, None],
                          optical_t=t[~gaps][::20])
    p_true = e[:, :3]
    q_true = geo.rotvec_to_quat(e[:, 3:])
    about_zero = fe.nees_figures(rec, p_true, q_true, np.ones(n, bool))["errors_about_zero"]
    assert about_zero["effective_samples"] < 1.5
    assert about_zero["bounds_95"][0] < 1.3 and about_zero["bounds_95"][1] > 14


@pytest.mark.parametrize("bad, why", [(-1e-9, "not positive definite"),
                                       (np.nan, "not finite")])
def test_a_published_covariance_without_a_nees_is_named(bad: float, why: str) -> None:
    """A fused covariance that is indefinite or not finite has no NEES: the eval names its
    sample (a LinAlgError from the Cholesky factor, or a NaN mean, otherwise)."""
    n = 40
    t = np.arange(n) / 300.0
    cov = np.tile(np.eye(6) * 1e-6, (n, 1, 1))
    cov[17, 2, 2] = bad
    rec = SimpleNamespace(t=t, p=np.zeros((n, 3)), q=np.tile([0, 0, 0, 1.0], (n, 1)),
                          cov=cov, optical_t=t[::20])
    with pytest.raises(InvalidInputError, match=rf"t = 0\.0567 s \(sample 17\) is {why}"):
        fe.nees_figures(rec, np.full((n, 3), 1e-4), rec.q, np.ones(n, bool))


@pytest.mark.slow
def test_short_eval_measures_gaps_from_the_last_optical_pose():
    """A 9 s ``uma eval fusion`` (the 60 s runs are by hand) on the realistic installation:
    one 1 s gap, every figure.  The fused covariance carries the laser tracker's
    installation error, which lasts the run: the NEES counted with the errors'
    autocorrelation about zero is inside its band (averaged as per-frame noise, the
    installation's error made it 35 on this seed: docs/FUSION_TUNING.md); that is the
    goal's band.  The band of the NEES series about its own mean cannot see an error that
    lasts the run: it is reported, not a goal."""
    f = fe.evaluate(9.0, seed=1, gap_lengths=[1.0], horizon_s=0.02)
    gap = f["gaps_by_length"]["1s"]
    assert gap["gaps"] == 1 and gap["outage_s_max"] >= 1.0  # 15 Hz: at least 16 frames
    assert gap["orientation_per_gap_deg"][0] == pytest.approx(gap["orientation_max_deg"],
                                                              abs=1e-3)
    assert 0 < gap["position_max_mm"] < 50 and gap["recovery_optical_frames_worst"] <= 3
    # the filter's own 1-sigma after 1 s on the accelerometers: millimetres and about a
    # degree, of the size of the error it has then
    (pos_std,), (rot_std,) = gap["filter_position_std_at_end_mm"], \
        gap["filter_orientation_std_at_end_deg"]
    assert 1 < pos_std < 50 and 0.2 < rot_std < 3
    assert 0.2 < gap["orientation_per_gap_deg"][0] / rot_std < 3
    nees = f["nees"]
    assert 1 < nees["autocorrelation_time_s"] * 300 < 0.5 * 6 * 300  # correlated, not all
    lo, hi = nees["bounds_95"]
    flo, fhi = nees["bounds_95_one_sample_per_optical_frame"]
    assert lo < flo < 6 < fhi < hi  # fewer effective samples than optical frames: wider
    for regime in ("tracking", "optical_gap"):
        r = nees["by_regime"][regime]
        assert 0 < r["share"] < 1 and r["position_mean"] > 0 and r["rotation_mean"] > 0
    about_zero = nees["errors_about_zero"]
    assert about_zero["within_bounds"] and about_zero["mean"] == pytest.approx(nees["mean"],
                                                                              abs=1e-3)
    assert about_zero["effective_samples"] < 0.1 * nees["effective_samples"]
    assert f["output_rate_hz"] > 290
    # every goal is met, in each region (run by hand at 60 s: docs/FUSION_TUNING.md)
    assert f["goals"] == dict.fromkeys(f["goals"], True) and len(f["goals"]) == 5
    n = f["samples"]
    assert n["inertial"] == 9 * 300 and n["non_finite_outputs"] == 0
    assert n["inertial"] == n["filter_not_running"] + n["warmup"] + n["scored"]
    assert n["scored"] == n["scored_inside_gaps"] + n["scored_outside_gaps"]
    assert 0 < n["filter_not_running"] < 0.2 * 300 and n["filter_not_running_after_warmup"] == 0
    assert f["filter_events"]["starts"] == 1 and f["filter_events"]["restarts"] == 0
    assert f["filter_events"]["pose_updates"] + f["filter_events"]["pose_rejected"] >= 100
    assert f["given_by_simulator"]["accel_latency_s"] == \
        accel_sim.default_device().latency_s(accel_sim.DEFAULT_RATE_HZ)
    hold, cv = f["baseline_hold_last"], f["baseline_constant_velocity"]
    assert hold["inside_gaps"]["samples"] == n["scored_inside_gaps"]
    assert cv["outside_gaps"]["position_rmse_mm"] < hold["outside_gaps"]["position_rmse_mm"]


@pytest.mark.slow
def test_optical_covariance_is_matched_per_block():
    """A tracker that overstates its rotation noise 4x gets that block scaled down, never
    below half (the NIS cannot tell overstated noise from persistent errors), while its
    honest position block stays; one that understates its position noise gets that block
    scaled up towards the truth."""
    ps, rs = OPT_STD
    *_, ekf = _simulate(12.0, seed=3, optical_noise=(ps, rs / 4), claimed=(ps, rs))
    pos_scale, rot_scale = ekf.stats.pose_noise_scale
    assert 0.7 < pos_scale < 1.3 and 0.5 <= rot_scale < 0.8
    # 2x understated (4x in variance): far enough to show, near enough for the gate
    *_, ekf = _simulate(12.0, seed=3, optical_noise=(2 * ps, rs), claimed=(ps, rs))
    assert 2.0 < ekf.stats.pose_noise_scale[0] < 6.0


@pytest.mark.slow
def test_a_trackers_persistent_offset_is_modelled_not_averaged_away():
    """An optical tracker whose position is off by a constant (calibration) keeps a white
    filter overconfident: averaging frames shrinks its covariance but not the offset.  With
    the offset modelled as the tracker's bias state, the position covariance stays at the
    bias's size (the offset is unobservable) and the position NEES is honest."""
    ps = OPT_STD[0]
    offset = (4e-4, -4e-4, 4e-4)
    white = FusionConfig(adapt_pose_noise=False)
    t, ep, _, nees_white, _ = _simulate(10.0, seed=3, optical_offset=offset, config=white)
    biased = FusionConfig(adapt_pose_noise=False, optical_bias_std=4e-4,
                          optical_bias_tau_s=30.0)
    t, ep_b, _, nees_b, ekf = _simulate(10.0, seed=3, optical_offset=offset, config=biased)
    late = t > 3.0
    assert float(np.mean(nees_white[late])) > 1.5 * float(np.mean(nees_b[late]))
    assert 3.0 < float(np.mean(nees_b[late])) < 9.0
    pos_std = np.sqrt(np.diag(ekf.P)[9:12])
    assert np.all(pos_std > 0.8 * 4e-4)  # never below the unobservable offset
    assert np.all(np.abs(ekf.optical_bias) < 3 * 4e-4)
    # the tracker's noise still averages out: the fused position is no worse than it
    assert np.sqrt(np.mean(ep_b[late] ** 2)) < np.sqrt(np.mean(ep[late] ** 2)) + ps


@pytest.mark.slow
def test_a_reported_systematic_error_is_carried_into_the_fused_covariance():
    """A tracker off by a constant that it reports as the systematic part of its covariance
    (the laser tracker's installation tolerances): the filter keeps the systematic part
    whole in its output covariance, so the position NEES stays honest.  The same
    covariance without the split, as if every frame's error were new, is averaged away:
    the filter claims an accuracy the tracker never had."""
    ps = OPT_STD[0]
    offset = (4e-4, -4e-4, 4e-4)
    sys = np.diag([4e-4**2] * 3 + [0.0] * 3)
    config = FusionConfig(adapt_pose_noise=False)
    t, _, _, nees_whole, _ = _simulate(10.0, seed=3, optical_offset=offset, config=config,
                                       claimed=(np.hypot(ps, 4e-4), OPT_STD[1]))
    t, ep, _, nees, ekf = _simulate(10.0, seed=3, optical_offset=offset, config=config,
                                    systematic=sys)
    late = t > 3.0
    assert float(np.mean(nees_whole[late])) > 1.5 * float(np.mean(nees[late]))
    assert 3.0 < float(np.mean(nees[late])) < 9.0
    np.testing.assert_array_equal(ekf.systematic, sys)
    assert np.all(np.sqrt(np.diag(ekf.pose_covariance_decoupled())[:3]) >= 4e-4)
    # the random part still averages out: the fused position is off by about the offset
    assert np.sqrt(np.mean(ep[late] ** 2)) < np.linalg.norm(offset) + ps


def test_the_fused_covariance_counts_the_optics_systematic_part_once():
    """Poses off by one installation error each run (drawn from their systematic part) plus
    new noise each frame, weighed by their whole covariance: the filter follows the error,
    so the fused pose carries it whole, and the share ``P`` took in as if it were new in
    each frame (``P_sys``) is not counted again.  Counted twice, the mean NEES of 80 runs
    was 3.3, under the band of 60 independent samples, [5.16, 6.91]."""
    rng = np.random.default_rng(7)
    random = np.diag([3e-4**2] * 3 + [np.radians(0.02)**2] * 3)
    sys = np.diag([1e-3**2] * 3 + [np.radians(0.06)**2] * 3)
    ekf = FusionEKF(_model(), FusionConfig(adapt_pose_noise=False))
    runs, frames = 60, 15
    draws = rng.standard_normal((runs, frames + 1, 6))
    nees = []
    for run in range(runs):
        ekf.stop()
        error = draws[run, 0] * np.sqrt(np.diag(sys))
        for k in range(frames):
            e = error + draws[run, k + 1] * np.sqrt(np.diag(random))
            assert ekf.update_pose(k / 15, e[:3], geo.rotvec_to_quat(e[3:]), random + sys, sys)
        p, q = ekf.pose()
        err = -np.concatenate([p, geo.quat_to_rotvec(q)])
        nees.append(float(err @ np.linalg.solve(ekf.pose_covariance_decoupled(), err)))
    lo, hi = mean_nees_band_95(6, runs)
    assert lo <= float(np.mean(nees)) <= hi


def test_a_systematic_part_larger_than_the_covariance_is_refused_by_name():
    ekf = FusionEKF(_model())
    cov = np.eye(6) * 1e-6
    with pytest.raises(ValueError, match="optical covariance minus its systematic part"):
        ekf.update_pose(0.0, np.zeros(3), [0, 0, 0, 1], cov, 2 * cov)
    with pytest.raises(ValueError, match="optical systematic covariance"):
        ekf.update_pose(0.0, np.zeros(3), [0, 0, 0, 1], cov, -cov)


def test_the_systematic_covariance_crosses_the_wire_and_old_poses_still_work():
    """The laser tracker's systematic part travels as an optional extra of the pose; a
    receiver reads it back, a pose without it has none, a malformed one is named."""
    from schemas.codec import (
        SYSTEMATIC_COVARIANCE,
        Measurement,
        decode_measurement,
        encode_measurement,
        pack_covariance,
        systematic_covariance,
    )

    sys = np.diag([1e-6, 2e-6, 3e-6, 1e-8, 2e-8, 3e-8])
    sys[0, 4] = sys[4, 0] = 1e-8
    m = decode_measurement(encode_measurement(Measurement(
        type="pose6d", t_ns=1, position=np.zeros(3), quaternion=np.array([0, 0, 0, 1.0]),
        covariance=2 * sys, extra={SYSTEMATIC_COVARIANCE: pack_covariance(sys)})))
    np.testing.assert_allclose(systematic_covariance(m), sys)
    m.extra = {}
    assert systematic_covariance(m) is None
    m.extra = {SYSTEMATIC_COVARIANCE: [1.0, "x"]}
    with pytest.raises(ValueError, match=f"extra '{SYSTEMATIC_COVARIANCE}'"):
        systematic_covariance(m)
    m.extra = {SYSTEMATIC_COVARIANCE: [float("nan"), *pack_covariance(sys)[1:]]}
    with pytest.raises(ValueError, match=f"extra '{SYSTEMATIC_COVARIANCE}': non-finite"):
        systematic_covariance(m)


def test_eval_what_if_device_reaches_the_device_and_the_filter_model():
    args = SimpleNamespace(accel_noise_uv=10.0, adc_conversions=4, converter_noise_lsb=0.1)
    quiet = device_from_args(accel_sim.default_device(), args)
    assert device_figures(quiet) == {"accel_noise_uv_per_sqrt_hz": 10.0, "adc_conversions": 4,
                                     "converter_noise_lsb": 0.1}
    _, cal = fe.calibrated_accelerometers(300.0, 1, quiet)
    _, cal_marvin = fe.calibrated_accelerometers(300.0, 1)
    assert cal.noise.density_v == pytest.approx(10e-6) and cal.noise.conversions == 4
    assert np.all(cal.accel_var(300.0) < 0.5 * cal_marvin.accel_var(300.0))
    base = dict(gaps="1", horizon_ms=20.0, no_cache=False, optical="pose", seconds=9.0, seed=1,
                from_file=None)
    for flag, value in (("accel_noise_uv", -1.0), ("adc_conversions", 3),
                        ("converter_noise_lsb", float("nan"))):
        with pytest.raises(ValueError, match="--" + flag.replace("_", "-")):
            fe.run(SimpleNamespace(**base, **{flag: value}))
    # a recording replayed in dot mode needs the walls the dots lie on
    with pytest.raises(ValueError, match="--display-calibration"):
        fe.run(SimpleNamespace(**{**base, "from_file": "demo.mcap", "optical": "dots",
                                  "display_calibration": None}))


@pytest.mark.parametrize("flag", ["--estimate-installation", "--no-estimate-installation",
                                  "--ideal"])
def test_eval_refuses_simulation_options_on_a_recording(flag):
    """With --from no installation is simulated and no laser tracker runs, so these
    options would do nothing."""
    estimate = {"--estimate-installation": True, "--no-estimate-installation": False}
    args = SimpleNamespace(horizon_ms=None, from_file="demo.mcap", optical="pose",
                           display_calibration=None,
                           estimate_installation=estimate.get(flag), ideal=flag == "--ideal")
    with pytest.raises(InvalidInputError, match=f"{flag} is for the simulated run"):
        fe.run(args)


@pytest.mark.parametrize("argv, flag", [(["--optical-bias-mm", "-1"], "--optical-bias-mm"),
                                        (["--optical-bias-tau-s", "0"], "--optical-bias-tau-s"),
                                        (["--model-floor", "nan"], "--model-floor"),
                                        (["--max-coast-s", "0"], "--max-coast-s"),
                                        (["--optical", "dots"], "--display-calibration"),
                                        (["--display-calibration", "ivy.json"],
                                         "--display-calibration is for --optical dots")])
def test_service_refuses_bad_noise_flags_by_name(argv, flag):
    import argparse
    import threading

    from services.fusion import service
    from services.fusion.plugin import add_fusion_arguments

    parser = argparse.ArgumentParser()
    add_fusion_arguments(parser)
    with pytest.raises(ValueError, match=flag):
        service.run(parser.parse_args(argv), threading.Event())


def _moving_filter(config: FusionConfig) -> FusionEKF:
    """A filter on a moving head (a generic rotation, far from symmetric), every block on."""
    ekf = FusionEKF(_model(), config)
    _set_true_state(ekf, HeadTrajectory(6), 2.1)
    ekf.x[18:] = 0.01 * np.arange(ekf.dim - 18) + 0.02  # biases, optical bias, jerks
    return ekf


def _propagated(ekf: FusionEKF, P0: np.ndarray, dt: float) -> np.ndarray:
    """What the filter's own time update makes of the covariance ``P0`` over ``dt``."""
    snap = ekf.snapshot()
    ekf.P = P0.copy()
    ekf.predict_to(ekf.t + dt)
    out = ekf.P.copy()
    ekf.restore(snap)
    return out


def _propagated_f_and_q(ekf: FusionEKF, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """F and Q of one step as the filter applies them, read off ``P' = F P F^T + Q``:
    ``P = 0`` gives Q; ``P = e_k e_k^T`` gives ``Q + f_k f_k^T``, whose k-th column over the
    root of its diagonal entry is F's k-th column ``f_k`` (``F[k, k]`` is 1 or a decay > 0)."""
    Q = _propagated(ekf, np.zeros((ekf.dim, ekf.dim)), dt)
    F = np.zeros_like(Q)
    for k in range(ekf.dim):
        e = np.zeros(ekf.dim)
        e[k] = 1.0
        outer = _propagated(ekf, np.outer(e, e), dt) - Q
        assert outer[k, k] > 0, k
        F[:, k] = outer[:, k] / np.sqrt(outer[k, k])
    return F, Q


def _continuous_model(ekf: FusionEKF, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The error state's continuous-time model ``dx/dt = A x + w``, ``E[w w^T] = Qc``:
    Hogue 2003 eq. 6.1's chains (rotation error in world axes driven by the body rate,
    rate by its derivative; position, velocity, acceleration), white jerk on the last link
    of each, Gauss-Markov jerk and optical-bias states, random-walk accelerometer biases.
    The rotation ``R`` is held over the step (the filter linearises there)."""
    cfg, lay, n = ekf.config, ekf.layout, ekf.dim
    eye = np.eye(3)
    A, Qc = np.zeros((n, n)), np.zeros((n, n))
    A[0:3, 3:6] = R
    A[3:6, 6:9] = A[9:12, 12:15] = A[12:15, 15:18] = eye
    Qc[6:9, 6:9] = cfg.angular_jerk_psd * eye
    Qc[15:18, 15:18] = cfg.linear_jerk_psd * eye
    ab = lay.accel_bias
    Qc[ab, ab] = cfg.bias_walk**2 * np.eye(lay.n_bias)
    for block, std, tau, drives in (
            (lay.angular_jerk, cfg.angular_jerk_std, cfg.angular_jerk_tau_s, slice(6, 9)),
            (lay.linear_jerk, cfg.linear_jerk_std, cfg.linear_jerk_tau_s, slice(15, 18)),
            (lay.optical_bias, cfg.optical_bias_std, cfg.optical_bias_tau_s, None)):
        if block.stop > block.start:
            A[block, block] = -eye / tau
            Qc[block, block] = 2 * std**2 / tau * eye   # stationary variance std^2
            if drives is not None:
                A[drives, block] = eye
    return A, Qc


def _van_loan(A: np.ndarray, Qc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Discrete F and Q of ``dx/dt = A x + w`` over ``dt`` (Van Loan, *Computing integrals
    involving the matrix exponential*, IEEE Trans. Automatic Control 1978)."""
    from scipy.linalg import expm

    n = A.shape[0]
    M = np.block([[-A, Qc], [np.zeros((n, n)), A.T]]) * dt
    E = expm(M)
    F = E[n:, n:].T
    return F, F @ E[:n, n:]


def test_time_update_propagates_the_closed_form_f_and_q():
    """The F and Q the filter really applies to P (read off its predict step) against the
    discretised continuous-time model (expm and Van Loan's integral).

    White jerk only: they agree to rounding.  With the Gauss-Markov jerk states the filter
    holds the jerk constant through a step, which is exact to O(dt / tau) ~ 1.5 % in the
    blocks the jerk drives; F is compared to 2 % there, exactly elsewhere, and Q's
    Gauss-Markov blocks exactly (the filter leaves out their few-percent share in the
    chains' Q)."""
    dt = 1.0 / 300.0
    white = FusionConfig(linear_jerk_std=0.0, angular_jerk_std=0.0, optical_bias_std=2e-4)
    ekf = _moving_filter(white)
    F, Q = _propagated_f_and_q(ekf, dt)
    ekf.predict_to(ekf.t + dt)
    R = geo.quat_to_matrix(ekf.q)
    assert np.abs(R - R.T).max() > 0.5    # R^T in place of R would show
    F_ref, Q_ref = _van_loan(*_continuous_model(ekf, R), dt)
    np.testing.assert_allclose(F, F_ref, rtol=1e-9, atol=1e-13)
    scale = np.sqrt(np.outer(np.diag(Q_ref), np.diag(Q_ref)))   # correlations to 1e-6
    assert np.all(np.abs(Q - Q_ref) <= 1e-6 * scale + 1e-30), np.abs(Q - Q_ref).max()

    ekf = _moving_filter(FusionConfig(optical_bias_std=2e-4))
    F, Q = _propagated_f_and_q(ekf, dt)
    ekf.predict_to(ekf.t + dt)
    F_ref, Q_ref = _van_loan(*_continuous_model(ekf, geo.quat_to_matrix(ekf.q)), dt)
    np.testing.assert_allclose(F, F_ref, rtol=0.02, atol=1e-15)
    assert np.array_equal(F == 0, F_ref == 0)
    jerks = np.r_[ekf.layout.linear_jerk, ekf.layout.angular_jerk, ekf.layout.optical_bias]
    np.testing.assert_allclose(Q[np.ix_(jerks, jerks)], Q_ref[np.ix_(jerks, jerks)],
                               rtol=1e-9, atol=1e-15)


def _error_between(a: FusionEKF, b: FusionEKF) -> np.ndarray:
    """b's state minus a's in the filter's error-state form (world rotation vector first)."""
    d = b.x - a.x
    d[0:3] = geo.quat_to_rotvec(geo.quat_multiply(b.q, geo.quat_conjugate(a.q)))
    return d


def test_time_update_jacobian_matches_finite_differences():
    """The F the filter propagates P with (read off its predict step), jerk states and the
    optical bias included, against perturbing each error-state component of a moving state
    and integrating the nonlinear mean (the quaternion on the manifold)."""
    ekf = _moving_filter(FusionConfig(optical_bias_std=2e-4))
    dt = 1.0 / 300.0
    F, _ = _propagated_f_and_q(ekf, dt)
    nominal = ekf.snapshot()
    ekf.predict_to(ekf.t + dt)
    after = FusionEKF(_model(), ekf.config)
    after.restore(ekf.snapshot())
    eps = 1e-4
    for k in range(ekf.dim):
        ekf.restore(nominal)
        d = np.zeros(ekf.dim)
        d[k] = eps
        ekf._inject(d)
        ekf.predict_to(ekf.t + dt)
        num = _error_between(after, ekf) / eps
        # the rotation rows are first order: R after the step stands for R times the right
        # Jacobian of the turn, |omega| dt / 2 ~ 0.5 % off; everything else is linear
        col = np.abs(F[:3, k]).max()
        assert np.allclose(num[:3], F[:3, k], rtol=0, atol=0.01 * col + 1e-9), k
        assert np.allclose(num[3:], F[3:, k], rtol=1e-6, atol=1e-8), k


def test_jerk_states_move_the_acceleration_smoothly():
    """A Gauss-Markov jerk j0 (time constant tau) adds j0 tau (1 - exp(-t / tau)) to the
    acceleration: the mean of the time update follows it, linear and angular alike."""
    cfg = FusionConfig()
    ekf = FusionEKF(_model(), cfg)
    ekf.initialise(0.0, np.zeros(3), geo.quat_identity(), np.eye(6) * 1e-8)
    j_lin, j_ang = np.array([3.0, -2.0, 1.0]), np.array([-5.0, 4.0, 8.0])
    ekf.x[ekf.layout.linear_jerk], ekf.x[ekf.layout.angular_jerk] = j_lin, j_ang
    for _ in range(90):
        ekf.predict_to(ekf.t + 1.0 / 300.0)
    for got, j0, tau in ((ekf.acceleration, j_lin, cfg.linear_jerk_tau_s),
                         (ekf.omega_dot, j_ang, cfg.angular_jerk_tau_s)):
        assert np.allclose(got, j0 * tau * (1.0 - np.exp(-0.3 / tau)), rtol=0.01)
    assert np.all(np.linalg.eigvalsh(ekf.P) > 0)
