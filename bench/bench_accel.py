"""Time to process one 300 Hz accelerometer sample (goal, issue 19: <= 2x the bare solve).

Measures ``DeadReckoner.update_volts`` per sample over a simulated head motion: validation,
conversion, eq. 4.42 solve, RK4 step, covariance propagation and the pose estimate with its
SE(3) covariance, i.e. everything the service does per sample before publishing.
Baseline in the same run: the eq. 4.42 solve of the sample alone (``layout.solve`` after
``to_accel``), the least any estimator must do; the ratio is the load-independent figure
on a shared machine.

    /work/venv/bin/python bench/bench_accel.py [--seconds 10] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from summary import cpu_model, median_p99

from services.accel_rig.integrator import DeadReckoner
from services.accel_rig.simulator import DEFAULT_RATE_HZ, default_device, simulate
from services.sim.trajectory import HeadTrajectory

#: issue 19: a sample may cost at most this many times the bare eq. 4.42 solve of the same run
GOAL_RATIO = 2.0


def _time_per_sample(fn, t, volts) -> np.ndarray:
    out = np.empty(len(t))
    for k in range(len(t)):
        t0 = time.perf_counter_ns()
        fn(t[k], volts[k])
        out[k] = time.perf_counter_ns() - t0
    return out / 1e3  # microseconds


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

    omega = np.zeros(3)
    baseline = _time_per_sample(lambda t, v: cal.layout.solve(cal.to_accel(v), omega),
                                sim.t, sim.volts)
    dr = fresh()
    update = _time_per_sample(dr.update_volts, sim.t, sim.volts)
    period_us = 1e6 / DEFAULT_RATE_HZ
    upd, base = median_p99(update, "us"), median_p99(baseline, "us")
    fig = {
        "cpu": cpu_model(),
        "samples": len(sim.t),
        "update_us": upd,
        "baseline_solve_only_us": base,
        "ratio_update_to_baseline": upd["median_us"] / base["median_us"],
        "realtime_factor_at_300hz": period_us / upd["median_us"],
        "goal_ratio": GOAL_RATIO,
        "meets_goal": upd["median_us"] <= GOAL_RATIO * base["median_us"],
    }
    print(f"cpu {fig['cpu']}")
    for key in ("update_us", "baseline_solve_only_us"):
        print(f"{key:24s} median {fig[key]['median_us']:8.1f}  p99 {fig[key]['p99_us']:8.1f}")
    print(f"ratio to baseline {fig['ratio_update_to_baseline']:.2f} (goal <= {GOAL_RATIO:g}), "
          f"real-time factor at 300 Hz {fig['realtime_factor_at_300hz']:.0f}x")
    if args.json:
        print(json.dumps(fig))


if __name__ == "__main__":
    main()
