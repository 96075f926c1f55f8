"""``uma eval fusion``: the whole simulated MARVIN against ground truth (Hogue 2003, ch. 6).

Pipeline, all real components:

* optical: ``IvyWorld`` renders the six camera images at 15 Hz, ``LaserTracker`` turns
  them into laser-rig poses with covariance (its calibration from the simulated
  calibration images, cached on disk because it takes ~20 s);
* inertial: the accelerometer simulator (appendix C.1 device: bias, gain and axis errors,
  noise, 110 Hz response, 12-bit A/D averaging 8 conversions) at 300 Hz, calibrated by
  the static procedure of §4.4.2 before the run (``--accel-noise-uv`` and friends run
  another device of the same design);
* the static mountings head -> laser rig and head -> accelerometer rig come from an SRG
  (``agent.srg.Graph`` static edges), as in the service;
* optical dropouts: the laser frames of scheduled gaps (0.25, 0.5, 1 s by default) are
  withheld; the filter runs on the accelerometers alone and must recover afterwards.

Figures, evaluated at every inertial sample (300 Hz) after a warm-up: RMSE and max of
position and orientation for the fused pose and for the two causal optical-only
baselines (hold the last optical pose; constant-velocity extrapolation of the last two,
at most one optical frame beyond the last), each over all samples, inside the gaps (a
scheduled gap and the RECOVERY_FRAMES frames after it) and outside them; the worst error
inside each gap length, the time to recover after each gap, the error of the pose
predicted +20 ms ahead, NEES against chi-square bounds, and the filter's updates per second
of CPU time.  What is left out is counted (``samples``: inertial samples while the filter
was not running, the warm-up, non-finite outputs; ``filter_events``: starts, restarts and
rejected measurements); no figure skips a NaN.

What the run is handed from the simulator instead of measuring it is listed under
``given_by_simulator``: the accelerometer calibration gets the device's true noise model
and latency (``calibrated_accelerometers``) and its true positions (it calibrates biases,
gains and axes); the rig mountings are the simulator's.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.special import erf
from scipy.stats import chi2

from agent import Graph
from agent import geometry as geo
from agent.errors import InvalidInputError
from services import consistency, frames
from services.accel_rig import simulator as accel_sim
from services.accel_rig.device_options import (
    device_figures,
    device_from_args,
)
from services.consistency import autocorrelation_time
from services.fusion.dots import display_walls, update_dots
from services.fusion.ekf import FusionEKF, FusionStats
from services.fusion.plugin import GAP_SPACING_S
from services.fusion.state import MODEL_FLOOR, AccelModel, FusionConfig
from services.laser_camera import plugin as laser_plugin
from services.sim import mounts
from services.sim.calibrations import calibrated_accelerometers, laser_calibration
from services.sim.world import IvyWorld

log = logging.getLogger("uma.eval")

OPTICAL_HZ = 15.0
WARMUP_S = 3.0
#: optical frames after a scheduled gap still counted inside it (the filter recovering)
RECOVERY_FRAMES = 3
#: output error within which the filter counts as recovered: a few times its normal error
RECOVERY_FACTOR = 3.0
RECOVERY_HOLD_S = 0.1
#: seconds after a (re)start over which its error is held to the optical pose's plus what
#: the filter's covariance claims
RESET_WINDOW_S = 2.0
#: what a covariance claims of a 3-D error at one dimension's 3 sigma: the squared
#: Mahalanobis distance its Gaussian exceeds with probability 0.0027 (chi-square(3))
CLAIM_99_73 = float(chi2.ppf(erf(3.0 / math.sqrt(2.0)), 3))


# ---------------------------------------------------------------------- set-up


def static_mounts(graph: Graph) -> tuple[tuple[np.ndarray, np.ndarray],
                                         tuple[np.ndarray, np.ndarray]]:
    """Head -> accelerometer rig and head -> laser rig, queried from the SRG."""
    a = graph.pose(frames.HEAD, frames.ACCEL_RIG)
    laser = graph.pose(frames.HEAD, frames.LASER_RIG)
    return (a.position, a.quaternion), (laser.position, laser.quaternion)


def simulation_graph() -> Graph:
    """The SRG of the simulated set-up: the rig mountings as static edges."""
    g = Graph()
    g.add_static(frames.HEAD, frames.ACCEL_RIG, *mounts.HEAD_TO_ACCEL_RIG)
    g.add_static(frames.HEAD, frames.LASER_RIG, *mounts.HEAD_TO_LASER_RIG)
    return g


def accel_model(cal: Any, head_to_accel: tuple[np.ndarray, np.ndarray], rate_hz: float,
                model_floor: float) -> AccelModel:
    """The filter's view of the calibrated accelerometers, moved into the head frame."""
    return AccelModel.from_layout(cal.layout.positions, cal.layout.axes, head_to_accel,
                                  cal.accel_var(rate_hz), cal.latency_s, model_floor)


def gap_schedule(seconds: float, lengths: list[float]) -> list[tuple[float, float]]:
    """Optical gaps (start, end): cycling through ``lengths``, GAP_SPACING_S apart."""
    gaps, t, k = [], WARMUP_S + 2.0, 0
    while lengths and t + lengths[k % len(lengths)] < seconds - 1.0:
        length = lengths[k % len(lengths)]
        gaps.append((t, t + length))
        t += length + GAP_SPACING_S
        k += 1
    return gaps


# ---------------------------------------------------------------------- the run


@dataclass
class Recording:
    """Per inertial sample: motion time, fused pose, covariance, prediction; optical log."""

    t: np.ndarray
    p: np.ndarray
    q: np.ndarray
    cov: np.ndarray          # (n, 6, 6) over [dp, dtheta] (position, world rotation)
    p_pred: np.ndarray
    q_pred: np.ndarray
    optical_t: np.ndarray    # times of optical poses the filter received
    optical_p: np.ndarray    # head poses from them
    optical_q: np.ndarray
    cpu_s: float
    stats: FusionStats       # the filter's counts at the end of the run
    optical_failures: dict[str, int]
    #: motion times of the inertial samples that came while the filter was not running
    #: (before its first start, or after a restart left it waiting for two poses)
    uninitialised_t: np.ndarray
    #: dot mode: the tracker's counts of dots labeled by prediction and left unlabeled
    dot_labels: dict[str, int] = field(default_factory=dict)
    #: times of the filter's starts, the first and every restart (its ``start_t``)
    starts: np.ndarray = field(default_factory=lambda: np.zeros(0))


def run_fusion(seconds: float, seed: int, gaps: list[tuple[float, float]], horizon_s: float,
               config: FusionConfig, model_floor: float, cache: bool,
               dots: bool = False, device: Any = None, ideal: bool = False,
               estimate_installation: bool = True) -> Recording:
    """Render, track, simulate and fuse ``seconds`` of motion; record everything.

    ``dots``: SCAAT with the laser dots one at a time instead of the tracker's pose (the
    pose only initialises the filter and brings its systematic covariance); frames where
    the tracker found no pose still contribute the dots it can label by the pose it
    predicts (``LaserTracker.label_dots``), as the live service publishes them.
    ``estimate_installation``: whether the tracker corrects its poses and dots by its
    online estimate of the installation (``TrackerParams.estimate_installation``).
    """
    from services.laser_camera.tracker import LaserTracker, TrackerParams

    # realistic unless ``ideal`` (docs/SIMULATION.md); every seed another housing and screens
    world = IvyWorld(seed=seed, ideal=ideal, imperfection_seed=seed)
    head_to_accel, head_to_laser = static_mounts(simulation_graph())
    rate = accel_sim.DEFAULT_RATE_HZ
    device, cal = calibrated_accelerometers(rate, seed, device)
    accel = accel_sim.simulate(world.trajectory, seconds, rate, seed=seed, sensor=device,
                               calibration=cal)
    tracker = LaserTracker(laser_calibration(world, cache), (
        TrackerParams.ideal if ideal else TrackerParams)(
        estimate_installation=estimate_installation))
    walls = display_walls(tracker.calibration)
    ekf = FusionEKF(accel_model(cal, head_to_accel, rate, model_floor), config)
    frames = [k / OPTICAL_HZ for k in range(int(seconds * OPTICAL_HZ))
              if not any(a <= k / OPTICAL_HZ < b for a, b in gaps)]
    motion_t = accel.t - cal.latency_s
    n = len(motion_t)
    rec = {k: [] for k in ("t", "p", "q", "cov", "pp", "qp")}
    opt_t, opt_p, opt_q, failures, waiting, starts = [], [], [], {}, [], []
    cpu, k_frame = 0.0, 0
    pm, qm = geo.inverse(*head_to_laser)
    for i in range(n):
        while k_frame < len(frames) and frames[k_frame] <= motion_t[i]:
            t_f = frames[k_frame]
            k_frame += 1
            images = world.render(t_f).images
            result = tracker.process(images, t_f)
            if dots and ekf.initialised:
                c0 = time.process_time()
                if result.ok:
                    ekf.carry_rig_systematic(result.position, result.quaternion,
                                             result.systematic, head_to_laser)
                update_dots(ekf, tracker.label_dots(result), walls, head_to_laser)
                cpu += time.process_time() - c0
            if not result.ok:
                failures[result.reason] = failures.get(result.reason, 0) + 1
                continue
            if not dots or not ekf.initialised:
                c0 = time.process_time()
                ekf.update_rig_pose(t_f, result.position, result.quaternion,
                                    result.covariance, head_to_laser, result.systematic)
                cpu += time.process_time() - c0
            hp, hq = geo.compose(result.position, result.quaternion, pm, qm)
            opt_t.append(t_f)
            opt_p.append(hp)
            opt_q.append(hq)
        if ekf.start_t is not None and (not starts or starts[-1] != ekf.start_t):
            starts.append(ekf.start_t)
        if not ekf.initialised:
            waiting.append(motion_t[i])
            continue
        c0 = time.process_time()
        ekf.update_accel_sample(accel.t[i], accel.accel[i])
        p, q = ekf.pose()
        pp, qp = ekf.pose(horizon_s)
        cpu += time.process_time() - c0
        rec["t"].append(ekf.t)
        rec["p"].append(p)
        rec["q"].append(q)
        rec["cov"].append(ekf.pose_covariance_decoupled())
        rec["pp"].append(pp)
        rec["qp"].append(qp)
    return Recording(np.array(rec["t"]), np.array(rec["p"]), np.array(rec["q"]),
                     np.array(rec["cov"]), np.array(rec["pp"]), np.array(rec["qp"]),
                     np.array(opt_t), np.array(opt_p).reshape(-1, 3),
                     np.array(opt_q).reshape(-1, 4), cpu, ekf.stats, failures,
                     np.array(waiting),
                     {k: v for k, v in tracker.counts.items() if k.startswith("dot_")},
                     np.array(starts))


# ---------------------------------------------------------------------- baselines


def optical_baselines(rec: Recording) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Causal optical-only estimates at the output times (each after an optical pose: the
    filter starts from two).

    ``hold_last`` keeps the last optical pose; ``constant_velocity`` extrapolates the last
    two at most one optical frame beyond the last and holds that pose after it.  Unlimited,
    the extrapolation ran ~16 frames through a 1 s gap, up to 0.6 m and 120 deg off (seed
    1), and made the baseline look worse than holding where it is better outside gaps.
    """
    k = np.searchsorted(rec.optical_t, rec.t, side="right") - 1
    if np.any(k < 0):
        raise InvalidInputError("fusion eval: an output before the first optical pose")
    hold_p, hold_q = rec.optical_p[k], rec.optical_q[k]
    k0 = np.clip(k - 1, 0, None)
    dt = rec.optical_t[k] - rec.optical_t[k0]
    ahead = np.minimum(rec.t - rec.optical_t[k], 1.0 / OPTICAL_HZ)
    safe = np.where(dt > 0, dt, 1.0)
    alpha = np.where(dt > 0, 1.0 + ahead / safe, 1.0)
    cv_p, cv_q = geo.interpolate(rec.optical_p[k0], rec.optical_q[k0], hold_p, hold_q, alpha)
    return {"hold_last": (hold_p, hold_q), "constant_velocity": (cv_p, cv_q)}


# ---------------------------------------------------------------------- figures


def _rms(x: np.ndarray) -> float:
    """Root mean square; NaN if ``x`` is empty or holds a NaN (never skipped)."""
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else float("nan")


def _max(x: np.ndarray) -> float:
    return float(np.max(x)) if x.size else float("nan")


def _err_figures(ep: np.ndarray, er: np.ndarray) -> dict[str, float]:
    return {"samples": int(ep.size),
            "position_rmse_mm": 1e3 * _rms(ep), "position_max_mm": 1e3 * _max(ep),
            "orientation_rmse_deg": math.degrees(_rms(er)),
            "orientation_max_deg": math.degrees(_max(er))}


def nees_figures(rec: Recording, p_true: np.ndarray, q_true: np.ndarray,
                 mask: np.ndarray) -> dict[str, Any]:
    """NEES of the 6-D pose error and the 95 % chi-square bounds of its mean.

    The bounds chi2(6 k) / k hold for the mean of k *independent* samples.  The 300 Hz
    errors are far from independent (an error lives as long as the filter takes to
    correct it), so k is the effective sample count n / tau, tau the integrated
    autocorrelation time of the NEES series itself: the mean of correlated samples varies
    tau times more than that of independent ones.  The bounds one would get counting one
    independent sample per optical frame are reported too, the share of single
    samples inside chi-square(6)'s two-sided 95 % interval (0.95 for an honest filter),
    and the mean NEES of the position and rotation parts (3 each when honest) while
    tracking and inside optical outages, where a filter can be honest in one regime and
    not in the other while the overall mean hides it.  ``tracking_beyond_3_sigma``: the
    reset bound's strict figure while tracking, position and rotation, each with the
    share a Gaussian error of the same covariances gives (``beyond_3_sigma``), and
    ``tracking_beyond_claim``: the share beyond the covariance's 99.73 % ellipsoid, the
    reset bound's test (0.0027 for a Gaussian error of any covariance): whether the
    errors' tails are heavier than the covariance says.

    ``errors_about_zero`` is ``services.consistency``'s figure of the same errors, the one
    the goal reads (as the laser tracker's does): its effective sample count comes from the
    errors' autocorrelation about zero, so an error that lasts the whole run (the
    installation's, carried by the fused covariance) counts as the one sample it is.  The
    errors go in whitened by their covariances (``whitened``), as the NEES sums them: in
    the optical outages the error grows several times larger for up to a second, and
    unwhitened those outages (an eighth of the samples, most of the squared error) set the
    count, as if the run held a dozen samples where its NEES, made while tracking, holds
    one.  The NEES
    series' autocorrelation about its own mean cannot see an error that lasts the run (it
    is part of that mean), so its band (``bounds_95``, ``within_bounds_about_own_mean``) is
    far narrower than the run's information on the realistic installation; it is reported
    for the ideal one, where the two agree.
    """
    e = error_vectors(rec.p, rec.q, p_true, q_true)[mask]
    cov = rec.cov[mask]
    w = whitened(e, cov, rec.t[mask])
    nees = np.einsum("ni,ni->n", w, w)
    tau = autocorrelation_time(nees, about="mean")
    k = nees.size / tau
    span = float(rec.t[mask][-1] - rec.t[mask][0]) if mask.any() else 0.0
    k_frames = max(1, int(span * OPTICAL_HZ))
    lo, hi = _mean_bounds(k)
    lo_1, hi_1 = chi2.ppf([0.025, 0.975], 6)
    tracking = _tracking(rec, mask)
    inside = (nees >= lo_1) & (nees <= hi_1)
    mean = float(np.mean(nees))
    return {"mean": mean, "bounds_95": [lo, hi], "effective_samples": k,
            "autocorrelation_time_s": tau * span / max(1, nees.size - 1),
            "bounds_95_one_sample_per_optical_frame": list(_mean_bounds(k_frames)),
            "share_inside_single_95": float(np.mean(inside)),
            "by_regime": _nees_by_regime(rec, e, cov, mask),
            "tracking_beyond_3_sigma": {
                part: beyond_3_sigma(e[tracking, b], cov[tracking][:, b, b])
                for part, b in (("position", slice(0, 3)), ("rotation", slice(3, 6)))},
            "tracking_beyond_claim": {
                part: float(np.mean(_mahalanobis_sq(e[tracking, b], cov[tracking][:, b, b])
                                    > CLAIM_99_73)) if tracking.any() else float("nan")
                for part, b in (("position", slice(0, 3)), ("rotation", slice(3, 6)))},
            "errors_about_zero": consistency.nees_figures(w, np.broadcast_to(
                np.eye(6), cov.shape)),
            "within_bounds_about_own_mean": bool(lo <= mean <= hi)}


def whitened(e: np.ndarray, cov: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Errors (n, d) at motion times ``t`` (n,) whitened by their covariances (n, d, d):
    ``L^-1 e`` with ``L L^T`` the covariance, whose squared norm is the NEES.  The filter
    keeps its covariances symmetric, not provably positive definite (``P_random``'s
    scalar updates subtract); a published one that is not, or is not finite, has no NEES,
    and the eval names the sample instead of a LinAlgError or a NaN mean."""
    finite = np.isfinite(cov).all(axis=(-2, -1))
    if finite.all():
        try:
            return np.linalg.solve(np.linalg.cholesky(cov), e[..., None])[..., 0]
        except np.linalg.LinAlgError:
            least = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2)))[:, 0]
            k = int(np.argmin(least))
            why = f"not positive definite (least eigenvalue {least[k]:.3g})"
    else:
        k = int(np.argmin(finite))
        why = "not finite"
    raise InvalidInputError(f"fusion eval: the fused covariance at t = {t[k]:.4f} s "
                            f"(sample {k}) is {why}: it has no NEES")


def _tracking(rec: Recording, mask: np.ndarray) -> np.ndarray:
    """Which samples of ``mask`` come while tracking: the last optical pose at most two
    frames old (the rest lie in outages)."""
    k = np.searchsorted(rec.optical_t, rec.t[mask], side="right") - 1
    age = rec.t[mask] - rec.optical_t[np.clip(k, 0, None)]
    return age <= 2.0 / OPTICAL_HZ


def _nees_by_regime(rec: Recording, e: np.ndarray, cov: np.ndarray,
                    mask: np.ndarray) -> dict[str, dict[str, float]]:
    """Position and rotation NEES while tracking (``_tracking``) and in outages."""
    tracking = _tracking(rec, mask)
    out = {}
    for name, sel in (("tracking", tracking), ("optical_gap", ~tracking)):
        if not sel.any():
            continue
        parts = {}
        for part, b in (("position", slice(0, 3)), ("rotation", slice(3, 6))):
            x = e[sel, b]
            parts[f"{part}_mean"] = float(np.mean(np.einsum(
                "ni,ni->n", x, np.linalg.solve(cov[sel][:, b, b], x[..., None])[..., 0])))
        out[name] = {"share": float(np.mean(sel)), **parts}
    return out


def error_vectors(p: np.ndarray, q: np.ndarray, p_true: np.ndarray, q_true: np.ndarray,
                  ) -> np.ndarray:
    """The fused poses' errors (n, 6): position (truth less estimate) and rotation vector
    (truth times the estimate's inverse), the order and frames of the filter's covariance."""
    return np.concatenate([p_true - p, geo.quat_to_rotvec(
        geo.quat_multiply(q_true, geo.quat_conjugate(q)))], axis=1)


def _mahalanobis_sq(e: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``e^T C^-1 e`` of errors ``e`` (n, 3) under covariances ``cov`` (n, 3, 3)."""
    return np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[..., None])[..., 0])


def claim_reach(e: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """How far the covariance's 99.73 % ellipsoid (``CLAIM_99_73``) reaches along each
    error's own direction: ``|e| sqrt(CLAIM / e^T C^-1 e)``, (n,).  A zero error has no
    direction; it gets the ellipsoid's shortest reach (it exceeds nothing anyway)."""
    length = np.linalg.norm(e, axis=1)
    m = _mahalanobis_sq(e, cov)
    reach = length * np.sqrt(CLAIM_99_73 / np.where(m > 0, m, 1.0))
    zero = m <= 0
    if zero.any():
        reach[zero] = np.sqrt(CLAIM_99_73 * np.linalg.eigvalsh(cov[zero])[:, 0])
    return reach


def beyond_3_sigma(e: np.ndarray, cov: np.ndarray) -> dict[str, float]:
    """The reset bound's strict figure on errors ``e`` (n, 3) of covariances ``cov`` (n, 3, 3):
    the share of samples whose error's length exceeds three standard deviations of its
    covariance's largest axis, and the share a Gaussian error of those covariances puts
    there (``gaussian_share_beyond_3_sigma``), the reference an honest filter meets.

    Why the reference: for a 3-D error that share is not 1-D's 0.27 %; it lies between
    0.27 % (one axis dominant) and 2.9 % (all three alike, chi-square(3) beyond 9)."""
    lam = np.linalg.eigvalsh(cov)
    beyond = np.einsum("ni,ni->n", e, e) > 9.0 * lam[:, -1]
    return {"share": float(np.mean(beyond)) if e.size else float("nan"),
            "gaussian_share": float(np.mean(gaussian_share_beyond_3_sigma(lam)))
            if e.size else float("nan")}


#: Gauss-Legendre nodes and weights on [0, pi/2], the angle ``t`` of ``z = c sin t`` along
#: each of the two smaller axes: 24 put the share within 1e-5 of its value (relative) for
#: every ratio of the axes (against a 12,001-point grid's integral)
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(24)
_SIN, _COS = np.sin((_NODES + 1) * math.pi / 4), np.cos((_NODES + 1) * math.pi / 4)
_WEIGHTS = _WEIGHTS * math.pi / 4
#: beyond 8.5 standard deviations a normal's density (1e-16) adds nothing
_Z_MAX = 8.5
_CHUNK = 2048


def gaussian_share_beyond_3_sigma(lam: np.ndarray) -> np.ndarray:
    """P(|e| > 3 sqrt(lam_max)) for e ~ N(0, C) whose eigenvalues, ascending, are the rows
    of ``lam`` (n, 3): with ``z`` standard normal along the axes, the largest axis's
    term is below ``a = 9 - r1 z1^2 - r2 z2^2`` (``r`` the smaller eigenvalues over the
    largest) with probability ``erf(sqrt(a / 2))``, averaged over z1 and z2 where
    ``a > 0``.

    Why ``z = c sin t``: the integrand ends with a kink where ``a`` reaches 0, which a rule
    over all z (Gauss-Hermite) crosses between its nodes, several percent off where an axis
    is near the largest; integrating each axis up to that end (``c``) instead, in ``t``,
    leaves a smooth integrand (``a`` becomes a multiple of ``cos(t)^2``)."""
    r = np.clip(lam[:, :2] / lam[:, 2:], 0.0, 1.0)
    out = np.empty(len(r))
    for k in range(0, len(r), _CHUNK):  # a 60 s run's samples at once: 70 MB per array
        r1, r2 = r[k:k + _CHUNK, :1], r[k:k + _CHUNK, 1:]
        c1 = _reach(9.0, r1)
        z1 = c1 * _SIN
        a = np.maximum(9.0 - r1 * z1**2, 0.0)
        c2 = _reach(a, r2)
        z2_sq = c2[..., None] ** 2 * _SIN**2
        rest = np.maximum(a[..., None] - r2[..., None] * z2_sq, 0.0)
        inner = np.exp(-0.5 * z2_sq) * erf(np.sqrt(0.5 * rest)) * (c2[..., None] * _COS)
        below = 2.0 * np.einsum("nij,j->ni", inner, _WEIGHTS)
        out[k:k + _CHUNK] = 1.0 - np.einsum("ni,ni,i->n", np.exp(-0.5 * z1**2) * below,
                                            c1 * _COS, _WEIGHTS) / math.pi
    return out


def _reach(a: np.ndarray | float, r: np.ndarray) -> np.ndarray:
    """How far ``z`` goes along an axis of ratio ``r`` before ``r z^2`` uses up ``a``, at
    most ``_Z_MAX``."""
    with np.errstate(divide="ignore"):
        return np.minimum(np.sqrt(a / r), _Z_MAX)


def _mean_bounds(k: float) -> tuple[float, float]:
    """Two-sided 95 % bounds of the mean of k independent chi-square(6) samples."""
    return tuple(chi2.ppf([0.025, 0.975], 6 * k) / k)


def recovery_figures(rec: Recording, ep: np.ndarray, er: np.ndarray,
                     gaps: list[tuple[float, float]], normal: np.ndarray) -> dict[str, Any]:
    """Per gap length L: the worst error through L seconds without optical data, and the
    time to recover after the gap.

    The outage starts at the last optical pose the filter received before the scheduled
    gap, so "through a 1 s gap" means up to 1 s after that pose, wherever the schedule
    falls between two 15 Hz frames.  The tracker may also fail just before a scheduled
    gap (too few dots in a corner), which makes the real outage longer: ``outage_s_max``
    reports the longest one; the error past L seconds is not charged to L.

    Recovered = the fused error is back within RECOVERY_FACTOR times the 95th percentile
    of the normal (no-gap) error and stays there for RECOVERY_HOLD_S.

    Each gap also reports the filter's own standard deviation (position, orientation;
    root of the covariance's trace) at the end of its L seconds: the error the sensors'
    noise leaves after L seconds on the accelerometers alone, if the filter is honest
    there (the ``optical_gap`` NEES says whether it is).
    """
    p_lim = RECOVERY_FACTOR * float(np.percentile(ep[normal], 95))
    r_lim = RECOVERY_FACTOR * float(np.percentile(er[normal], 95))
    by_length: dict[str, dict[str, list[float]]] = {}
    for a, b_sched in gaps:
        length = b_sched - a
        d = by_length.setdefault(f"{length:g}s", {"pos": [], "rot": [], "rec": [], "out": [],
                                                   "pos_std": [], "rot_std": []})
        k = np.searchsorted(rec.optical_t, a)
        if k == 0:
            continue  # no optical pose before the gap: nothing to coast from
        start = float(rec.optical_t[k - 1])
        # the gap lasts until the next optical pose actually reaches the filter
        k = np.searchsorted(rec.optical_t, b_sched)
        b = float(rec.optical_t[k]) if k < rec.optical_t.size else float(rec.t[-1])
        inside = (rec.t >= start) & (rec.t < min(b, start + length))
        if not inside.any():
            continue
        d["out"].append(b - start)
        d["pos"].append(float(ep[inside].max()))
        d["rot"].append(float(er[inside].max()))
        end = rec.cov[np.flatnonzero(inside)[-1]]
        d["pos_std"].append(math.sqrt(float(np.trace(end[:3, :3]))))
        d["rot_std"].append(math.sqrt(float(np.trace(end[3:, 3:]))))
        d["rec"].append(_recovery_s(rec, ep, er, b, p_lim, r_lim))
    out: dict[str, Any] = {}
    for key, d in by_length.items():
        if not d["pos"]:
            continue
        worst_rec = max(d["rec"])
        out[key] = {"gaps": len(d["pos"]),
                    "outage_s_max": max(d["out"]),
                    "position_max_mm": 1e3 * max(d["pos"]),
                    "orientation_max_deg": math.degrees(max(d["rot"])),
                    "position_per_gap_mm": [round(1e3 * x, 2) for x in d["pos"]],
                    "orientation_per_gap_deg": [round(math.degrees(x), 3) for x in d["rot"]],
                    "filter_position_std_at_end_mm": [round(1e3 * x, 2) for x in d["pos_std"]],
                    "filter_orientation_std_at_end_deg": [round(math.degrees(x), 3)
                                                          for x in d["rot_std"]],
                    "recovery_s_worst": worst_rec,
                    "recovery_optical_frames_worst": (
                        math.ceil(worst_rec * OPTICAL_HZ + 1e-9)
                        if math.isfinite(worst_rec) else None)}
    out["recovery_threshold"] = {"position_mm": 1e3 * p_lim,
                                 "orientation_deg": math.degrees(r_lim)}
    return out


def _recovery_s(rec: Recording, ep: np.ndarray, er: np.ndarray, b: float, p_lim: float,
                r_lim: float) -> float:
    """Seconds after the first optical pose past a gap (at ``b``) until the error is back
    within the limits for RECOVERY_HOLD_S; NaN if it never is."""
    after = np.flatnonzero(rec.t >= b)
    ok = (ep[after] <= p_lim) & (er[after] <= r_lim)
    hold = max(1, int(RECOVERY_HOLD_S * 300))
    for j in range(len(after) - hold):
        if ok[j:j + hold].all():
            return float(rec.t[after[j]] - b)
    return float("nan")


def evaluate(seconds: float, seed: int, gap_lengths: list[float], horizon_s: float,
             config: FusionConfig | None = None, model_floor: float = MODEL_FLOOR,
             cache: bool = True, dots: bool = False, device: Any = None,
             ideal: bool = False, estimate_installation: bool | None = None) -> dict[str, Any]:
    """Run the simulated MARVIN once and compute every figure (``device``: another
    simulated accelerometer device than MARVIN's; ``estimate_installation``: as
    :func:`run_fusion`, None: unless ``ideal``, as ``TrackerParams``)."""
    if estimate_installation is None:
        estimate_installation = not ideal
    if seconds < WARMUP_S + 2.0:
        raise InvalidInputError(f"--seconds must be at least {WARMUP_S + 2.0:g} (warm-up "
                                f"{WARMUP_S:g} s plus some tracking)")
    gaps = gap_schedule(seconds, gap_lengths)
    device = device or accel_sim.default_device()
    rec = run_fusion(seconds, seed, gaps, horizon_s, config or FusionConfig(), model_floor,
                     cache, dots, device, ideal, estimate_installation)
    if rec.t.size == 0:
        raise InvalidInputError("fusion never started: the laser tracker found no pose")
    figures: dict[str, Any] = {
        "seconds": seconds, "seed": seed, "optical_update": "dots" if dots else "pose",
        "installation": "ideal" if ideal else "realistic",
        "installation_estimate": estimate_installation,
        "accel_device": device_figures(device),
        "given_by_simulator": given_by_simulator(device, accel_sim.DEFAULT_RATE_HZ),
        **figures_of(rec, IvyWorld(seed=seed).trajectory, gaps, horizon_s),
    }
    figures["goals"] = goals(figures)
    return figures


def given_by_simulator(device: Any, rate_hz: float) -> dict[str, Any]:
    """What the run takes from the simulator's truth instead of measuring it: a real rig
    would have to estimate these, and the figures are better for not having to."""
    return {
        "accel_noise_model": "the simulated device's own (calibrated_accelerometers hands "
                             "device.noise_model() to the calibration)",
        "accel_latency_s": device.latency_s(rate_hz),
        "accel_positions": "the simulated device's true positions (the calibration "
                           "estimates biases, gains and axes)",
        "rig_mountings": "the simulator's head -> laser rig and head -> accelerometer rig",
    }


def figures_of(rec: Recording, traj: Any, gaps: list[tuple[float, float]],
               horizon_s: float) -> dict[str, Any]:
    """Every figure of a recorded run against the trajectory ``traj`` (``pose(t)``)."""
    p_true, q_true = traj.pose(rec.t)
    p_fut, q_fut = traj.pose(rec.t + horizon_s)
    after = rec.t >= WARMUP_S
    in_gap = np.zeros(rec.t.shape, bool)
    for a, b in gaps:
        in_gap |= (rec.t >= a) & (rec.t < b + RECOVERY_FRAMES / OPTICAL_HZ)
    in_gap &= after
    normal = after & ~in_gap
    ep, er = geo.pose_error(rec.p, rec.q, p_true, q_true)
    figures: dict[str, Any] = {
        "output_rate_hz": float(rec.t.size / (rec.t[-1] - rec.t[0])),
        "optical_poses": int(rec.optical_t.size),
        "optical_failures": rec.optical_failures,
        "optical_dot_labels": rec.dot_labels,
        "gaps": [[round(a, 3), round(b, 3)] for a, b in gaps],
        "samples": _sample_counts(rec, after, in_gap, ep, er),
        "filter_events": _filter_events(rec.stats),
        "fused": _err_figures(ep[after], er[after]),
        "fused_inside_gaps": _err_figures(ep[in_gap], er[in_gap]),
        "fused_outside_gaps": _err_figures(ep[normal], er[normal]),
    }
    for name, (bp, bq) in optical_baselines(rec).items():
        bep, ber = geo.pose_error(bp, bq, p_true, q_true)
        figures[f"baseline_{name}"] = {
            region: _err_figures(bep[mask], ber[mask])
            for region, mask in (("all", after), ("inside_gaps", in_gap),
                                 ("outside_gaps", normal))}
    figures["gaps_by_length"] = recovery_figures(rec, ep, er, gaps, normal)
    figures["resets"] = reset_figures(rec, traj)
    pep, per = geo.pose_error(rec.p_pred, rec.q_pred, p_fut, q_fut)
    nep, ner = geo.pose_error(rec.p, rec.q, p_fut, q_fut)
    figures[f"prediction_{1e3 * horizon_s:g}ms"] = {
        **_err_figures(pep[normal], per[normal]),
        "without_prediction_position_rmse_mm": 1e3 * _rms(nep[normal]),
        "without_prediction_orientation_rmse_deg": math.degrees(_rms(ner[normal]))}
    figures["nees"] = nees_figures(rec, p_true, q_true, after)
    updates = rec.stats.measurement_updates + rec.stats.time_updates
    figures["filter_updates_per_cpu_s"] = updates / rec.cpu_s if rec.cpu_s > 0 else None
    return figures


def reset_figures(rec: Recording, traj: Any) -> dict[str, Any]:
    """How far each start (the first and every restart) lets the error grow in the
    ``RESET_WINDOW_S`` after it (or until the next start), against the error of the
    optical pose it started from (the second of the two it starts from: the filter stands
    on it, ``FusionEKF.start_from_poses``) plus what the filter's covariance claims, at
    each instant; a start that converges stays under that bound (``excess`` <= 0).

    What a covariance claims of the error, at one dimension's 3 sigma, is its 99.73 %
    ellipsoid: ``worst_*_excess`` is the error's length beyond the starting pose's error
    plus that ellipsoid's reach along the error's own direction (``claim_reach``);
    ``bounded``: no instant of any start beyond it.  ``largest_axis_3_sigma`` holds the
    same against three standard deviations of the covariance's largest axis in every
    direction, a sphere a 3-D Gaussian error leaves with probability 0.27-2.9 % at each
    instant (``gaussian_share_beyond_3_sigma``): a claim the covariance does not make,
    tighter than its own wherever its axes are alike."""
    rows = []  # per start: worst position (m), orientation (rad), excesses: claim, sphere
    ends = np.append(rec.starts[1:], math.inf)[:rec.starts.size].tolist()
    for s, nxt in zip(rec.starts.tolist(), ends, strict=True):
        window = (rec.t >= s) & (rec.t < min(s + RESET_WINDOW_S, nxt))
        used = np.flatnonzero(rec.optical_t <= s + 1e-9)
        if not window.any() or not used.size:
            continue
        k = int(used[-1])  # the optical pose the filter started at
        p0, q0 = traj.pose(rec.optical_t[k])
        e0 = geo.pose_error(rec.optical_p[k], rec.optical_q[k], p0[0], q0[0])
        p_true, q_true = traj.pose(rec.t[window])
        e = error_vectors(rec.p[window], rec.q[window], p_true, q_true)
        worst, claim, sphere = [], [], []
        for b, start_error in ((slice(0, 3), e0[0]), (slice(3, 6), e0[1])):
            x, cov = e[:, b], rec.cov[window][:, b, b]
            length = np.linalg.norm(x, axis=1)
            worst.append(length.max())
            claim.append(np.max(length - (start_error + claim_reach(x, cov))))
            sigma = np.sqrt(np.linalg.eigvalsh(cov)[:, -1])
            sphere.append(np.max(length - (start_error + 3 * sigma)))
        rows.append(worst + claim + sphere)
    out: dict[str, Any] = {"starts": int(rec.starts.size), "window_s": RESET_WINDOW_S}
    if rows:
        w = np.max(np.array(rows), axis=0)
        out.update({"worst_position_mm": round(1e3 * w[0], 3),
                    "worst_orientation_deg": round(math.degrees(w[1]), 4),
                    **_excesses(w[2], w[3]),
                    "largest_axis_3_sigma": _excesses(w[4], w[5])})
    return out


def _excesses(position_m: float, rotation_rad: float) -> dict[str, Any]:
    """The worst excesses over a bound (mm, deg) and whether both are <= 0."""
    return {"worst_position_excess_mm": round(1e3 * position_m, 3),
            "worst_orientation_excess_deg": round(math.degrees(rotation_rad), 4),
            "bounded": bool(position_m <= 0 and rotation_rad <= 0)}


def _sample_counts(rec: Recording, after: np.ndarray, in_gap: np.ndarray, ep: np.ndarray,
                   er: np.ndarray) -> dict[str, int]:
    """Where every inertial sample went: scored (inside or outside the gaps), in the
    warm-up, or dropped while the filter was not running; and how many scored outputs are
    not finite (they make the RMSE NaN rather than being skipped)."""
    return {"inertial": int(rec.t.size + rec.uninitialised_t.size),
            "filter_not_running": int(rec.uninitialised_t.size),
            "filter_not_running_after_warmup": int(np.sum(rec.uninitialised_t >= WARMUP_S)),
            "warmup": int(np.sum(~after)),
            "scored": int(np.sum(after)),
            "scored_inside_gaps": int(np.sum(in_gap)),
            "scored_outside_gaps": int(np.sum(after & ~in_gap)),
            "non_finite_outputs": int(np.sum(~(np.isfinite(ep) & np.isfinite(er))[after]))}


def _filter_events(stats: FusionStats) -> dict[str, int]:
    """Starts (the first included: every start is from two optical poses), restarts and
    the measurements the filter's gates refused."""
    return {"starts": stats.reinitialised, "restarts": max(0, stats.reinitialised - 1),
            "pose_updates": stats.pose_updates, "pose_rejected": stats.pose_rejected,
            "dot_updates": stats.dot_updates, "dot_rejected": stats.dot_rejected,
            "accel_updates": stats.accel_updates, "accel_rejected": stats.accel_rejected}


def goals(f: dict[str, Any]) -> dict[str, bool]:
    """The targets, each a yes/no.  The fused RMSE must be at most half the better
    baseline's over all samples and in each region that has samples (inside the gaps the
    hold usually wins, outside them the one-frame extrapolation)."""
    half_best = all(
        f[fused]["samples"] == 0 or all(
            f[fused][key] <= 0.5 * min(f[f"baseline_{b}"][region][key]
                                       for b in ("hold_last", "constant_velocity"))
            for key in ("position_rmse_mm", "orientation_rmse_deg"))
        for fused, region in (("fused", "all"), ("fused_inside_gaps", "inside_gaps"),
                              ("fused_outside_gaps", "outside_gaps")))
    gaps = f["gaps_by_length"]
    one = gaps.get("1s")
    frames = [g["recovery_optical_frames_worst"] for k, g in gaps.items()
              if k != "recovery_threshold"]
    return {
        "output_rate_ge_290hz": f["output_rate_hz"] >= 290.0,
        "rmse_le_half_best_baseline": half_best,
        "gap_1s_within_3cm_1deg": bool(one and one["position_max_mm"] <= 30.0
                                       and one["orientation_max_deg"] <= 1.0),
        "recovery_within_3_frames": bool(frames) and all(
            fr is not None and fr <= 3 for fr in frames),
        "nees_within_95_bounds": f["nees"]["errors_about_zero"]["within_bounds"],
    }


def _estimate_flag(given: bool | None) -> str:
    """The flag that set the laser tracker's installation estimate, for an error message."""
    return "--no-estimate-installation" if given is False else "--estimate-installation"


def run(args: argparse.Namespace) -> dict[str, Any]:
    if args.horizon_ms is not None and not (math.isfinite(args.horizon_ms)
                                            and 0 <= args.horizon_ms <= 500):
        raise InvalidInputError(f"--horizon-ms must be within 0..500, got {args.horizon_ms!r}")
    if args.from_file is not None:
        from services.fusion.replay import replay

        if args.optical == "dots" and not args.display_calibration:
            raise InvalidInputError(
                "--from with --optical dots needs --display-calibration FILE "
                "(the laser tracker's calibration, whose walls the dots lie on)")
        estimate = getattr(args, "estimate_installation", None)
        for flag, given in ((_estimate_flag(estimate), estimate is not None),
                            ("--ideal", args.ideal)):
            if given:
                raise InvalidInputError(
                    f"{flag} is for the simulated run: with --from the optical samples come "
                    "tracked already, no simulated installation or laser tracker runs")
        return replay(args.from_file, None if args.horizon_ms is None else args.horizon_ms / 1e3,
                      display_calibration=args.display_calibration
                      if args.optical == "dots" else None)
    horizon_ms = 20.0 if args.horizon_ms is None else args.horizon_ms
    try:
        lengths = [float(x) for x in args.gaps.split(",") if x.strip()]
    except ValueError:
        raise InvalidInputError(
            f"--gaps: expected comma-separated seconds, got {args.gaps!r}") from None
    if any(not (math.isfinite(x) and x > 0) for x in lengths):
        raise InvalidInputError(f"--gaps: gap lengths must be positive seconds, got {args.gaps!r}")
    device = device_from_args(accel_sim.default_device(), args)
    return evaluate(float(args.seconds), int(args.seed), lengths, horizon_ms / 1e3,
                    cache=not args.no_cache, dots=args.optical == "dots", device=device,
                    ideal=args.ideal,
                    estimate_installation=laser_plugin.estimate_installation(args))
