"""``uma demo``: the embedded default -- the whole MARVIN tracking system in one command.

With no set-up and no hardware, on loopback with free ports, multicast off and a realm of
its own, it starts

* two agents in this process: ``tracking`` (the tracking host, whose SRG holds the rig
  mountings as static edges) and ``application`` (the application host, connected to it);
* the tracker services as child processes registered with ``tracking``: the laser-dot
  camera on the rendered IVY display, the accelerometer rig simulator and the fusion, by
  default in dot mode (one SCAAT update per labeled laser dot, also of frame sets without
  a pose: on seeds 1-10 more accurate than pose updates with an equally honest covariance,
  docs/FUSION_TUNING.md), its walls from the laser tracker's calibration file;
* a client on the application host that queries ``ivy/world -> alice/head`` across the
  two agents (``Client.pose``) and streams it (``Client.subscribe``), and compares every
  answer with the simulator's ground truth.

It prints a live line per second and a summary (``--json``: one JSON object), and stops
every process it started, also on Ctrl-C or an error.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.errors import UmaError
from agent.runtime import lease_ms_default, stop_processes
from services import frames
from services.figures import error_stats
from services.sim import mounts

log = logging.getLogger("uma.demo")

SERVICES = ("laser-camera", "accel-rig", "fusion")
#: where a recorded demo's simulator publishes the true head: not ``*/head``, so neither
#: queries of the tracked head nor needs of one ever reach the truth
TRUTH_FRAME = "alice/head_truth"
#: the recorder's start-up (imports, session) and its clean stop (writing the summary)
RECORDER_START_S = 30.0
RECORDER_STOP_S = 20.0
#: how long the fused pose may take to appear after the services start (s)
FIRST_POSE_TIMEOUT_S = 30.0
QUERY_HZ = 20.0
#: the fused pose is the one-hop path; the optical and dead-reckoned poses reach the head
#: through a rig's static mounting (two hops)
ERROR = "hops"
STOP_TIMEOUT_S = 3.0
#: the Zenoh lease of the demo's agents and services (ms), unless UMA_LEASE_MS says
#: otherwise.  Everything runs on this host, where a process that dies is seen at once (its
#: sockets close); the lease only decides when a *frozen* one counts as gone.  The default
#: 1 s lapsed on a host loaded to three demos per two cores, and the application host lost
#: its route for a moment.  The demo shows no failover, so it waits longer.
DEMO_LEASE_MS = 5000


def _free_endpoint() -> str:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _static_edges() -> list[dict[str, Any]]:
    """The rig mountings as the tracking host's static SRG edges (its calibration)."""
    edges = []
    for child, (p, q) in ((frames.LASER_RIG, mounts.HEAD_TO_LASER_RIG),
                          (frames.ACCEL_RIG, mounts.HEAD_TO_ACCEL_RIG)):
        edges.append({"parent": frames.HEAD, "child": child, "position": list(map(float, p)),
                      "quaternion": list(map(float, q))})
    return edges


@dataclass
class Tally:
    """What the client saw."""

    latencies_s: list[float] = field(default_factory=list)
    pos_err_m: list[float] = field(default_factory=list)
    rot_err_rad: list[float] = field(default_factory=list)
    stream_times: list[float] = field(default_factory=list)
    stream_pos_err_m: list[float] = field(default_factory=list)
    #: the subscription's own count of silent spells and route moves
    stream_stalls: int = 0
    stream_route_changes: int = 0
    failures: dict[str, int] = field(default_factory=dict)
    path: list[str] = field(default_factory=list)
    last: tuple[np.ndarray, np.ndarray] | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)

    def fail(self, why: str) -> None:
        with self.lock:
            self.failures[why] = self.failures.get(why, 0) + 1


class Children:
    """Service child processes, always stopped (SIGTERM, then SIGKILL) by their PID; their
    logs go to ``log_dir/<name>.log`` if given, else to temporary files."""

    def __init__(self, log_dir: Path | None = None, lease_ms: int = DEMO_LEASE_MS) -> None:
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Any] = {}
        self.log_dir = log_dir
        self.lease_ms = lease_ms

    def start(self, name: str, argv: list[str], env: dict[str, str] | None = None) -> None:
        """The service ``name`` (``uma service run NAME ARGV``)."""
        self.start_command(name, ["service", "run", name, *argv], env)

    def start_command(self, name: str, argv: list[str], env: dict[str, str] | None = None,
                      ) -> None:
        """``uma ARGV``, its log kept as ``name``'s; ``env`` on top of this process's."""
        env = dict(os.environ, PYTHONUNBUFFERED="1", UMA_LEASE_MS=str(self.lease_ms),
                   **(env or {}))
        # a file, not a pipe: a chatty child must never block on a full pipe (closed in stop())
        log_file = (tempfile.TemporaryFile("w+") if self.log_dir is None  # noqa: SIM115
                    else open(self.log_dir / f"{name}.log", "w+"))  # noqa: SIM115
        self.logs[name] = log_file
        self.procs[name] = subprocess.Popen(
            [sys.executable, "-m", "agent.cli", *argv],
            env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=log_file, text=True)

    def dead(self) -> dict[str, str]:
        """Children that exited, with the last line of their error output."""
        out = {}
        for name, p in self.procs.items():
            if p.poll() is not None:
                f = self.logs[name]
                f.seek(0)
                lines = f.read().strip().splitlines()
                out[name] = f"exit {p.returncode}: {lines[-1] if lines else 'no output'}"
        return out

    def stop(self) -> None:
        stop_processes(self.procs.values(), STOP_TIMEOUT_S)
        for f in self.logs.values():
            f.close()


def _interrupted(*_: object) -> None:
    raise KeyboardInterrupt


def main(args: argparse.Namespace) -> int:
    # SIGTERM stops the demo as Ctrl-C does, through run_demo's cleanup: without this it
    # ended the process at once and left its child processes running
    signal.signal(signal.SIGTERM, _interrupted)
    seconds = float(args.seconds)
    if not (math.isfinite(seconds) and 0 < seconds <= 3600):
        raise UmaError(f"--seconds must be in (0, 3600], got {args.seconds!r}")
    logging.getLogger("uma").setLevel(logging.WARNING)
    log_dir = None
    if args.logs is not None:
        log_dir = Path(args.logs)
        if log_dir.exists() and not log_dir.is_dir():
            raise UmaError(f"--logs {args.logs}: exists and is not a directory")
        log_dir.mkdir(parents=True, exist_ok=True)
    if args.cameras:
        from services.fiducials.demo import main as cameras

        return cameras(args)
    if args.outside_in:
        from services.outside_in.demo import main as outside_in

        return outside_in(args)
    if args.record is not None and not Path(args.record).resolve().parent.is_dir():
        raise UmaError(f"--record {args.record}: its directory does not exist")
    view_port = None
    if getattr(args, "view", False):
        from agent.view import import_viser

        import_viser()  # says what to install before anything starts
        if not 0 < args.view_port <= 65535:
            raise UmaError(f"--view-port must be in 1..65535, got {args.view_port}")
        view_port = int(args.view_port)
    report = run_demo(seconds, int(args.seed), live=not args.json, log_dir=log_dir,
                      record=args.record, view_port=view_port,
                      optical=getattr(args, "optical", "dots"))
    if args.json:
        print(json.dumps(report))
    else:
        print(format_summary(report))
    return 0 if report["ok"] else 1


def run_demo(seconds: float, seed: int, live: bool = True,
             log_dir: Path | None = None, record: str | None = None,
             view_port: int | None = None, optical: str = "dots") -> dict[str, Any]:
    """Start everything, measure for ``seconds``, stop everything; the figures (the
    services' logs kept in ``log_dir`` if given; everything recorded into ``record`` if
    given, with the simulator's ground truth on its own frame, ``TRUTH_FRAME``;
    ``view_port``: also serve ``uma view`` of the realm on that port; ``optical``: the
    fusion's optical update, ``dots`` or ``pose``)."""
    from agent import Client
    from agent.daemon import Agent, AgentSettings
    from services.sim.calibrations import accel_calibration_file, laser_calibration_file
    from services.sim.trajectory import HeadTrajectory
    from services.sim.world import IvyWorld, sim_time_s

    t_start = time.monotonic()
    realm = f"demo{uuid.uuid4().hex[:10]}"
    ep_tracking, ep_app = _free_endpoint(), _free_endpoint()
    if live:
        print(f"uma demo: realm {realm}, tracking host on {ep_tracking}, application host on "
              f"{ep_app}", flush=True)
    calibration = laser_calibration_file(IvyWorld(seed=seed), announce=live)
    accel_calibration = accel_calibration_file(announce=live)
    truth = HeadTrajectory(seed)
    lease_ms = lease_ms_default() if "UMA_LEASE_MS" in os.environ else DEMO_LEASE_MS
    children = Children(log_dir, lease_ms)
    agents: list[Any] = []
    tally = Tally()
    sub = None
    recording: Any = None
    try:
        tracking = Agent(AgentSettings(realm=realm, agent_id="tracking", listen=[ep_tracking],
                                       static_edges=_static_edges(), lease_ms=lease_ms),
                         client=Client)
        tracking.start()
        agents.append(tracking)
        app = Agent(AgentSettings(realm=realm, agent_id="application", listen=[ep_app],
                                  connect=[ep_tracking], lease_ms=lease_ms),
                    client=Client)
        app.start()
        agents.append(app)
        common = ["--realm", realm, "--agent", "tracking", "--connect", ep_tracking]
        if record is not None:
            recording = _Recording(record, realm, ep_tracking)
            children.start("sim", [*common, "--seed", str(seed), "--mountings", "none",
                                   "--head-frame", TRUTH_FRAME])
        children.start("laser-camera", [*common, "--seed", str(seed), "--calibration",
                                        str(calibration)])
        # The fusion uses the raw accelerometer stream; the rig's own dead reckoning is reset
        # from the fused head pose (its default reset frame, */head): MARVIN's loop.
        children.start("accel-rig", [*common, "--seed", str(seed), "--calibration",
                                     str(accel_calibration)])
        children.start("fusion", [*common, *_fusion_optical(optical, calibration)])
        if view_port is not None:
            children.start_command("view", ["view", "--realm", realm, "--connect", ep_app,
                                             "--port", str(view_port)])
            print(f"uma demo: the view of realm {realm} is on http://127.0.0.1:{view_port}/",
                  file=sys.stdout if live else sys.stderr, flush=True)
        with Client(realm=realm, connect=[ep_app], timeout=1.0) as client:
            t_first = _wait_first_pose(client, children, tally)
            if live:
                print(f"first fused pose after {t_first - t_start:.1f} s; measuring for "
                      f"{seconds:g} s", flush=True)

            def on_pose(r: Any) -> None:
                err = _error_vs_truth(r, truth, sim_time_s)
                if err is None:
                    tally.fail("streamed pose without a time")
                    return
                with tally.lock:
                    tally.stream_times.append(time.monotonic())
                    tally.stream_pos_err_m.append(err[0])

            sub = client.subscribe(frames.WORLD, frames.HEAD, on_pose=on_pose)
            _measure(client, truth, sim_time_s, seconds, tally, live)
            tally.stream_stalls, tally.stream_route_changes = sub.stalls, sub.replans
            matches = _matches(tracking)
    finally:
        if sub is not None:
            with contextlib.suppress(Exception):
                sub.close()
        try:
            recorded = recording.close() if recording is not None else None
        finally:
            children.stop()
        for a in reversed(agents):
            with contextlib.suppress(Exception):
                a.close()
    report = _report(tally, matches, seconds, time.monotonic() - t_start,
                     [p.pid for p in children.procs.values()], optical)
    report["logs"] = None if log_dir is None else str(log_dir)
    report["recording"] = recorded
    if recorded is not None and recorded["error"]:
        report["ok"] = False
    return report


def _fusion_optical(optical: str, calibration: Path) -> list[str]:
    """The fusion's arguments for its optical update: in dot mode the display's walls come
    from the calibration file the laser tracker maps its dots with."""
    if optical == "pose":
        return ["--optical", "pose"]
    if optical != "dots":
        raise UmaError(f"--optical must be 'dots' or 'pose', got {optical!r}")
    return ["--optical", "dots", "--display-calibration", str(calibration)]


class _Recording:
    """``uma record`` of the demo's realm as a child process (its writer then never competes
    with the agents of this process for the interpreter), from before the services start
    (so the fusion's whole input is in the file) until the measurement ends."""

    def __init__(self, path: str, realm: str, endpoint: str) -> None:
        self.path = path
        self.started = time.monotonic()
        self.out = tempfile.TemporaryFile("w+")  # noqa: SIM115 (closed by close())
        self.err = tempfile.TemporaryFile("w+")  # noqa: SIM115
        with contextlib.suppress(FileNotFoundError):
            os.remove(path)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "agent.cli", "record", path, "--realm", realm, "--connect",
             endpoint, "--json"], stdin=subprocess.DEVNULL, stdout=self.out, stderr=self.err,
            text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        deadline = time.monotonic() + RECORDER_START_S
        while not os.path.exists(path) and self.proc.poll() is None \
                and time.monotonic() < deadline:
            time.sleep(0.05)
        if not os.path.exists(path):
            self.close()
            raise UmaError(f"demo: the recorder did not start ({self._last_error()})")

    def _last_error(self) -> str:
        self.err.seek(0)
        lines = self.err.read().strip().splitlines()
        return lines[-1] if lines else f"exit {self.proc.poll()}"

    def close(self) -> dict[str, Any]:
        """Stop the recorder as Ctrl-C does (it writes the file's summary) and return its
        figures."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        stop_processes([self.proc], RECORDER_STOP_S)
        self.out.seek(0)
        lines = [ln for ln in self.out.read().splitlines() if ln.startswith("{")]
        error = None if lines and self.proc.returncode == 0 else self._last_error()
        self.out.close()
        self.err.close()
        stats = json.loads(lines[-1]) if lines else {"messages": {}, "dropped": {}}
        seconds = time.monotonic() - self.started
        size = os.path.getsize(self.path) if os.path.exists(self.path) else 0
        return {"file": self.path, "seconds": seconds,
                "messages": sum(stats["messages"].values()), "bytes": size,
                "mb_per_minute": size / 1e6 / seconds * 60.0,
                "dropped": sum(stats["dropped"].values()), "error": stats.get("error") or error}


def _wait_first_pose(client: Any, children: Children, tally: Tally) -> float:
    deadline = time.monotonic() + FIRST_POSE_TIMEOUT_S
    last = "no answer yet"
    while time.monotonic() < deadline:
        dead = children.dead()
        if dead:
            raise UmaError("demo: a service stopped: " + "; ".join(
                f"{k} ({v})" for k, v in dead.items()))
        try:
            r = client.pose(frames.WORLD, frames.HEAD, error=ERROR)
            if list(r.path) == [frames.WORLD, frames.HEAD]:   # the fused edge itself
                tally.path = list(r.path)
                return time.monotonic()
            last = f"only the path {' -> '.join(r.path)} so far"
        except UmaError as exc:
            last = str(exc)
        time.sleep(0.2)
    raise UmaError(f"demo: no fused head pose within {FIRST_POSE_TIMEOUT_S:g} s ({last})")


def _measure(client: Any, truth: Any, sim_time_s: Any, seconds: float, tally: Tally,
             live: bool) -> None:
    """Query at QUERY_HZ for ``seconds``; a live line per second."""
    end = time.monotonic() + seconds
    next_line = time.monotonic() + 1.0
    while time.monotonic() < end:
        t0 = time.perf_counter()
        try:
            r = client.pose(frames.WORLD, frames.HEAD, error=ERROR)
        except UmaError as exc:
            tally.fail(type(exc).__name__)
            time.sleep(1.0 / QUERY_HZ)
            continue
        latency = time.perf_counter() - t0
        err = _error_vs_truth(r, truth, sim_time_s)
        if err is None:
            tally.fail("answer without a time")
            continue
        with tally.lock:
            tally.latencies_s.append(latency)
            tally.pos_err_m.append(err[0])
            tally.rot_err_rad.append(err[1])
            tally.last = (np.asarray(r.position), np.asarray(r.quaternion))
        if live and time.monotonic() >= next_line:
            next_line += 1.0
            print(_live_line(tally), flush=True)
        time.sleep(max(0.0, 1.0 / QUERY_HZ - (time.perf_counter() - t0)))


def _error_vs_truth(r: Any, truth: Any, sim_time_s: Any) -> tuple[float, float] | None:
    """Position (m) and rotation (rad) error of a pose answer against the simulated truth
    at the time it describes; None if it names no time."""
    t_ns = _answer_time(r)
    if t_ns is None:
        return None
    p_t, q_t = truth.pose(sim_time_s(t_ns))
    e_p, e_r = geo.pose_error(r.position, r.quaternion, p_t[0], q_t[0])
    return float(e_p), float(e_r)


def _answer_time(r: Any) -> int | None:
    """The time a pose answer describes: its ``t_ns``, else its newest sample stamp (the
    client leaves ``t_ns`` empty for a one-segment ``at=None`` query)."""
    if r.t_ns is not None:
        return int(r.t_ns)
    stamps = [s[-1] for s in (getattr(r, "stamps", None) or []) if s and s[-1] is not None]
    return int(max(stamps)) if stamps else None


def _live_line(t: Tally) -> str:
    with t.lock:
        now = time.monotonic()
        rate = sum(1 for s in t.stream_times if s > now - 1.0)
        p, q = t.last if t.last is not None else (np.full(3, np.nan), geo.quat_identity())
        ypr = np.degrees(geo.quat_to_rotvec(q))
        return (f"stream {rate:4d} Hz | query latency {1e3 * t.latencies_s[-1]:6.2f} ms | "
                f"head ({p[0]:+.3f}, {p[1]:+.3f}, {p[2]:+.3f}) m rotvec ({ypr[0]:+6.1f}, "
                f"{ypr[1]:+6.1f}, {ypr[2]:+6.1f}) deg | error {1e3 * t.pos_err_m[-1]:6.2f} mm "
                f"{np.degrees(t.rot_err_rad[-1]):5.2f} deg")


def _matches(agent: Any) -> dict[str, list[str]]:
    """The tracking agent's current matches: ``service.need -> [data keys]``."""
    out = {}
    for (sid, need), state in sorted(getattr(agent, "needs", {}).items()):
        current = state.current() if callable(state.current) else state.current
        out[f"{sid}.{need}"] = sorted(current)
    return out


def _report(t: Tally, matches: dict[str, list[str]], seconds: float, wall_s: float,
            pids: list[int], optical: str = "dots") -> dict[str, Any]:
    with t.lock:
        span = (t.stream_times[-1] - t.stream_times[0]) if len(t.stream_times) > 1 else 0.0
        stream_hz = (len(t.stream_times) - 1) / span if span > 0 else 0.0
        report = {
            "seconds": seconds,
            "wall_s": wall_s,
            "path": t.path,
            "matches": matches,
            "queries": len(t.latencies_s),
            "query_failures": t.failures,
            "query_latency_ms": error_stats(t.latencies_s, 1e3),
            "stream_poses": len(t.stream_times),
            "stream_rate_hz": stream_hz,
            "stream_stalls": t.stream_stalls,
            "stream_route_changes": t.stream_route_changes,
            "position_error_mm": error_stats(t.pos_err_m, 1e3),
            "orientation_error_deg": error_stats(t.rot_err_rad, 180.0 / math.pi),
            "stream_position_error_mm": error_stats(t.stream_pos_err_m, 1e3),
            "child_pids": pids,
            "optical": optical,
        }
    report["ok"] = bool(report["queries"] and report["stream_poses"]
                        and matches.get("fusion.optical") and matches.get("fusion.accel")
                        and (optical == "pose" or matches.get("fusion.dots")))
    return report


def _recording_line(rec: dict[str, Any]) -> str:
    line = (f"  recorded {rec['messages']} messages, {rec['bytes'] / 1e6:.1f} MB "
            f"({rec['mb_per_minute']:.1f} MB/min) to {rec['file']}; not written: "
            f"{rec['dropped']}")
    return line + (f"; {rec['error']}" if rec["error"] else "")


def format_summary(r: dict[str, Any]) -> str:
    def s(d: dict[str, float] | None, unit: str) -> str:
        return "n/a" if d is None else (f"median {d['median']:.3g} {unit}, p99 {d['p99']:.3g} "
                                        f"{unit}, max {d['max']:.3g} {unit}")
    lines = ["", "uma demo summary",
             f"  ran {r['wall_s']:.1f} s (measured {r['seconds']:g} s); path "
             f"{' -> '.join(r['path'])}", "  matches made:"]
    lines += [f"    {k}: {', '.join(v) or 'none'}" for k, v in r["matches"].items()]
    lines += [f"  queries: {r['queries']} (failures {r['query_failures'] or 'none'}), latency "
              f"{s(r['query_latency_ms'], 'ms')}",
              f"  stream: {r['stream_poses']} poses at {r['stream_rate_hz']:.0f} Hz, stalled "
              f"{r['stream_stalls']} times, {r['stream_route_changes']} route changes",
              f"  fused vs ground truth: position {s(r['position_error_mm'], 'mm')}",
              f"                         orientation {s(r['orientation_error_deg'], 'deg')}",
              f"  all processes stopped (pids {', '.join(map(str, r['child_pids']))})",
              *([f"  service logs in {r['logs']}"] if r.get("logs") else []),
              *([_recording_line(r["recording"])] if r.get("recording") else []),
              f"  {'OK' if r['ok'] else 'FAILED'}"]
    return "\n".join(lines)
