"""``uma view`` under load: page update latency, the viewer's CPU, many frames.

Real processes on loopback: one agent (``uma agent``), a publisher (this script with
``--publish``: one service with N pose abilities, every frame moving, at RATE Hz each),
``uma view`` on it, and the page open in a headless Chromium (Selenium; the distribution's
``chromium`` and ``chromium-driver``).

- **page update latency**: from a sample's own time (taken just before it is published) to
  the moment the page's text shows it as the newest sample drawn (a MutationObserver in the
  page stamps every change of that text; both clocks are this host's).  The 3D scene is
  sent in the same redraw as that text.
- **age at the view**: the same sample's age when the view drew it (the page's text says
  it): what the page's latency owes to the data path (publisher, agent, digest) rather than
  to the page.
- **viewer CPU**: the ``uma view`` process's user+system time over the measured window, in
  % of one core.
- The anchor, measured in the same run: the same with 1 frame at RATE Hz.
- ``--demo``: instead, ``uma demo --view`` with the page open; the view's CPU and latency
  while the demo runs.

    python bench/bench_view.py [--frames 200] [--rate 100] [--seconds 10] [--demo] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
from summary import cpu_model, median_p99, report

ROOT = str(Path(__file__).resolve().parents[1])
#: the Zenoh lease of every process here (ms): 20,000 samples/s through one agent on a
#: loaded 2-core host let the default 1 s lapse (the agent then looks gone for a moment)
LEASE_MS = "5000"
sys.path.insert(0, str(Path(ROOT) / "tests"))
from agent_helpers.browser import chromium_driver, page_text  # noqa: E402

from agent.runtime.processes import stop_processes  # noqa: E402

OBSERVER = """
window.__uma = [];
new MutationObserver(records => {
  const now = performance.timeOrigin + performance.now();
  for (const r of records) {
    const m = (r.target.textContent || "").match(
      /newest sample drawn: t=(\\d+) ns \\((-?\\d+) ms old\\)/);
    if (m) { window.__uma.push([now - Number(m[1]) / 1e6, Number(m[2])]); break; }
  }
}).observe(document.body, {subtree: true, childList: true, characterData: true});
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _uma(*args: str, out: int | None = subprocess.DEVNULL) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=ROOT, UMA_LEASE_MS=LEASE_MS)
    log = open(f"/tmp/bench_view_{args[0]}.log", "w")  # noqa: SIM115
    return subprocess.Popen([sys.executable, "-m", "agent.cli", *args], env=env, cwd=ROOT,
                            stdout=out, stderr=log, text=True)


def _wait_listening(port: int, timeout: float = 60.0) -> None:
    """Until something accepts connections on ``port``: the agent (a service started
    before it would wait) or the view's page."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise RuntimeError(f"the agent never listened on port {port}")


def _url(view: subprocess.Popen, timeout: float = 60.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = view.stdout.readline()
        m = re.search(r"view[^\n]*(http://\S+/)", line)
        if m:
            return m.group(1)
        if not line and view.poll() is not None:
            break
    raise RuntimeError("the view never printed its address")


def measure_page(url: str, pid: int, seconds: float, ready: str) -> dict[str, float]:
    """Open the page, wait (at most 90 s) until it shows ``ready``, then measure ``seconds``;
    what the page showed is reported either way (a realm that never settles is a figure
    too: ``ready`` 0, and how many frames were placed at the end)."""
    with chromium_driver() as browser:
        browser.get(url)
        deadline = time.monotonic() + 90
        while ready not in page_text(browser) and time.monotonic() < deadline:
            time.sleep(0.2)
        reached = ready in page_text(browser)
        browser.execute_script(OBSERVER)
        cpu0, t0 = _cpu_s(pid), time.monotonic()
        time.sleep(seconds)
        cpu = (_cpu_s(pid) - cpu0) / (time.monotonic() - t0)
        shown = browser.execute_script("return window.__uma;")
        text = page_text(browser)
    latencies = [page for page, _ in shown]
    at_view = [view for _, view in shown]
    placed = re.search(r"(\d+) frame\(s\) placed", text)
    nan = float("nan")
    stats = median_p99(latencies, "ms") if latencies else {"median_ms": nan, "p99_ms": nan}
    view = ({"age_at_view_median_ms": float(np.median(at_view))} if at_view
            else {"age_at_view_median_ms": nan})
    return {**stats, **view, "updates": float(len(latencies)), "cpu_pct": 100.0 * cpu,
            "ready": float(reached), "frames_placed_at_end": float(placed.group(1)) if placed
            else 0.0, "agent_departures_seen": float(text.count("left the realm"))}


def run_frames(frames: int, rate: float, seconds: float) -> dict[str, float]:
    realm = f"bv{uuid.uuid4().hex[:8]}"
    ep = f"tcp/127.0.0.1:{_free_port()}"
    procs = []
    try:
        procs.append(_uma("agent", "--realm", realm, "--id", "bench", "--listen", ep))
        _wait_listening(int(ep.rsplit(":", 1)[1]))
        pub = subprocess.Popen(
            [sys.executable, __file__, "--publish", str(frames), "--rate", str(rate),
             "--realm", realm, "--connect", ep, "--seconds", str(seconds + 300)],
            env=dict(os.environ, PYTHONPATH=ROOT, UMA_LEASE_MS=LEASE_MS), cwd=ROOT,
            stdout=subprocess.PIPE, text=True,
            stderr=open(f"/tmp/bench_view_pub_{frames}.log", "w"))  # noqa: SIM115
        procs.append(pub)
        view = _uma("view", "--realm", realm, "--connect", ep, "--port", "0", "--root",
                    "bench/world", out=subprocess.PIPE)
        procs.append(view)
        out = measure_page(_url(view), view.pid, seconds, f"{frames + 1} frame(s) placed")
        out["published_hz_per_frame"] = _published(pub)
        return out
    finally:
        stop_processes(procs, 5.0)


def _published(pub: subprocess.Popen) -> float:
    """The publisher's own rate so far (it prints one on SIGUSR1)."""
    import signal

    pub.send_signal(signal.SIGUSR1)
    line = pub.stdout.readline()
    return float(json.loads(line)["hz"]) if line else float("nan")


def publish(frames: int, rate: float, realm: str, connect: str, seconds: float) -> None:
    """The publisher: ``frames`` frames on circles, each at ``rate`` Hz."""
    import signal

    import numpy as np

    from agent import Service

    start, sent = time.monotonic(), 0
    # first of all: SIGUSR1's default would end a publisher asked while it still registers
    signal.signal(signal.SIGUSR1, lambda *_: print(json.dumps(
        {"hz": sent / max(1e-9, time.monotonic() - start)}), flush=True))
    with Service("bench-frames", realm=realm, agent="bench", connect=[connect]) as svc:
        outs = [svc.ability(f"f{i}", type="pose6d", edge=("bench/world", f"bench/f{i:04d}"),
                            frequency_hz=rate, latency_s=0.001) for i in range(frames)]
        svc.start()
        angle0 = np.linspace(0, 2 * np.pi, frames, endpoint=False)
        q = [0.0, 0.0, 0.0, 1.0]
        start = next_at = time.monotonic()
        while time.monotonic() < start + seconds:
            a = angle0 + 0.5 * (time.monotonic() - start)
            for i, out in enumerate(outs):
                out.publish(time.time_ns(), [np.cos(a[i]), np.sin(a[i]), 0.01 * i], q)
            sent += 1
            next_at += 1.0 / rate
            time.sleep(max(0.0, next_at - time.monotonic()))


def run_demo(seconds: float) -> dict[str, float]:
    port = _free_port()
    demo = _uma("demo", "--view", "--view-port", str(port), "--seconds", str(seconds + 90),
                out=subprocess.PIPE)
    try:
        url = _url(demo, 120)
        _wait_listening(port, 120)
        view_pid = _child_view(demo.pid)
        return measure_page(url, view_pid, seconds, "alice/head")
    finally:
        stop_processes([demo], 15.0)  # SIGTERM: the demo stops its children


def _child_view(parent: int) -> int:
    """The demo's ``uma view`` child."""
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        for pid in os.listdir("/proc"):
            if not pid.isdigit():
                continue
            try:
                stat = Path(f"/proc/{pid}/stat").read_text()
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == parent and b"view" in cmd:
                return int(pid)
        time.sleep(0.2)
    raise RuntimeError("the demo's view process was not found")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--rate", type=float, default=100.0, help="Hz per frame")
    p.add_argument("--seconds", type=float, default=10.0, help="measured window")
    p.add_argument("--demo", action="store_true", help="measure the view of uma demo")
    p.add_argument("--json", action="store_true")
    p.add_argument("--publish", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--realm", help=argparse.SUPPRESS)
    p.add_argument("--connect", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.publish is not None:
        publish(args.publish, args.rate, args.realm, args.connect, args.seconds)
        return
    figures: dict[str, object] = {"cpu": cpu_model()}
    if args.demo:
        figures.update({f"demo_{k}": v for k, v in run_demo(args.seconds).items()})
    else:
        anchor = run_frames(1, args.rate, args.seconds) if args.frames > 1 else None
        many = run_frames(args.frames, args.rate, args.seconds)
        figures.update({f"anchor_1_frame_{k}": v for k, v in anchor.items()})
        figures.update({f"{args.frames}_frames_{k}": v for k, v in many.items()})
        figures["latency_ratio_to_anchor"] = many["median_ms"] / anchor["median_ms"]
        figures["cpu_ratio_to_anchor"] = many["cpu_pct"] / anchor["cpu_pct"]
    report(figures, args.json)


if __name__ == "__main__":
    main()
