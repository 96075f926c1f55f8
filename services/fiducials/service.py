"""``uma service run fiducials``: printed markers seen by a calibrated camera, as poses.

::

    uma service run fiducials --source 0 --calibration cam.yaml \\
        --family apriltag36h11 --size 0.08 --frame lab/cam1

Every frame of ``--source`` (a camera index, a video file, an image folder, a URL; files
are replayed at their own rate) goes through :class:`~services.fiducials.tracker.
FiducialTracker`.  Each body seen (a marker, or a bundle of ``--bundles``) becomes a
``pose6d`` ability the first time it is seen, named after it (``apriltag36h11-3``, or the
bundle's name), with the edge ``FRAME -> PREFIX/NAME`` (``--name ID=FRAME`` renames a
marker's frame).  Each sample carries the frame's capture time, the 6x6 covariance (uma's
SE(3) form) and, in ``extra``: ``ambiguity`` (``none``, ``history``: the IPPE solution the
track's accumulated evidence supports, ``covered``: the covariance spans both solutions),
``flip_probability`` (the evidence's chance that the other IPPE solution is the true pose),
``sigma_px`` (the corner noise estimated from the residuals), ``rms_px`` and ``markers``
(the ids used).

The attributes each ability advertises are measured: ``frequency_hz`` (samples over the
last ``WINDOW_S``), ``latency_s`` (publication minus capture time, median), ``pos_std_m``
and ``rot_std_rad`` (the root of the covariance's position and rotation traces, median
over the last ``ACCURACY_WINDOW_S``),
``confidence`` (share of frames with the body); re-advertised when one drifts by more
than ``DRIFT`` (the accuracy by more than ``ACCURACY_DRIFT``; at most every ``UPDATE_S``),
and at once as lost (``pos_std_m`` ``LOST_STD_M``, ``confidence`` 0) when the body has
not been seen in ``LOST_FRAMES`` frames in a row, so a need with ``prefer="pos_std_m"``
moves to the camera that sees the body best as the body moves, and away from one that no
longer sees it.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from agent import Service
from agent import geometry as geo
from agent.errors import UmaError
from schemas.codec import Measurement
from services.camera import markers
from services.camera.capture import Capture
from services.camera.model import load
from services.fiducials.bodies import load_bundles
from services.fiducials.tracker import Estimate, FiducialTracker

log = logging.getLogger("uma.fiducials")
WINDOW_S = 2.0
#: accuracy follows the body faster than rate and latency: it changes as the body moves
ACCURACY_WINDOW_S = 0.3
DRIFT = 0.2
#: two cameras' accuracies cross slowly: a 20 % drift held the advertised crossing back
#: by up to 2 s
ACCURACY_DRIFT = 0.05
UPDATE_S = 0.1
#: a body missing from this many frames in a row is advertised as lost: its position
#: unknown (a finite stand-in, attributes are finite), its confidence 0 (one missed
#: detection is not enough: a need would flap between cameras)
LOST_FRAMES = 2
LOST_STD_M = 1000.0
LOG_EVERY_S = 10.0


@dataclass
class _Quality:
    """What one ability has shown lately: the measured attributes it advertises."""

    times: deque = field(default_factory=deque)  # (capture s, latency s, pos std, rot std)
    advertised: dict[str, float] = field(default_factory=dict)
    updated: float = 0.0
    lost: bool = False
    seen_frame: int = 0  # the number of the last frame the body was seen in

    def add(self, t_s: float, latency_s: float, cov: np.ndarray) -> None:
        self.times.append((t_s, latency_s, math.sqrt(np.trace(cov[:3, :3])),
                           math.sqrt(np.trace(cov[3:, 3:]))))
        while self.times and self.times[0][0] < t_s - WINDOW_S:
            self.times.popleft()

    def attributes(self, frames_in_window: int) -> dict[str, float]:
        rows = np.array(self.times)
        span = max(rows[-1, 0] - rows[0, 0], 1e-3) if len(rows) > 1 else WINDOW_S
        rate = (len(rows) - 1) / span if len(rows) > 1 else 1.0 / WINDOW_S
        recent = rows[rows[:, 0] >= rows[-1, 0] - ACCURACY_WINDOW_S]
        return {"frequency_hz": round(float(rate), 2),
                "latency_s": round(float(np.median(rows[:, 1])), 4),
                "pos_std_m": float(np.median(recent[:, 2])),
                "rot_std_rad": float(np.median(recent[:, 3])),
                "confidence": round(min(1.0, len(rows) / max(frames_in_window, 1)), 3)}


class Publisher:
    """Estimates -> abilities (created on first sight) with measured attributes."""

    def __init__(self, svc: Any, args: argparse.Namespace) -> None:
        self.svc = svc
        self.args = args
        self.frames_of = dict(args.name)
        self.handles: dict[str, Any] = {}
        self.quality: dict[str, _Quality] = {}
        self.frame_times: deque = deque()
        self.frames = 0
        self.published = 0

    def frame(self, t_ns: int) -> None:
        """A frame captured at ``t_ns`` (before its estimates): counted for the rate and
        confidence; a body missing from the ``LOST_FRAMES`` frames before it is
        advertised as lost."""
        t = t_ns / 1e9
        self.frames += 1
        self.frame_times.append(t)
        while self.frame_times and self.frame_times[0] < t - WINDOW_S:
            self.frame_times.popleft()
        for name, q in self.quality.items():
            if not q.lost and self.frames - 1 - q.seen_frame >= LOST_FRAMES:
                attrs = {**q.advertised, "pos_std_m": LOST_STD_M, "rot_std_rad": math.pi,
                         "confidence": 0.0}
                self.handles[name].update(**attrs)
                q.advertised, q.updated, q.lost = attrs, time.monotonic(), True

    def __call__(self, est: Estimate, marker_id: int | None) -> None:
        now = time.time_ns()
        cov = geo.decoupled_to_se3(est.t, est.covariance)
        q = self.quality.setdefault(est.name, _Quality())
        q.add(est.t_ns / 1e9, (now - est.t_ns) / 1e9, est.covariance)
        q.seen_frame = self.frames
        handle = self.handles.get(est.name)
        if handle is None:
            target = self.frames_of.get(marker_id) if marker_id is not None else None
            target = target or f"{self.args.prefix}/{est.name}"
            attrs = q.attributes(len(self.frame_times))
            handle = self.svc.ability(est.name, type="pose6d", edge=(self.args.frame, target),
                                      **attrs)
            self.handles[est.name] = handle
            q.advertised, q.updated = attrs, time.monotonic()
            log.info("fiducials: %s -> %s (%s)", self.args.frame, target, attrs)
        elif q.lost or time.monotonic() - q.updated > UPDATE_S:
            attrs = q.attributes(len(self.frame_times))
            if q.lost or _drifted(q.advertised, attrs):
                handle.update(**attrs)
                q.advertised, q.updated, q.lost = attrs, time.monotonic(), False
        handle.publish_measurement(Measurement(
            type="pose6d", t_ns=est.t_ns, position=est.t, quaternion=geo.matrix_to_quat(est.R),
            covariance=cov,
            extra={"ambiguity": est.ambiguity, "flip_probability": est.flip_probability,
                   "sigma_px": round(est.sigma_px, 4),
                   "rms_px": round(est.rms_px, 4), "markers": list(est.markers)}))
        self.published += 1


def _drifted(advertised: dict[str, float], measured: dict[str, float]) -> bool:
    return any(abs(v - advertised.get(k, 0.0)) > (ACCURACY_DRIFT if k.endswith("_std_m")
                                                  or k.endswith("_std_rad") else DRIFT)
               * max(abs(advertised.get(k, 0.0)), 1e-9) for k, v in measured.items())


def tracker_from(args: argparse.Namespace) -> FiducialTracker:
    """The tracker the arguments describe; ``UmaError`` for a bad file or family."""
    camera = load(args.calibration)
    try:
        markers.dictionary(args.family)
    except ValueError as exc:
        raise UmaError(str(exc)) from None
    bundles = load_bundles(args.bundles, args.family) if args.bundles else []
    if args.size is None and not args.marker_size and not bundles:
        raise UmaError("give --size (or --marker-size / --bundles): a marker's pose needs its "
                       "printed size")
    return FiducialTracker(camera, args.family, args.size, dict(args.marker_size), bundles)


def run(args: argparse.Namespace, stop: threading.Event) -> int:

    tracker = tracker_from(args)
    size = tracker.camera.size
    with Capture(args.source, fps=args.fps, pace=True, max_frames=args.max_frames) as cap, \
            Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect,
                    listen=args.listen or None) as svc:
        svc.start()
        publish = Publisher(svc, args)
        log.info("fiducials: %s (%s) -> %s, %s", args.source, cap.clock, args.frame,
                 args.family)
        last_log, unsized_said = time.monotonic(), set()
        bundles = {b.name for b in tracker.bundles}
        for frame in cap.frames(stop):
            h, w = frame.image.shape[:2]
            if (w, h) != size:
                raise UmaError(f"{args.source}: frames are {w}x{h}, the calibration "
                               f"{args.calibration} is for {size[0]}x{size[1]}")
            gray = frame.image if frame.image.ndim == 2 else \
                cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
            publish.frame(frame.t_ns)
            for est in tracker.process(gray, frame.t_ns):
                publish(est, None if est.name in bundles else est.markers[0])
            for marker_id in tracker.unsized - unsized_said:
                log.warning("fiducials: marker %d has no size (--size, --marker-size): "
                            "ignored", marker_id)
            unsized_said |= tracker.unsized
            if time.monotonic() - last_log > LOG_EVERY_S:
                log.info("fiducials: %d frames, %d poses published", cap.delivered,
                         publish.published)
                last_log = time.monotonic()
        log.info("fiducials: source ended after %d frames, %d poses published",
                 cap.delivered, publish.published)
    return 0
