"""Local SRG query speed against pytransform3d's TransformManager, measured in the same run.

1. A cached query at a time between samples over a path of 4 measured edges (interpolated
   at a random time each call, so nothing but the plan is reused) against
   ``TransformManager.get_transform`` over the same 4 edges as a static graph.  Reported
   with and without covariance, with the compiled chain kernel and the pure-Python one,
   and against TransformManager without its checks (``check=False``, the goal's anchor)
   and with them (the default).  The candidates are timed in alternating blocks.
2. One new measurement followed by a query on a 1,000-frame graph against
   ``add_transform`` + ``get_transform``.
3. ``Client.pose`` on a kept route (``Client.keep``) of 4 measured edges at a past time:
   an agent (its own process) and a tracker service publishing the 4 edges at 100 Hz with
   their standard deviations, the client keeping the route; once 1.5 s of samples are
   kept the tracker stops, and the kept answer (with covariance, no network) is timed
   against the same query on a local ``agent.srg.Graph`` holding the same samples and
   against pytransform3d's ``TemporalTransformManager(check=False)`` over them (fewer
   calls: it is slow), interleaved.  Every kept answer is checked to come from the kept
   route and to equal the local graph's to 1e-12.  ``--no-kept`` leaves it out.

Usage: python bench/bench_srg_local.py [--iterations N] [--no-kept] [--json]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
from loopback import free_port, wait_listening
from pytransform3d.transform_manager import (
    NumpyTimeseriesTransform,
    TemporalTransformManager,
    TransformManager,
)
from summary import cpu_model, median_p99

from agent import geometry as geo
from agent.srg import Graph, kernel

S = 1_000_000_000
COMPILED = kernel.NATIVE  # None: not built, or UMA_SRG_PURE_PYTHON=1


def _timed(fn, n: int) -> np.ndarray:
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter_ns()
        fn(i)
        out[i] = time.perf_counter_ns() - t0
    return out / 1000.0  # microseconds


def _random_pose(rng):
    return rng.normal(size=3), geo.rotvec_to_quat(rng.normal(size=3) * 0.5)


def _interleaved(fns: dict[str, Callable[[int], object]], n: int, rounds: int = 10,
                 ) -> dict[str, np.ndarray]:
    """``n`` timed calls of each function, in ``rounds`` alternating blocks: on a shared
    machine the load drifts, and ratios of figures taken side by side are what compare."""
    out = {label: np.empty(n) for label in fns}
    bounds = np.linspace(0, n, rounds + 1).astype(int)
    for lo, hi in itertools.pairwise(bounds):
        for label, fn in fns.items():
            dest = out[label]
            for i in range(lo, hi):
                t0 = time.perf_counter_ns()
                fn(i)
                dest[i] = time.perf_counter_ns() - t0
    return {label: a / 1000.0 for label, a in out.items()}  # microseconds


def _kernel(native: object) -> Callable[[Callable[[int], object]], Callable[[int], object]]:
    """A query run with the given chain kernel (None: the pure-Python one)."""
    def wrap(fn: Callable[[int], object]) -> Callable[[int], object]:
        def run(i: int) -> object:
            kernel.NATIVE = native
            try:
                return fn(i)
            finally:
                kernel.NATIVE = COMPILED
        return run
    return wrap


def bench_path4(n: int, rng: np.random.Generator) -> dict:
    frames = [f"f{i}" for i in range(5)]
    samples = 200  # 2 s at 100 Hz per edge
    series = [[_random_pose(rng) for _ in range(samples)] for _ in range(4)]
    graphs = {}
    for label, attrs in (("no_covariance", {}),
                         ("with_covariance", {"pos_std_m": 0.01, "rot_std_rad": 0.01})):
        g = Graph(buffer_s=10.0)
        for e in range(4):
            for k, (p, q) in enumerate(series[e]):
                g.add_measurement(frames[e], frames[e + 1], k * 10_000_000, p, q,
                                  frequency_hz=100.0, **attrs)
        graphs[label] = g
    times = rng.integers(10_000_000, (samples - 2) * 10_000_000, n)
    times[times % 10_000_000 == 0] += 1  # strictly between samples
    fns: dict[str, Callable[[int], object]] = {}
    for label, g in graphs.items():
        g.pose(frames[0], frames[4], at=int(times[0]))  # build the plan once
        for i in range(min(n, 2000)):  # warm the per-sample slerp logs as a running system does
            g.pose(frames[0], frames[4], at=int(times[i]))

        def query(i: int, g: Graph = g) -> object:
            return g.pose(frames[0], frames[4], at=int(times[i]))

        fns[label] = query  # the kernel in use: the compiled one when it was built
        if COMPILED is not None:
            fns[f"{label}_python"] = _kernel(None)(query)
    for label, check in (("pytransform3d_default", True), ("pytransform3d_check_false", False)):
        tm = TransformManager(check=check)
        for e in range(4):
            tm.add_transform(frames[e + 1], frames[e], geo.to_matrix(*series[e][50]))
        fns[label] = lambda i, tm=tm: tm.get_transform(frames[4], frames[0])
    out: dict = {"edges": 4, "samples_per_edge": samples,
                 "kernel": "python" if COMPILED is None else "compiled"}
    out.update({label: median_p99(a, "us") for label, a in _interleaved(fns, n).items()})
    for label in ("no_covariance", "with_covariance"):
        out.setdefault(f"{label}_python", out[label])
    strict, default = (out[k]["median_us"] for k in ("pytransform3d_check_false",
                                                      "pytransform3d_default"))
    for label in ("no_covariance", "with_covariance", "no_covariance_python",
                  "with_covariance_python"):
        out[f"ratio_{label}_to_check_false"] = out[label]["median_us"] / strict
    out["ratio_to_pytransform3d_default"] = out["no_covariance"]["median_us"] / default
    return out


def bench_update_1000(n: int, seed: int) -> dict:
    """A random recursive tree of 1,000 frames (its own seed, so the same tree whatever the
    other benchmark drew); the query runs from the root to the last frame, whose edge is
    the measured one updated before each query."""
    rng = np.random.default_rng(seed)
    count = 1000
    parents = [int(rng.integers(0, i)) for i in range(1, count)]
    values = [_random_pose(rng) for _ in range(1, count)]
    leaf = count - 1
    g = Graph(buffer_s=10.0)
    tm = TransformManager()
    for child, (parent, (p, q)) in enumerate(zip(parents, values, strict=True), start=1):
        if child == leaf:
            g.add_measurement(f"n{parent}", f"n{child}", 0, p, q, frequency_hz=100.0)
        else:
            g.add_static(f"n{parent}", f"n{child}", p, q)
        tm.add_transform(f"n{child}", f"n{parent}", geo.to_matrix(p, q))
    src, dst, upd_parent = "n0", f"n{leaf}", f"n{parents[leaf - 1]}"
    new = [_random_pose(rng) for _ in range(n)]
    hops = len(g.pose(src, dst, at=0).path) - 1

    def ours(i: int) -> None:
        t = (i + 1) * 10_000_000
        g.add_measurement(upd_parent, dst, t, new[i][0], new[i][1], frequency_hz=100.0)
        g.pose(src, dst, at=t)

    # matrices are built outside the timing for pytransform3d too
    mats = [geo.to_matrix(*v) for v in new]

    def theirs_prebuilt(i: int) -> None:
        tm.add_transform(dst, upd_parent, mats[i % n])
        tm.get_transform(dst, src)

    out = {"frames": count, "path_hops": hops, "srg": median_p99(_timed(ours, n), "us"),
           "pytransform3d": median_p99(_timed(theirs_prebuilt, max(50, n // 4)), "us")}
    out["speedup_vs_pytransform3d"] = out["pytransform3d"]["median_us"] / out["srg"]["median_us"]
    return out


KEPT_FRAMES = [f"kept/f{i}" for i in range(5)]
KEPT_RATE_HZ = 100.0


def run_tracker(args: argparse.Namespace) -> None:
    """The kept route's tracker: 4 measured edges f0 -> f1 -> ... -> f4 at 100 Hz, each a
    smooth motion, with standard deviations (so the kept answer has a covariance)."""
    from agent import Service
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with Service("tracker", realm=args.realm, agent="A", connect=[args.connect]) as svc:
        outs = [svc.ability(f"e{i}", type="pose6d", edge=(KEPT_FRAMES[i], KEPT_FRAMES[i + 1]),
                            frequency_hz=KEPT_RATE_HZ, latency_s=0.001, pos_std_m=0.002,
                            rot_std_rad=0.01) for i in range(4)]
        svc.start()
        k = 0
        while not stop.is_set():
            k += 1
            t = time.time_ns()
            for i, out in enumerate(outs):
                a = k / 50 + i
                out.publish(t, [0.1 * np.sin(a), 0.2 * np.cos(a), 0.3 + i],
                            geo.rotvec_to_quat(np.array([0.3 * np.sin(a), 0.2, i * 0.1])))
            stop.wait(1.0 / KEPT_RATE_HZ)


def _same_samples(kept) -> tuple[Graph, TemporalTransformManager]:
    """A local graph and a TemporalTransformManager holding the kept route's samples (on
    the route's clock, as the mirror holds them)."""
    g = Graph(buffer_s=60.0, max_samples=100_000)
    tm = TemporalTransformManager(check=False)
    for info in kept.graph.edges():
        parent, child, source = info["parent"], info["child"], info["source"]
        edge = kept.graph.edge(parent, child, source)
        buf = edge.buffer
        attrs = {k: v for k, v in edge.attrs.items() if k != "covariance"}
        for t, v, c in zip(buf.times, buf.values, buf.covs, strict=True):
            g.add_measurement(parent, child, t, np.array(v[:3]), np.array(v[3:]), c,
                              source=source, **attrs)
        # pytransform3d's pq: x, y, z, qw, qx, qy, qz
        pqs = np.array([(*v[:3], v[6], *v[3:6]) for v in buf.values])
        tm.add_transform(child, parent, NumpyTimeseriesTransform(
            np.array(buf.times, dtype=float) * 1e-9, pqs))
    return g, tm


def bench_kept(n: int, seed: int) -> dict:
    """Row 3 of the module docstring."""
    from agent.runtime.processes import stop_processes
    from agent.sdk.client import Client

    realm = f"bench{uuid.uuid4().hex[:8]}"
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONUNBUFFERED="1", UMA_LEASE_MS="10000")
    agent = subprocess.Popen([sys.executable, "-m", "agent.cli", "agent", "--realm", realm,
                              "--id", "A", "--listen", ep], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [agent]
    try:
        wait_listening([port], 60.0)
        tracker = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--role",
                                    "tracker", "--realm", realm, "--connect", ep], env=env)
        procs.append(tracker)
        with Client(realm=realm, connect=[ep], timeout=2.0) as c:
            kept = _keep_when_ready(c)
            deadline = time.monotonic() + 30
            while min(len(kept.graph.edge(*_kept_edge(kept, i)).buffer)
                      for i in range(4)) < 1.5 * KEPT_RATE_HZ:
                if time.monotonic() > deadline:
                    raise SystemExit("setup failed: the kept route got no samples")
                time.sleep(0.1)
            stop_processes([tracker])
            return _time_kept(c, kept, n, np.random.default_rng(seed))
    finally:
        stop_processes(procs)


def _keep_when_ready(c):
    """The kept route, once the agent has the tracker's 4 edges (setup, bounded)."""
    from agent.errors import UmaError
    deadline = time.monotonic() + 30
    while True:
        try:
            c.pose(KEPT_FRAMES[0], KEPT_FRAMES[4], error="hops")
            return c.keep(KEPT_FRAMES[0], KEPT_FRAMES[4], buffer_s=10.0, error="hops",
                          stall_s=3600.0)
        except (LookupError, ValueError, UmaError) as exc:
            if time.monotonic() > deadline:
                raise SystemExit(f"setup failed: {exc}") from None
        time.sleep(0.2)


def _kept_edge(kept, i: int) -> tuple[str, str, str]:
    info = next(e for e in kept.graph.edges() if e["parent"] == KEPT_FRAMES[i])
    return info["parent"], info["child"], info["source"]


def _time_kept(c, kept, n: int, rng: np.random.Generator) -> dict:
    """The kept answer, the local graph's and pytransform3d's, interleaved; every kept
    answer checked against the local graph's."""
    g, tm = _same_samples(kept)
    offset = c.clock.offset(kept.clock_agent) or 0
    times = [kept.graph.edge(*_kept_edge(kept, i)).buffer.times for i in range(4)]
    lo, hi = max(t[0] for t in times), min(t[-1] for t in times)
    route_times = rng.integers(lo + 1, hi, n)
    src, dst = KEPT_FRAMES[0], KEPT_FRAMES[4]
    answered = kept.answered
    checked = max(1, n // 200)  # every checked-th kept answer is compared below
    results: dict[int, object] = {}
    n_tm = max(1, n // 20)

    def kept_pose(i: int) -> None:
        r = c.pose(src, dst, at=int(route_times[i]) - offset, error="hops")
        if i % checked == 0:  # only those: thousands held alive would tax the collector
            results[i] = r

    def graph_pose(i: int) -> None:
        g.pose(src, dst, at=int(route_times[i]))

    def temporal(i: int) -> None:
        tm.current_time = route_times[i % n_tm] * 1e-9
        tm.get_transform(dst, src)

    for i in range(min(n, 500)):  # warm the slerp logs of both, as a running system does
        kept_pose(i)
        graph_pose(i)
    us = _interleaved({"kept": kept_pose, "graph": graph_pose}, n)
    us["temporal"] = _timed(temporal, n_tm)
    assert kept.answered - answered == n + min(n, 500), "a kept query went to the network"
    for i in range(0, n, checked):
        mine, local = results[i], g.pose(src, dst, at=int(route_times[i]))
        assert np.abs(mine.position - local.position).max() <= 1e-12
        assert np.abs(mine.quaternion - local.quaternion).max() <= 1e-12
        assert np.abs(mine.covariance - local.covariance).max() <= 1e-12
    out: dict = {"edges": 4, "samples_per_edge": min(len(t) for t in times),
                 "temporal_calls": n_tm}
    out.update({label: median_p99(a, "us") for label, a in us.items()})
    out["ratio_to_graph"] = out["kept"]["median_us"] / out["graph"]["median_us"]
    out["ratio_to_temporal_check_false"] = (out["kept"]["median_us"]
                                            / out["temporal"]["median_us"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=5000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-kept", action="store_true",
                    help="leave out the kept route (it starts an agent and a tracker)")
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    ap.add_argument("--role", default="main", choices=["main", "tracker"],
                    help=argparse.SUPPRESS)
    ap.add_argument("--realm", help=argparse.SUPPRESS)
    ap.add_argument("--connect", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == "tracker":
        return run_tracker(args)
    rng = np.random.default_rng(args.seed)
    figures = {"cpu": cpu_model(), "cached_query_4_edges": bench_path4(args.iterations, rng),
               "update_and_query_1000_frames": bench_update_1000(args.iterations // 5,
                                                                 args.seed + 1)}
    if not args.no_kept:
        figures["kept_route_4_edges"] = bench_kept(args.iterations, args.seed + 2)
    a, b = figures["cached_query_4_edges"], figures["update_and_query_1000_frames"]

    def us(label: str) -> str:
        return f"{a[label]['median_us']:.1f} us"

    print(f"cpu: {figures['cpu']}; chain kernel: {a['kernel']}")
    print(f"cached query, 4 interpolated edges: {us('no_covariance')}; pytransform3d "
          f"get_transform(check=False) {us('pytransform3d_check_false')}; ratio "
          f"{a['ratio_no_covariance_to_check_false']:.2f} (goal <= 1.0)")
    print(f"  pure-Python kernel {us('no_covariance_python')} (ratio "
          f"{a['ratio_no_covariance_python_to_check_false']:.2f}); with covariance "
          f"{us('with_covariance')} (pure Python {us('with_covariance_python')}); "
          f"pytransform3d with its default checks {us('pytransform3d_default')}")
    print(f"new measurement + query, 1000 frames: {b['srg']['median_us']:.1f} us; "
          f"pytransform3d add+get {b['pytransform3d']['median_us']:.1f} us; speedup "
          f"{b['speedup_vs_pytransform3d']:.1f}x (goal >= 10x)")
    k = figures.get("kept_route_4_edges")
    if k:
        print(f"pose() on a kept route, 4 edges with covariance, past time: "
              f"{k['kept']['median_us']:.1f} us (p99 {k['kept']['p99_us']:.1f}); the same "
              f"query on a local Graph {k['graph']['median_us']:.1f} us, ratio "
              f"{k['ratio_to_graph']:.2f} (goal <= 1.5); TemporalTransformManager"
              f"(check=False) {k['temporal']['median_us']:.1f} us, ratio "
              f"{k['ratio_to_temporal_check_false']:.3f} (goal <= 1.0)")
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
