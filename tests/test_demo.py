"""``uma demo``: the whole system in one command, in a subprocess like a user runs it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

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
    # dot mode by default: the fusion also takes the laser tracker's labeled dots
    assert r["optical"] == "dots" and r["matches"]["fusion.dots"], why
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


@pytest.mark.parametrize("which", [[], ["--outside-in"], ["--cameras"]])
def test_demo_refuses_a_log_dir_that_is_a_file(tmp_path, which):
    f = tmp_path / "f"
    f.write_text("")
    p = subprocess.run([sys.executable, "-m", "agent.cli", "demo", *which, "--logs", str(f)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and "--logs" in p.stderr and "not a directory" in p.stderr


@pytest.mark.slow
def test_demo_view_serves_the_page_and_sigterm_stops_everything():
    """``uma demo --view``: the view's page is served on the port asked for; SIGTERM stops
    the demo and every process it started (the view included)."""
    import signal
    import socket
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([sys.executable, "-m", "agent.cli", "demo", "--view", "--view-port",
                          str(port), "--seconds", "120"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline, page = time.monotonic() + 120, ""
        while time.monotonic() < deadline and p.poll() is None and "viser" not in page:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5) as r:
                    page = r.read().decode("utf-8", "replace")
            except OSError:
                time.sleep(0.5)
        assert "viser" in page.lower(), f"no page on port {port}: exit {p.poll()}"
        children = _children(p.pid)
        assert any(b"view" in cmd for cmd in children.values()), children
    finally:
        p.send_signal(signal.SIGTERM)
        p.wait(60)
    assert p.returncode == 130, p.stderr.read()[-2000:]
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in children), children


def _children(parent: int) -> dict[int, bytes]:
    """The child processes of ``parent`` and their command lines."""
    out = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
                cmd = Path(f"/proc/{entry}/cmdline").read_bytes()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == parent:
                out[int(entry)] = cmd
    return out
