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


def _tails(log_dir, lines: int = 15) -> str:
    """The end of each service's log, for a failure message."""
    out = []
    for f in sorted(log_dir.glob("*.log")):
        out.append(f"--- {f.name}\n" + "\n".join(f.read_text().splitlines()[-lines:]))
    return "\n".join(out)


@pytest.mark.slow
def test_demo_runs_end_to_end_and_stops_everything(tmp_path):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    logs = tmp_path / "logs"
    t0 = time.monotonic()
    # generous: a cold cache calibrates the simulated cameras first (~20 s on a busy CI)
    p = subprocess.run([sys.executable, "-m", "agent.cli", "demo", "--seconds", "3", "--json",
                        "--logs", str(logs)],
                       capture_output=True, text=True, timeout=240, env=env)
    wall = time.monotonic() - t0
    assert p.returncode == 0, p.stderr[-2000:] + _tails(logs)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    assert len(lines) == 1, p.stdout
    r = json.loads(lines[0])
    why = f"{r}\n{_tails(logs)}"
    assert r["ok"] and r["path"] == ["ivy/world", "alice/head"], why
    assert r["matches"]["fusion.optical"] and r["matches"]["fusion.accel"], why
    assert r["queries"] > 10 and r["stream_poses"] > 100, why
    # the subscription's health is part of the report (a loaded host may stall it)
    assert isinstance(r["stream_stalls"], int) and isinstance(r["stream_route_changes"], int)
    assert r["position_error_mm"]["median"] < 5.0, why
    assert r["orientation_error_deg"]["median"] < 0.5, why
    assert r["wall_s"] < wall + 1.0
    assert not any(_alive(pid) for pid in r["child_pids"])
    assert r["logs"] == str(logs)
    assert {f.name for f in logs.glob("*.log")} == {"laser-camera.log", "accel-rig.log",
                                                    "fusion.log"}
    assert "fusion: publishing" in (logs / "fusion.log").read_text()   # INFO lines kept


def test_demo_refuses_bad_seconds():
    p = subprocess.run([sys.executable, "-m", "agent.cli", "demo", "--seconds", "-1"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and "--seconds" in p.stderr


def test_demo_refuses_a_log_dir_that_is_a_file(tmp_path):
    f = tmp_path / "f"
    f.write_text("")
    p = subprocess.run([sys.executable, "-m", "agent.cli", "demo", "--logs", str(f)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and "--logs" in p.stderr and "not a directory" in p.stderr
