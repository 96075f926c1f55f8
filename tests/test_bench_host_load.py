"""bench_host_load at a tiny size: every figure the issue's table asks for is there and
sane (the figures themselves are the benchmark's business, not the test's)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_bench_host_load_reports_every_figure() -> None:
    out = subprocess.run([sys.executable, "bench/bench_host_load.py", "--services", "4",
                          "--per-process", "2", "--rate", "10", "--agents", "2",
                          "--seconds", "3", "--json"], cwd=ROOT, capture_output=True,
                         text=True, timeout=240)
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["cpu"]
    row = report["rows"][0]
    assert (row["services"], row["processes"], row["agents"]) == (4, 2, 2)
    assert row["uma_services_listed"] == 4
    assert (row["uma_services_ok"], row["uma_query_ok"]) == ("3/3", "3/3"), row["uma_cli_errors"]
    assert 0 < row["uma_services_median_s"] <= row["uma_services_max_s"]
    assert 0 < row["uma_query_median_s"] <= row["uma_query_max_s"]
    # two agents linked to each other, two service processes to the first agent: every
    # link counted at both ends
    assert row["tcp_links_max_per_service_process"] == 1  # a client of its agent
    assert row["tcp_links_agents"] == [3, 1] and row["tcp_links_total"] == 6
    assert len(row["agents_cpu_pct"]) == 2 and all(c >= 0 for c in row["agents_cpu_pct"])
    assert row["services_cpu_pct"] >= 0 and row["bare_publishers_cpu_pct"] >= 0
    assert row["services_rss_mb"] > 2 * row["process_base_rss_mb"] > 0
    assert row["bare_published_hz"] == 40 and row["bare_delivered_hz"] > 20
    assert row["client_pose_ok"] == "200/200" and row["client_pose_failures"] == {}
    assert 0 < row["client_pose_median_ms"] <= row["client_pose_p99_ms"]
    assert row["new_need_first_sample_ms"] > 0 and row["need_received"] > 0
    assert row["need_lost"] == 0 and row["need_received"] == row["need_published"]
    assert 5 < row["need_source_hz"] < 15  # the source's 10 Hz
    assert isinstance(row["goals_missed"], list)


def test_bench_host_load_refuses_an_uneven_split() -> None:
    out = subprocess.run([sys.executable, "bench/bench_host_load.py", "--services", "5",
                          "--per-process", "2"], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2
    assert "5 services do not split into processes of --per-process 2" in out.stderr
