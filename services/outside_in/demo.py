"""``uma demo --outside-in``: the outside-in tracker end to end on simulated hosts.

On loopback with free ports and a realm of its own it starts three agents (``hostA``,
``hostB``, ``hostC``, as ``uma agent`` processes), the marker cameras of a simulated
4-camera rig split between the first two (``cam0``, ``cam1`` on A; ``cam2``, ``cam3`` on
B) and the reconstruction on C.  The hosts' clocks disagree: A's runs ``skew_ms`` ahead of
C's and B's as far behind (``UMA_CLOCK_SKEW_NS`` for every process of a host), as
unsynchronised machines' do; the reconstruction's SDK moves each camera's times onto C's
clock.  With ``single_host`` everything runs on one agent with one clock: the reference
the distributed figures are held against.

It measures two things against the simulator's truth: every pose the reconstruction
publishes, received by a service of the demo's own process (its times moved onto this
process's clock, which is the simulated world's), and a client on A asking for every
body's pose across the agents at 10 Hz.  It prints a summary and stops every process it
started (by PID), also on Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from agent import Client, Measurement, Service
from agent import geometry as geo
from agent.errors import UmaError
from agent.protocol import SKEW_ENV
from services.demo import Children
from services.outside_in.bodies import dump_bodies
from services.outside_in.rigfile import save_rig
from services.outside_in.simulator import SimConfig, Simulation

RATE_HZ = 20.0
FIRST_POSE_S = 60.0
CAMERAS = {"hostA": ("cam0", "cam1"), "hostB": ("cam2", "cam3")}
RECONSTRUCTION = "hostC"


def main(args: argparse.Namespace) -> int:
    report = run(float(args.seconds), int(args.seed), args.logs, float(args.skew_ms),
                 bool(args.single_host))
    print(json.dumps(report) if args.json else summary(report))
    return 0 if report["ok"] else 1


def layout(single_host: bool, skew_ms: float) -> tuple[dict[str, tuple[str, ...]], str,
                                                       dict[str, int]]:
    """Which host serves which cameras, which runs the reconstruction, each host's skew."""
    if single_host:
        return {"hostA": ("cam0", "cam1", "cam2", "cam3")}, "hostA", {"hostA": 0}
    skew = round(skew_ms * 1e6)
    return dict(CAMERAS), RECONSTRUCTION, {"hostA": skew, "hostB": -skew, RECONSTRUCTION: 0}


def run(seconds: float, seed: int, log_dir: str | None = None, skew_ms: float = 20.0,
        single_host: bool = False) -> dict[str, Any]:
    if not 0 <= skew_ms <= 1000:
        raise UmaError(f"--skew-ms must be in [0, 1000], got {skew_ms}")
    sim = Simulation(seed=seed, config=SimConfig(n_cameras=4, rate_hz=RATE_HZ))
    realm = f"demo-oi-{uuid.uuid4().hex[:8]}"
    cameras, recon, skews = layout(single_host, skew_ms)
    children = Children(Path(log_dir) if log_dir else None)
    with tempfile.TemporaryDirectory() as tmp:
        rig = save_rig(Path(tmp) / "rig.toml", sim.cameras, np.zeros((4, 6, 6)), "lab/world",
                       "lab", 0.0)
        bodies = Path(tmp) / "bodies.toml"
        bodies.write_text(dump_bodies(sim.bodies))
        eps = {h: f"tcp/127.0.0.1:{_free_port()}" for h in skews}
        env = {h: {SKEW_ENV: str(s)} for h, s in skews.items()}
        first = next(iter(eps))
        try:
            for h, ep in eps.items():
                connect = [] if h == first else ["--connect", eps[first]]
                children.start_command(f"agent-{h}", ["agent", "--realm", realm, "--id", h,
                                                      "--listen", ep, *connect], env[h])
            net = {h: ["--realm", realm, "--agent", h, "--connect", ep] for h, ep in eps.items()}
            children.start("outside-in", [*net[recon], "--rig", str(rig), "--bodies",
                                          str(bodies), "--rate-hz", str(RATE_HZ)], env[recon])
            for h, cams in cameras.items():
                children.start_command(f"marker-camera-{h}", [
                    "service", "run", "marker-camera", *net[h], "--rig", str(rig), "--sim",
                    str(seed), "--rate-hz", str(RATE_HZ),
                    *[x for c in cams for x in ("--camera", c)]], env[h])
            report = _measure(sim, realm, first, eps[first], seconds, children)
        finally:
            children.stop()
    return {**report, "hosts": {h: list(c) for h, c in cameras.items()},
            "reconstruction_on": recon, "client_on": first,
            "clock_skew_ms": {h: s / 1e6 for h, s in skews.items()}}


class _Published:
    """Every pose the reconstruction publishes, as its error against the truth."""

    def __init__(self, sim: Simulation) -> None:
        self.sim = sim
        self.names = [b.name for b in sim.bodies]
        self.errors: dict[str, list[tuple[float, float]]] = {n: [] for n in self.names}
        self.lock = threading.Lock()

    def on_sample(self, m: Measurement) -> None:
        name = m.edge[1].rsplit("/", 1)[-1] if m.edge else None
        if name not in self.errors:
            return
        p, q = self.sim.body_pose(self.names.index(name), m.t_ns / 1e9)
        dp, da = geo.pose_error(m.position, m.quaternion, p, q)
        with self.lock:
            self.errors[name].append((float(dp), float(da)))

    def reset(self) -> None:
        with self.lock:
            self.errors = {n: [] for n in self.names}


def _measure(sim: Simulation, realm: str, host: str, ep: str, seconds: float,
             children: Children) -> dict[str, Any]:
    """The client and the observer, both of ``host``'s agent (in this process, whose clock
    is the simulated world's, not that host's)."""
    names = [b.name for b in sim.bodies]
    errors: dict[str, list[tuple[float, float]]] = {n: [] for n in names}
    published = _Published(sim)
    failures = 0
    with _client(realm, ep, children) as client, \
            Service(f"observer-{uuid.uuid4().hex[:6]}", realm=realm, agent=host,
                    connect=[ep]) as observer:
        observer.need("poses", type="pose6d", edge=("lab/world", "lab/*"),
                      max_count=len(names), on_sample=published.on_sample)
        observer.start()
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
                published.reset()
            if first is not None and time.monotonic() - start > first + seconds:
                break
            time.sleep(0.1)
    with published.lock:
        poses = {n: _errors(e) for n, e in published.errors.items()}
    queried = {n: _errors(e) for n, e in errors.items()}
    ok = (first is not None and all(v["answers"] for v in queried.values())
          and all(v["answers"] for v in poses.values()))
    return {"ok": ok, "realm": realm, "first_pose_s": None if first is None else round(first, 1),
            "seconds": seconds, "failed_queries": failures, "bodies": queried,
            "published": poses}


def _errors(e: list[tuple[float, float]]) -> dict[str, Any]:
    """Median and RMS of a body's position (mm) and orientation (deg) errors."""
    if not e:
        return {"answers": 0}
    dp, da = np.array([x for x, _ in e]), np.degrees([a for _, a in e])
    return {"answers": len(e),
            "position_error_mm_median": round(float(np.median(dp)) * 1e3, 3),
            "position_error_mm_rms": round(float(np.sqrt(np.mean(dp ** 2))) * 1e3, 3),
            "orientation_error_deg_median": round(float(np.median(da)), 4),
            "orientation_error_deg_rms": round(float(np.sqrt(np.mean(da ** 2))), 4)}


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
    lines = [f"outside-in demo: cameras {r['hosts']}, the reconstruction on "
             f"{r['reconstruction_on']}, queries from {r['client_on']}, clocks skewed "
             f"{r['clock_skew_ms']} ms; first pose after {r['first_pose_s']} s; errors "
             "against the simulator's truth (median, RMS):"]
    for n, b in r["bodies"].items():
        pub = r["published"][n]
        lines.append(f"  lab/world -> lab/{n}: {pub['answers']} poses published, "
                     f"{_figures(pub)}; {b['answers']} queried, {_figures(b)}")
    lines.append("ok" if r["ok"] else "FAILED: some body got no pose")
    return "\n".join(lines)


def _figures(b: dict[str, Any]) -> str:
    if not b["answers"]:
        return "none"
    return (f"{b['position_error_mm_median']}, {b['position_error_mm_rms']} mm, "
            f"{b['orientation_error_deg_median']}, {b['orientation_error_deg_rms']} deg")


def _free_port() -> int:
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
