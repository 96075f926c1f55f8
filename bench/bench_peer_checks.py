"""What the checks against buggy and hostile peers cost on the hot path.

1. Decoding a ``pose6d`` sample with a covariance, with the positive semi-definite check
   and without it (the anchor), interleaved in one run: a diagonally dominant covariance
   (Gershgorin's test in plain Python) and a correlated one (a 6x6 Cholesky).
2. One cross-agent plan over forged summaries (``--forged`` agents of 801 links each on
   the route's frames) with the planner's link bounds, against the same plan without them
   (the anchor: what a plan cost before the bounds).

Usage: python bench/bench_peer_checks.py [--iterations N] [--forged N] [--json]
"""

from __future__ import annotations

import argparse
import itertools
import logging
import time

import numpy as np
from summary import cpu_model, median_p99, report

import schemas.codec as codec
from agent.protocol.query import Summary
from agent.sdk import planner
from agent.srg.errorfn import error_function


def _decode_us(data: bytes, n: int) -> float:
    t0 = time.perf_counter_ns()
    for _ in range(n):
        codec.decode_measurement(data, "pose6d")
    return (time.perf_counter_ns() - t0) / n / 1000.0


def bench_decode(iterations: int) -> dict:
    rng = np.random.default_rng(1)
    a = rng.normal(size=(6, 6))
    check = codec._check_psd
    out: dict = {}
    for label, cov in (("diagonal", np.diag([1e-4] * 3 + [1e-5] * 3)),
                       ("correlated", a @ a.T * 1e-4)):
        data = codec.encode_pose(1, [0.1, 0.2, 0.3], [0, 0, 0, 1], cov)
        on, off = [], []
        for _ in range(iterations):
            codec._check_psd = check
            on.append(_decode_us(data, 200))
            codec._check_psd = lambda values, cov, kind: None
            off.append(_decode_us(data, 200))
        codec._check_psd = check
        out[f"decode_{label}"] = {**median_p99(on, "us"),
                                  "anchor_unchecked": median_p99(off, "us"),
                                  "ratio": float(np.median(on) / np.median(off))}
    return out


def _summary(agent: str, frames: list[str], links: list[tuple[str, str]]) -> Summary:
    attrs = {"hops": {"hops": 1, "latency_s": 0.01, "cost": 0.0, "confidence": 1.0,
                      "accuracy": 0.0, "pos_std_m": 0.0, "rot_std_rad": 0.0, "static": True}}
    return Summary(agent, 1, set(frames), [set(frames)], [(a, b, attrs) for a, b in links])


def bench_plan(iterations: int, forged: int) -> dict:
    frames = [f"f{i}" for i in range(41)]
    clique = list(itertools.combinations(frames, 2))[:801]
    summaries = {"h1": _summary("h1", ["src", "f0"], [("src", "f0")]),
                 "h2": _summary("h2", ["f40", "dst"], [("f40", "dst")]),
                 "h3": _summary("h3", ["f0", "f40"], [("f0", "f40")])}
    for i in range(forged):
        summaries[f"evil{i}"] = _summary(f"evil{i}", frames, clique)
    fn = error_function("hops")
    bounds = planner.MAX_LINKS_PER_AGENT, planner.MAX_PLAN_LINKS

    def timed(per_agent: int, total: int, n: int) -> list[float]:
        planner.MAX_LINKS_PER_AGENT, planner.MAX_PLAN_LINKS = per_agent, total
        samples = []
        for _ in range(n):
            t0 = time.perf_counter_ns()
            planner.plan_routes(summaries, "src", "dst", fn)
            samples.append((time.perf_counter_ns() - t0) / 1e6)
        return samples
    logging.getLogger("uma.client").setLevel(logging.ERROR)  # the bounds say what they drop
    bounded = timed(*bounds, iterations)
    unbounded = timed(10**9, 10**9, max(1, iterations // 10))
    planner.MAX_LINKS_PER_AGENT, planner.MAX_PLAN_LINKS = bounds
    return {"forged_agents": forged, "links_each": len(clique),
            "plan_bounded": median_p99(bounded, "ms"),
            "anchor_unbounded": median_p99(unbounded, "ms"),
            "speedup": float(np.median(unbounded) / np.median(bounded))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--iterations", type=int, default=30, help="rounds per figure (30)")
    ap.add_argument("--forged", type=int, default=20, help="forged agents in the plan (20)")
    ap.add_argument("--json", action="store_true", help="also print one JSON object")
    args = ap.parse_args()
    figures = {"cpu": cpu_model(), **bench_decode(args.iterations),
               "plan": bench_plan(args.iterations, args.forged)}
    report(figures, args.json)


if __name__ == "__main__":
    main()
