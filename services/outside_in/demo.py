"""``uma demo --outside-in``: the outside-in tracker end to end on two simulated hosts.

On loopback with free ports and a realm of its own it starts two agents (``hostA`` and
``hostB``, as ``uma agent`` processes), the marker cameras of a simulated 4-camera rig
split between them (``cam0``, ``cam1`` on A; ``cam2``, ``cam3`` on B), the reconstruction
on B, and a client on A that asks for every body's pose across the agents at 10 Hz and
compares it with the simulator's truth.  It prints a summary and stops every process it
started (by PID), also on Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from agent import Client
from agent import geometry as geo
from agent.errors import UmaError
from services.demo import Children
from services.outside_in.bodies import dump_bodies
from services.outside_in.rigfile import save_rig
from services.outside_in.simulator import SimConfig, Simulation

RATE_HZ = 20.0
FIRST_POSE_S = 60.0
HOSTS = {"hostA": ("cam0", "cam1"), "hostB": ("cam2", "cam3")}


def main(args: argparse.Namespace) -> int:
    report = run(float(args.seconds), int(args.seed), args.logs)
    print(json.dumps(report) if args.json else summary(report))
    return 0 if report["ok"] else 1


def run(seconds: float, seed: int, log_dir: str | None = None) -> dict[str, Any]:
    sim = Simulation(seed=seed, config=SimConfig(n_cameras=4, rate_hz=RATE_HZ))
    realm = f"demo-oi-{uuid.uuid4().hex[:8]}"
    children = Children(Path(log_dir) if log_dir else None)
    with tempfile.TemporaryDirectory() as tmp:
        rig = save_rig(Path(tmp) / "rig.toml", sim.cameras, np.zeros((4, 6, 6)), "lab/world",
                       "lab", 0.0)
        bodies = Path(tmp) / "bodies.toml"
        bodies.write_text(dump_bodies(sim.bodies))
        eps = {h: f"tcp/127.0.0.1:{_free_port()}" for h in HOSTS}
        try:
            for h, ep in eps.items():
                connect = [] if h == "hostA" else ["--connect", eps["hostA"]]
                children.start_command(f"agent-{h}", ["agent", "--realm", realm, "--id", h,
                                                      "--listen", ep, *connect])
            net = {h: ["--realm", realm, "--agent", h, "--connect", ep] for h, ep in eps.items()}
            children.start("outside-in", [*net["hostB"], "--rig", str(rig), "--bodies",
                                          str(bodies), "--rate-hz", str(RATE_HZ)])
            for h, cams in HOSTS.items():
                children.start_command(f"marker-camera-{h}", [
                    "service", "run", "marker-camera", *net[h], "--rig", str(rig), "--sim",
                    str(seed), "--rate-hz", str(RATE_HZ),
                    *[x for c in cams for x in ("--camera", c)]])
            return _measure(sim, realm, eps["hostA"], seconds, children)
        finally:
            children.stop()


def _measure(sim: Simulation, realm: str, ep: str, seconds: float,
             children: Children) -> dict[str, Any]:
    names = [b.name for b in sim.bodies]
    errors: dict[str, list[tuple[float, float]]] = {n: [] for n in names}
    failures = 0
    with _client(realm, ep, children) as client:
        start = time.monotonic()
        first = None
        while time.monotonic() - start < FIRST_POSE_S + seconds:
            if children.dead():
                raise UmaError(f"a demo process ended: {children.dead()}")
            got = False
            for k, n in enumerate(names):
                try:
                    r = client.pose("lab/world", f"lab/{n}")
                except (UmaError, LookupError):
                    failures += first is not None
                    continue
                p, q = sim.body_pose(k, r.t_ns / 1e9)
                dp, da = geo.pose_error(r.position, r.quaternion, p, q)
                errors[n].append((float(dp), float(da)))
                got = True
            if got and first is None:
                first = time.monotonic() - start
                errors = {n: [] for n in names}   # measure from here on
            if first is not None and time.monotonic() - start > first + seconds:
                break
            time.sleep(0.1)
    per_body = {n: {"answers": len(e),
                    "position_error_mm_median": round(float(np.median([x for x, _ in e]))
                                                      * 1e3, 3) if e else None,
                    "orientation_error_deg_median": round(float(np.degrees(np.median(
                        [a for _, a in e]))), 4) if e else None} for n, e in errors.items()}
    ok = first is not None and all(v["answers"] for v in per_body.values())
    return {"ok": ok, "realm": realm, "first_pose_s": None if first is None else round(first, 1),
            "seconds": seconds, "hosts": {h: list(c) for h, c in HOSTS.items()},
            "reconstruction_on": "hostB", "client_on": "hostA", "failed_queries": failures,
            "bodies": per_body}


def _client(realm: str, ep: str, children: Children) -> Client:
    """A client of host A's agent, once that agent listens."""
    deadline = time.monotonic() + FIRST_POSE_S
    while True:
        try:
            return Client(realm=realm, connect=[ep])
        except UmaError:
            if children.dead() or time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def summary(r: dict[str, Any]) -> str:
    lines = [f"outside-in demo: cameras {r['hosts']} on two agents, the reconstruction on "
             f"{r['reconstruction_on']}, queries from {r['client_on']}; first pose after "
             f"{r['first_pose_s']} s"]
    for n, b in r["bodies"].items():
        lines.append(f"  lab/world -> lab/{n}: {b['answers']} answers, error median "
                     f"{b['position_error_mm_median']} mm, {b['orientation_error_deg_median']}"
                     " deg against the simulator's truth")
    lines.append("ok" if r["ok"] else "FAILED: some body got no pose")
    return "\n".join(lines)


def _free_port() -> int:
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
