"""Calibration from static poses (Hogue 2003, §4.4.2), the calibration file, input validation,
and the honesty of the dead reckoner's covariance (NEES).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from agent import geometry as geo
from services.accel_rig import sensor as sn
from services.accel_rig.calibration import (
    SIX_POSES,
    THESIS_POSES,
    StaticRecording,
    calibrate,
    calibration_errors,
)
from services.accel_rig.integrator import dead_reckon_from_truth
from services.accel_rig.rig import layout_by_name, marvin_six, nine_accelerometer
from services.accel_rig.simulator import (
    SensorTruth,
    axis_down_quaternion,
    default_device,
    simulate,
    simulate_static,
)
from services.sim.trajectory import HeadTrajectory

RATE = 300.0


def _recordings(device: SensorTruth, labels, seconds: float, seed: int = 0):
    return [StaticRecording(axis_down_quaternion(lab),
                            simulate_static(axis_down_quaternion(lab), seconds, RATE,
                                            seed=seed + i, sensor=device))
            for i, lab in enumerate(labels)]


def _errors(cal: sn.Calibration, device: SensorTruth):
    return calibration_errors(cal, device.bias_v, device.gain_v_per_mps2, device.layout.axes)


def test_axis_down_poses_put_the_named_axis_along_gravity():
    for lab in SIX_POSES:
        d = np.zeros(3)
        d["xyz".index(lab[1])] = 1.0 if lab[0] == "+" else -1.0
        down = geo.quat_rotate(axis_down_quaternion(lab), d)
        np.testing.assert_allclose(down, [0, 0, -1], atol=1e-12)
    with pytest.raises(ValueError, match="expected one of"):
        axis_down_quaternion("x+")


@pytest.mark.parametrize("labels", [THESIS_POSES, SIX_POSES], ids=["four-thesis", "six-lsq"])
def test_noise_free_calibration_is_exact(labels):
    device = default_device().noise_free()  # table 4.1 axes, random bias and gain errors
    cal = calibrate(marvin_six(), _recordings(device, labels, 0.1), RATE, latency_s=0.0)
    err = _errors(cal, device).worst()
    assert err["bias_lsb"] < 1e-9 and err["scale_percent"] < 1e-9 and err["axis_deg"] < 1e-9
    # the calibration was not trivially close already: the device really is off
    assert np.abs(device.bias_v).max() > 10 * sn.LSB_V
    assert np.abs(device.scale_error).max() > 0.005


def test_noise_free_calibration_of_a_nine_accelerometer_rig():
    device = SensorTruth.draw(7, nine_accelerometer()).noise_free()
    cal = calibrate(nine_accelerometer(), _recordings(device, SIX_POSES, 0.1), RATE)
    assert max(_errors(cal, device).worst().values()) < 1e-9


def test_calibration_with_appendix_c_noise_meets_the_tolerances():
    """Four thesis poses, 2 s each, with noise, 110 Hz response and 12-bit quantisation."""
    device = default_device()
    cal = calibrate(marvin_six(), _recordings(device, THESIS_POSES, 2.0, seed=11), RATE,
                    noise=device.noise_model(), latency_s=device.latency_s(RATE))
    err = _errors(cal, device).worst()
    assert err["bias_lsb"] < 1.0 and err["scale_percent"] < 0.5 and err["axis_deg"] < 0.2
    # and the reported parameter uncertainty is of the size of the actual error
    sd_bias_lsb = np.sqrt(cal.param_cov[:, 0, 0]) / sn.LSB_V
    assert np.abs(_errors(cal, device).bias_lsb).max() < 5 * sd_bias_lsb.max()


def test_calibration_of_a_quiet_device_reports_what_quantisation_leaves():
    """At 10 uV/sqrt(Hz) and without the converter's own noise the 1 mV steps are barely
    dithered: averaging a static pose cannot get below the quantisation error, and the
    reported bias uncertainty says so."""
    device = replace(default_device(), noise_density_v=10e-6, converter_noise_lsb=0.0)
    cal = calibrate(marvin_six(), _recordings(device, SIX_POSES, 3.0, seed=12), RATE,
                    noise=device.noise_model(), latency_s=device.latency_s(RATE))
    sd_bias_lsb = np.sqrt(cal.param_cov[:, 0, 0]) / sn.LSB_V
    white_only = math.sqrt(device.noise_model().per_sample_var_v2(RATE) / (3.0 * RATE)
                           / len(SIX_POSES)) / sn.LSB_V
    assert sd_bias_lsb.min() > 5 * white_only  # averaging alone would promise far less
    errors = np.abs(_errors(cal, device).bias_lsb)
    assert errors.max() > 3 * white_only  # and the error really is that large
    assert errors.max() < 4 * sd_bias_lsb.max()


def test_calibration_refuses_bad_recordings_with_reasons():
    device = default_device()
    recs = _recordings(device, THESIS_POSES, 0.5)
    with pytest.raises(ValueError, match="at least 4 static orientations"):
        calibrate(marvin_six(), recs[:3], RATE)
    with pytest.raises(ValueError, match="do not determine bias and axis"):
        calibrate(marvin_six(), [recs[0]] * 4, RATE)
    moving = simulate(HeadTrajectory(1), 0.5, RATE, seed=1, sensor=device).volts
    with pytest.raises(ValueError, match=r"pose 2: .*not held still"):
        calibrate(marvin_six(), [recs[0], StaticRecording(recs[1].quaternion, moving),
                                 *recs[2:]], RATE)
    nan = recs[3].volts.copy()
    nan[5, 2] = np.nan
    with pytest.raises(ValueError, match="pose 4 voltages: non-finite value nan"):
        calibrate(marvin_six(), [*recs[:3], StaticRecording(recs[3].quaternion, nan)], RATE)
    with pytest.raises(ValueError, match=r"pose 1 voltages: 3.5 V .* outside the A/D range"):
        calibrate(marvin_six(), [StaticRecording(recs[0].quaternion,
                                                 np.full((10, 6), 3.5)), *recs[1:]], RATE)
    with pytest.raises(ValueError, match=r"must be \(samples, 6\)"):
        calibrate(marvin_six(), [StaticRecording(recs[0].quaternion, recs[0].volts[:, :5]),
                                 *recs[1:]], RATE)


def test_voltages_are_validated_before_conversion():
    cal = default_device().calibration()
    ok = np.full(6, 0.1)
    np.testing.assert_allclose(cal.to_volts(cal.to_accel(ok)), ok)
    with pytest.raises(ValueError, match=r"amplifier rail.*saturated"):
        cal.to_accel(np.array([0.1, 0.1, 2.0, 0.1, 0.1, 0.1]))
    with pytest.raises(ValueError, match="outside the A/D range"):
        cal.to_accel(np.array([0.1, 0.1, 0.1, -9.0, 0.1, 0.1]))
    with pytest.raises(ValueError, match="non-finite"):
        cal.to_accel(np.array([0.1, np.inf, 0.1, 0.1, 0.1, 0.1]))
    with pytest.raises(ValueError, match="5 channels, the calibration has 6"):
        cal.to_accel(np.full(5, 0.1))


def test_calibration_file_round_trip_and_errors(tmp_path):
    device = default_device()
    cal = calibrate(marvin_six(), _recordings(device, SIX_POSES, 0.2), RATE,
                    noise=device.noise_model(), latency_s=device.latency_s(RATE))
    path = tmp_path / "cal.json"
    cal.save(path)
    back = sn.Calibration.load(path)
    np.testing.assert_array_equal(back.bias_v, cal.bias_v)
    np.testing.assert_array_equal(back.axes, cal.axes)
    np.testing.assert_array_equal(back.param_cov, cal.param_cov)
    assert back.latency_s == cal.latency_s and back.noise == cal.noise
    d = cal.to_dict()
    del d["gain_v_per_mps2"]
    with pytest.raises(ValueError, match="missing field 'gain_v_per_mps2'"):
        sn.Calibration.from_dict(d)
    with pytest.raises(ValueError, match="format"):
        sn.Calibration.from_dict({**cal.to_dict(), "format": "other"})
    with pytest.raises(ValueError, match="gains are positive"):
        sn.Calibration.from_dict({**cal.to_dict(), "gain_v_per_mps2": [-1.0] * 6})
    with pytest.raises(ValueError, match="conversions must be a whole number"):
        sn.Calibration.from_dict({**cal.to_dict(), "adc_conversions": 0})
    # a file from before the averaging A/D: one conversion per reading, no converter noise
    old = {k: v for k, v in cal.to_dict().items()
           if k not in ("adc_conversions", "converter_noise_lsb")}
    noise = sn.Calibration.from_dict(old).noise
    assert noise.conversions == 1 and noise.converter_noise_lsb == 0.0
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not JSON"):
        sn.Calibration.load(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="No such file"):
        sn.Calibration.load(tmp_path / "missing.json")


def _mean_nees(cal: sn.Calibration, device: SensorTruth, runs: int) -> float:
    """Average 6-dof pose NEES after 1 s over independent runs from random start times."""
    traj = HeadTrajectory(2)
    rng = np.random.default_rng(21)
    nees = []
    for r in range(runs):
        run = simulate(traj, 1.0, RATE, seed=500 + r, t0=rng.uniform(0, 50), sensor=device,
                       calibration=cal)
        e = dead_reckon_from_truth(cal, run.t, run.accel, run.truth, RATE)[-1]
        dp = run.truth.position[-1] - e.position
        dth = geo.quat_to_rotvec(geo.quat_multiply(run.truth.quaternion[-1],
                                                   geo.quat_conjugate(e.quaternion)))
        x = np.concatenate([dp, dth])
        nees.append(x @ np.linalg.solve(e.decoupled_covariance, x))
    return float(np.mean(nees))


@pytest.mark.slow
def test_reported_covariance_is_honest_nees():
    """Mean NEES within the two-sided 95 % chi-square bounds; a model that claims 4x less
    noise than there is fails the same check."""
    device = default_device()
    cal = calibrate(marvin_six(), _recordings(device, SIX_POSES, 3.0, seed=40), RATE,
                    noise=device.noise_model(), latency_s=device.latency_s(RATE))
    runs = 30
    lo, hi = chi2.ppf([0.025, 0.975], 6 * runs) / runs
    honest = _mean_nees(cal, device, runs)
    assert lo < honest < hi, (lo, honest, hi)
    overconfident = replace(cal, noise=replace(cal.noise, density_v=cal.noise.density_v / 4))
    assert _mean_nees(overconfident, device, runs) > hi


def test_eval_plugin_reports_every_figure():
    """A short ``uma eval accel-rig`` (the full one is run by hand: 100 runs per seed)."""
    from argparse import Namespace

    from services.accel_rig.evaluate import run

    fig = run(Namespace(seconds=10.0, seed=1, json=True, runs=4, layout="marvin-six",
                               poses="thesis", pose_seconds=2.0))
    cal = fig["calibration"]
    assert cal["poses"] == list(THESIS_POSES)
    assert cal["bias_lsb_max"] < 1.0 and cal["scale_percent_max"] < 0.5
    assert cal["axis_deg_max"] < 0.2 and cal["uncalibrated_bias_lsb_max"] > 5
    # with these seeds the 4 runs give an orientation p95 of 0.065, 0.169, 0.51, 1.38 deg
    # and a median position error of 0.062, 0.50, 6.7, 75 mm; another draw of 4 runs'
    # noise moves such figures by tens of percent, so the bounds are half and twice them
    measured = {"0.25s": (0.065, 6.2e-5), "0.5s": (0.169, 5.0e-4), "1s": (0.51, 6.7e-3),
                "2s": (1.38, 0.075)}
    for key, (ori_p95, pos_median) in measured.items():
        ori, pos = fig["orientation_error_deg"][key], fig["position_error_m"][key]
        assert 0 < ori["median"] <= ori["p95"] and 0.5 < ori["p95"] / ori_p95 < 2, (key, ori)
        assert 0 < pos["median"] <= pos["p95"] and 0.5 < pos["median"] / pos_median < 2, \
            (key, pos)
        assert fig["nees"][key]["within_bounds"], (key, fig["nees"][key])
    assert fig["goals"] == dict.fromkeys(fig["goals"], True) and len(fig["goals"]) == 3
    device = SensorTruth.draw(1001, layout_by_name("marvin-six-table-4.1"))   # seed 1's
    assert fig["given_by_simulator"]["accel_latency_s"] == device.latency_s(fig["rate_hz"]) > 0
    # drift grows with time, as inertial drift must
    assert fig["position_error_m"]["2s"]["median"] > 10 * fig["position_error_m"]["0.25s"][
        "median"]
    for key in measured:  # the shared calibration error widens the band, never narrows it
        n = fig["nees"][key]
        shape = n["shape"]
        assert shape["orientation_nees"] + shape["position_given_orientation_nees"] == \
            pytest.approx(n["mean"])
        assert shape["nees_variance"] > 0 and -1 <= shape["orientation_position_correlation"] <= 1
        assert "noise_draws" not in n
        lo, hi = n["bounds_95_independent_runs"]
        assert lo < 6 < hi
        assert 1 <= n["effective_runs"] <= 4 + 1e-9
        assert n["bounds_95"][0] <= lo + 1e-9 and n["bounds_95"][1] >= hi - 1e-9
    # the calibration's error against its covariance (24 dof), and what it adds to the mean
    # NEES of the runs, which share it, against what that covariance expects: a part of the
    # pose covariance (so of the 6 dof) that grows with the horizon
    assert cal["nees_dof"] == 24 and 0 < cal["nees"] < 100
    shares = [fig["nees"][key]["calibration_share"] for key in measured]
    assert all(sh["this_calibration"] >= 0 for sh in shares)
    expected = [sh["expected"] for sh in shares]
    assert 0 < expected[0] < expected[1] < expected[2] < expected[3] < 6
    with pytest.raises(ValueError, match="--seconds must exceed"):
        run(Namespace(seconds=2.0, seed=1, json=True, runs=4, layout="marvin-six",
                             poses="six", pose_seconds=2.0))


@pytest.mark.slow
def test_eval_noise_draws_repeat_the_runs_with_fresh_noise_only():
    """``--noise-draws``: the eval's own runs are unchanged, each repeat has the same rig and
    start times (its errors are of the same size) and other noise (another mean NEES)."""
    from argparse import Namespace

    from services.accel_rig.evaluate import run

    base = dict(seconds=10.0, seed=2, json=True, runs=3, layout="marvin-six", poses="thesis",
                pose_seconds=2.0)
    plain = run(Namespace(**base))
    fig = run(Namespace(**base, noise_draws=2))
    assert fig["calibration"] == plain["calibration"]
    for key in ("0.25s", "2s"):
        own, draws = fig["nees"][key], fig["nees"][key]["noise_draws"]
        assert {k: v for k, v in own.items() if k != "noise_draws"} == plain["nees"][key]
        assert draws["draws"] == len(draws["means"]) == 2
        assert len({own["mean"], *draws["means"]}) == 3
        assert 0 <= draws["draws_within_bounds"] <= 2 and draws["spread_ratio"] >= 0
        assert draws["pooled_mean"] == pytest.approx(np.mean([own["mean"], *draws["means"]]))
    with pytest.raises(ValueError, match="--noise-draws"):
        run(Namespace(**base, noise_draws=-1))


def test_eval_random_streams_are_all_apart():
    """The eval's random streams over seeds 1-20 are all different: each run's noise in
    each draw, the start times, the trajectory's parameters, the device's errors and the
    calibration poses' noise.  A run that drew another seed's calibration noise, or start
    times that were the trajectory's own draws, would tie what the bands take as
    independent."""
    from services.accel_rig.evaluate import (
        _STARTS,
        _device_seed,
        _noise_streams,
        _pose_seed,
        _stream,
    )

    seeds = []
    for s in range(1, 21):
        seeds += [s, _device_seed(s), _stream(s, _STARTS)]
        seeds += [_pose_seed(s, i) for i in range(len(SIX_POSES))]
        seeds += [x for k in range(3) for x in _noise_streams(s, k, 100)]
    first = {tuple(np.random.default_rng(x).bit_generator.random_raw(2)) for x in seeds}
    assert len(first) == len(seeds) == 20 * (3 + 6 + 300)


def test_eval_runs_do_not_depend_on_each_other():
    """A run's errors follow from its start time and its noise stream alone: the same runs
    in the reverse order, two of them overlapping in time, give the same figures to the
    bit, so nothing carries over from one run to the next."""
    from services.accel_rig.evaluate import _noise_streams, _runs

    device = default_device()
    cal = device.calibration(RATE)
    traj = HeadTrajectory(3)
    starts = np.array([4.0, 4.1, 9.0])
    streams = _noise_streams(3, 0, len(starts))
    ahead = _runs(device, cal, traj, starts, streams, RATE)
    back = _runs(device, cal, traj, starts[::-1], streams[::-1], RATE)
    assert np.array_equal(ahead.nees, back.nees[::-1])
    assert np.array_equal(ahead.err, back.err[:, ::-1])
    assert len(set(ahead.nees[:, 0])) == 3


def test_nees_shape_tells_an_honest_covariance_from_one_of_the_right_size_only():
    """Honest Gaussian errors: two 3-dof parts of mean 3, uncorrelated, NEES variance 12.
    Errors whose scale varies from run to run (the covariance right on average) keep the
    mean, raise the variance and correlate the parts."""
    from services.accel_rig.evaluate import _shape

    rng = np.random.default_rng(3)
    n = 4000
    A = rng.normal(size=(n, 6, 6))
    cov = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(6)
    white = rng.standard_normal((n, 6))
    err = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), white)
    honest = _shape(err, cov)
    assert 2.8 < honest["orientation_nees"] < 3.2
    assert 2.8 < honest["position_given_orientation_nees"] < 3.2
    assert 10.5 < honest["nees_variance"] < 13.5
    assert abs(honest["orientation_position_correlation"]) < 0.06
    scale = np.sqrt(rng.choice([0.5, 1.5], n))  # right on average, wrong run by run
    mixed = _shape(err * scale[:, None], cov)
    assert 5.6 < mixed["orientation_nees"] + mixed["position_given_orientation_nees"] < 6.4
    assert mixed["nees_variance"] > 18 and mixed["orientation_position_correlation"] > 0.1
