"""End to end: align the laser rig and the accelerometer rig from their live streams.

Starts (as child processes, stopped by their PIDs at the end) an agent, the simulated
world, the laser-camera and accel-rig trackers on their simulators, and the alignment
service with ``--a ivy/world:marvin/laser_rig --b ivy/world:marvin/accel_rig``; waits for
the calibration file and compares the edge ``marvin/laser_rig -> marvin/accel_rig`` with
the truth of ``services/sim/mounts.py``.  Real time: takes a minute or more.

    /work/venv/bin/python bench/bench_alignment_e2e.py [--timeout S] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from loopback import free_port

from agent import geometry as geo
from agent.cli.agent import load_config
from agent.daemon.settings import check_static_edge
from agent.runtime.processes import stop_processes
from services import frames
from services.sim import mounts


def _start(logdir: Path, name: str, *args: str) -> subprocess.Popen:
    log = open(logdir / f"{name}.log", "w")  # noqa: SIM115 (closed with the process)
    return subprocess.Popen([sys.executable, "-m", "agent.cli", *args], stdout=log,
                            stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))


def run(timeout: float, extra: list[str]) -> dict[str, Any]:
    realm = f"e2e{os.getpid()}"
    ep = f"tcp/127.0.0.1:{free_port()}"
    work = Path(tempfile.mkdtemp(prefix="uma-align-e2e-"))
    out = work / "alignment.toml"
    net = ["--realm", realm, "--agent", "lab", "--connect", ep]
    procs = [_start(work, "agent", "agent", "--realm", realm, "--id", "lab", "--listen", ep)]
    time.sleep(1.0)
    procs += [
        _start(work, "sim", "service", "run", "sim", *net),
        _start(work, "laser", "service", "run", "laser-camera", *net),
        _start(work, "accel", "service", "run", "accel-rig", *net),
        _start(work, "alignment", "service", "run", "alignment", *net,
               "--a", f"{frames.WORLD}:{frames.LASER_RIG}",
               "--b", f"{frames.WORLD}:{frames.ACCEL_RIG}", "--output", str(out), *extra),
    ]
    start = time.monotonic()
    try:
        while not out.exists():
            dead = [p.args[4] if len(p.args) > 4 else "agent" for p in procs
                    if p.poll() is not None]
            if dead:
                raise RuntimeError(f"exited early: {dead}; logs in {work}")
            if time.monotonic() - start > timeout:
                raise TimeoutError(f"no calibration within {timeout:.0f} s; logs in {work}")
            time.sleep(0.5)
        elapsed = time.monotonic() - start
    finally:
        stop_processes(procs, 10.0)
    edge = check_static_edge(load_config(str(out))["static"][0], 0)
    true_p, true_q = geo.compose(*geo.inverse(*mounts.HEAD_TO_LASER_RIG),
                                 *mounts.HEAD_TO_ACCEL_RIG)
    dp, dr = geo.pose_error(np.array(edge["position"]), np.array(edge["quaternion"]),
                            true_p, true_q)
    return {"edge": f"{edge['parent']} -> {edge['child']}",
            "seconds_to_calibration": elapsed,
            "position_error_mm": 1e3 * float(dp), "rotation_error_deg": float(np.degrees(dr)),
            "reported_pos_std_mm": 1e3 * edge["pos_std_m"],
            "reported_rot_std_deg": float(np.degrees(edge["rot_std_rad"])),
            "calibration_file": out.read_text(), "logs": str(work)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timeout", type=float, default=300.0,
                        help="seconds to wait for the calibration (default 300)")
    parser.add_argument("--json", action="store_true", help="last line: one JSON object")
    parser.add_argument("extra", nargs="*", help="extra options for the alignment service "
                                                 "(after --)")
    args = parser.parse_args()
    figures = run(args.timeout, args.extra)
    for key, value in figures.items():
        print(f"{key}: {value}")
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
