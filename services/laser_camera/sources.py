"""Where the laser-dot tracker's images come from: the simulator or OpenCV captures.

``--source sim`` (the default) renders the simulated IVY display at the current wall-clock
time.  Real input names one capture per camera of the calibration file:
``--source front=video:front.avi --source ceiling=camera:2`` (a video file or a camera
device index, read through ``cv2.VideoCapture``, converted to 8-bit gray).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from agent.errors import InvalidInputError
from services.sim.world import IvyWorld, sim_time_s


@dataclass(frozen=True)
class CaptureSpec:
    camera: str
    kind: str  # "video" or "camera"
    target: str  # file name or device index


def parse_sources(values: list[str]) -> list[CaptureSpec] | None:
    """``None`` for the simulator, else one capture per camera; ``ValueError`` explains."""
    if not values or values == ["sim"]:
        return None
    if "sim" in values:
        raise InvalidInputError("--source sim cannot be mixed with real captures")
    specs = []
    for v in values:
        cam, eq, rest = v.partition("=")
        kind, colon, target = rest.partition(":")
        if not eq or not colon or not cam or not target or kind not in ("video", "camera"):
            raise InvalidInputError(f"--source {v!r}: expected CAMERA=video:FILE or "
                                    "CAMERA=camera:INDEX (or 'sim')")
        if kind == "camera" and not target.isdigit():
            raise InvalidInputError(f"--source {v!r}: a camera index is a number")
        specs.append(CaptureSpec(cam, kind, target))
    names = [s.camera for s in specs]
    if len(set(names)) != len(names):
        raise InvalidInputError(f"--source: camera named twice in {names}")
    return specs


class SimSource:
    """Images of the simulated display at the current time (trajectory of ``world``)."""

    def __init__(self, world: IvyWorld):
        self.world = world

    def grab(self) -> tuple[int, dict[str, np.ndarray], float] | None:
        """(t_ns, camera -> image, trajectory time s) of a frame set taken now."""
        t_ns = time.time_ns()
        t = sim_time_s(t_ns)
        return t_ns, self.world.render(t).images, t

    def close(self) -> None:
        pass


class CaptureSource:
    """One ``cv2.VideoCapture`` per camera, read in lock step; ends with the first video."""

    def __init__(self, specs: list[CaptureSpec]):
        self.caps: dict[str, cv2.VideoCapture] = {}
        try:
            for s in specs:
                cap = cv2.VideoCapture(int(s.target) if s.kind == "camera" else s.target)
                if not cap.isOpened():
                    raise InvalidInputError(f"camera {s.camera}: cannot open {s.kind} {s.target!r}")
                self.caps[s.camera] = cap
        except BaseException:
            self.close()
            raise
        self._t0 = time.time_ns()

    def grab(self) -> tuple[int, dict[str, np.ndarray], float] | None:
        # grab() all first, retrieve() after: the frames are as close in time as OpenCV allows
        if not all(cap.grab() for cap in self.caps.values()):
            return None
        t_ns = time.time_ns()
        images = {}
        for name, cap in self.caps.items():
            ok, img = cap.retrieve()
            if not ok:
                return None
            images[name] = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return t_ns, images, (t_ns - self._t0) * 1e-9

    def close(self) -> None:
        for cap in self.caps.values():
            cap.release()
        self.caps = {}
