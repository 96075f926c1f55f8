"""Fusion filter speed (goal >= 3000 filter updates/s on one core) and end-to-end latency.

1. **Filter**: the SCAAT EKF (``services.fusion.ekf``) on simulated accelerometer samples at
   300 Hz (six scalar updates and one time update each) and optical poses at 15 Hz, on one
   core.  Baseline in the same run: the same filter with each sample's six readings as one
   6-D update through filterpy's ``ExtendedKalmanFilter.update`` (matrix inverse, Joseph
   form), the textbook non-SCAAT way.  Reported: filter updates (measurement + time) per
   second, and per-sample processing time (median, p99).
2. **End to end** (``--e2e``, needs the agent and the fusion service): an agent on
   loopback, the fusion service as a child process, this process publishing optical poses
   and ``accel_raw`` samples through the Service SDK, and a client subscribing to the fused
   pose: latency from publishing an accelerometer sample to receiving the fused pose it
   produced (median, p99).

    /work/venv/bin/python bench/bench_fusion.py [--seconds 10] [--e2e] [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import time

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from summary import median_p99

from agent import geometry as geo
from services.accel_rig import simulator as accel_sim
from services.fusion.ekf import FusionEKF
from services.fusion.evaluate import accel_model
from services.fusion.state import MODEL_FLOOR
from services.sim.calibrations import calibrated_accelerometers
from services.sim.mounts import HEAD_TO_ACCEL_RIG
from services.sim.trajectory import HeadTrajectory

OPT_STD = (3e-4, np.radians(0.02))


def _inputs(seconds: float, seed: int = 1):
    traj = HeadTrajectory(seed)
    device, cal = calibrated_accelerometers(300.0, seed)
    run = accel_sim.simulate(traj, seconds, seed=seed, sensor=device, calibration=cal)
    frames = np.arange(0.0, seconds, 1 / 15)
    p, q = traj.pose(frames)
    return cal, run, frames, p, q


def _batch_update(ekf: FusionEKF, t: float, readings: np.ndarray,
                  kf: ExtendedKalmanFilter) -> None:
    """Baseline: all six readings in one filterpy update of the error state."""
    ekf.predict_to(t - ekf.accel.latency_s)
    rows = [ekf.predict_reading(j) for j in range(ekf.accel.count)]
    H = np.array([h for _, h in rows])
    z_pred = np.array([z for z, _ in rows])
    kf.x = np.zeros(ekf.dim)
    kf.P = ekf.P
    kf.update(readings, lambda x: H, lambda x: z_pred, R=np.diag(ekf.accel.variance))
    ekf._inject(kf.x)
    ekf.P = kf.P


def bench_filter(seconds: float, batch: bool) -> dict[str, float]:
    cal, run, frames, p_opt, q_opt = _inputs(seconds)
    ekf = FusionEKF(accel_model(cal, HEAD_TO_ACCEL_RIG, 300.0, MODEL_FLOOR))
    kf = ExtendedKalmanFilter(dim_x=ekf.dim, dim_z=ekf.accel.count)
    cov = np.diag([OPT_STD[0] ** 2] * 3 + [OPT_STD[1] ** 2] * 3)
    per_sample = []
    k = 0
    motion_t = run.t - cal.latency_s
    t_all = time.process_time()
    for i in range(len(run.t)):
        while k < len(frames) and frames[k] <= motion_t[i]:
            ekf.update_pose(frames[k], p_opt[k], q_opt[k], cov)
            k += 1
        if not ekf.initialised:
            continue
        t0 = time.perf_counter_ns()
        if batch:
            _batch_update(ekf, run.t[i], run.accel[i], kf)
        else:
            ekf.update_accel_sample(run.t[i], run.accel[i])
        per_sample.append(time.perf_counter_ns() - t0)
    cpu = time.process_time() - t_all
    s = ekf.stats
    updates = s.time_updates + s.pose_updates + (
        len(per_sample) * ekf.accel.count if batch else s.accel_updates)
    us = np.array(per_sample) / 1e3
    return {"updates_per_s": updates / cpu, "samples_per_s": len(us) / cpu,
            **{f"sample_{k}": v for k, v in median_p99(us, "us").items()}}


def bench_e2e(seconds: float) -> dict[str, float]:
    """Accelerometer sample published -> fused pose received by a remote client."""
    import socket
    import subprocess
    import sys
    import threading
    import uuid

    from agent import Service
    from agent.daemon.agent import Agent
    from agent.daemon.settings import AgentSettings
    from agent.runtime.session import open_session
    from services.demo import _static_edges

    with socket.socket() as s1, socket.socket() as s2:
        s1.bind(("127.0.0.1", 0))
        s2.bind(("127.0.0.1", 0))
        ep, ep_client = (f"tcp/127.0.0.1:{s.getsockname()[1]}" for s in (s1, s2))
    realm = f"bench{uuid.uuid4().hex[:8]}"
    cal, run, frames, p_opt, q_opt = _inputs(seconds + 5.0)
    agent = Agent(AgentSettings(realm=realm, agent_id="bench", listen=[ep],
                                static_edges=_static_edges()))
    agent.start()
    child = subprocess.Popen([sys.executable, "-m", "agent.cli", "service", "run", "fusion",
                              "--realm", realm, "--agent", "bench", "--connect", ep],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    latencies: list[float] = []
    lock = threading.Lock()
    sent: dict[int, int] = {}
    try:
        with Service("bench-inputs", realm=realm, agent="bench", connect=[ep]) as svc, \
                open_session("peer", [ep_client], [ep], realm) as session:
            optical = svc.ability("pose", type="pose6d", edge=(frames.WORLD, frames.LASER_RIG),
                                  frequency_hz=15.0, latency_s=0.03)
            attrs = {k: v for k, v in cal.to_dict().items() if v is not None}
            attrs.update(frequency_hz=300.0, latency_s=0.0)
            accel = svc.ability("accel", type="accel_raw", edge=(frames.WORLD, frames.ACCEL_RIG),
                                **attrs)
            svc.start()
            key = f"uma/{realm}/data/bench/fusion/head"

            def on_fused(smp) -> None:
                now = time.time_ns()
                from schemas.codec import decode_measurement
                m = decode_measurement(smp.payload.to_bytes())
                with lock:
                    t_sent = sent.pop(m.t_ns, None)
                if t_sent is not None:
                    latencies.append((now - t_sent) / 1e6)

            sub = session.declare_subscriber(key, on_fused)
            _feed(optical, accel, run, frames, p_opt, q_opt, seconds + 5.0, sent, lock)
            sub.undeclare()
    finally:
        child.terminate()
        try:
            child.wait(timeout=5)
        except subprocess.TimeoutExpired:
            child.kill()
        agent.close()
    warm = latencies[len(latencies) // 5:]
    if not warm:
        raise RuntimeError("no fused pose reached the client: is the fusion service working?")
    return {"samples": len(warm),
            **{f"latency_{k}": v for k, v in median_p99(warm, "ms").items()}}


def _feed(optical, accel, run, frames, p_opt, q_opt, seconds, sent, lock) -> None:
    """Publish at real time: optical rig poses at 15 Hz, accelerometer samples at 300 Hz."""
    from schemas.codec import Measurement
    from services.sim.mounts import HEAD_TO_LASER_RIG

    cov = geo.covariance_from_std(np.zeros(3), *OPT_STD)
    t0 = time.monotonic()
    k = 0
    for i in range(int(seconds * 300)):
        target = t0 + run.t[i]
        delay = target - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        t_ns = time.time_ns()
        while k < len(frames) and frames[k] <= run.t[i]:
            p, q = geo.compose(p_opt[k], q_opt[k], *HEAD_TO_LASER_RIG)
            optical.publish(t_ns, p, q, cov)
            k += 1
        with lock:
            sent[t_ns] = t_ns
        accel.publish_measurement(Measurement("accel_raw", t_ns, values=run.accel[i]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0,
                        help="simulated seconds of 300 Hz samples (default 10)")
    parser.add_argument("--e2e", action="store_true",
                        help="also measure accelerometer -> remote client latency")
    parser.add_argument("--json", action="store_true", help="last line: one JSON object")
    args = parser.parse_args()
    cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setaffinity(0, {min(cores)})   # the filter on one core
    scaat = bench_filter(args.seconds, batch=False)
    base = bench_filter(args.seconds, batch=True)
    with contextlib.suppress(AttributeError, OSError, TypeError):
        os.sched_setaffinity(0, cores)          # the distributed part: all cores again
    out = {"scaat": scaat, "baseline_filterpy_batch": base,
           "ratio_updates_per_s": scaat["updates_per_s"] / base["updates_per_s"],
           "ratio_sample_time": base["sample_median_us"] / scaat["sample_median_us"],
           "goal_3000_updates_per_s": scaat["updates_per_s"] >= 3000}
    if args.e2e:
        out["end_to_end"] = bench_e2e(args.seconds)
    for name in ("scaat", "baseline_filterpy_batch"):
        r = out[name]
        print(f"{name:24s} {r['updates_per_s']:9.0f} updates/s  {r['samples_per_s']:7.0f} "
              f"samples/s  per sample median {r['sample_median_us']:.0f} us, p99 "
              f"{r['sample_p99_us']:.0f} us")
    print(f"ratio (SCAAT / baseline updates per s): {out['ratio_updates_per_s']:.2f}")
    if "end_to_end" in out:
        e = out["end_to_end"]
        print(f"accelerometer sample -> fused pose at a remote client: median "
              f"{e['latency_median_ms']:.2f} ms, p99 {e['latency_p99_ms']:.2f} ms "
              f"({e['samples']} samples)")
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
