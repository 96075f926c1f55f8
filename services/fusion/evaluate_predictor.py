"""``uma eval predictor``: the simulated experiments of Dorfmüller-Ulhaas, §3.3 (figs. 9-15).

Three experiments, each a table of the estimates per filter iteration (the paper's
figures, printed):

* **ideal** (figs. 9a-11a): constant ``omega = (0, 0, 0.02)``, ``a = (0, 0, 0.001)``,
  ``v`` growing from ``(0, 0, 0.2)`` by ``a dt``, ``dt = 20 ms``, exact poses;
* **corrupted** (figs. 9b-11b): the same motion with each frame's ``omega``, ``v`` and
  ``a`` perturbed by uniform noise of +-1e-3, +-1e-2 and +-1e-5 (rectangular, not
  Gaussian, as in the paper);
* **abrupt change** (figs. 12-15): the corrupted motion switches at frame 10 to
  ``omega = (0.005, -0.01, -0.02)``, ``v = (0.2, 0.1, -0.2)``, ``a = (0.001, 0.0008,
  -0.001)``; the 20 ms pose prediction error per frame shows the overshoot of fig. 15.

Convergence: the first iteration from which the error stays within tolerance: 1 % of the
true value for exact data; the perturbation bound for ``omega`` and ``v`` on corrupted data.
On corrupted data the +-1e-2 m/s velocity jitter per 20 ms frame makes ``a`` resolvable
only to about 0.1 m/s^2 in ten frames (far above the true 0.001), so for ``a`` there the
figure is whether the error stays inside the filter's own 3 sigma (reported, not a goal).

A fourth figure runs the predictor on the simulated head trajectory (``--seconds``,
``--seed``) at 60 Hz with 1 mm / 0.1 deg pose noise and compares its +20 ms prediction
with holding the last pose.

Dorfmüller-Ulhaas: Dorfmüller-Ulhaas, *Robust Optical User Motion Tracking Using a Kalman
Filter*.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent import geometry as geo
from services.fusion.predictor import DorfmullerPredictor, PredictorConfig, motion_matrices
from services.sim.trajectory import HeadTrajectory

PAPER_DT = 0.02
FRAMES = 20
CHANGE_FRAME = 10
#: uniform perturbation half-ranges of omega, v, a (Dorfmüller-Ulhaas, §3.3)
PERTURBATION = (1e-3, 1e-2, 1e-5)
#: numerical floor of the point noise for exact data: the covariance's dynamic range must
#: stay well inside double precision
EXACT_POINT_STD_M = 1e-6


@dataclass(frozen=True)
class Segment:
    """Nominal kinematics from frame ``start`` on; ``v`` grows from ``v0`` by ``a dt``."""

    start: int
    omega: tuple[float, float, float]
    v0: tuple[float, float, float]
    a: tuple[float, float, float]


FIRST = Segment(1, (0.0, 0.0, 0.02), (0.0, 0.0, 0.2), (0.0, 0.0, 0.001))
CHANGE = Segment(CHANGE_FRAME, (0.005, -0.01, -0.02), (0.2, 0.1, -0.2), (0.001, 0.0008, -0.001))


@dataclass
class Motion:
    """Poses of frames 0..n and the nominal kinematics of each step 1..n."""

    t: np.ndarray           # (n+1,)
    p: np.ndarray           # (n+1, 3)
    q: np.ndarray           # (n+1, 4)
    truth: np.ndarray       # (n, 9): nominal omega, v, a of step k (index k-1)
    segment_start: np.ndarray  # (n,) first frame of the segment of step k


def simulate(frames: int, segments: list[Segment], perturb: bool,
             rng: np.random.Generator, dt: float = PAPER_DT) -> Motion:
    """The paper's rigid-body motion, built with Theorem 1 itself (the filter's model)."""
    p, q = np.zeros(3), geo.quat_identity()
    ps, qs, truth, starts = [p], [q], [], []
    for k in range(1, frames + 1):
        seg = [s for s in segments if s.start <= k][-1]
        v_nominal = np.asarray(seg.v0) + np.asarray(seg.a) * dt * (k - seg.start + 1)
        nominal = np.concatenate([seg.omega, v_nominal, seg.a])
        noise = np.repeat(PERTURBATION, 3) * rng.uniform(-1, 1, 9) if perturb else 0.0
        actual = nominal + noise
        W, V, A = motion_matrices(actual[:3], dt)
        p = p + V @ actual[3:6] + A @ actual[6:9]
        q = geo.quat_multiply(geo.matrix_to_quat(W), q)
        ps.append(p)
        qs.append(q)
        truth.append(nominal)
        starts.append(seg.start)
    return Motion(np.arange(frames + 1) * dt, np.array(ps), np.array(qs), np.array(truth),
                  np.array(starts))


def experiment_config(perturb: bool, dt: float = PAPER_DT) -> PredictorConfig:
    """The filter's noise model matched to the data (the paper's Kalman assumptions).

    Exact data: point noise at the numerical floor.  Corrupted data: the per-frame jitter
    of ``v`` and ``omega`` moves each point by ``dt * jitter``; a uniform +-b has variance
    b^2 / 3, and two poses enter each residual, hence the further 1/sqrt(2).
    """
    if not perturb:
        return PredictorConfig(point_std_m=EXACT_POINT_STD_M, omega_walk=0.0,
                               velocity_walk=0.0, accel_walk=0.0, initial_std=(1.0, 1.0, 1.0))
    r_om, r_v, _ = PERTURBATION
    jitter = dt * np.hypot(r_v, r_om * 1.0) / np.sqrt(3.0)
    return PredictorConfig(point_std_m=float(jitter / np.sqrt(2.0)), omega_walk=0.0,
                           velocity_walk=0.0, accel_walk=0.0, initial_std=(1.0, 1.0, 1.0))


def run_filter(motion: Motion, config: PredictorConfig) -> dict[str, np.ndarray]:
    """Feed the poses; record estimates, 1-sigma and the 20 ms prediction error per step."""
    f = DorfmullerPredictor(config)
    f.update(motion.t[0], motion.p[0], motion.q[0])
    est, sig, pred_pos, pred_rot = [], [], [], []
    n = len(motion.t) - 1
    for k in range(1, n + 1):
        f.update(motion.t[k], motion.p[k], motion.q[k])
        est.append(np.concatenate([f.omega, f.velocity, f.acceleration]))
        sig.append(np.sqrt(np.diag(f.covariance)))
        if k < n:
            p, q = f.predict(motion.t[k + 1] - motion.t[k])
            e_p, e_r = geo.pose_error(p, q, motion.p[k + 1], motion.q[k + 1])
            pred_pos.append(float(e_p))
            pred_rot.append(float(e_r))
    return {"estimate": np.array(est), "sigma": np.array(sig),
            "prediction_position_m": np.array(pred_pos),
            "prediction_rotation_rad": np.array(pred_rot), "manoeuvres": f.stats.manoeuvres}


def _convergence(ok: np.ndarray) -> int | None:
    """First 1-based iteration from which ``ok`` holds to the end, or None."""
    bad = np.flatnonzero(~ok)
    if len(bad) == 0:
        return 1
    return None if bad[-1] == len(ok) - 1 else int(bad[-1]) + 2


def _within(result: dict[str, np.ndarray], motion: Motion, perturb: bool,
            block: slice, name: str) -> np.ndarray:
    err = np.linalg.norm(result["estimate"][:, block] - motion.truth[:, block], axis=1)
    if not perturb:
        return err <= 0.01 * np.linalg.norm(motion.truth[:, block], axis=1)
    if name == "a":
        sigma = np.linalg.norm(result["sigma"][:, block], axis=1)
        return err <= 3.0 * sigma
    bound = PERTURBATION[0 if name == "omega" else 1] * np.sqrt(3.0)
    return err <= bound


BLOCKS = {"omega": slice(0, 3), "v": slice(3, 6), "a": slice(6, 9)}


def _fmt(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:+.5f}" for x in v) + ")"


def experiment(name: str, segments: list[Segment], perturb: bool, seed: int) -> dict[str, Any]:
    """One of the paper's simulations with its printed figures and convergence figures."""
    motion = simulate(FRAMES if len(segments) > 1 else CHANGE_FRAME, segments, perturb,
                      np.random.default_rng(seed))
    result = run_filter(motion, experiment_config(perturb))
    out: dict[str, Any] = {"description": name, "frames": len(motion.t) - 1}
    for seg_index, seg in enumerate(segments):
        in_seg = motion.segment_start == seg.start
        label = "convergence" if seg_index == 0 else f"reconvergence_after_frame_{seg.start}"
        out[label] = {
            f"{q}_iterations": _convergence(
                _within(result, motion, perturb, b, q)[in_seg]) for q, b in BLOCKS.items()}
    table = {}
    for k in range(len(motion.truth)):
        e = result["estimate"][k]
        row = (f"omega={_fmt(e[0:3])} v={_fmt(e[3:6])} a={_fmt(e[6:9])}")
        if k < len(result["prediction_position_m"]):
            row += (f" | +20ms err {1e3 * result['prediction_position_m'][k]:.3f} mm "
                    f"{np.degrees(result['prediction_rotation_rad'][k]):.4f} deg")
        table[f"iteration {k + 1:02d}"] = row
    out["true_first"] = (f"omega={_fmt(motion.truth[0, :3])} v={_fmt(motion.truth[0, 3:6])} "
                         f"a={_fmt(motion.truth[0, 6:9])}")
    out["estimates"] = table
    out["max_prediction_error_mm"] = float(1e3 * result["prediction_position_m"].max())
    out["manoeuvre_resets"] = int(result["manoeuvres"])
    return out


def head_trajectory_prediction(seconds: float, seed: int, rate_hz: float = 60.0,
                               horizon_s: float = 0.02) -> dict[str, Any]:
    """The predictor on realistic head motion: +20 ms prediction vs holding the last pose."""
    traj = HeadTrajectory(seed)
    rng = np.random.default_rng(seed + 1000)
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    p_true, q_true = traj.pose(t)
    p_fut, q_fut = traj.pose(t + horizon_s)
    pos_std, rot_std = 1e-3, np.radians(0.1)
    p_meas = p_true + rng.normal(0, pos_std, p_true.shape)
    q_meas = geo.quat_multiply(geo.rotvec_to_quat(rng.normal(0, rot_std, (len(t), 3))), q_true)
    cfg = PredictorConfig(point_std_m=float(np.hypot(pos_std, rot_std)), lever_m=1.0,
                          omega_walk=20.0, velocity_walk=3.0, accel_walk=30.0,
                          initial_std=(5.0, 2.0, 10.0))
    f = DorfmullerPredictor(cfg)
    errs_p, errs_r, hold_p, hold_r = [], [], [], []
    for k in range(len(t)):
        f.update(t[k], p_meas[k], q_meas[k])
        if k < int(rate_hz):  # one second to converge
            continue
        p, q = f.predict(horizon_s)
        e_p, e_r = geo.pose_error(p, q, p_fut[k], q_fut[k])
        h_p, h_r = geo.pose_error(p_meas[k], q_meas[k], p_fut[k], q_fut[k])
        errs_p.append(e_p)
        errs_r.append(e_r)
        hold_p.append(h_p)
        hold_r.append(h_r)

    def rms(x: list[float]) -> float:
        return float(np.sqrt(np.mean(np.square(x)))) if x else float("nan")

    return {"rate_hz": rate_hz, "horizon_ms": 1e3 * horizon_s, "samples": len(errs_p),
            "predicted_position_rmse_mm": 1e3 * rms(errs_p),
            "predicted_orientation_rmse_deg": float(np.degrees(rms(errs_r))),
            "hold_last_position_rmse_mm": 1e3 * rms(hold_p),
            "hold_last_orientation_rmse_deg": float(np.degrees(rms(hold_r))),
            "manoeuvre_resets": f.stats.manoeuvres}


def run(args: argparse.Namespace) -> dict[str, Any]:
    seed = int(args.seed)
    figures = {
        "ideal (figs 9a-11a)": experiment("exact poses", [FIRST], False, seed),
        "corrupted (figs 9b-11b)": experiment("uniformly perturbed kinematics", [FIRST], True,
                                              seed),
        "abrupt change, exact (figs 12-15)": experiment("motion switches at frame 10",
                                                        [FIRST, CHANGE], False, seed),
        "abrupt change, corrupted (figs 12-15)": experiment(
            "perturbed motion switching at frame 10", [FIRST, CHANGE], True, seed),
        "head trajectory": head_trajectory_prediction(float(args.seconds), seed),
    }
    figures["goal_met"] = _goal_met(figures)
    return figures


def _goal_met(figures: dict[str, Any]) -> bool:
    """omega and v converge (and re-converge) within four iterations everywhere, a on exact
    data; on corrupted data a is noise-limited (module docstring) and only reported."""
    for name, fig in figures.items():
        if not name.startswith(("ideal", "corrupted", "abrupt")):
            continue
        exact = "corrupted" not in name
        for key, conv in fig.items():
            if not key.startswith(("convergence", "reconvergence")):
                continue
            judged = {q: v for q, v in conv.items() if exact or not q.startswith("a_")}
            if any(v is None or v > 4 for v in judged.values()):
                return False
    return True
