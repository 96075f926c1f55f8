"""Local SRG query speed against pytransform3d's TransformManager, measured in the same run.

1. A cached query at a time between samples over a path of 4 measured edges (interpolated
   at a random time each call, so nothing but the plan is reused) against
   ``TransformManager.get_transform`` over the same 4 edges as a static graph.  Reported
   with and without covariance, with the compiled chain kernel and the pure-Python one,
   and against TransformManager without its checks (``check=False``, the goal's anchor)
   and with them (the default).  The candidates are timed in alternating blocks.
2. One new measurement followed by a query on a 1,000-frame graph against
   ``add_transform`` + ``get_transform``.

Usage: python bench/bench_srg_local.py [--iterations N] [--json]
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from collections.abc import Callable

import numpy as np
from pytransform3d.transform_manager import TransformManager
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=5000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    figures = {"cpu": cpu_model(), "cached_query_4_edges": bench_path4(args.iterations, rng),
               "update_and_query_1000_frames": bench_update_1000(args.iterations // 5,
                                                                 args.seed + 1)}
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
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
