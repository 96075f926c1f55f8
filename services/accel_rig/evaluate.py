"""``uma eval accel-rig``: calibration and dead-reckoning accuracy against simulated truth.

1. Calibrate a simulated device (random bias and gain errors, table 4.1 axes, appendix C
   noise, 110 Hz response, 12-bit A/D averaging 8 conversions) from static poses, as seed
   003 §4.4.2, and compare with the device's true parameters.
2. From random starting points of the head trajectory, reset the dead reckoner to the true
   state and integrate the simulated samples for 2 s (Hogue 2003, §4.3); measure orientation
   and position error after 0.25, 0.5, 1 and 2 s, and the normalised estimation error
   squared (NEES) of the reported 6-dof pose covariance against its chi-square bounds.

The runs of one seed share one calibration, hence one calibration error: their NEES are
not independent, and the band of their mean counts that shared error once
(``services.consistency.shared_error_effective_runs``, from the covariance and calibration
sensitivity each estimate reports).  The band of as many independent runs, narrower, is
reported beside it (``bounds_95_independent_runs``).  Otherwise the runs are independent:
each draws its noise from a stream of its own, and the start times come from another,
apart from the trajectory's and the calibration's (``_stream``).

Per horizon, ``shape`` says whether the covariance has the errors' shape as well as their
size (the NEES split into orientation and position given orientation, the per-run NEES
variance: 12 for an honest 6-dof Gaussian), and ``--noise-draws K`` repeats the runs with
fresh sensor noise on the same rig, calibration, trajectory and start times, which tells a
seed that misses its band by its draw from one that misses by its rig; ``calibration_share``
says what this seed's calibration error (known to the simulator) adds to its runs' mean
NEES against what the calibration covariance expects of it, and ``calibration.nees`` is
that error against its covariance (``nees_dof`` = 4 per accelerometer).

The calibration is handed the device's true noise model and latency (``_calibrate``; the
output's ``given_by_simulator`` says so): it estimates biases, gains and axes, and the
covariance it reports rests on a noise model a real rig would have to measure.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.accel_rig import sensor as sn
from services.accel_rig.calibration import (
    POSE_SETS,
    StaticRecording,
    calibrate,
    calibration_errors,
)
from services.accel_rig.device_options import (
    device_figures,
    device_from_args,
)
from services.accel_rig.integrator import calibration_covariance, dead_reckon_from_truth
from services.accel_rig.rig import RigLayout, layout_by_name
from services.accel_rig.simulator import (
    DEFAULT_RATE_HZ,
    SensorTruth,
    axis_down_quaternion,
    simulate,
    simulate_static,
)
from services.consistency import shared_error_nees_figures
from services.sim.trajectory import HeadTrajectory

HORIZONS_S = (0.25, 0.5, 1.0, 2.0)


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The figures of the evaluation as a JSON-serialisable dict."""
    horizon = max(HORIZONS_S)
    if args.seconds <= horizon + 0.1:
        raise InvalidInputError(
            f"--seconds must exceed {horizon + 0.1:g}: the runs start at random "
            f"times in the first (seconds - {horizon:g}) s of the trajectory")
    if args.runs < 1:
        raise InvalidInputError("--runs must be at least 1")
    noise_draws = getattr(args, "noise_draws", 0)
    if not 0 <= noise_draws <= 100:
        raise InvalidInputError(f"--noise-draws must be within 0..100, got {noise_draws!r}")
    if not (math.isfinite(args.pose_seconds) and args.pose_seconds > 0):
        raise InvalidInputError("--pose-seconds must be positive")
    rate = DEFAULT_RATE_HZ
    nominal = layout_by_name(args.layout)
    truth_layout = layout_by_name("marvin-six-table-4.1") if args.layout == "marvin-six" \
        else nominal
    device = device_from_args(SensorTruth.draw(_device_seed(args.seed), truth_layout), args)
    cal, cal_figures = _calibrate(device, nominal, POSE_SETS[args.poses], args.pose_seconds,
                                  rate, args.seed)
    errors = _dead_reckon(device, cal, args.seed, args.runs, args.seconds - horizon, rate,
                           noise_draws)
    return {"seed": args.seed, "runs": args.runs, "rate_hz": rate, "layout": args.layout,
            "accel_device": device_figures(device),
            "given_by_simulator": {
                "accel_noise_model": "the simulated device's own (_calibrate hands "
                                     "device.noise_model() to the calibration)",
                "accel_latency_s": device.latency_s(rate),
                "start_state": "each dead-reckoning run starts from the true state"},
            "calibration": cal_figures, **errors}


def _calibrate(device: SensorTruth, nominal: RigLayout, labels: Sequence[str], seconds: float,
               rate: float, seed: int) -> tuple[sn.Calibration, dict[str, Any]]:
    """The device calibrated for the ``nominal`` layout from ``seconds`` held still in each
    of the poses ``labels`` (their noise the seed's), and how far it is from the device's
    true parameters."""
    recs = [StaticRecording(axis_down_quaternion(lab),
                            simulate_static(axis_down_quaternion(lab), seconds, rate,
                                            seed=_pose_seed(seed, i), sensor=device))
            for i, lab in enumerate(labels)]
    cal = calibrate(nominal, recs, rate, noise=device.noise_model(),
                    latency_s=device.latency_s(rate))
    err = calibration_errors(cal, device.bias_v, device.gain_v_per_mps2, device.layout.axes)
    c = _calibration_error(device, cal)
    return cal, {
        "nees": float(c @ np.linalg.solve(calibration_covariance(cal), c)),
        "nees_dof": int(c.size),
        "poses": list(labels), "seconds_per_pose": seconds,
        "bias_lsb_max": float(np.abs(err.bias_lsb).max()),
        "bias_lsb_rms": float(np.sqrt(np.mean(err.bias_lsb**2))),
        "scale_percent_max": float(np.abs(err.scale_percent).max()),
        "axis_deg_max": float(np.abs(err.axis_deg).max()),
        "uncalibrated_bias_lsb_max": float(np.abs(device.bias_v).max() / sn.LSB_V),
        "uncalibrated_scale_percent_max": float(100 * np.abs(device.scale_error).max()),
    }


class _Runs(NamedTuple):
    """Per run (rows) and horizon (columns): errors, NEES and what the band needs."""

    ori: np.ndarray  # (runs, horizons) deg
    pos: np.ndarray  # (runs, horizons) m
    nees: np.ndarray  # (runs, horizons)
    err: np.ndarray  # (horizons, runs, 6) [position error, world rotation error]
    cov: np.ndarray  # (horizons, runs, 6, 6) its reported covariance
    sens: np.ndarray  # (horizons, runs, 6, 4N) its calibration sensitivity


def _dead_reckon(device: SensorTruth, cal: sn.Calibration, seed: int, runs: int,
                 start_span_s: float, rate: float, noise_draws: int = 0) -> dict[str, Any]:
    traj = HeadTrajectory(seed)
    starts = np.random.default_rng(_stream(seed, _STARTS)).uniform(0.0, start_span_s, runs)
    first, *draws = [_runs(device, cal, traj, starts, _noise_streams(seed, k, runs), rate)
                     for k in range(noise_draws + 1)]
    out: dict[str, Any] = {"orientation_error_deg": {}, "position_error_m": {},
                           "nees": {"dof": 6}}
    cal_cov = calibration_covariance(cal)
    for i, h in enumerate(HORIZONS_S):
        key = f"{h:g}s"
        out["orientation_error_deg"][key] = _stats(first.ori[:, i])
        out["position_error_m"][key] = _stats(first.pos[:, i])
        figures = _nees_figures(first.nees[:, i], first.cov[i], first.sens[i], cal_cov)
        figures["shape"] = _shape(first.err[i], first.cov[i])
        if cal_cov is not None:
            figures["calibration_share"] = _calibration_share(
                first.cov[i], first.sens[i], cal_cov, _calibration_error(device, cal))
        if draws:
            figures["noise_draws"] = _draw_figures(
                [_nees_figures(d.nees[:, i], d.cov[i], d.sens[i], cal_cov) for d in draws],
                figures)
        out["nees"][key] = figures
    one = HORIZONS_S.index(1.0)
    out["goals"] = {
        "median_orientation_error_1s_le_1deg": bool(np.median(first.ori[:, one]) <= 1.0),
        "nees_1s_within_95_bounds": out["nees"]["1s"]["within_bounds"],
        "nees_within_factor_2_all_horizons": bool(all(
            0.5 <= out["nees"][f"{h:g}s"]["ratio_to_dof"] <= 2.0 for h in HORIZONS_S)),
    }
    return out


#: Spawn keys of a seed's random streams (``_stream``): the runs' start times, and the
#: sensor noise of each run in each draw (draw 0 the eval's own, 1.. the ``--noise-draws``).
_STARTS, _RUN_NOISE = 0, 1


def _stream(seed: int, *key: int) -> np.random.SeedSequence:
    """The seed's random stream ``key``.  A spawn key keeps it apart from every stream seeded
    by a plain integer: the trajectory's (``seed``), the device's and the calibration
    poses' noise, whose integers could equal another seed's run's, and from every other
    key; so start times, runs and seeds are independent as the bands assume."""
    return np.random.SeedSequence(seed, spawn_key=key)


def _device_seed(seed: int) -> int:
    """The integer seed of the seed's simulated device (its biases and gain errors)."""
    return 1000 + seed


def _pose_seed(seed: int, pose: int) -> int:
    """The integer seed of the noise of the seed's calibration pose ``pose``."""
    return 10_000 * seed + pose


def _noise_streams(seed: int, draw: int, runs: int) -> list[np.random.SeedSequence]:
    """The sensor noise of the runs of draw ``draw`` (0: the eval's own)."""
    return [_stream(seed, _RUN_NOISE, draw, r) for r in range(runs)]


def _runs(device: SensorTruth, cal: sn.Calibration, traj: HeadTrajectory, starts: np.ndarray,
          noise_seeds: list[np.random.SeedSequence], rate: float) -> _Runs:
    """Dead-reckon from the truth at each start time, with that run's noise seed."""
    steps = [round(h * rate) for h in HORIZONS_S]
    runs = len(starts)
    ori = np.empty((runs, len(steps)))
    pos = np.empty_like(ori)
    nees = np.empty_like(ori)
    err = np.empty((len(steps), runs, 6))
    cov = np.empty((len(steps), runs, 6, 6))
    sens = np.zeros((len(steps), runs, 6, 4 * cal.layout.count))
    for r, (t0, noise_seed) in enumerate(zip(starts, noise_seeds, strict=True)):
        sim = simulate(traj, max(HORIZONS_S) + 1.5 / rate, rate, seed=noise_seed,
                       t0=float(t0), sensor=device, calibration=cal)
        est = dead_reckon_from_truth(cal, sim.t, sim.accel, sim.truth, rate)
        for i, k in enumerate(steps):
            e, s = est[k], sim.truth
            dp = s.position[k] - e.position
            dth = geo.quat_to_rotvec(geo.quat_multiply(s.quaternion[k],
                                                       geo.quat_conjugate(e.quaternion)))
            x = np.concatenate([dp, dth])
            ori[r, i] = math.degrees(float(np.linalg.norm(dth)))
            pos[r, i] = float(np.linalg.norm(dp))
            nees[r, i] = float(x @ np.linalg.solve(e.decoupled_covariance, x))
            err[i, r] = x
            cov[i, r] = e.decoupled_covariance
            if e.calibration_sensitivity is not None:
                sens[i, r] = _decoupled_rows(e.position, e.calibration_sensitivity)
    return _Runs(ori, pos, nees, err, cov, sens)


def _decoupled_rows(position: np.ndarray, sensitivity: np.ndarray) -> np.ndarray:
    """An SE(3) pose error's sensitivity ``[rho; phi]`` as one of ``[dp; dtheta]``
    (``dp = rho + phi x p``, the conversion of ``geometry.se3_to_decoupled``)."""
    rho, phi = sensitivity[:3], sensitivity[3:]
    return np.vstack([rho - np.cross(position, phi, axis=0), phi])


def _nees_figures(nees: np.ndarray, cov: np.ndarray, sens: np.ndarray,
                  cal_cov: np.ndarray | None) -> dict[str, Any]:
    """One horizon's mean NEES against the band that counts the runs' shared calibration
    error once, and against the stricter band of independent runs."""
    figures = shared_error_nees_figures(nees, cov, sens, cal_cov)
    return {**figures, "ratio_to_dof": figures["mean"] / 6.0}


def _shape(err: np.ndarray, cov: np.ndarray) -> dict[str, float | None]:
    """Whether the covariance has the errors' shape, not only their size.  Whitened by it,
    orientation first and then position given orientation, the errors of an honest Gaussian
    covariance split the NEES into two independent parts of 3 dof (mean 3 each, correlation
    0), and the per-run NEES has variance 12.  A mean of 6 from errors of another shape has
    a larger variance, so the means of 100 runs spread wider than their band assumes; a
    correlation says how: large orientation errors come with large position errors."""
    order = [3, 4, 5, 0, 1, 2]
    L = np.linalg.cholesky(cov[:, order][:, :, order])
    z = np.linalg.solve(L, err[:, order, None])[..., 0]
    rot, pos = (z[:, :3] ** 2).sum(axis=1), (z[:, 3:] ** 2).sum(axis=1)
    several = len(z) > 1 and np.ptp(rot) > 0 and np.ptp(pos) > 0
    return {"nees_variance": float(np.var(rot + pos, ddof=1)) if len(z) > 1 else None,
            "orientation_nees": float(rot.mean()),
            "position_given_orientation_nees": float(pos.mean()),
            "orientation_position_correlation":
                float(np.corrcoef(rot, pos)[0, 1]) if several else None}


def _calibration_error(device: SensorTruth, cal: sn.Calibration) -> np.ndarray:
    """The calibration's error in its parameters ``[bias, gain * axis]`` per accelerometer
    (true minus estimated, the order of ``calibration_covariance``): the simulator knows it."""
    true = np.column_stack([device.bias_v, device.gain_v_per_mps2[:, None] * device.layout.axes])
    est = np.column_stack([cal.bias_v, cal.gain_v_per_mps2[:, None] * cal.axes])
    return (true - est).ravel()


def _calibration_share(cov: np.ndarray, sens: np.ndarray, cal_cov: np.ndarray,
                       cal_error: np.ndarray) -> dict[str, float]:
    """What this calibration's error adds to the runs' mean NEES, ``c^T M c`` with ``M`` the
    runs' mean ``S^T C^-1 S``, against what the calibration covariance expects of it,
    ``tr(M C_cal)``.  Every run of a seed shares the error, so one calibration drawn far
    out in the directions the pose is sensitive to moves the whole seed's mean: the seed
    then misses its band by its rig, not by its runs' noise."""
    M = np.einsum("rdi,rdj->ij", sens, np.linalg.solve(cov, sens)) / len(cov)
    return {"expected": float(np.einsum("ij,ji->", M, cal_cov)),
            "this_calibration": float(cal_error @ M @ cal_error)}


def _draw_figures(draws: list[dict[str, Any]], own: dict[str, Any]) -> dict[str, Any]:
    """The mean NEES of fresh noise draws on the same rig, calibration, trajectory and start
    times, beside the eval's own.  A seed outside its band in the eval's draw and inside in
    fresh ones missed by its draw; one outside in all of them by its rig.  ``spread_ratio``:
    the variance of the draws' means (the eval's included) over what honest runs allow
    (``2 dof / effective_runs``), 1 on average; above it, the runs of one draw share an
    error the band does not count."""
    means = [own["mean"], *(d["mean"] for d in draws)]
    return {"draws": len(draws), "means": [d["mean"] for d in draws],
            "draws_within_bounds": sum(d["within_bounds"] for d in draws),
            "pooled_mean": float(np.mean(means)),
            "spread_ratio": float(np.var(means, ddof=1) * own["effective_runs"] / 12.0)}


def _stats(x: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95))}
