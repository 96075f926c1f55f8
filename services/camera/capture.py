"""Frames from a camera, a video file, an image folder or a stream URL, each stamped.

Every source but an image folder goes through ``cv2.VideoCapture``, the path a real
webcam takes, so the simulator's video files test the same code a USB camera runs.

Timestamps are integer nanoseconds in this host's clock (``time.time_ns``), the capture
time of the frame, not the time it was processed:

* **live** sources (a device index, a URL): the clock read right after ``grab()`` returns,
  i.e. when the frame reached the host (a webcam's exposure ended a few ms earlier; USB
  transfer time is not known here).  ``clock = "host-at-grab"``.
* **files** (a video, an image folder): the container's presentation time
  (``CAP_PROP_POS_MSEC``; ``index / fps`` for a folder) added to the host time at which
  the source was opened.  ``clock = "file-mapped"``.  With ``pace=True`` (a service
  replaying a file as if live) each frame is held back until its mapped time.

Sequence numbers count the frames delivered from 0; the source stops at its end, after
``max_frames`` or when ``stop`` is set, and releases the device on :meth:`close`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from agent.errors import UmaError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


class CaptureError(UmaError):
    """A source that cannot be opened or read: says which and why."""


@dataclass(frozen=True)
class Frame:
    """One image with its capture time (host clock, ns) and sequence number."""

    image: np.ndarray
    t_ns: int
    seq: int


class Capture:
    """An open source; iterate it for :class:`Frame` objects (see the module docstring)."""

    def __init__(self, source: str | int, fps: float | None = None, pace: bool = False,
                 max_frames: int | None = None, gray: bool = False) -> None:
        self.source = source
        self.pace = pace
        self.max_frames = max_frames
        self.gray = gray
        self.delivered = 0
        self._cap: cv2.VideoCapture | None = None
        self._files: list[Path] = []
        self.live = False
        text = str(source)
        if text.isdigit():
            self._cap = _open(int(text), f"camera device {text} (e.g. /dev/video{text})")
            self.live = True
        elif "://" in text:
            self._cap = _open(text, f"stream {text}")
            self.live = True
        elif Path(text).is_dir():
            self._files = sorted(p for p in Path(text).iterdir()
                                 if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self._files:
                raise CaptureError(f"image folder {text} holds no images "
                                   f"({', '.join(IMAGE_SUFFIXES)})")
        elif Path(text).is_file():
            self._cap = _open(text, f"video file {text}")
        else:
            raise CaptureError(f"source {text!r} is neither a device index, a URL, a video "
                               "file nor an image folder")
        self.fps = fps or (self._cap.get(cv2.CAP_PROP_FPS) if self._cap else 0.0) or 30.0
        self.clock = "host-at-grab" if self.live else "file-mapped"
        self._t0_ns = time.time_ns()

    def frames(self, stop: threading.Event | None = None) -> Iterator[Frame]:
        """Frames until the source ends, ``max_frames`` were delivered or ``stop`` is set."""
        while (stop is None or not stop.is_set()) and \
                (self.max_frames is None or self.delivered < self.max_frames):
            frame = self.read()
            if frame is None:
                return
            yield frame

    __iter__ = frames

    def read(self) -> Frame | None:
        """The next frame, or ``None`` at the end of a file or folder; a live source that
        stops delivering is a :class:`CaptureError`."""
        got = self._read_file() if self._files else self._read_capture()
        if got is None:
            return None
        image, t_ns = got
        if self.gray and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if self.pace and not self.live:
            wait = (t_ns - time.time_ns()) / 1e9
            if wait > 0:
                time.sleep(wait)
        frame = Frame(image, t_ns, self.delivered)
        self.delivered += 1
        return frame

    def _read_capture(self) -> tuple[np.ndarray, int] | None:
        cap = self._cap
        if cap is None:
            raise CaptureError(f"source {self.source!r} is closed")
        if not cap.grab():
            if self.live:
                raise CaptureError(f"{self.source!r} stopped delivering frames "
                                   f"after {self.delivered}")
            return None
        t_host = time.time_ns()
        ok, image = cap.retrieve()
        if not ok or image is None:
            raise CaptureError(f"{self.source!r}: frame {self.delivered} cannot be decoded")
        if self.live:
            return image, t_host
        pos_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
        if not pos_ms >= 0:
            pos_ms = self.delivered * 1000.0 / self.fps
        return image, self._t0_ns + round(pos_ms * 1e6)

    def _read_file(self) -> tuple[np.ndarray, int] | None:
        if self.delivered >= len(self._files):
            return None
        path = self._files[self.delivered]
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise CaptureError(f"{path}: not an image OpenCV can read")
        return image, self._t0_ns + round(self.delivered * 1e9 / self.fps)

    def close(self) -> None:
        """Release the device or file (idempotent)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __enter__(self) -> Capture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _open(target: str | int, what: str) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(target)
    if not cap.isOpened():
        cap.release()
        raise CaptureError(f"cannot open {what}: OpenCV's VideoCapture refused it "
                           "(missing, busy, no permission or an unknown format)")
    return cap
