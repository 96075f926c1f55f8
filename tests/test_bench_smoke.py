"""The benchmarks still run, and report their figures through ``bench/summary.py``.

Only the pure-computation benchmarks that finish in seconds with tiny options run here, and
``bench_scale.py --quick`` (one realm of two agents) and bench_tls (three routers, a few
seconds); the other ones that start agents or services (failover, query_remote,
alignment_e2e, fusion ``--e2e``) and the slow ones (laser: camera calibration first;
srg_local: a 1,000-frame pytransform3d graph to build) are left out.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"


def _load_summary():
    spec = importlib.util.spec_from_file_location("bench_summary", BENCH / "summary.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SUMMARY = _load_summary()
median_p99 = SUMMARY.median_p99


def test_median_p99_values_and_unit_naming() -> None:
    out = median_p99(list(range(101)), "ms")
    assert out == {"median_ms": 50.0, "p99_ms": 99.0}
    assert all(type(v) is float for v in out.values())  # JSON-ready, not numpy scalars
    samples = np.array([4.0, 1.0, 3.0, 2.0])
    assert median_p99(samples, "us") == {
        "median_us": pytest.approx(2.5), "p99_us": pytest.approx(np.percentile(samples, 99))}
    assert median_p99([7.0], "s") == {"median_s": 7.0, "p99_s": 7.0}


@pytest.mark.parametrize("empty", [[], np.array([])])
def test_median_p99_rejects_no_samples(empty) -> None:
    with pytest.raises(ValueError, match="no samples"):
        median_p99(empty, "ms")


def test_cpu_model_is_the_model_name_of_proc_cpuinfo() -> None:
    names = [line.split(":", 1)[1].strip() for line in
             Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("model name")]
    assert SUMMARY.cpu_model().startswith(names[0] if names else "unknown")
    assert SUMMARY.cpu_model().endswith(" CPUs)")  # and how many this process may use


# bench file, tiny options, and where its median/p99 figures are: (path to a dict in the
# JSON, the keys that dict must have)
BENCHES = {
    "bench_accel.py": (["--seconds", "0.5"], [
        (("update_us",), ("median_us", "p99_us")),
        (("baseline_solve_only_us",), ("median_us", "p99_us")),
    ]),
    "bench_idle_floor.py": (["--puts", "20"], [
        ((f"{rate}_hz", "bare_put"), ("median_us", "p99_us")) for rate in (100, 1000, 5000)
    ] + [(("hot_python_loop",), ("median_us", "p99_us"))]),
    "bench_peer_checks.py": (["--iterations", "2", "--forged", "1"], [
        (("decode_diagonal",), ("median_us", "p99_us")),
        (("decode_correlated", "anchor_unchecked"), ("median_us", "p99_us")),
        (("plan", "plan_bounded"), ("median_ms", "p99_ms")),
        (("plan", "anchor_unbounded"), ("median_ms", "p99_ms")),
    ]),
    "bench_matching.py": (["--abilities", "50", "--needs", "10", "--repeat", "3"], [
        ((), ("index_build_median_ms",
              "match_all_cold_median_ms", "match_all_cold_p99_ms",
              "match_all_warm_median_ms", "match_all_warm_p99_ms",
              "baseline_naive_median_ms", "baseline_naive_p99_ms")),
    ]),
    "bench_outside_in.py": (["--frames", "3", "--cameras", "3"], [
        ((name,), ("median_ms", "p99_ms"))
        for name in ("detection", "anchor_contours", "tracker", "anchor_opencv_baseline")
    ]),
    "bench_fusion.py": (["--seconds", "1"], [
        (("scaat",), ("sample_median_us", "sample_p99_us")),
        (("baseline_filterpy_batch",), ("sample_median_us", "sample_p99_us")),
    ]),
    "bench_alignment.py": (["--sizes", "10", "--repeats", "1"], [
        (("stations_10", name), ("median_ms", "p99_ms"))
        for name in ("daniilidis", "tsai_lenz", "cv2_daniilidis", "cv2_tsai",
                     "align_stations_full")
    ]),
    "bench_tls.py": (["--queries", "5", "--samples", "5", "--rounds", "1"], [
        ((), tuple(f"{kind}_{variant}_{stat}" for kind in ("query", "stream")
                   for variant in ("tcp", "tls", "tls_acl")
                   for stat in ("median_us", "p99_us", "ratio_to_tcp"))),
    ]),
}


def run_bench(bench: str, options: list[str], timeout: float = 120) -> dict:
    """``bench/BENCH OPTIONS --json``'s figures (its last line)."""
    # the working tree's packages, whatever is installed
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p))
    proc = subprocess.run([sys.executable, f"bench/{bench}", *options, "--json"], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = [line for line in proc.stdout.splitlines() if line.strip()]
    assert lines, f"{bench} printed nothing"
    return json.loads(lines[-1])  # --json: the last line is one JSON object


@pytest.mark.slow
@pytest.mark.parametrize("bench", sorted(BENCHES))
def test_bench_runs_and_reports_median_p99(bench: str) -> None:
    options, expected = BENCHES[bench]
    figures = run_bench(bench, options)
    for path, keys in expected:
        node = figures
        for part in path:
            node = node[part]
        for key in keys:
            assert isinstance(node[key], float), (bench, path, key, node)
            assert node[key] >= 0.0, (bench, path, key, node)


@pytest.mark.slow
def test_bench_scale_quick_reports_every_sweep_with_its_growth() -> None:
    """``bench_scale.py --quick``: one realm of 2 agents on loopback and tiny in-process
    sweeps; every row has its figures, later rows their growth, no row failed."""
    figures = run_bench("bench_scale.py", ["--quick"], timeout=300)
    assert figures["cpu"] and len(figures["load_at_start"]) == 3
    summary, matching = figures["summary"], figures["matching"]
    assert all(r["bytes_compact"] < r["bytes_spelt_out"] for r in summary)
    assert summary[1]["links"] > summary[0]["links"] and "bytes_compact_x" in summary[1]
    shared = figures["summary_shared"]
    assert shared[1]["shared"] == 2 and shared[1]["links"] > shared[0]["links"]
    assert matching[1]["abilities"] > matching[0]["abilities"]
    assert isinstance(matching[1]["cold_median_ms_x"], float)
    (row,) = figures["frames"]
    assert "error" not in row, row
    assert row["summaries"] == row["agents"] == 2
    assert row["query_failed"] == 0 and row["subscription_poses"] > 0
    for key in ("query_median_ms", "subscription_median_ms", "agent_cpu_pct_per_1k_samples_s",
                "agent_rss_mb_median", "new_need_connected_ms", "formed_s"):
        assert isinstance(row[key], float) and row[key] > 0, (key, row)


def _outside_in_live() -> Any:
    """bench/outside_in_live.py as a module (the bench's folder is no package)."""
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location("bench_oi_live", BENCH / "outside_in_live.py")
        live = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(live)
    finally:
        sys.path.remove(str(BENCH))
    return live


def test_outside_in_live_counts_missing_frame_sets_and_reconstruction_reports(tmp_path) -> None:
    """``bench_outside_in --live``'s diagnostics of a rate short of the cameras': the
    frame sets between a body's poses that gave it none, and the reconstruction's counts
    between its first and last report inside the measurement."""
    live = _outside_in_live()
    period = round(1e9 / 120)
    got = live._missing({"a": [10 * period, 11 * period, 14 * period, 15 * period],
                         "b": [k * period for k in range(10, 16)]}, 120.0, 10 * period / 1e9,
                        6 / 120)
    assert got["a"]["frame_sets"] == 2 and got["a"]["at_s"] == [round(1 / 120, 2)]
    assert got["b"] == {"frame_sets": 0, "at_s": []}

    def report(clock: str, sets: int, stale: int) -> str:
        return (f"2026-01-02 10:00:{clock} uma.outside_in INFO outside-in: {sets} frame sets, "
                f"{{'tracked': {3 * sets}, 'acquired': 3, 'refused_fit': 1, 'refused_filter': "
                f"0, 'ambiguous_blobs': 7}}, 0 samples refused, 2 late, {stale} stale; CPU per "
                "frame set: tracking 2.00 ms, publishing 0.30 ms")
    (tmp_path / "outside-in.log").write_text("\n".join(
        [report("00,000", 10, 0), report("05,000", 610, 4), report("10,000", 1210, 9)]))
    procs = live._Procs(tmp_path)
    start = time.mktime(time.strptime("2026-01-02 10:00:01", "%Y-%m-%d %H:%M:%S"))
    assert live._counts_between(procs, start, start + 9.5) == {
        "seconds": 5.0, "frame_sets": 600, "tracked": 1800, "refused_fit": 0, "late": 0,
        "stale": 5, "superseded": 0}
    assert live._counts_between(procs, start, start + 5) is None


def test_outside_in_live_stall_says_when_the_rate_came_back() -> None:
    """``bench_outside_in --live --stall``'s recovery figure: from how long after the
    stall's end every bin of exposure time had poses of nearly all its frame sets, and
    none when the last bin had not."""
    live = _outside_in_live()
    period = 1 / 120
    every = [k * period for k in range(round(4 / period))]        # 4 s of frame sets
    # nothing during the stall (1.0-1.3 s), every other frame set until 2.0 s, then all
    back = [t for t in every if not 1.0 <= t < 1.3 and (t >= 2.0 or t < 1.0
                                                         or round(t / period) % 2)]
    stall = live.Stall(1.0, 0.3)
    got = stall.recovery({"a": [round(t * 1e9) for t in back],
                          "b": [round(t * 1e9) for t in every]}, 120.0, 0.0, 4.0)["stall"]
    assert got["recovered_after_s"] == 0.7 and got["share_by_bin"][:4] == [1.0] * 4
    assert min(got["share_by_bin"][4:8]) < 0.6 and got["share_by_bin"][8:] == [1.0] * 8
    never = [t for t in back if t < 3.75]
    assert stall.recovery({"a": [round(t * 1e9) for t in never]}, 120.0, 0.0,
                          4.0)["stall"]["recovered_after_s"] is None
