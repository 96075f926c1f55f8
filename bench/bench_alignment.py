"""Solve time of the AX = XB solvers against cv2.calibrateHandEye, measured in the same run.

For n stations (noisy poses along the simulated head trajectory) each contender gets the
same input and does the same work: form the motions of all n(n-1)/2 station pairs and
solve.  Ours: Tsai-Lenz and Daniilidis closed forms (``relative_motions`` included), and
the full ``align_stations`` (selection, RANSAC, refinement, 100-resample bootstrap) for
scale.  Baseline: OpenCV's TSAI and DANIILIDIS.  Prints median and p99 per size and the
ratio ours / OpenCV; ``--json`` makes the last line one JSON object.

    /work/venv/bin/python bench/bench_alignment.py [--repeats N] [--json]
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from summary import median_p99

from services.alignment import opencv_reference
from services.alignment.pipeline import AlignmentOptions, align_stations
from services.alignment.simulate import StreamConfig, random_pose, simulate_streams
from services.alignment.solvers import Pose, all_pairs, daniilidis, relative_motions, tsai_lenz
from services.sim import mounts


def _stations(n: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    a, b = simulate_streams(seed, Pose(*mounts.HEAD_TO_LASER_RIG), random_pose(rng, 0.2),
                            random_pose(rng, 2.0), StreamConfig(seconds=60.0))
    pick = np.linspace(0, len(a) - 1, n).astype(int)
    return (a.position[pick], a.quaternion[pick], *b.at(a.t[pick])[:2])


def _time(fn: Callable[[], Any], repeats: int) -> dict[str, float]:
    fn()  # warm-up (imports, caches)
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return median_p99(np.array(samples) * 1e3, "ms")


def _row(n: int, repeats: int) -> dict[str, Any]:
    """Timings for n stations; every contender gets the same stations."""
    st = _stations(n)
    ij = all_pairs(n)
    row: dict[str, Any] = {
        "pairs": len(ij),
        "daniilidis": _time(lambda: daniilidis(relative_motions(*st, ij)), repeats),
        "tsai_lenz": _time(lambda: tsai_lenz(relative_motions(*st, ij)), repeats),
        "cv2_daniilidis": _time(
            lambda: opencv_reference.calibrate_hand_eye(*st, "daniilidis"), repeats),
        "cv2_tsai": _time(lambda: opencv_reference.calibrate_hand_eye(*st, "tsai"), repeats),
        "align_stations_full": _time(lambda: align_stations(*st, AlignmentOptions()),
                                     max(3, repeats // 20)),
    }
    row["ratio_daniilidis_over_cv2"] = (row["daniilidis"]["median_ms"]
                                        / row["cv2_daniilidis"]["median_ms"])
    row["ratio_tsai_over_cv2"] = row["tsai_lenz"]["median_ms"] / row["cv2_tsai"]["median_ms"]
    return row


def run(sizes: list[int], repeats: int) -> dict[str, Any]:
    return {f"stations_{n}": _row(n, repeats) for n in sizes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 20, 40],
                        help="numbers of stations (default 10 20 40)")
    parser.add_argument("--repeats", type=int, default=100, help="timed runs per contender")
    parser.add_argument("--json", action="store_true", help="last line: one JSON object")
    args = parser.parse_args()
    if args.repeats < 1 or min(args.sizes) < 4:
        # three stations give three pairs: too few for the full pipeline's bootstrap
        parser.error("--repeats must be >= 1 and every size >= 4")
    figures = run(args.sizes, args.repeats)
    for size, row in figures.items():
        print(f"{size} ({row['pairs']} pairs):")
        for name, value in row.items():
            if isinstance(value, dict):
                print(f"  {name:22s} median {value['median_ms']:8.3f} ms   "
                      f"p99 {value['p99_ms']:8.3f} ms")
        print(f"  ours / cv2: daniilidis {row['ratio_daniilidis_over_cv2']:.2f}, "
              f"tsai {row['ratio_tsai_over_cv2']:.2f}")
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
