"""``uma demo --cameras``: two simulated webcams on two agents watching a tagged object.

On loopback, in a realm of its own, it starts

* two agents in this process, ``left`` and ``right`` (connected), each holding its camera's
  extrinsics as a static SRG edge ``lab/world -> lab/cam-left`` / ``lab/cam-right`` (what
  an agent's TOML ``[[static_edges]]`` gives it);
* two camera services, ``cam-left`` on agent ``left`` and ``cam-right`` on ``right``: each
  renders its simulated 640x480 camera (:class:`~services.camera.simulator.SimCamera`,
  blur, noise, lens distortion) at ``FPS`` and runs the fiducial tracker and the same
  publisher as ``uma service run fiducials`` on it (ability ``apriltag36h11-7``, edge
  ``lab/cam-X -> markers/apriltag36h11-7``, attributes measured);
* an application service on ``left`` with a need for ``lab/* -> markers/apriltag36h11-7``
  that prefers ``pos_std_m`` (the accuracy the cameras advertise) and keeps the other
  camera as its standby (``standby=1``: its samples stand in at once while the chosen
  camera sends none), and a client on ``right`` that queries the tag's pose in
  ``lab/world`` across the agents.

The tag (10 cm) swings from in front of the left camera to in front of the right one and
back (period ``PERIOD_S``), so which camera sees it best changes, and at the ends of the
swing it leaves both cameras' views for a moment; the summary says when the need moved to
the better camera (the one whose samples claim the smaller position std), how long after
the change, the longest gap in the need's stream (and the longest while some camera saw
the tag: a gap no camera could fill is not the need's), and the world-frame query's error
against the ground truth.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import socket
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent import geometry as geo
from services.camera.simulator import SceneObject, SimCamera, static
from services.fiducials.service import Publisher
from services.fiducials.simulate import FACING, tags, webcam
from services.fiducials.tracker import FiducialTracker

FAMILY = "apriltag36h11"
TAG_ID = 7
TAG_M = 0.10
FPS = 15.0
PERIOD_S = 12.0
CAMERAS = {"left": -0.7, "right": 0.7}  # x of each camera in lab/world, m
TOE_IN_RAD = 0.25
TARGET = f"markers/{FAMILY}-{TAG_ID}"
#: a camera without a sample this close to a moment does not see the tag then
UNSEEN_S = 0.25
#: a camera counts as the better one when it stays so this long (the time within which
#: the need should follow it)
HOLD_S = 0.5


def _endpoint() -> str:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def camera_pose(side: str) -> np.ndarray:
    """``lab/world -> lab/cam-SIDE``: ``lab/world`` is camera-like (x right, y down, z away
    from the cameras); each camera turned in towards the middle."""
    x = CAMERAS[side]
    T = np.eye(4)
    T[:3, :3] = geo.quat_to_matrix(geo.rotvec_to_quat(np.array([0.0, -np.sign(x) * TOE_IN_RAD,
                                                                  0.0])))
    T[:3, 3] = (x, 0.0, 0.0)
    return T


def tag_pose(t: float) -> np.ndarray:
    """The tag in ``lab/world`` at simulated time ``t``: swinging along x at 1.3-1.6 m,
    facing the cameras, wobbling a little."""
    T = np.eye(4)
    phase = 2 * math.pi * t / PERIOD_S
    wobble = geo.quat_to_matrix(geo.rotvec_to_quat(np.array(
        [0.25 * math.sin(1.3 * phase), 0.3 * math.sin(phase + 1.0), 0.2 * math.sin(0.7 * phase)])))
    T[:3, :3] = FACING @ wobble
    T[:3, 3] = (-1.1 * math.cos(phase), 0.1 * math.sin(2 * phase), 1.45 + 0.15 * math.sin(phase))
    return T


@dataclass
class _Seen:
    """What the demo observes, shared by its threads."""

    claims: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # side: (t, std)
    frames: dict[str, list[float]] = field(default_factory=dict)  # side: capture times, s
    stream: list[tuple[float, str]] = field(default_factory=list)  # (arrival, source)
    queries: list[tuple[float, float, list[str]]] = field(default_factory=list)
    failed_queries: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)


class _CameraLoop(threading.Thread):
    """One simulated camera, its tracker and its service, at ``FPS``."""

    def __init__(self, side: str, realm: str, endpoint: str, rng: np.random.Generator,
                 t0_ns: int, stop: threading.Event, seen: _Seen) -> None:
        super().__init__(name=f"uma-demo-cam-{side}", daemon=True)
        self.side, self.realm, self.endpoint = side, realm, endpoint
        model = webcam(rng)
        self.sim = SimCamera(model, trajectory=static(camera_pose(side)))
        self.scene = [SceneObject(o.name, o.drawable, tag_pose)
                      for o in tags(FAMILY, [TAG_ID], TAG_M, [tag_pose])]
        self.tracker = FiducialTracker(model, FAMILY, TAG_M)
        self.rng, self.t0_ns, self.stop, self.seen = rng, t0_ns, stop, seen

    def run(self) -> None:
        from agent import Service

        args = argparse.Namespace(frame=f"lab/cam-{self.side}", prefix="markers", name=[])
        try:
            with Service(f"cam-{self.side}", realm=self.realm, agent=self.side,
                         connect=[self.endpoint]) as svc:
                svc.start()
                publish = Publisher(svc, args)
                next_t = time.monotonic()
                while not self.stop.is_set():
                    t_ns = time.time_ns()
                    image = self.sim.render(self.scene, (t_ns - self.t0_ns) / 1e9, self.rng)
                    publish.frame(t_ns)
                    with self.seen.lock:
                        self.seen.frames.setdefault(self.side, []).append(t_ns / 1e9)
                    for est in self.tracker.process(image, t_ns):
                        publish(est, TAG_ID)
                        with self.seen.lock:
                            self.seen.claims.setdefault(self.side, []).append(
                                (t_ns / 1e9, math.sqrt(np.trace(est.covariance[:3, :3]))))
                    next_t += 1 / FPS
                    self.stop.wait(max(next_t - time.monotonic(), 0.0))
        except Exception as exc:  # reported in the summary, never a silent thread death
            with self.seen.lock:
                self.seen.errors.append(f"cam-{self.side}: {type(exc).__name__}: {exc}")


def run_demo(seconds: float, seed: int, live: bool = True,
             done: Callable[[dict[str, Any]], bool] | None = None) -> dict[str, Any]:
    """Start everything, watch for ``seconds`` (or less: until ``done(report)`` holds, asked
    twice a second; a loaded host's startup and stalls then shorten only what is left of
    the watch, not what it shows), stop everything; the figures."""
    from agent import Client, Service
    from agent.daemon import Agent, AgentSettings

    realm = f"cams{uuid.uuid4().hex[:10]}"
    ep = {side: _endpoint() for side in CAMERAS}
    seen, stop = _Seen(), threading.Event()
    agents: list[Any] = []
    loops: list[_CameraLoop] = []
    t0_ns = time.time_ns()
    try:
        for k, side in enumerate(CAMERAS):
            p, q = geo.from_matrix(camera_pose(side))
            edge = {"parent": "lab/world", "child": f"lab/cam-{side}",
                    "position": [float(v) for v in p], "quaternion": [float(v) for v in q]}
            a = Agent(AgentSettings(realm=realm, agent_id=side, listen=[ep[side]],
                                    connect=[ep["left"]] if k else [], static_edges=[edge]))
            a.start()
            agents.append(a)
        if live:
            print(f"uma demo --cameras: realm {realm}, agents left {ep['left']} and right "
                  f"{ep['right']}", flush=True)
        for side in CAMERAS:
            loop = _CameraLoop(side, realm, ep[side], np.random.default_rng([seed, len(loops)]),
                               t0_ns, stop, seen)
            loop.start()
            loops.append(loop)

        def on_sample(m: Any) -> None:
            with seen.lock:
                seen.stream.append((time.monotonic(), str(m.source)))

        with Service("app", realm=realm, agent="left", connect=[ep["left"]]) as app, \
                Client(realm=realm, connect=[ep["right"]], timeout=1.0) as client:
            app.need("tag", type="pose6d", edge=("lab/*", TARGET), prefer="pos_std_m",
                     standby=1, on_sample=on_sample)
            app.start()
            _watch(client, seconds, t0_ns, seen, live, done)
    finally:
        stop.set()
        for loop in loops:
            loop.join(5)
        for a in reversed(agents):
            with contextlib.suppress(Exception):
                a.close()
    return _report(seen, seconds)


def _watch(client: Any, seconds: float, t0_ns: int, seen: _Seen, live: bool,
           done: Callable[[dict[str, Any]], bool] | None) -> None:
    """Query the tag in the world frame twice a second, until ``seconds`` are up or
    ``done`` holds for the report so far; a live line per second."""
    end = time.monotonic() + seconds
    last_line = 0.0
    while time.monotonic() < end and not (done is not None and done(_report(seen, seconds))):
        try:
            r = client.pose("lab/world", TARGET)
        except Exception as exc:  # no route yet, or an agent slow to answer: counted
            with seen.lock:
                seen.failed_queries.append(f"{type(exc).__name__}: {exc}")
            time.sleep(0.5)
            continue
        truth = tag_pose((r.t_ns - t0_ns) / 1e9)
        err_m = float(np.linalg.norm(np.asarray(r.position) - truth[:3, 3]))
        with seen.lock:
            seen.queries.append((time.monotonic(), err_m, list(r.path)))
            source = seen.stream[-1][1] if seen.stream else "-"
        if live and time.monotonic() - last_line >= 1.0:  # a line a second
            last_line = time.monotonic()
            print(f"  need follows {source:9s} | lab/world -> {TARGET} via "
                  f"{' -> '.join(r.path[1:-1])}: error {err_m * 1000:6.1f} mm", flush=True)
        time.sleep(0.5)


def _report(seen: _Seen, seconds: float) -> dict[str, Any]:
    """Switches of the need, each against the moment the other camera became the better."""
    with seen.lock:
        stream, claims, queries = list(seen.stream), dict(seen.claims), list(seen.queries)
        frames = {side: list(t) for side, t in seen.frames.items()}
    switches, delays, followed = [], [], set()
    for (t_prev, s_prev), (t, s) in itertools.pairwise(stream):
        if s != s_prev:  # the handover: last sample of the old camera to first of the new
            switches.append({"at_s": round(t - stream[0][0], 2), "from": s_prev, "to": s,
                             "handover_gap_s": round(t - t_prev, 3)})
    better = _better_changes(claims)
    for change_wall, side in better:
        mono = change_wall - time.time() + time.monotonic()
        follow = next((t for t, s in stream if t >= mono and s == f"cam-{side}"), None)
        if follow is not None:
            delays.append(round(follow - mono, 3))
            followed.add(f"cam-{side}")
    gaps = np.diff([t for t, _ in stream]) if len(stream) > 1 else np.array([math.inf])
    worst = int(np.argmax(gaps)) if len(stream) > 1 else 0
    seen_gaps = _gaps_while_seen(stream, claims)
    errors = [e for _, e, _ in queries]
    return {"seconds": seconds, "samples_received": len(stream), "switches": switches,
            "better_camera_changes": len(better), "follow_delays_s": delays,
            # the cameras the need moved to after they became the better one
            "followed": sorted(followed),
            "max_stream_gap_s": round(float(gaps.max()), 3),
            "max_handover_gap_s": max((s["handover_gap_s"] for s in switches), default=None),
            # a camera's own longest pause between frames (a loaded host): the stream
            # cannot be steadier than its cameras
            "max_frame_gap_s": {side: round(float(np.diff(t).max()), 3)
                                for side, t in frames.items() if len(t) > 1},
            "max_gap_at_s": round(stream[worst][0] - stream[0][0], 2) if stream else None,
            "max_gap_while_seen_s": round(max(seen_gaps, default=0.0), 3),
            "queries": len(queries), "queries_failed": len(seen.failed_queries),
            "first_query_failure": seen.failed_queries[0] if seen.failed_queries else None,
            "world_error_mm": None if not errors else
            {"median": round(1000 * float(np.median(errors)), 2),
             "max": round(1000 * float(np.max(errors)), 2)},
            "paths": sorted({" -> ".join(p) for _, _, p in queries}),
            "errors": seen.errors[:10], "ok": bool(switches) and not seen.errors}


def _gaps_while_seen(stream: list[tuple[float, str]],
                     claims: dict[str, list[tuple[float, float]]]) -> list[float]:
    """The gaps in the stream during which some camera saw the tag: a frame with the tag
    was captured more than a frame interval before the gap ended (one captured just before
    is the sample that ends it, or its twin of the other camera)."""
    offset = time.monotonic() - time.time()  # claims are wall-clock capture times
    seen = np.sort([t + offset for rows in claims.values() for t, _ in rows])
    out = []
    for (a, _), (b, _) in itertools.pairwise(stream):
        i = np.searchsorted(seen, a, side="right")
        if i < len(seen) and seen[i] < b - 1 / FPS:
            out.append(b - a)
    return out


def _better_changes(claims: dict[str, list[tuple[float, float]]]) -> list[tuple[float, str]]:
    """(wall time, side) each time the other camera's claimed position std (smoothed over
    half a second) becomes the smaller one and stays so for ``HOLD_S`` (a shorter lead
    is noise a need should not chase); a camera with no sample within ``UNSEEN_S`` of a
    moment does not see the tag then (worse than any claim), and while neither sees it
    neither is the better."""
    if len(claims) < 2:
        return []
    grid = np.arange(max(c[0][0] for c in claims.values()), min(c[-1][0] for c in
                                                                 claims.values()), 0.1)
    smooth = {}
    for side, rows in claims.items():
        t, s = np.array(rows).T
        at = np.interp(grid, t, np.convolve(np.pad(s, 3, mode="edge"), np.ones(7) / 7,
                                            mode="valid"))
        after = np.clip(np.searchsorted(t, grid), 0, len(t) - 1)
        nearest = np.minimum(np.abs(t[after] - grid), np.abs(t[np.maximum(after - 1, 0)] - grid))
        smooth[side] = np.where(nearest > UNSEEN_S, np.inf, at)
    best = np.where(smooth["left"] <= smooth["right"], "left", "right")
    seen = np.isfinite(np.minimum(smooth["left"], smooth["right"]))
    hold = round(HOLD_S / 0.1)
    changes, current = [], None
    for i in np.flatnonzero(seen):
        if best[i] != current and np.all(best[i:i + hold][seen[i:i + hold]] == best[i]):
            if current is not None:
                changes.append((float(grid[i]), str(best[i])))
            current = best[i]
    return changes


def main(args: argparse.Namespace) -> int:
    report = run_demo(args.seconds, args.seed, live=not args.json)
    if args.json:
        print(json.dumps(report))
    else:
        print(f"need moved {len(report['switches'])} times: " + ", ".join(
            f"{s['at_s']} s {s['from']} -> {s['to']} (handover {s['handover_gap_s']} s)"
            for s in report["switches"]))
        print(f"better camera changed {report['better_camera_changes']} times; the need followed "
              f"after {report['follow_delays_s']} s; longest gap in its stream "
              f"{report['max_stream_gap_s']} s (at {report['max_gap_at_s']} s), while a camera "
              f"saw the tag {report['max_gap_while_seen_s']} s, at a switch "
              f"{report['max_handover_gap_s']} s; the cameras' longest pause between frames "
              f"{report['max_frame_gap_s']} s")
        print(f"world-frame queries: {report['queries']} answered, {report['queries_failed']} "
              f"not, error {report['world_error_mm']} mm, "
              f"paths {report['paths']}")
        if report["errors"]:
            print(f"errors: {report['errors']}")
    return 0
