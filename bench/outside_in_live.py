"""``bench_outside_in.py --live``: the outside-in services running, as processes on loopback.

One ``uma agent``; the simulated rig's cameras as ``marker-camera`` services,
``--per-process`` cameras to a process (each renders its frames at the wall clock's
exposure times, finds their blobs in the windows the reconstruction predicts, publishes);
the ``outside-in`` reconstruction; and in this process a ``Service`` that needs every
body's pose.  Measured over ``--live`` seconds once they run steadily (``_settle``):

- **exposure to pose**: a pose's arrival here minus its time (the exposure of the frame
  set it came from), median and p99: everything from the shutter to an application,
  rendering, detection, two hops through the agent and the tracking included;
- **bare transport**, in the same run: a child process puts a timestamp on a bare Zenoh
  key at the camera rate and this process's bare subscriber takes it (both Zenoh clients
  of the agent, as the services are): one hop without uma;
- **published rate** per body against the camera rate, over the cameras' window: the
  poses of the frames exposed during the measurement, however late they came (up to
  ``LATE_POSE_S``); ``arrived_hz`` counts the poses that arrived during it instead, off
  the cameras' rate by however much the latency differs between the window's ends (a
  pose 80 ms late at one end moves it by 10 poses, 1 per second over 10 s);
- each process's CPU (cores, from ``/proc``); the frames the cameras searched whole and
  in windows come from their logs;
- where a rate short of the cameras' comes from: per body the frame sets exposed in the
  window that gave it no pose and when the gaps were (``poses_missing``), and what the
  reconstruction counted between its reports inside the measurement (frame sets, fits
  refused, samples late, samples stale: skipped while it was behind, frame sets
  superseded: not tracked, it was behind the newest);
- with ``--stall AT SECONDS`` (``Stall``) the reconstruction's process is stopped for a
  while during the measurement: whether and how soon its poses come at the camera rate
  again.

A real camera hands its host finished images; the simulator's rendering costs about as
much as the services' work on them.  So the marker cameras render their frames first
(``marker-camera --prerender``: the measurement and ``PRERENDER_MARGIN_S`` before it) and
replay them at their exposure times, a copy per frame: their CPU while measuring is the
segmentation's and the SDK's, as a real camera's host would spend.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
from loopback import free_port, wait_listening, zenoh_config
from summary import median_p99

ROOT = Path(__file__).resolve().parents[1]
#: how long after the replayed frames' start the services may take to give every body a pose
FIRST_POSE_S = 60.0
#: the cameras' frames rendered ahead cover the measurement and this much before it (the
#: first poses, the bare publisher's start)
PRERENDER_MARGIN_S = 8.0
#: how long the measurement waits at most for the services to run steadily, and what
#: counts as steady: every frame set of the last second with a pose of every body, none
#: later than this after its exposure
SETTLE_MAX_S = 4.0
STEADY_LATENCY_S = 0.05
#: how long after the measurement its last exposures' poses may take to come (a pose
#: more than 0.1 s late is not made: the reconstruction skips stale samples)
LATE_POSE_S = 1.0


def bare_publisher(ep: str, key: str, rate_hz: float, seconds: float) -> int:
    """Child: put the time (ns) on ``key`` at ``rate_hz`` for ``seconds``."""
    import zenoh
    session = zenoh.open(zenoh_config("client", connect=ep))
    pub = session.declare_publisher(key)
    period = 1.0 / rate_hz
    end = time.monotonic() + seconds
    next_t = time.monotonic()
    while next_t < end:
        pub.put(str(time.time_ns()).encode())
        next_t += period
        time.sleep(max(0.0, next_t - time.monotonic()))
    session.close()
    return 0


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _threads_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds so far of ``pid``'s live threads, by name with the digits taken out
    (Zenoh's runtime ``rx-N``, ``tx-N``, ...; uma's ``uma-markers-camN``, ...), in
    nanoseconds (``/proc/PID/task/*/schedstat``)."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError, ValueError):
            name = re.sub(r"\d+", "N", (task / "comm").read_text().strip())
            out[name] = out.get(name, 0.0) + int((task / "schedstat").read_text().split()[0]) / 1e9
    return out


class _Procs:
    """Child processes by name, their logs in files, all stopped by PID."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, argv: list[str]) -> None:
        log = open(self.folder / f"{name}.log", "w")  # noqa: SIM115 (closed by the child's end)
        self.procs[name] = subprocess.Popen([sys.executable, *argv], cwd=ROOT, stdout=log,
                                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                            env=dict(os.environ, PYTHONUNBUFFERED="1"))

    def dead(self) -> list[str]:
        return [n for n, p in self.procs.items() if p.poll() is not None]

    def log(self, name: str) -> str:
        return (self.folder / f"{name}.log").read_text(errors="replace")

    def stop(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.terminate()
        for p in self.procs.values():
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)


def run(cameras: int, rate_hz: float, seconds: float, per_process: int,
        seed: int, logs: str | None = None, stall: Stall | None = None) -> dict[str, Any]:
    """The measurement (module docstring); ``logs``: a folder that keeps every process's
    log (default: a temporary one); ``stall``: the reconstruction stopped for a while
    during it (``Stall``)."""
    if logs is not None:
        Path(logs).mkdir(parents=True, exist_ok=True)
        return _run(cameras, rate_hz, seconds, per_process, seed, Path(logs), stall)
    with tempfile.TemporaryDirectory() as tmp:
        return _run(cameras, rate_hz, seconds, per_process, seed, Path(tmp), stall)


def _run(cameras: int, rate_hz: float, seconds: float, per_process: int, seed: int,
         folder: Path, stall: Stall | None) -> dict[str, Any]:
    from services.outside_in.bodies import dump_bodies
    from services.outside_in.rigfile import save_rig
    from services.outside_in.simulator import SimConfig, Simulation

    sim = Simulation(seed=seed, config=SimConfig(n_cameras=cameras, rate_hz=rate_hz))
    realm = f"bench-oi-{uuid.uuid4().hex[:8]}"
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    net = ["--realm", realm, "--agent", "host", "--connect", ep]
    rig = save_rig(folder / "rig.toml", sim.cameras, np.zeros((cameras, 6, 6)),
                   "lab/world", "lab", 0.0)
    (folder / "bodies.toml").write_text(dump_bodies(sim.bodies))
    procs = _Procs(folder)
    try:
        procs.start("agent", ["-m", "agent.cli", "agent", "--realm", realm, "--id", "host",
                              "--listen", ep])
        wait_listening([port])
        procs.start("outside-in", ["-m", "agent.cli", "service", "run", "outside-in",
                                   *net, "--rig", str(rig), "--bodies",
                                   str(folder / "bodies.toml"), "--rate-hz", str(rate_hz)])
        names = [c.name for c in sim.cameras]
        replay_s = seconds + PRERENDER_MARGIN_S
        processes = -(-cameras // per_process)
        replay_at = time.time() + _render_time(sim, replay_s, processes)
        for i in range(0, cameras, per_process):
            procs.start(f"cameras-{i // per_process}", [
                "-m", "agent.cli", "service", "run", "marker-camera", *net, "--rig",
                str(rig), "--sim", str(seed), "--rate-hz", str(rate_hz),
                "--prerender", str(replay_s), "--replay-at", f"{replay_at:.3f}",
                *[x for n in names[i:i + per_process] for x in ("--camera", n)]])
        figures = _measure(procs, realm, ep, [b.name for b in sim.bodies], cameras, rate_hz,
                           seconds, replay_at + FIRST_POSE_S, stall)
        figures["replay_covered_measurement"] = figures.pop("measured_until") \
            <= replay_at + replay_s
    finally:
        procs.stop()
    figures["camera_frames_windowed_whole"] = _windowed(procs)
    figures["reconstruction_cpu_per_frame_set"] = _last(procs, "outside-in", "CPU per frame set: ")
    figures |= _at_camera_rate(procs, figures, cameras, rate_hz)
    return {"cameras": cameras, "rate_hz": rate_hz, "seconds": seconds,
            "cameras_per_process": per_process, **figures}


def _render_time(sim: Any, seconds: float, processes: int) -> float:
    """How long (s) the cameras' ``processes`` may take to start and render ``seconds`` of
    every camera's frames: twice the time this process takes for them now (on this
    machine, at its load; the first frames, which warm caches up, not timed), shared
    by the processes on the machine's cores, and 8 s to start."""
    cameras = len(sim.cameras)
    for c in range(cameras):
        sim.render(c, 0)
    t0 = time.perf_counter()
    for index in range(1, 4):
        for c in range(cameras):
            sim.render(c, index)
    per_frame = (time.perf_counter() - t0) / (3 * cameras)
    parallel = max(1, min(processes, len(os.sched_getaffinity(0))))
    return 8.0 + 2.0 * per_frame * cameras * seconds * sim.config.rate_hz / parallel


def _measure(procs: _Procs, realm: str, ep: str, bodies: list[str], cameras: int,
             rate_hz: float, seconds: float, first_pose_by: float,
             stall: Stall | None = None) -> dict[str, Any]:
    import zenoh

    from agent import Measurement, Service

    poses: dict[str, list[tuple[int, int]]] = {b: [] for b in bodies}
    bare: list[float] = []
    measuring = threading.Event()

    def on_pose(m: Measurement) -> None:
        now = time.time_ns()
        name = m.edge[1].rsplit("/", 1)[-1] if m.edge else ""
        if name in poses:
            poses[name].append((now, m.t_ns))

    def on_bare(smp: zenoh.Sample) -> None:
        if measuring.is_set():
            bare.append((time.time_ns() - int(smp.payload.to_bytes())) / 1e6)

    key = f"bench/{realm}/bare"
    with Service("bench-sink", realm=realm, agent="host", connect=[ep]) as sink, \
            contextlib.closing(zenoh.open(zenoh_config("client", connect=ep))) as session:
        sink.need("poses", type="pose6d", edge=("lab/world", "lab/*"), max_count=len(bodies),
                  on_sample=on_pose)
        sink.start()
        sub = session.declare_subscriber(key, on_bare)
        while not all(poses.values()) or (replayed := _replay_start(procs, cameras)) is None:
            if procs.dead() or time.time() > first_pose_by:
                raise SystemExit(f"setup failed: no pose of every body from every camera's "
                                 f"replayed frames within {FIRST_POSE_S:g} s of their start "
                                 f"(ended: {procs.dead() or 'none'})")
            time.sleep(0.2)
        time.sleep(max(0.0, replayed - time.time()))
        procs.start("bare", [str(Path(__file__)), "--bare-publisher", ep, key, str(rate_hz),
                             str(seconds + 3)])
        time.sleep(2.0)     # the bare publisher's process is up and putting
        settled = _settle(poses, rate_hz)
        for v in poses.values():
            v.clear()
        cpu0 = {n: _cpu_s(p.pid) for n, p in procs.procs.items() if p.poll() is None}
        threads0 = {n: _threads_cpu_s(procs.procs[n].pid) for n in cpu0}
        t0 = time.monotonic()
        start = time.time_ns()
        measuring.set()
        if stall is not None:
            stall.inflict(procs.procs["outside-in"].pid, seconds)
        else:
            time.sleep(seconds)
        measuring.clear()
        elapsed = time.monotonic() - t0
        end = time.time_ns()
        cpu = {n: round((_cpu_s(procs.procs[n].pid) - c) / elapsed, 3)
               for n, c in cpu0.items() if procs.procs[n].poll() is None}
        threads = {n: _busiest({k: (v - threads0[n].get(k, 0.0)) / elapsed
                                for k, v in _threads_cpu_s(procs.procs[n].pid).items()})
                   for n in cpu if n != "bare"}
        time.sleep(LATE_POSE_S)    # the poses of the window's last exposures come in
        sub.undeclare()
    services = {n: c for n, c in cpu.items() if n != "bare"}
    window = seconds * 1e9
    # the rate over the cameras' window: the poses of the frames exposed while measuring
    poses = {b: list(v) for b, v in poses.items()}
    exposed = {b: [t for _, t in v if start <= t < start + window] for b, v in poses.items()}
    lat = [(arrival - t) / 1e6 for v in poses.values() for arrival, t in v
           if start <= t < start + window]
    if not lat:
        tails = {n: procs.log(n).splitlines()[-3:] for n in procs.procs}
        raise SystemExit(f"no pose arrived while measuring; the processes' last lines: {tails}")
    return {"exposure_to_pose": median_p99(lat, "ms"),
            "load_after": os.getloadavg()[0],
            "bare_transport": median_p99(bare, "ms") if bare else None,
            "settled_after_s": settled,
            "published_hz": {b: round(len(v) / seconds, 2) for b, v in exposed.items()},
            "arrived_hz": {b: round(sum(start <= a < end for a, _ in v) / (end - start) * 1e9,
                                    2) for b, v in poses.items()},
            "poses_missing": _missing(exposed, rate_hz, start / 1e9, seconds),
            **(stall.recovery(exposed, rate_hz, start / 1e9, seconds) if stall else {}),
            "reconstruction_in_window": _counts_between(procs, start / 1e9, end / 1e9),
            "measured_until": time.time(),
            "cores": services, "cores_all_services": round(sum(services.values()), 3),
            "cores_by_thread": threads}


class Stall:
    """The reconstruction's process held back ``at_s`` into the measurement for
    ``seconds``, as a machine's load spike or a long pause would hold it: stopped
    (``SIGSTOP``) all along, or with ``share`` > 0 let run that share of every
    ``DUTY_S`` (stopped the rest: the CPU a busy machine would leave it, the same from run
    to run), then continued (``SIGCONT``); whether, and how soon after, its poses come at
    the camera rate again.  A stall that leaves the tracker in a lasting bad state
    (behind, the cameras searching whole images, bodies lost) shows as a rate that does
    not come back."""

    #: the rate is counted over bins this long (s) of exposure time
    BIN_S = 0.25
    #: a bin counts as recovered with poses of this share of its frame sets
    RECOVERED = 0.95
    #: with a ``share``, the process runs that share of every this many seconds
    DUTY_S = 0.02

    def __init__(self, at_s: float, seconds: float, share: float = 0.0) -> None:
        self.at_s, self.seconds, self.share = at_s, seconds, share

    def inflict(self, pid: int, measure_s: float) -> None:
        """Hold ``pid`` back at its times; return at the measurement's end."""
        t0 = time.monotonic()
        time.sleep(self.at_s)
        end = time.monotonic() + self.seconds
        stopped_s = (1.0 - self.share) * self.DUTY_S if self.share else self.seconds
        try:
            while (left := end - time.monotonic()) > 0:
                os.kill(pid, signal.SIGSTOP)
                time.sleep(min(left, stopped_s))
                os.kill(pid, signal.SIGCONT)
                time.sleep(self.share * self.DUTY_S)
        finally:
            os.kill(pid, signal.SIGCONT)
        time.sleep(max(0.0, measure_s - (time.monotonic() - t0)))

    def recovery(self, exposures: dict[str, list[int]], rate_hz: float, start: float,
                 seconds: float) -> dict[str, Any]:
        """Per ``BIN_S`` of exposure time, the share of its frame sets that gave every
        body a pose (the least over the bodies), and ``recovered_after_s``: from how long
        after the stall's end every later bin had ``RECOVERED`` of them (None: the last
        bin had not)."""
        bins = int(seconds / self.BIN_S)
        per_bin = rate_hz * self.BIN_S
        shares = np.ones(bins)
        for times in exposures.values():
            k = ((np.asarray(times, np.int64) / 1e9 - start) / self.BIN_S).astype(int)
            shares = np.minimum(shares, np.bincount(k[(k >= 0) & (k < bins)],
                                                    minlength=bins) / per_bin)
        end = self.at_s + self.seconds
        bad = [i for i in range(bins) if shares[i] < self.RECOVERED
               and (i + 1) * self.BIN_S > end]
        recovered = (None if bad and bad[-1] == bins - 1
                     else round(max(0.0, ((bad[-1] + 1) if bad else 0) * self.BIN_S - end), 2))
        return {"stall": {"at_s": self.at_s, "seconds": self.seconds, "share": self.share,
                          "recovered_after_s": recovered,
                          "share_by_bin": [round(float(x), 2) for x in shares]}}


def _settle(poses: dict[str, list[tuple[int, int]]], rate_hz: float) -> float | None:
    """Wait (at most ``SETTLE_MAX_S``) until the services run steadily: the last second
    of exposures gave every body a pose, each within ``STEADY_LATENCY_S``.  Their start
    is no steady state: each camera searches its whole images until the reconstruction's
    windows come, the bodies are acquired, the reconstruction catches up on samples
    queued meanwhile (skipping the stale ones).  How long it took (s), None when it did
    not settle (the measurement then starts anyway)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < SETTLE_MAX_S:
        now = time.time_ns()
        window = (now - round(1.1e9), now - round(0.1e9))
        if all(sum(window[0] <= t < window[1] and a - t < STEADY_LATENCY_S * 1e9
                   for a, t in v[-round(3 * rate_hz):]) >= rate_hz - 1
               for v in list(poses.values())):
            return round(time.monotonic() - t0, 2)
        time.sleep(0.1)
    return None


def _missing(exposures: dict[str, list[int]], rate_hz: float, start: float,
             seconds: float) -> dict[str, Any]:
    """Per body, the frame sets exposed in the window (``seconds`` from ``start``, unix
    time) that gave it no pose, and when the gaps between its poses were (s after the
    start; a gap of more than 1.5 frame periods): whether a rate short of the cameras'
    comes from losses throughout the window or at a time."""
    period_ns = 1e9 / rate_hz
    out: dict[str, Any] = {}
    for body, times in exposures.items():
        t = np.sort(np.asarray(times, np.int64))
        lost = np.rint(np.diff(t) / period_ns).astype(int) - 1
        at = np.flatnonzero(lost > 0)
        out[body] = {"frame_sets": max(round(seconds * rate_hz) - len(t), 0),
                     "at_s": [round(float(t[i] / 1e9 - start), 2) for i in at[:12]]}
    return out


def _counts_between(procs: _Procs, start: float, end: float) -> dict[str, Any] | None:
    """What the reconstruction counted (frame sets, poses tracked, fits refused, samples
    late and stale) between its first and last report inside ``start .. end`` (unix
    times; it reports every 5 s), and over how many seconds."""
    reports = []
    for line in procs.log("outside-in").splitlines():
        m = _RECONSTRUCTION.search(line)
        if m:
            t = _log_time(m.group(1))
            if start <= t <= end:
                reports.append((t, [int(x or 0) for x in m.group(2, 3, 4, 5, 6, 7)]))
    if len(reports) < 2:
        return None
    (t0, a), (t1, b) = reports[0], reports[-1]
    return {"seconds": round(t1 - t0, 2),
            **{k: y - x for k, x, y in zip(("frame_sets", "tracked", "refused_fit", "late",
                                            "stale", "superseded"), a, b, strict=True)}}


#: the reconstruction's report: its time, frame sets, poses tracked, fits refused, late,
#: stale, superseded (frame sets not tracked: it was behind the newest)
_RECONSTRUCTION = re.compile(r"^(\S+ \S+) .*outside-in: (\d+) frame sets, \{'tracked': (\d+)"
                             r".*'refused_fit': (\d+).*, (\d+) late, (\d+) stale"
                             r"(?:, (\d+) sets superseded)?")


def _busiest(cores: dict[str, float]) -> dict[str, float]:
    """The threads that used 1 % of a core or more, busiest first."""
    return {k: round(v, 3) for k, v in sorted(cores.items(), key=lambda kv: -kv[1])
            if v >= 0.01}


def _replay_start(procs: _Procs, cameras: int) -> float | None:
    """When the last camera's replayed frames start (unix time, from the cameras' logs);
    None until every camera has rendered its frames."""
    starts = [float(m.group(1)) for name in procs.procs if name.startswith("cameras-")
              for m in _REPLAY.finditer(procs.log(name))]
    return max(starts) if len(starts) == cameras else None


_REPLAY = re.compile(r"rendered ahead, replayed from ([0-9.]+) \(unix time\)")


def _at_camera_rate(procs: _Procs, figures: dict[str, Any], cameras: int,
                    rate_hz: float) -> dict[str, Any]:
    """What the services' CPU comes to per unit of work, so that a run on a loaded machine
    (where they get less CPU than they need and fall behind) still says what the camera
    rate would take: the cameras' frames per second (over their reports while replaying,
    5 s apart: a run of 10 s or more has two), their
    CPU per frame; the reconstruction's and the agent's per published frame set; and the
    cores all of it would take with every camera at the rate and a pose per frame set
    (linear in the work; an extrapolation, not a measurement)."""
    frames = 0.0
    for name in procs.procs:
        if name.startswith("cameras-"):
            # from its first report with frames (it is silent before its replay) to its last
            found = [_REPORT.search(x) for x in procs.log(name).splitlines()]
            reports = [r for r in (_report(m) for m in found if m) if r[1] > 0]
            if len(reports) < 2:
                return {}
            (t0, n0), (t1, n1) = reports[0], reports[-1]
            frames += (n1 - n0) / (t1 - t0)
    cores = figures["cores"]
    sets = float(np.mean(list(figures["published_hz"].values())))
    cam_cores = sum(v for k, v in cores.items() if k.startswith("cameras-"))
    if frames <= 0 or sets <= 0:
        return {}
    per_frame = cam_cores / frames
    per_set = (cores["outside-in"] + cores["agent"]) / sets
    return {"camera_frames_per_s": round(frames, 1),
            "camera_cpu_ms_per_frame": round(1e3 * per_frame, 3),
            "reconstruction_and_agent_cpu_ms_per_frame_set": round(1e3 * per_set, 3),
            "cores_at_camera_rate": round(per_frame * cameras * rate_hz + per_set * rate_hz,
                                          3)}


#: a camera process's report: its time and every camera's frames searched windowed / whole
_REPORT = re.compile(r"^(\S+ \S+) .*windows / whole: (.*?);")


def _report(m: re.Match) -> tuple[float, int]:
    """A camera report's time (s) and its cameras' frames so far."""
    return _log_time(m.group(1)), sum(int(a) + int(b)
                                      for a, b in re.findall(r"(\d+)/(\d+)", m.group(2)))


def _log_time(stamp: str) -> float:
    """A log line's time (``2026-01-02 10:11:12,345``, local) as a unix time."""
    day, ms = stamp.split(",")
    return time.mktime(time.strptime(day, "%Y-%m-%d %H:%M:%S")) + int(ms) / 1e3


def _windowed(procs: _Procs) -> dict[str, str]:
    """The cameras' last report of frames searched in windows / whole and their CPU per
    frame in segmentation and publishing (the rest of their process's CPU is the SDK's
    and Zenoh's receiving and sending)."""
    return {name: _last(procs, name, "whole: ") for name in procs.procs
            if name.startswith("cameras-")}


def _last(procs: _Procs, name: str, after: str) -> str | None:
    """What follows ``after`` on the last line of process ``name``'s log that has it."""
    lines = [x for x in procs.log(name).splitlines() if after in x]
    return lines[-1].split(after, 1)[-1] if lines else None


if __name__ == "__main__" and sys.argv[1:2] == ["--bare-publisher"]:
    sys.exit(bare_publisher(sys.argv[2], sys.argv[3], float(sys.argv[4]), float(sys.argv[5])))
