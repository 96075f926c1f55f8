"""Time to process one 300 Hz accelerometer sample (goal: <= 2x the bare solve).

Measures ``DeadReckoner.update_volts`` per sample over a simulated head motion: validation,
conversion, eq. 4.42 solve, RK4 step, covariance propagation and the pose estimate with its
SE(3) covariance, i.e. everything the service does per sample before publishing.
Baseline in the same run, interleaved sample by sample with the update so that both see
the same load: the eq. 4.42 solve of the sample alone (validation, conversion, projection
and centripetal correction), the least any estimator must do, done both ways the code
can, with numpy (``layout.solve(cal.to_accel(v), omega)``) and on Python floats (the
update's own per-sample path); the faster one is the anchor.  The ratio to it is the
load-independent figure on a shared machine.  For scale, the bench also times the three
matrix products every sample's covariance needs at the least (F P F^T, F S and the pose
rows of S cov S^T, on matrices of the rig's sizes).  The update runs the compiled step
where it was built (``UMA_ACCEL_PURE_PYTHON=1`` forces pure Python); the bench says which,
and with the compiled one it times the pure-Python update too, in a second pass interleaved
with the float solve again (not in the first: there it raised the update's ratio from
1.76-1.78 to 1.87-1.89, three alternating runs of each, presumably as its hundred
microseconds per sample evict from the caches what the compiled update uses).

    /work/venv/bin/python bench/bench_accel.py [--seconds 10] [--json]
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import numpy as np
from summary import cpu_model, median_p99

from services.accel_rig import integrator
from services.accel_rig.integrator import DeadReckoner
from services.accel_rig.simulator import DEFAULT_RATE_HZ, default_device, simulate
from services.sim.trajectory import HeadTrajectory

#: goal: a sample may cost at most this many times the bare eq. 4.42 solve of the same run
GOAL_RATIO = 2.0

_Timed = Callable[[float, np.ndarray], object]


def _time_interleaved(fns: dict[str, _Timed], t: np.ndarray,
                      volts: np.ndarray) -> dict[str, np.ndarray]:
    """Microseconds of each function on each sample, the functions taking turns per
    sample (a load that comes and goes hits them alike)."""
    out = {name: np.empty(len(t)) for name in fns}
    clock = time.perf_counter_ns
    for k in range(len(t)):
        tk, vk = t[k], volts[k]
        for name, fn in fns.items():
            t0 = clock()
            fn(tk, vk)
            out[name][k] = clock() - t0
    return {name: ns / 1e3 for name, ns in out.items()}


def _covariance_products(dr: DeadReckoner) -> _Timed:
    """F P F^T, F S and the pose rows of S cov S^T on fixed matrices of the rig's sizes."""
    rng = np.random.default_rng(0)
    F, P = rng.normal(size=(2, 12, 12))
    S = rng.normal(size=(12, 4 * dr.layout.count))
    cov = np.eye(S.shape[1])

    def products(_t: float, _v: np.ndarray) -> object:
        S6 = S[:6]
        return F @ P @ F.T, F @ S, S6 @ cov @ S6.T
    return products


def _pure_python(update: _Timed) -> _Timed:
    """``update`` with the compiled step switched off for the call (a reference figure:
    the switch costs a fraction of a microsecond, the pure-Python update a hundred)."""
    native = integrator.NATIVE

    def run(t: float, v: np.ndarray) -> object:
        integrator.NATIVE = None
        try:
            return update(t, v)
        finally:
            integrator.NATIVE = native
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0,
                        help="simulated seconds of 300 Hz samples to process (default 10)")
    parser.add_argument("--json", action="store_true", help="last line: one JSON object")
    args = parser.parse_args()
    device = default_device()
    cal = device.calibration(DEFAULT_RATE_HZ)
    sim = simulate(HeadTrajectory(1), args.seconds, DEFAULT_RATE_HZ, seed=1, t0=5.0,
                   sensor=device)
    s = sim.truth

    def fresh() -> DeadReckoner:
        dr = DeadReckoner(cal, DEFAULT_RATE_HZ)
        dr.reset(s.t[0], s.position[0], s.quaternion[0], velocity=s.velocity[0],
                 omega=s.omega_body[0])
        return dr

    layout, omega, omega_floats = cal.layout, np.zeros(3), [0.0, 0.0, 0.0]
    compiled = integrator.NATIVE is not None
    fns = {
        "update": fresh().update_volts,
        "solve_numpy": lambda t, v: layout.solve(cal.to_accel(v), omega),
        "solve_floats": lambda t, v: layout.solve_floats(
            layout.project_floats(cal.to_accel_floats(v)), omega_floats),
        "covariance_products": _covariance_products(fresh()),
    }
    times = _time_interleaved(fns, sim.t, sim.volts)
    pure = None
    if compiled:
        pure = _time_interleaved({"update_pure_python": _pure_python(fresh().update_volts),
                                  "solve_floats": fns["solve_floats"]}, sim.t, sim.volts)
    period_us = 1e6 / DEFAULT_RATE_HZ
    figs = {name: median_p99(us, "us") for name, us in times.items()}
    kind = min(("solve_numpy", "solve_floats"), key=lambda n: figs[n]["median_us"])
    upd, base = figs["update"], figs[kind]
    fig = {
        "cpu": cpu_model(),
        "samples": len(sim.t),
        "step": "compiled" if compiled else "pure Python",
        "update_us": upd,
        "baseline_solve_only_us": base,
        "baseline_kind": kind,
        "solve_numpy_us": figs["solve_numpy"],
        "solve_floats_us": figs["solve_floats"],
        "covariance_products_us": figs["covariance_products"],
        "ratio_update_to_baseline": upd["median_us"] / base["median_us"],
        "ratio_covariance_products_to_baseline":
            figs["covariance_products"]["median_us"] / base["median_us"],
        "realtime_factor_at_300hz": period_us / upd["median_us"],
        "goal_ratio": GOAL_RATIO,
        "meets_goal": upd["median_us"] <= GOAL_RATIO * base["median_us"],
    }
    keys = ["update_us", "solve_numpy_us", "solve_floats_us", "covariance_products_us"]
    if pure is not None:
        upd_py, base_py = (median_p99(pure[n], "us") for n in ("update_pure_python",
                                                                "solve_floats"))
        fig["update_pure_python_us"] = upd_py
        fig["ratio_update_pure_python_to_solve_floats"] = \
            upd_py["median_us"] / base_py["median_us"]
        keys.append("update_pure_python_us")
    print(f"cpu {fig['cpu']}, dead reckoner step: {fig['step']}")
    for key in keys:
        print(f"{key:24s} median {fig[key]['median_us']:8.1f}  p99 {fig[key]['p99_us']:8.1f}")
    print(f"ratio to baseline ({kind}) {fig['ratio_update_to_baseline']:.2f} "
          f"(goal <= {GOAL_RATIO:g}), real-time factor at 300 Hz "
          f"{fig['realtime_factor_at_300hz']:.0f}x; the covariance products alone "
          f"{fig['ratio_covariance_products_to_baseline']:.2f}x"
          + (f"; the pure-Python update {fig['ratio_update_pure_python_to_solve_floats']:.2f}x "
             "(second pass)" if pure is not None else ""))
    if args.json:
        print(json.dumps(fig))


if __name__ == "__main__":
    main()
