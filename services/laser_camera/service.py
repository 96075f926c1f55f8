"""``uma service run laser-camera``: MARVIN's laser-dot tracker as a uma service.

Abilities:

* ``pose`` -- ``pose6d`` ``ivy/world -> marvin/laser_rig`` with a 6x6 covariance per
  sample, and that covariance's systematic part (the installation's tolerances, which hold
  from frame to frame) under ``extra[SYSTEMATIC_COVARIANCE]``; its attributes
  (``frequency_hz``, ``latency_s``, ``pos_std_m``, ``rot_std_rad``, ``confidence`` = share
  of frame sets with a pose) are measured by the service itself: a warm-up before it
  advertises, then updated as they drift;
* ``dots`` -- ``points3d`` on the same edge: the labeled world-frame laser spots (ids =
  diode labels 1..4) of every frame set that has any, for one-dot-at-a-time (SCAAT)
  fusion (Welch & Bishop, SCAAT, 1997): a pose's four, and of a frame set without a pose
  (fewer than four dots seen) those the pose predicted from the last two labels
  (``LaserTracker.label_dots``); each dot's noise and installation std ride along
  (``schemas.codec.DOT_STD``, ``DOT_SYSTEMATIC_STD``).  A dot that gets no label is not
  published; the tracker counts it (``dot_unlabeled_*``), logged with the other counts.

Input is the simulator (default) or one OpenCV capture per camera (``sources``).
``--calibrate`` calibrates the simulated cameras from rendered checkerboards and writes
``--calibration``.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agent import Service
from agent import geometry as geo
from agent.errors import InvalidInputError
from schemas.codec import (
    DOT_STD,
    DOT_SYSTEMATIC_STD,
    SYSTEMATIC_COVARIANCE,
    Measurement,
    pack_covariance,
)
from services import frames
from services.laser_camera.calibration import Calibration, calibrate_sim
from services.laser_camera.plugin import estimate_installation
from services.laser_camera.sources import CaptureSource, SimSource, parse_sources
from services.laser_camera.tracker import (
    LabeledDots,
    LaserTracker,
    PoseEstimate,
    TrackerParams,
)
from services.sim.world import IvyWorld

log = logging.getLogger("uma.laser_camera")
WARMUP_FRAMES = 10
#: the warm-up waits for a first pose (a start with the head in a corner or upside down
#: gives none) at most this many frame sets, then advertises what it measured
MAX_WARMUP_FRAMES = 150
ATTRIBUTE_WINDOW = 150  # frame sets over which the advertised attributes are measured
ATTRIBUTE_UPDATE_S = 5.0
ATTRIBUTE_CHANGE = 0.25  # re-advertise when a figure drifted by more than this fraction


def run(args: argparse.Namespace, stop: threading.Event) -> int:
    specs = parse_sources(args.source)
    if not 0 < args.rate_hz <= 240:
        raise InvalidInputError(f"--rate-hz must be in (0, 240], got {args.rate_hz}")
    if args.calibrate:
        return _calibrate(args, specs)
    cal, source = _open(args, specs)
    try:
        return _serve(args, cal, source, stop)
    finally:
        source.close()


def _calibrate(args: argparse.Namespace, specs) -> int:
    if specs is not None:
        raise InvalidInputError("--calibrate calibrates the simulated display; real cameras need "
                                "their checkerboard images calibrated with "
                                "services.laser_camera.calibration (calibrate_intrinsics, "
                                "calibrate_screen) and saved as a calibration file")
    path = Path(args.calibration or "laser_calibration.json")
    cal = calibrate_sim(IvyWorld(n_cameras=args.cameras, seed=args.seed, ideal=args.ideal))
    cal.save(path)
    for c in cal.cameras:
        q = c.quality
        print(f"{c.name:9s} intrinsics rms {q['intrinsic_rms_px']:.3f} px, screen rms "
              f"{q['screen_rms_m'] * 1000:.2f} mm over {q['corners']} corners, DLT vs "
              f"OpenCV {q['dlt_vs_opencv_m'] * 1000:.4f} mm")
    print(f"wrote {path}")
    return 0


def _open(args: argparse.Namespace, specs) -> tuple[Calibration, SimSource | CaptureSource]:
    if specs is None:
        world = IvyWorld(n_cameras=args.cameras, seed=args.seed, ideal=args.ideal)
        if args.calibration:
            cal = Calibration.load(args.calibration)
        else:
            log.info("laser-camera: calibrating the simulated cameras (no --calibration)")
            cal = calibrate_sim(world)
        missing = {c.name for c in world.cameras} - {c.name for c in cal.cameras}
        if missing:
            raise InvalidInputError(f"calibration lacks the simulated cameras {sorted(missing)}")
        return cal, SimSource(world)
    if not args.calibration:
        raise InvalidInputError("real sources need --calibration FILE")
    cal = Calibration.load(args.calibration)
    for s in specs:
        cal.camera(s.camera)  # ValueError naming the unknown camera
    return cal, CaptureSource(specs)


#: the rate advertised when (almost) no frame gives a pose, the smallest the two-decimal
#: attribute can state
MIN_RATE_HZ = 0.01


class _Performance:
    """What the service measures about itself, for its advertised attributes."""

    def __init__(self) -> None:
        self.times: deque[float] = deque(maxlen=ATTRIBUTE_WINDOW)  # frame-set wall times
        self.latency: deque[float] = deque(maxlen=ATTRIBUTE_WINDOW)
        self.got_pose: deque[bool] = deque(maxlen=ATTRIBUTE_WINDOW)
        self.got_dots: deque[bool] = deque(maxlen=ATTRIBUTE_WINDOW)
        self.pos_std: deque[float] = deque(maxlen=ATTRIBUTE_WINDOW)
        self.rot_std: deque[float] = deque(maxlen=ATTRIBUTE_WINDOW)

    def add(self, latency_s: float, result, dots: LabeledDots | None) -> None:
        self.times.append(time.monotonic())
        self.latency.append(latency_s)
        self.got_pose.append(isinstance(result, PoseEstimate))
        self.got_dots.append(dots is not None and bool(dots.labels))
        if isinstance(result, PoseEstimate):
            dec = geo.se3_to_decoupled(result.position, result.covariance)
            self.pos_std.append(float(np.sqrt(np.trace(dec[:3, :3]) / 3)))
            self.rot_std.append(float(np.sqrt(np.trace(dec[3:, 3:]) / 3)))

    def frame_hz(self, nominal_hz: float) -> float:
        """The measured rate of frame sets (``nominal_hz`` until two were taken)."""
        span = self.times[-1] - self.times[0] if len(self.times) > 1 else 0.0
        return (len(self.times) - 1) / span if span > 0 else nominal_hz

    def latency_s(self) -> float:
        """The median latency from capture to result."""
        return round(float(np.median(self.latency)), 4) if self.latency else 0.0

    def attributes(self, nominal_hz: float) -> dict[str, float]:
        share = float(np.mean(self.got_pose)) if self.got_pose else 0.0
        # the rate of poses, not of frames; never 0 (the schema wants a positive rate):
        # a warm-up in which no frame gave a pose advertises the lowest rate it can state
        out = {"frequency_hz": max(round(self.frame_hz(nominal_hz) * share, 2), MIN_RATE_HZ),
               "latency_s": self.latency_s(),
               "confidence": round(share, 3)}
        if self.pos_std:
            out["pos_std_m"] = float(f"{np.median(self.pos_std):.3g}")
            out["rot_std_rad"] = float(f"{np.median(self.rot_std):.3g}")
        return out

    def dot_attributes(self, nominal_hz: float) -> dict[str, float]:
        """The dots stream's: the rate and share of frame sets with labeled dots (more
        than have a pose), the same latency."""
        share = float(np.mean(self.got_dots)) if self.got_dots else 0.0
        return {"frequency_hz": max(round(self.frame_hz(nominal_hz) * share, 2), MIN_RATE_HZ),
                "latency_s": self.latency_s(),
                "confidence": round(share, 3)}


def _serve(args: argparse.Namespace, cal: Calibration, source, stop: threading.Event) -> int:
    """Track at the source's pace; advertise after a warm-up measured at that pace."""
    tracker = LaserTracker(cal, (TrackerParams.ideal if args.ideal else TrackerParams)(
        model_pos_std_m=args.model_pos_std_mm / 1000,
        model_rot_std_rad=float(np.radians(args.model_rot_std_deg)),
        estimate_installation=estimate_installation(args)))
    perf = _Performance()
    period = 1.0 / args.rate_hz if isinstance(source, SimSource) else 0.0
    with contextlib.ExitStack() as stack:
        outputs = None
        warmup: list = []
        next_update = next_tick = time.monotonic()
        while not stop.is_set():
            r = _step(tracker, source, perf)
            if r is None:
                log.info("laser-camera: input ended")
                break
            if outputs is None:
                warmup.append(r)
                if _warmed_up(warmup):
                    outputs = _advertise(args, stack, perf)
                    for step in warmup:
                        _publish(outputs, *step)
                    next_update = time.monotonic() + ATTRIBUTE_UPDATE_S
            else:
                _publish(outputs, *r)
                if time.monotonic() >= next_update:
                    _maybe_update(outputs, perf, args.rate_hz)
                    log.info("laser-camera: %s", dict(tracker.counts))
                    next_update = time.monotonic() + ATTRIBUTE_UPDATE_S
            next_tick = next_frame_time(next_tick, period, time.monotonic())
            stop.wait(max(0.0, next_tick - time.monotonic()))
    log.info("laser-camera: %s", dict(tracker.counts))
    return 0


def next_frame_time(tick: float, period: float, now: float) -> float:
    """When the simulated cameras take their next frame set after the one at ``tick``.

    They run free, as real ones: a frame set missed while the tracker overran is gone, not
    taken late in a burst (which also made the measured rate, and so the advertised
    ``frequency_hz``, twice the cameras' on a loaded host).  ``period`` 0: no pacing.
    """
    tick += period
    if period and tick < now:
        tick += period * math.ceil((now - tick) / period)
    return tick


@dataclass
class _Outputs:
    """The two abilities and the attributes they were last advertised with."""

    pose: Any
    dots: Any
    pose_attrs: dict[str, float]
    dot_attrs: dict[str, float]


def _advertise(args: argparse.Namespace, stack: contextlib.ExitStack,
               perf: _Performance) -> _Outputs:
    """Declare the abilities with the measured attributes and start the service."""

    svc = stack.enter_context(Service(args.id, realm=args.realm, agent=args.agent,
                                      connect=args.connect, listen=args.listen or None))
    attrs = perf.attributes(args.rate_hz)
    dot_attrs = perf.dot_attributes(args.rate_hz)
    pose_out = svc.ability("pose", type="pose6d", edge=(frames.WORLD, frames.LASER_RIG),
                           **attrs)
    dots_out = svc.ability("dots", type="points3d", edge=(frames.WORLD, frames.LASER_RIG),
                           **dot_attrs)
    svc.start()
    return _Outputs(pose_out, dots_out, attrs, dot_attrs)


def _warmed_up(warmup: list) -> bool:
    """Enough frame sets to measure the rate and, unless that takes too long, a pose among
    them: an ability advertised at the rate of no poses would not match any need."""
    if len(warmup) < WARMUP_FRAMES:
        return False
    got_pose = any(isinstance(result, PoseEstimate) for _, result, _ in warmup)
    return got_pose or len(warmup) >= MAX_WARMUP_FRAMES


def _step(tracker: LaserTracker, source, perf: _Performance):
    """Grab and process one frame set: (t_ns, result, labeled dots), or None when the input
    ended.  The dots are labeled now: without a pose, by the tracker's state of this
    frame set."""
    grabbed = source.grab()
    if grabbed is None:
        return None
    t_ns, images, t = grabbed
    try:
        result = tracker.process(images, t)
    except ValueError as exc:  # e.g. an image of the wrong format from a capture
        log.warning("laser-camera: frame set refused: %s", exc)
        result = None
    dots = None if result is None else tracker.label_dots(result)
    perf.add((time.time_ns() - t_ns) * 1e-9, result, dots)  # capture to result
    return t_ns, result, dots


def _publish(out: _Outputs, t_ns: int, result, dots: LabeledDots | None) -> None:
    """The pose, if the frame set gave one, and its labeled dots, if it has any."""
    if isinstance(result, PoseEstimate):
        out.pose.publish_measurement(Measurement(
            type="pose6d", t_ns=t_ns, position=result.position, quaternion=result.quaternion,
            covariance=result.covariance,
            extra={SYSTEMATIC_COVARIANCE: pack_covariance(result.systematic)}))
    if dots is not None and dots.labels:
        out.dots.publish_measurement(dots_measurement(t_ns, dots))


def dots_measurement(t_ns: int, dots: LabeledDots) -> Measurement:
    """The ``points3d`` of labeled dots, each with its noise and installation std."""
    return Measurement(type="points3d", t_ns=t_ns, points=dots.points, ids=list(dots.labels),
                       extra={DOT_STD: dots.std_m.tolist(),
                              DOT_SYSTEMATIC_STD: dots.systematic_std_m.tolist()})


def _maybe_update(out: _Outputs, perf: _Performance, nominal_hz: float) -> None:
    """Re-advertise an ability whose attributes drifted by more than ``ATTRIBUTE_CHANGE``."""
    attrs = perf.attributes(nominal_hz)
    dot_attrs = perf.dot_attributes(nominal_hz)
    if _drifted(out.pose_attrs, attrs):
        out.pose.update(**attrs)
        out.pose_attrs = attrs
    if _drifted(out.dot_attrs, dot_attrs):
        out.dots.update(**dot_attrs)
        out.dot_attrs = dot_attrs


def _drifted(advertised: dict[str, float], measured: dict[str, float]) -> bool:
    return any(abs(measured[k] - advertised.get(k, 0.0))
               > ATTRIBUTE_CHANGE * max(abs(advertised.get(k, 0.0)), 1e-9) for k in measured)
