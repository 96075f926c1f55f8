"""The outside-in services: ``marker-camera`` and ``outside-in`` (declared in ``plugin``).

A **marker camera** serves one or more cameras of a rig (each its own ``Service``
``markers-NAME``): every frame's blobs (``blobs.find_blobs``) go out as a ``markers2d``
sample on the edge ``world -> SITE/NAME``, stamped with the capture time in this host's
clock (``Service.now_ns``; the reconstruction's SDK moves it onto its own host's clock),
with the camera's name and the calibration's version (a digest of the rig file) in
``extra``.  Frames come from ``services.camera.capture`` (devices, videos, folders, URLs)
or from the simulated rig, whose time is the wall clock so that cameras on several hosts
render one world.

The reconstruction feeds its filter's predictions back (Dorfmüller-Ulhaas §2): after a
frame set it publishes, per camera (at most every ``WINDOWS_EVERY_S``, and only while
they can come in time: ``Reconstruction.windows``), where the tracked bodies' markers will
image at that camera's next exposure (a ``markers2d`` ability ``windows-NAME`` on ``SITE/NAME ->
SITE/NAME/windows``, its time the exposure's, ``extra["search"]`` true while a body is
lost; each point's value the least distance in pixels within which the reconstruction
takes a blob, ``TrackerParams.gate_px``: where its prediction is less sure it takes one
further off, ``tracker.GATE_SIGMAS``).  Each marker camera needs its own and looks for
blobs only in windows around those points (``find_blobs``' windowed mode: a fraction of
the whole image's cost), and in the whole image when no prediction for this exposure (or
up to ``PREDICTION_AGE_S`` before it) has come, and while a body is lost: every camera's
every frame then, since the search needs a body's markers in two cameras' whole images of
one frame set.

The **reconstruction** needs ``markers2d`` on ``world -> SITE/*`` from up to 16 cameras:
whatever camera appears is used, one that stops is left out.  Samples are gathered into
frame sets (a set is complete when every live camera sent one, when a camera sends its
next frame, or when a frame of a later exposure arrives), run through
``OutsideInTracker``, and each body's pose is published on ``world -> SITE/BODY`` with its
covariance.  The service's dispatch thread gathers the samples into sets; its tracking
thread tracks them, skipping to the present any set more than ``BEHIND_S`` older than
the newest gathered (``RecentSets``), and a sample ``STALE_S`` older than the freshest is
not even gathered: a reconstruction held back (a busy machine, a pause) goes on from the
present, its windows in time for the cameras, instead of working through a queue.  Lost
bodies are searched for within ``SEARCH_SHARE`` of the time (``Reconstruction.track``).
A sample of another calibration than the
rig file's, or of a camera the rig does not hold, is refused, counted and logged
(rate-limited), never used.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import hashlib
import logging
import math
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

from agent import Service
from agent.errors import UmaError
from agent.runtime import RateLimitedLog
from schemas.codec import MARKERS_CALIBRATION, MARKERS_CAMERA, Measurement
from services.camera.capture import Capture
from services.outside_in.blobs import Blobs, find_blobs
from services.outside_in.bodies import load_bodies
from services.outside_in.rigfile import load_rig
from services.outside_in.simulator import Replay, SimConfig, Simulation
from services.outside_in.tracker import BodyEstimate, CameraFrame, OutsideInTracker

log = logging.getLogger("uma.outside_in")
#: a camera silent this long is not waited for when a frame set is complete
LIVE_S = 0.5
#: how long after the exposure it was made for a prediction still places the windows:
#: the reconstruction's answer comes a frame or more late at 60-120 Hz, and a marker
#: moving 1 m/s 3 m away moves 6 px in 40 ms, inside a window (``BlobParams.window_px``)
PREDICTION_AGE_S = 0.04
#: a sample this much older (s) than the freshest of the last ``FLOOR_S`` is not tracked:
#: the reconstruction has fallen behind (its queue grows while the machine is busy) and
#: catches up by skipping to the present, as a tracker's poses are for now
STALE_S = 0.1
FLOOR_S = 10.0
#: the reconstruction sends a camera new windows once its last are this much older (s)
WINDOWS_EVERY_S = 0.02
#: the share of the exposure time that searching for lost bodies may take (``track``)
SEARCH_SHARE = 0.25
SEARCH_BURST_S = 0.06
#: the reconstruction tracks a frame set only while it is at most this much (s) older
#: than the newest it has gathered: behind further, it skips to the present
#: (``RecentSets``), its windows then still in time for the cameras (``PREDICTION_AGE_S``)
BEHIND_S = 0.025
#: one frame set's tracking CPU (s) beyond which a warning names it: a frame period and more
#: holds every set after it back
SLOW_SET_S = 0.1
#: ``extra`` key of a windows sample: a body is lost, search whole images too
SEARCH = "search"


def calibration_version(path: str | Path) -> str:
    """The rig file's version: the first 12 hex digits of its SHA-256."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]
    except OSError as exc:
        raise UmaError(f"rig file {path}: cannot be read ({exc})") from None


def keep_startup_objects() -> None:
    """Take what a service made while starting (its modules, the rig, the bodies, the
    frames rendered ahead) out of the garbage collector's scans, having collected once:
    it lives as long as the process, and a full collection that scanned it (some 76,000
    objects in the reconstruction's path run in one process) paused the thread it ran
    in for 46-94 ms at load 20: long enough for the reconstruction to fall ``STALE_S``
    behind and skip frame sets, or for a camera to miss frames."""
    gc.collect()
    gc.freeze()


# ------------------------------------------------------------------ marker cameras


def run_marker_camera(args: argparse.Namespace, stop: threading.Event) -> int:
    cams, _, _ = load_rig(args.rig)
    version = calibration_version(args.rig)
    by_name = {c.name: i for i, c in enumerate(cams)}
    names = args.camera or [n for n, _ in args.source]
    if not names:
        raise UmaError("say which cameras this process serves: --camera NAME (with --sim) or "
                       "--source NAME=SOURCE")
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise UmaError(f"cameras {unknown} are not in the rig file {args.rig} "
                       f"(it has {sorted(by_name)})")
    sources = dict(args.source)
    if args.sim is None and set(names) - set(sources):
        raise UmaError(f"cameras {sorted(set(names) - set(sources))} need --source NAME=SOURCE "
                       "(or --sim SEED)")
    if args.prerender and args.sim is None:
        raise UmaError("--prerender needs --sim SEED (it renders the simulated frames ahead)")
    if not 0 <= args.prerender <= 600:
        raise UmaError(f"--prerender must be in [0, 600] seconds, got {args.prerender}")
    if args.replay_at is not None and not (args.prerender and 0 < args.replay_at < 1e10):
        raise UmaError("--replay-at needs --prerender and a unix time in seconds, got "
                       f"{args.replay_at}")
    if not 0 < args.rate_hz <= 240:
        raise UmaError(f"--rate-hz must be in (0, 240], got {args.rate_hz}")
    sim = (Simulation(seed=args.sim, config=SimConfig(n_cameras=len(cams),
                                                      rate_hz=args.rate_hz))
           if args.sim is not None else None)
    threads = []
    found: dict[str, Windows] = {}
    with contextlib.ExitStack() as stack:
        for name in names:
            svc = stack.enter_context(Service(f"markers-{name}", realm=args.realm,
                                              agent=args.agent, connect=args.connect,
                                              listen=args.listen or None))
            out = svc.ability("markers", type="markers2d",
                              edge=(args.world, f"{args.site}/{name}"),
                              frequency_hz=args.rate_hz, latency_s=0.01)
            windows = found[name] = Windows(version)
            svc.need("windows", type="markers2d",
                     edge=(f"{args.site}/{name}", f"{args.site}/{name}/windows"),
                     on_sample=windows.on_sample)
            svc.start()
            extra = {MARKERS_CAMERA: name, MARKERS_CALIBRATION: version}
            frames = (_sim_frames(sim, by_name[name], stop, args.max_frames,
                                  args.prerender, len(names), args.replay_at) if sim
                      else _capture_frames(sources[name], stop, args.max_frames))
            t = threading.Thread(target=_publish_frames,
                                 args=(frames, out, extra, svc.clock_skew_ns, windows,
                                       round(1e9 / args.rate_hz)),
                                 name=f"uma-markers-{name}", daemon=True)
            t.start()
            threads.append(t)
        log.info("marker-camera: serving %s (calibration %s)", ", ".join(names), version)
        while not stop.is_set() and any(t.is_alive() for t in threads):
            if stop.wait(5.0):
                break
            log.info("marker-camera: frames searched in the predicted windows / whole: %s; "
                     "CPU per frame, segmentation / publishing: %s",
                     ", ".join(f"{n} {w.windowed}/{w.whole}" for n, w in found.items()),
                     ", ".join(f"{n} {1e3 * w.cpu_s[0] / max(w.frames, 1):.3f}/"
                               f"{1e3 * w.cpu_s[1] / max(w.frames, 1):.3f} ms"
                               for n, w in found.items()))
        stop.set()
        for t in threads:
            t.join(timeout=5.0)
    return 0


class Windows:
    """The reconstruction's latest prediction for one camera (its ``windows`` need): where
    to look in the frame it is for."""

    def __init__(self, version: str) -> None:
        self.version = version
        self.latest: Measurement | None = None
        self.frames = 0
        #: frames searched whole / in windows only
        self.whole = 0
        self.windowed = 0
        #: thread CPU (s) in segmentation, in publishing
        self.cpu_s = [0.0, 0.0]

    def on_sample(self, m: Measurement) -> None:
        if m.extra.get(MARKERS_CALIBRATION) == self.version:
            self.latest = m      # a reference swap: the capture thread reads it as is

    def find(self, image: np.ndarray, t_ns: int, period_ns: int) -> Blobs:
        """The frame's blobs: in the predicted windows when a prediction for this
        exposure (from half a period before it to ``PREDICTION_AGE_S`` after) came and no
        body is lost, else in all of it.  Not every n-th frame while lost: each camera
        would count its own frames, and cameras whose whole frames never fall in one
        frame set leave the search never two cameras' blobs of a body (a stall for good,
        on a quiet machine whose predictions are always fresh); a whole frame costs
        little more than windows (1.55 against 1.1 ms at 640x480)."""
        self.frames += 1
        m = self.latest
        fresh = (m is not None
                 and -period_ns // 2 <= t_ns - m.t_ns <= max(period_ns // 2,
                                                             PREDICTION_AGE_S * 1e9))
        if not fresh or m.extra.get(SEARCH):
            self.whole += 1
            return find_blobs(image)
        self.windowed += 1
        return find_blobs(image, predicted_uv=m.points) if len(m.points) else Blobs.empty()


def _publish_frames(frames, out, extra: dict, skew_ns: int, windows: Windows,
                    period_ns: int) -> None:
    """Each frame's blobs, stamped on this host's clock: the frames' times are the system
    clock's (the capture's, the simulated world's), which a test may skew (``skew_ns``)."""
    for t_ns, image in frames:
        t0 = time.thread_time()
        blobs = windows.find(image, t_ns + skew_ns, period_ns)
        t1 = time.thread_time()
        out.publish_measurement(Measurement(type="markers2d", t_ns=t_ns + skew_ns,
                                            points=blobs.uv,
                                            values=blobs.std_px, extra=extra))
        windows.cpu_s[0] += t1 - t0
        windows.cpu_s[1] += time.thread_time() - t1


def _sim_frames(sim: Simulation, camera: int, stop: threading.Event, max_frames: int | None,
                prerender_s: float = 0.0, renderers: int = 1, replay_at: float | None = None):
    """The simulated camera's frames, paced by the wall clock: frame ``i`` is exposed at
    ``i / rate`` seconds since the epoch (plus the camera's phase).  With ``prerender_s``
    that many seconds of frames, starting once they are rendered (``renderers`` cameras
    render at once), are rendered first and replayed (``Simulation.prerender``) from
    ``replay_at`` (unix time) or once rendered, the camera silent until the first of them;
    frames after them are rendered live."""
    rate = sim.config.rate_hz

    def now_index() -> int:
        # from the rate, not a rounded period: at 120 Hz a period of 8333333 ns would put
        # the index of today's date 18 s ahead of the exposure times i / rate
        return int(time.time_ns() * rate / 1e9)
    replay = _prerendered(sim, camera, now_index(), prerender_s, renderers, replay_at) \
        if prerender_s > 0 else None
    keep_startup_objects()
    i = max(now_index() + 1, replay.first if replay is not None else 0)
    n = 0
    while not stop.is_set() and (max_frames is None or n < max_frames):
        ready = replay.frame(i) if replay is not None else None
        if ready is None:
            frame = sim.render(camera, i)
            ready = frame.t, frame.image
        t_ns = round(ready[0] * 1e9)
        wait = (t_ns - time.time_ns()) / 1e9
        if wait > 0:
            stop.wait(wait)
        yield t_ns, ready[1]
        n += 1
        i = max(i + 1, now_index())   # a frame missed while busy is gone


def _prerendered(sim: Simulation, camera: int, now: int, seconds: float, renderers: int,
                 start: float | None) -> Replay:
    """``seconds`` of the camera's frames from ``start`` (unix time; all cameras of a rig
    given the same start replay one world), or when not given from the index the
    rendering will have reached when it is done (timed on a few frames, with a margin for
    the other cameras' rendering and the machine's load)."""
    rate = sim.config.rate_hz
    count = max(1, round(seconds * rate))
    if start is None:
        sim.render(camera, now)            # the first render warms caches up: not timed
        t0 = time.perf_counter()
        for k in range(1, 4):
            sim.render(camera, now + k)
        start = (now + 1) / rate + 1.5 * (time.perf_counter() - t0) / 3 * count * renderers \
            + 1.0
    replay = sim.prerender(camera, math.ceil(start * rate), count)
    # frames whose time passed while rendering are skipped: the replay starts now then
    log.info("marker-camera: %s: %d frames rendered ahead, replayed from %.3f (unix time)",
             sim.cameras[camera].name, count, max(replay.times[0], time.time()))
    return replay


def _capture_frames(source: str, stop: threading.Event, max_frames: int | None):
    with Capture(source, pace=True, gray=True, max_frames=max_frames) as cap:
        for frame in cap.frames(stop):
            yield frame.t_ns, frame.image


# ------------------------------------------------------------------ reconstruction


class Reconstruction:
    """Gathers markers2d samples into frame sets and tracks the bodies (no I/O: the
    service calls ``add`` from its dispatch thread and publishes what it returns)."""

    def __init__(self, rig_path: str | Path, bodies_path: str | Path, site: str):
        cams, _, _ = load_rig(rig_path)
        self.version = calibration_version(rig_path)
        self.bodies = load_bodies(bodies_path)
        self.tracker = OutsideInTracker(cams, self.bodies)
        self.index = {c.name: i for i, c in enumerate(cams)}
        self.site = site
        self.pending: dict[int, CameraFrame] = {}
        self.last_seen: dict[int, float] = {}
        self.last_t: dict[int, float] = {}
        self.period: float | None = None   # the shortest frame period seen
        self.refused = RateLimitedLog(log)
        self.refused_count = 0
        self.frame_sets = 0
        #: frames that came after their exposure's set was tracked, not used
        self.late = 0
        #: per camera, the exposure (ns) of the last windows sent
        self.windows_sent: dict[int, int] = {}
        #: samples not tracked, too far behind the freshest (the reconstruction behind)
        self.stale = 0
        #: the CPU (s) searches for lost bodies may still take, the last set's time
        #: (``track``)
        self._search_budget = SEARCH_BURST_S
        self._last_set_t: float | None = None
        self._block = -1
        self._floors: tuple[float, float] = (np.inf, np.inf)

    def add(self, m: Measurement, now: float | None = None,
            now_ns: int | None = None) -> list[BodyEstimate]:
        """One camera's sample; the poses of the frame sets it completed, if any
        (``gather`` then ``track``)."""
        return [e for frames in self.gather(m, now, now_ns) for e in self.track(frames)]

    def track(self, frames: list[CameraFrame]) -> list[BodyEstimate]:
        """The poses of one frame set (``gather``'s).  Lost bodies are searched for in it
        while the searches' CPU is within ``SEARCH_SHARE`` of the exposure time (a
        budget that grows by that share of the time between frame sets, up to
        ``SEARCH_BURST_S``, and that each search spends): searching the whole images'
        blobs costs about 20 ms a lost body at 8 cameras (eight frame sets' tracking),
        and searching every set would take more than the camera rate leaves, the tracked
        bodies' sets then skipped too."""
        t = max(f.t for f in frames)
        if self._last_set_t is not None and t > self._last_set_t:
            self._search_budget = min(SEARCH_BURST_S, self._search_budget
                                      + SEARCH_SHARE * (t - self._last_set_t))
        self._last_set_t = t
        search = self.tracker.searching and self._search_budget > 0
        t0 = time.thread_time()
        out = self.tracker.process(frames, search=search)
        if search:
            self._search_budget -= time.thread_time() - t0
        return out

    def gather(self, m: Measurement, now: float | None = None,
               now_ns: int | None = None) -> list[list[CameraFrame]]:
        """One camera's sample into its frame set; the frame sets it completed, oldest
        first (none, one, or the pending one and this sample alone).  With ``now_ns``
        (this clock) a sample that is ``STALE_S`` older than the freshest of the last
        ``FLOOR_S`` is not gathered (``stale``)."""
        now = time.monotonic() if now is None else now
        cam = self._camera(m)
        if cam is None:
            return []
        self.last_seen[cam] = now
        t = m.t_ns / 1e9
        if cam in self.last_t and t > self.last_t[cam]:
            self.period = min(self.period or np.inf, t - self.last_t[cam])
        self.last_t[cam] = t
        out: list[list[CameraFrame]] = []
        if now_ns is not None and self._stale(now_ns - m.t_ns, now_ns):
            self.stale += 1
            return out
        if (self.period is not None and self.pending
                and t < max(f.t for f in self.pending.values()) - 0.5 * self.period):
            # of an exposure whose set was already tracked (it came late): it would make
            # the pending set one of two exposures
            self.late += 1
            return out
        # a camera's next frame, or a frame of a later exposure than the pending set's:
        # the pending set is as complete as it gets
        later = (self.period is not None and self.pending
                 and t - min(f.t for f in self.pending.values()) > 0.5 * self.period)
        if cam in self.pending or later:
            out.append(self._flush())
        n = len(m.points)
        self.pending[cam] = CameraFrame(cam, t, Blobs(
            m.points, m.values, np.zeros(n), np.zeros(n), np.ones(n)))
        live = {c for c, t in self.last_seen.items() if now - t <= LIVE_S}
        if live <= set(self.pending):
            out.append(self._flush())
        return out

    def _stale(self, age_ns: int, now_ns: int) -> bool:
        """Whether a sample of this age is ``STALE_S`` older than the freshest samples
        (the least age in this and the last ``FLOOR_S`` block of time: the transport's
        own delay, or a replayed recording's offset)."""
        block = now_ns // round(FLOOR_S * 1e9)
        if block != self._block:
            self._floors = (self._floors[1] if block == self._block + 1 else np.inf, np.inf)
            self._block = block
        self._floors = (self._floors[0], min(self._floors[1], age_ns))
        return age_ns > min(self._floors) + STALE_S * 1e9

    def windows(self, now_ns: int) -> list[tuple[str, int, np.ndarray]]:
        """Per camera seen so far whose windows are due at ``now_ns`` (this clock): its
        name, its next exposure (ns) and where the tracked bodies' markers will image then
        (none before the frame period is known).

        A camera takes a prediction for the frames up to ``PREDICTION_AGE_S`` after the
        exposure it was made for: one that would come later is not sent (the
        reconstruction is behind), nor one within ``WINDOWS_EVERY_S`` of the last sent to
        that camera (at 120 Hz every third frame set; each message costs its sender,
        the agent and the camera more than the windows save the segmentation)."""
        if self.period is None:
            return []
        names = {i: n for n, i in self.index.items()}
        times = {}
        for cam, t in self.last_t.items():
            t_next = t + self.period
            due = round(t_next * 1e9)
            if (now_ns >= due + PREDICTION_AGE_S * 1e9
                    or due - self.windows_sent.get(cam, -2**62) < WINDOWS_EVERY_S * 1e9):
                continue
            self.windows_sent[cam] = due
            times[cam] = t_next
        images = self.tracker.predicted_images(times)
        return [(names[cam], self.windows_sent[cam], images[cam]) for cam in times]

    def _flush(self) -> list[CameraFrame]:
        frames = list(self.pending.values())
        self.pending = {}
        self.frame_sets += 1
        return frames

    def _camera(self, m: Measurement) -> int | None:
        name = m.extra.get(MARKERS_CAMERA)
        source = m.source or "?"
        if name not in self.index:
            self._refuse(source, f"camera {name!r} is not in the rig")
            return None
        if m.extra.get(MARKERS_CALIBRATION) != self.version:
            self._refuse(source, f"calibration {m.extra.get(MARKERS_CALIBRATION)!r} is not "
                                 f"the rig file's {self.version}")
            return None
        return self.index[name]

    def _refuse(self, source: str, reason: str) -> None:
        self.refused_count += 1
        self.refused.warning(source, f"markers2d refused: {reason}")


class RecentSets:
    """The frame sets gathered and not tracked yet, between the service's dispatch thread
    (which gathers every sample into its set, a small cost, and puts each set it
    completes) and its tracking thread (which takes them oldest first).  A set more than
    ``BEHIND_S`` older than the newest gathered is not tracked (``superseded``): a tracker
    that got less CPU than the camera rate needs for a while (a busy machine, a pause of
    its process) goes on near the present at once, its windows in time for the cameras'
    next frames, and tracks as many sets as it can.  Working through the queue instead
    kept it behind: its windows came too late to be sent, the cameras searched their
    whole images and the frame sets (cut by the stale samples) cost more."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._sets: deque[list[CameraFrame]] = deque()
        self.superseded = 0

    def put(self, frames: list[CameraFrame]) -> None:
        with self._cond:
            self._sets.append(frames)
            self._cond.notify()

    def take(self, timeout: float) -> list[CameraFrame] | None:
        """The oldest set within ``BEHIND_S`` of the newest (None when none came within
        ``timeout`` s)."""
        with self._cond:
            if not self._sets:
                self._cond.wait(timeout)
            if not self._sets:
                return None
            newest = _set_time(self._sets[-1])
            while _set_time(self._sets[0]) < newest - BEHIND_S:
                self._sets.popleft()
                self.superseded += 1
            return self._sets.popleft()


def _set_time(frames: list[CameraFrame]) -> float:
    return max(f.t for f in frames)


def run_outside_in(args: argparse.Namespace, stop: threading.Event) -> int:
    rec = Reconstruction(args.rig, args.bodies, args.site)
    lock = threading.Lock()    # the frame sets' bookkeeping: dispatch and tracking threads
    recent = RecentSets()
    failed = RateLimitedLog(log)
    slow = RateLimitedLog(log)
    with Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect,
                 listen=args.listen or None) as svc:
        outs = {b.name: svc.ability(b.name, type="pose6d",
                                    edge=(args.world, f"{args.site}/{b.name}"),
                                    frequency_hz=args.rate_hz, latency_s=0.03,
                                    pos_std_m=0.0005, rot_std_rad=0.002)
                for b in rec.bodies}

        windows = {name: svc.ability(f"windows-{name}", type="markers2d",
                                     edge=(f"{args.site}/{name}", f"{args.site}/{name}/windows"),
                                     frequency_hz=args.rate_hz, latency_s=0.01)
                   for name in rec.index}

        def on_sample(m: Measurement) -> None:
            with lock:
                sets = rec.gather(m, now_ns=svc.now_ns())
            for frames in sets:
                recent.put(frames)

        def track_one(frames: list[CameraFrame]) -> None:
            t0 = time.thread_time()
            estimates = rec.track(frames)
            with lock:
                ahead = rec.windows(svc.now_ns())
            search = rec.tracker.searching
            t1 = time.thread_time()
            if t1 - t0 > SLOW_SET_S:
                slow.warning("outside-in", f"one frame set took {1e3 * (t1 - t0):.0f} ms of "
                             f"CPU ({len(frames)} cameras, "
                             f"{sum(len(f.blobs.uv) for f in frames)} blobs, search {search})")
            for e in estimates:
                outs[e.body].publish(round(e.t * 1e9), e.p, e.q, e.cov_se3)
            extra = {MARKERS_CALIBRATION: rec.version, SEARCH: search}
            for name, t_ns, uv in ahead:
                windows[name].publish_measurement(Measurement(
                    type="markers2d", t_ns=t_ns, points=uv,
                    values=np.full(len(uv), rec.tracker.params.gate_px),
                    extra={**extra, MARKERS_CAMERA: name}))
            cpu[0] += t1 - t0
            cpu[1] += time.thread_time() - t1
            cpu[2] += 1

        def tracking() -> None:
            while not stop.is_set():
                frames = recent.take(0.5)
                if frames is None:
                    continue
                try:
                    track_one(frames)
                except Exception as exc:   # one bad set must not end the tracking
                    failed.warning("outside-in", f"a frame set failed: "
                                                 f"{type(exc).__name__}: {exc}")

        cpu = [0.0, 0.0, 0]   # tracking thread CPU (s) tracking, publishing; sets tracked

        svc.need("markers", type="markers2d", edge=(args.world, f"{args.site}/*"),
                 min_count=2, max_count=16, on_sample=on_sample)
        tracker = threading.Thread(target=tracking, name="uma-outside-in-tracking",
                                   daemon=True)
        tracker.start()
        svc.start()
        keep_startup_objects()
        log.info("outside-in: tracking %s with %d cameras (calibration %s)",
                 ", ".join(b.name for b in rec.bodies), len(rec.index), rec.version)
        while not stop.wait(5.0):
            _log_counts(rec, recent, cpu)
        tracker.join(timeout=5.0)
        _log_counts(rec, recent, cpu)   # the whole run's, also when it lasted under 5 s
    return 0


def _log_counts(rec: Reconstruction, recent: RecentSets, cpu: list[float]) -> None:
    """The reconstruction's counts so far and its tracking thread's CPU per frame set
    (``cpu``: tracking s, publishing s, sets): every 5 s and once more on stop, so that a
    run shorter than that (a demo, a test) still leaves them in its log."""
    n = max(cpu[2], 1)
    log.info("outside-in: %d frame sets, %s, %d samples refused, %d late, %d stale, %d sets "
             "superseded; CPU per frame set: tracking %.2f ms, publishing %.2f ms",
             rec.frame_sets, dict(rec.tracker.counts), rec.refused_count, rec.late,
             rec.stale, recent.superseded, 1e3 * cpu[0] / n, 1e3 * cpu[1] / n)
