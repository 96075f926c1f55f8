"""``uma demo``: the whole system in one command, in a subprocess like a user runs it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.slow
def test_demo_runs_end_to_end_and_stops_everything():
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    t0 = time.monotonic()
    # generous: a cold cache calibrates the simulated cameras first (~20 s on a busy CI)
    p = subprocess.run([sys.executable, "-m", "agent.cli", "demo", "--seconds", "3", "--json"],
                       capture_output=True, text=True, timeout=240, env=env)
    wall = time.monotonic() - t0
    assert p.returncode == 0, p.stderr[-2000:]
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    assert len(lines) == 1, p.stdout
    r = json.loads(lines[0])
    assert r["ok"] and r["path"] == ["ivy/world", "marvin/head"]
    assert r["matches"]["fusion.optical"] and r["matches"]["fusion.accel"]
    assert r["queries"] > 10 and r["stream_poses"] > 100
    assert r["position_error_mm"]["median"] < 5.0
    assert r["orientation_error_deg"]["median"] < 0.5
    assert r["wall_s"] < wall + 1.0
    assert not any(_alive(pid) for pid in r["child_pids"])


def test_demo_refuses_bad_seconds():
    p = subprocess.run([sys.executable, "-m", "agent.cli", "demo", "--seconds", "-1"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and "--seconds" in p.stderr
