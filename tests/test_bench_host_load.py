"""bench_host_load at a tiny size: every figure the issue's table asks for is there and
sane (the figures themselves are the benchmark's business, not the test's)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_bench_host_load_reports_every_figure() -> None:
    out = subprocess.run([sys.executable, "bench/bench_host_load.py", "--services", "4",
                          "--per-process", "2", "--rate", "10", "--agents", "2",
                          "--seconds", "2", "--json"], cwd=ROOT, capture_output=True,
                         text=True, timeout=240)
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["cpu"]
    row = report["rows"][0]
    assert row["services"] == 4 and row["uma_services_listed"] == 4
    assert row["uma_services_ok"] == "3/3" and row["uma_query_ok"] == "3/3"
    assert row["tcp_links"]["services"] == [1, 1]  # clients of their agent: one link each
    assert all(c >= 0 for c in row["agents_cpu_pct"]) and row["services_cpu_pct"] >= 0
    assert row["anchor"]["publishers_cpu_pct"] >= 0
    assert 0 < row["client_pose"]["median_ms"] <= row["client_pose"]["p99_ms"]
    assert row["new_need_first_sample_ms"] is not None and row["need_received"] > 0
    assert row["need_lost"] == 0
