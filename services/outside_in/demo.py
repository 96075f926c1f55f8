"""``uma demo --outside-in``: the outside-in tracker end to end on simulated hosts.

On loopback with free ports and a realm of its own it starts three agents (``hostA``,
``hostB``, ``hostC``, as ``uma agent`` processes), the marker cameras of a simulated
4-camera rig split between the first two (``cam0``, ``cam1`` on A; ``cam2``, ``cam3`` on
B) and the reconstruction on C.  The hosts' clocks disagree: A's runs ``skew_ms`` ahead of
C's and B's as far behind (``UMA_CLOCK_SKEW_NS`` for every process of a host), as
unsynchronised machines' do; the reconstruction's SDK moves each camera's times onto C's
clock.  With ``single_host`` everything runs on one agent with one clock: the reference
the distributed figures are held against.  ``compare`` runs both at once, each in a realm
of its own, on the same simulated frames (a simulated camera's frame is a function of the
seed, the camera and its exposure time alone, and both layouts' cameras expose at the same
times): the poses of one frame set in either layout then differ by what the distribution
does alone, not by other motion, other noise or other load.

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
    if args.compare:
        report = compare(float(args.seconds), int(args.seed), args.logs, float(args.skew_ms))
        text = compare_summary
    else:
        report = run(float(args.seconds), int(args.seed), args.logs, float(args.skew_ms),
                     bool(args.single_host))
        text = summary
    print(json.dumps(report) if args.json else text(report))
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
    """One layout: its poses and queries against the truth."""
    report = _run_layouts(seconds, seed, log_dir, skew_ms, (single_host,))[0]
    report.pop("published_at")
    return report


def compare(seconds: float, seed: int, log_dir: str | None = None,
            skew_ms: float = 20.0) -> dict[str, Any]:
    """The single-host and the three-host layouts at once on the same simulated frames:
    each one's figures, and the two held against each other on the frame sets both
    published a pose of (``paired``)."""
    one, three = _run_layouts(seconds, seed, log_dir, skew_ms, (True, False))
    paired = _paired(one.pop("published_at"), three.pop("published_at"))
    return {"ok": one["ok"] and three["ok"], "seed": seed, "single_host": one,
            "three_hosts": three, "paired": paired}


def _run_layouts(seconds: float, seed: int, log_dir: str | None, skew_ms: float,
                 layouts: tuple[bool, ...]) -> list[dict[str, Any]]:
    """Each layout (single host or not) started in a realm of its own and measured at the
    same time; their reports in that order."""
    if not 0 <= skew_ms <= 1000:
        raise UmaError(f"--skew-ms must be in [0, 1000], got {skew_ms}")
    sim = Simulation(seed=seed, config=SimConfig(n_cameras=4, rate_hz=RATE_HZ))
    children = Children(Path(log_dir) if log_dir else None)
    with tempfile.TemporaryDirectory() as tmp:
        rig = save_rig(Path(tmp) / "rig.toml", sim.cameras, np.zeros((4, 6, 6)), "lab/world",
                       "lab", 0.0)
        bodies = Path(tmp) / "bodies.toml"
        bodies.write_text(dump_bodies(sim.bodies))
        try:
            started = [_launch(children, seed, rig, bodies, single, skew_ms,
                               ("one-" if single else "three-") if len(layouts) > 1 else "")
                       for single in layouts]
            reports: list[dict[str, Any]] = [{} for _ in layouts]

            def measure(k: int) -> None:
                try:
                    reports[k] = _measure(sim, started[k], seconds, children)
                except UmaError as e:
                    reports[k] = {"ok": False, "error": str(e)}
            threads = [threading.Thread(target=measure, args=(k,), daemon=True)
                       for k in range(len(layouts))]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
        finally:
            children.stop()
    for r in reports:
        if "error" in r:
            raise UmaError(r["error"])
    return [{**r, **{k: v for k, v in st.items() if k != "eps"}}
            for r, st in zip(reports, started, strict=True)]


def _launch(children: Children, seed: int, rig: Path, bodies: Path, single_host: bool,
            skew_ms: float, prefix: str) -> dict[str, Any]:
    """One layout's agents and services (their names prefixed by ``prefix``) in a realm of
    its own; where its client connects."""
    realm = f"demo-oi-{uuid.uuid4().hex[:8]}"
    cameras, recon, skews = layout(single_host, skew_ms)
    eps = {h: f"tcp/127.0.0.1:{_free_port()}" for h in skews}
    env = {h: {SKEW_ENV: str(s)} for h, s in skews.items()}
    first = next(iter(eps))
    for h, ep in eps.items():
        connect = [] if h == first else ["--connect", eps[first]]
        children.start_command(f"{prefix}agent-{h}", ["agent", "--realm", realm, "--id", h,
                                                      "--listen", ep, *connect], env[h])
    net = {h: ["--realm", realm, "--agent", h, "--connect", ep] for h, ep in eps.items()}
    children.start_command(f"{prefix}outside-in", [
        "service", "run", "outside-in", *net[recon], "--rig", str(rig), "--bodies",
        str(bodies), "--rate-hz", str(RATE_HZ)], env[recon])
    for h, cams in cameras.items():
        children.start_command(f"{prefix}marker-camera-{h}", [
            "service", "run", "marker-camera", *net[h], "--rig", str(rig), "--sim",
            str(seed), "--rate-hz", str(RATE_HZ),
            *[x for c in cams for x in ("--camera", c)]], env[h])
    return {"realm": realm, "eps": eps, "hosts": {h: list(c) for h, c in cameras.items()},
            "reconstruction_on": recon, "client_on": first,
            "clock_skew_ms": {h: s / 1e6 for h, s in skews.items()}}


class _Published:
    """Every pose the reconstruction publishes, as its error against the truth."""

    def __init__(self, sim: Simulation) -> None:
        self.sim = sim
        self.names = [b.name for b in sim.bodies]
        self.errors: dict[str, list[tuple[float, float]]] = {n: [] for n in self.names}
        #: the same by frame set (its exposure's frame index)
        self.at: dict[str, dict[int, tuple[float, float, float]]] = {n: {} for n in self.names}
        self.lock = threading.Lock()

    def on_sample(self, m: Measurement) -> None:
        name = m.edge[1].rsplit("/", 1)[-1] if m.edge else None
        if name not in self.errors:
            return
        p, q = self.sim.body_pose(self.names.index(name), m.t_ns / 1e9)
        dp, da = geo.pose_error(m.position, m.quaternion, p, q)
        with self.lock:
            self.errors[name].append((float(dp), float(da)))
            index = round(m.t_ns * RATE_HZ / 1e9)
            self.at[name][index] = (float(dp), float(da), m.t_ns - index * 1e9 / RATE_HZ)

    def seen_all(self) -> bool:
        """Whether every body has had a pose since the last reset."""
        with self.lock:
            return all(self.errors.values())

    def reset(self) -> None:
        with self.lock:
            self.errors = {n: [] for n in self.names}
            self.at = {n: {} for n in self.names}


def _measure(sim: Simulation, started: dict[str, Any], seconds: float,
             children: Children) -> dict[str, Any]:
    """The client, of the first host's agent, and the observer, of the reconstruction's
    (both in this process, whose clock is the simulated world's and the reconstruction's
    host's: the poses are held against the truth at the times the reconstruction gave
    them, not at those times moved by this process's own estimate of that host's clock,
    whose error is no error of the reconstruction's)."""
    realm, host, recon = started["realm"], started["client_on"], started["reconstruction_on"]
    ep = started["eps"][host]
    names = [b.name for b in sim.bodies]
    errors: dict[str, list[tuple[float, float]]] = {n: [] for n in names}
    published = _Published(sim)
    failures = 0
    with _client(realm, ep, children) as client, \
            Service(f"observer-{uuid.uuid4().hex[:6]}", realm=realm, agent=recon,
                    connect=[started["eps"][recon]]) as observer:
        observer.need("poses", type="pose6d", edge=("lab/world", "lab/*"),
                      max_count=len(names), on_sample=published.on_sample)
        observer.start()
        start = time.monotonic()
        first = None
        # when each link first carried every body: which one came late, if one did
        links: dict[str, float] = {}
        answered: set[str] = set()
        while time.monotonic() - start < FIRST_POSE_S + seconds:
            if children.dead():
                raise UmaError(f"a demo process ended: {children.dead()}")
            for k, n in enumerate(names):
                try:
                    r = client.pose("lab/world", f"lab/{n}")
                except (UmaError, LookupError):
                    failures += first is not None
                    continue
                p, q = sim.body_pose(k, r.t_ns / 1e9)
                dp, da = geo.pose_error(r.position, r.quaternion, p, q)
                errors[n].append((float(dp), float(da)))
                answered.add(n)
            _first_time(links, "queries", len(answered) == len(names), start)
            if first is None:   # the measurement starts after it
                _first_time(links, "published", published.seen_all(), start)
            # measured from when both the client's queries and the observer's stream
            # carry every body: on a loaded host the observer's link can come later
            if first is None and len(links) == 2:
                first = time.monotonic() - start
                errors = {n: [] for n in names}   # measure from here on
                published.reset()
            if first is not None and time.monotonic() - start > first + seconds:
                break
            time.sleep(0.1)
    with published.lock:
        poses = {n: _errors(e) for n, e in published.errors.items()}
        at = {n: dict(e) for n, e in published.at.items()}
    queried = {n: _errors(e) for n, e in errors.items()}
    ok = (first is not None and all(v["answers"] for v in queried.values())
          and all(v["answers"] for v in poses.values()))
    return {"ok": ok, "realm": realm, "first_pose_s": None if first is None else round(first, 1),
            "first_every_body_s": links,
            "seconds": seconds, "failed_queries": failures, "bodies": queried,
            "published": poses, "published_at": at}


def _first_time(links: dict[str, float], link: str, carried: bool, start: float) -> None:
    """Note when ``link`` first ``carried`` every body (s since ``start``, monotonic)."""
    if carried and link not in links:
        links[link] = round(time.monotonic() - start, 1)


def _paired(one: dict[str, dict[int, tuple[float, float, float]]],
            three: dict[str, dict[int, tuple[float, float, float]]]) -> dict[str, Any]:
    """Both layouts' poses of the frame sets both published one of, per body: each one's
    median error there and their ratio (three hosts over one), how far the two poses'
    errors and times differ (the distribution's own effect on a pose, as the frames are
    the same), and the frame sets of the time both measured that only one posed; over
    the bodies, the median of the bodies' ratios."""
    out: dict[str, Any] = {}
    for n in one:
        common = sorted(set(one[n]) & set(three[n]))
        if not common:
            out[n] = {"frame_sets": 0}
            continue
        # frame sets of the time both measured: the measurements start at different times
        lo, hi = max(min(one[n]), min(three[n])), min(max(one[n]), max(three[n]))
        a_only = sum(lo <= i <= hi for i in set(one[n]) - set(three[n]))
        b_only = sum(lo <= i <= hi for i in set(three[n]) - set(one[n]))
        a = np.array([one[n][i] for i in common])
        b = np.array([three[n][i] for i in common])
        med_a, med_b = np.median(a[:, :2], axis=0), np.median(b[:, :2], axis=0)
        diff = np.abs(b - a)
        out[n] = {"frame_sets": len(common),
                  "only_single_host": a_only, "only_three_hosts": b_only,
                  "single_host_mm_deg": [round(float(med_a[0]) * 1e3, 4),
                                         round(float(np.degrees(med_a[1])), 5)],
                  "three_hosts_mm_deg": [round(float(med_b[0]) * 1e3, 4),
                                         round(float(np.degrees(med_b[1])), 5)],
                  "ratio": [round(float(med_b[0] / med_a[0]), 4),
                            round(float(med_b[1] / med_a[1]), 4)],
                  "error_difference_median_mm_deg": [
                      round(float(np.median(diff[:, 0])) * 1e3, 5),
                      round(float(np.degrees(np.median(diff[:, 1]))), 6)],
                  "error_difference_max_mm_deg": [
                      round(float(np.max(diff[:, 0])) * 1e3, 4),
                      round(float(np.degrees(np.max(diff[:, 1]))), 5)],
                  # the pose's time, three hosts less one: the clock offsets' error
                  "time_difference_median_max_ms": [round(float(np.median(diff[:, 2])) / 1e6, 4),
                                                    round(float(np.max(diff[:, 2])) / 1e6, 4)]}
    ratios = np.array([b["ratio"] for b in out.values() if "ratio" in b])
    out["median_ratio"] = ([round(float(x), 4) for x in np.median(ratios, axis=0)]
                           if len(ratios) else None)
    return out


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
             f"{r['clock_skew_ms']} ms; first pose after {r['first_pose_s']} s "
             f"(every body's: {_links(r['first_every_body_s'])}); errors "
             "against the simulator's truth (median, RMS):"]
    for n, b in r["bodies"].items():
        pub = r["published"][n]
        lines.append(f"  lab/world -> lab/{n}: {pub['answers']} poses published, "
                     f"{_figures(pub)}; {b['answers']} queried, {_figures(b)}")
    lines.append("ok" if r["ok"] else "FAILED: some body got no pose")
    return "\n".join(lines)


def compare_summary(r: dict[str, Any]) -> str:
    lines = [f"outside-in demo, seed {r['seed']}: one host and three hosts at once on the "
             "same simulated frames"]
    for key, title in (("single_host", "one host"), ("three_hosts", "three hosts")):
        lines.append(f"{title}: " + summary(r[key]).replace("\n", "\n  "))
    lines.append("the frame sets both published a pose of (median errors, three hosts over "
                 "one):")
    for n, b in r["paired"].items():
        if n == "median_ratio" or not b.get("frame_sets"):
            continue
        lines.append(f"  {n}: {b['frame_sets']} frame sets, {b['single_host_mm_deg']} -> "
                     f"{b['three_hosts_mm_deg']} mm/deg, ratio {b['ratio']}, poses differing "
                     f"by {b['error_difference_median_mm_deg']} (median) mm/deg, their "
                     f"times by {b['time_difference_median_max_ms']} ms (median, max)")
    lines.append(f"median ratio over the bodies (position, orientation): "
                 f"{r['paired']['median_ratio']}")
    return "\n".join(lines)


def _links(first: dict[str, float]) -> str:
    """When each link first carried every body, for the summary ("none" if none did)."""
    return ", ".join(f"{k} {v} s" for k, v in first.items()) or "none"


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
