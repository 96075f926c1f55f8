"""A simulated camera: what a real one would deliver, from a ground-truth trajectory.

The camera (a :class:`~services.camera.model.CameraModel` and a pose that may move) sees
a scene of objects, each something that can draw itself into an ideal pinhole image
(:class:`Drawable`: :class:`PlanarTarget` for printed markers and calibration boards;
other trackers add their own, e.g. blobs) moving along its own trajectory.  One frame:

1. for a few instants across the exposure (more when the image moves more: motion blur
   at speed), every object draws itself far to near into an ideal image of a slightly
   larger pinhole camera, at ``supersampling`` times the sensor's resolution each way
   (a textured plane: ``cv2.warpPerspective`` of its texture over the window it covers,
   choosing a texture level near the image's scale so small targets do not alias);
2. the lens: ``cv2.remap`` through the model's distortion (every sample of the sensor's
   finer grid looks up where it lies in the ideal image, ``CameraModel.distortion_map``),
   then each pixel the mean of its samples (``cv2.resize``, ``INTER_AREA``): the light
   a pixel integrates over its area;
3. the optics' blur (Gaussian), the lighting (gain and offset, which may vary in time),
   the sensor's shot and read noise, 8-bit quantisation.

Pixel centres are integers (OpenCV's convention), so the corners OpenCV finds in these
images are directly comparable with ``CameraModel.project`` of the true corners.  Frames
go to a lossless video (FFV1 in ``.avi``, which OpenCV's bundled FFmpeg writes and reads)
or a PNG folder (:func:`write_video`), to be read back through
:class:`~services.camera.capture.Capture` like a real device.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from agent.errors import InvalidInputError
from services.camera.model import CameraModel

#: the :attr:`SimCamera.supersampling` of accuracy measurements: a tag's edge, tilted
#: 57 degrees at 1 m, crossed its mid-level 0.04 px (RMS; at most 0.07) from where it is,
#: row by row, against 0.13 (0.19) sampled at the pixels' centres
FAITHFUL = 4

#: a trajectory: time (s) -> 4x4 pose of an object (or the camera) in the world
Trajectory = Callable[[float], np.ndarray]


def pose_matrix(rotvec: Sequence[float] = (0, 0, 0),
                position: Sequence[float] = (0, 0, 0)) -> np.ndarray:
    """A 4x4 pose from a rotation vector (rad) and a position (m)."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, np.float64).reshape(3, 1))[0]
    T[:3, 3] = position
    return T


def static(T: np.ndarray) -> Trajectory:
    """A trajectory that stays at ``T``."""
    T = np.asarray(T, np.float64)
    return lambda t: T


class Drawable(Protocol):
    """Something a simulated camera can see."""

    def draw(self, canvas: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray) -> None:
        """Draw into ``canvas`` (float32 gray, 0..1), an ideal pinhole image of camera
        matrix ``K``, with the object at ``T_cam_obj`` (4x4, camera frame: x right, y down,
        z forward).  Draws nothing if the object is not in front of the camera."""


@dataclass
class PlanarTarget:
    """A flat printed texture (gray, 0..255) of ``width_m`` x ``height_m``, centred on
    its frame's origin: x to the texture's right, y to its top, z out of the print
    (OpenCV's marker convention: the top-left texel is at (-w/2, +h/2))."""

    texture: np.ndarray
    width_m: float
    height_m: float
    _levels: list[np.ndarray] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        tex = np.asarray(self.texture)
        if tex.ndim != 2:
            raise InvalidInputError("a target's texture is a 2D gray image")
        level = tex.astype(np.float32) / 255.0
        self._levels = [level]
        while min(level.shape) >= 8:
            level = cv2.resize(level, (level.shape[1] // 2, level.shape[0] // 2),
                               interpolation=cv2.INTER_AREA)
            self._levels.append(level)

    def corners(self) -> np.ndarray:
        """The print's corners (4, 3) in its frame: top-left, top-right, bottom-right,
        bottom-left."""
        w, h = self.width_m / 2, self.height_m / 2
        return np.array([[-w, h, 0], [w, h, 0], [w, -h, 0], [-w, -h, 0]])

    def draw(self, canvas: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray) -> None:
        corners_c = self.corners() @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
        if np.any(corners_c[:, 2] < 0.02):
            return
        uv = corners_c[:, :2] / corners_c[:, 2:] @ K[:2, :2].T + K[:2, 2]
        x0, y0 = np.maximum(np.floor(uv.min(0)).astype(int) - 1, 0)
        x1, y1 = np.minimum(np.ceil(uv.max(0)).astype(int) + 2, canvas.shape[::-1])
        if x1 <= x0 or y1 <= y0:
            return
        plane = K @ np.column_stack([T_cam_obj[:3, 0], T_cam_obj[:3, 1], T_cam_obj[:3, 3]])
        texels_per_px = self.texture.shape[1] / max(np.ptp(uv[:, 0]), np.ptp(uv[:, 1]), 1.0)
        level = int(np.clip(math.ceil(math.log2(max(texels_per_px, 1.0))), 0,
                            len(self._levels) - 1))
        tex = self._levels[level]
        # texel index (centre of texel i at i) -> plane (x, y, 1) -> the canvas' window
        A = np.array([[self.width_m / tex.shape[1], 0,
                       -self.width_m / 2 + 0.5 * self.width_m / tex.shape[1]],
                      [0, -self.height_m / tex.shape[0],
                       self.height_m / 2 - 0.5 * self.height_m / tex.shape[0]],
                      [0, 0, 1]])
        H = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]]) @ plane @ A
        # drawn premultiplied by the print's coverage (its texture is 0 outside), so that
        # the print's own edge blends into what lies behind it
        size = (x1 - x0, y1 - y0)
        colour = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        cover = cv2.warpPerspective(np.ones_like(tex), H, size, flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        region = canvas[y0:y1, x0:x1]
        region *= 1 - cover
        region += colour


@dataclass
class SceneObject:
    """A drawable moving along a trajectory (``T_world_obj(t)``)."""

    name: str
    drawable: Drawable
    trajectory: Trajectory


@dataclass
class Lighting:
    """Image = gain * scene + offset (0..1 units); ``flicker_hz`` modulates the gain by
    ``flicker`` (relative) to imitate changing exposure or lights."""

    gain: float = 0.85
    offset: float = 0.08
    flicker: float = 0.0
    flicker_hz: float = 0.5

    def at(self, t: float) -> tuple[float, float]:
        return self.gain * (1 + self.flicker * math.sin(2 * math.pi * self.flicker_hz * t)), \
            self.offset


@dataclass
class SimCamera:
    """A camera of ``model`` at ``trajectory`` (``T_world_cam(t)``) with its optics' blur,
    exposure time and sensor noise (units of 0..255 gray levels).  Each pixel is the
    mean of ``supersampling`` x ``supersampling`` samples over its area, as a sensor's
    pixel integrates the light on it.  Sampled at the pixels' centres alone (1, the
    default: five times cheaper than 4), the edges of a tilted print (whose texture a
    pixel spans more of one way than the other) lock to the pixel grid, up to 0.2 px off
    where they are; sub-pixel accuracy measurements take 4 (:data:`FAITHFUL`)."""

    model: CameraModel
    trajectory: Trajectory = field(default_factory=lambda: static(np.eye(4)))
    blur_sigma_px: float = 0.6
    exposure_s: float = 0.008
    read_noise: float = 1.5
    shot_noise: float = 0.05
    background: float = 0.55
    lighting: Lighting = field(default_factory=Lighting)
    max_subframes: int = 8
    supersampling: int = 1
    _ideal: tuple[np.ndarray, tuple[int, int]] | None = field(default=None, repr=False)
    _sensor_map: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not (isinstance(self.supersampling, int) and self.supersampling >= 1):
            raise InvalidInputError("a simulated camera's supersampling is a whole number "
                                    f">= 1, got {self.supersampling!r}")

    def render(self, scene: Iterable[SceneObject], t: float,
               rng: np.random.Generator) -> np.ndarray:
        """The 8-bit gray frame whose exposure is centred on ``t`` (so the ground truth of a
        moving object is its pose at ``t``, not a blur-length behind it)."""
        scene = list(scene)
        n = self._subframes(scene, t)
        times = [t + self.exposure_s * ((i + 0.5) / n - 0.5) for i in range(n)] if n > 1 \
            else [t]
        ideal = sum(self._ideal_image(scene, s) for s in times) / len(times)
        image = cv2.remap(ideal, *self._sensor_samples(), cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)
        if self.supersampling > 1:
            image = cv2.resize(image, self.model.size, interpolation=cv2.INTER_AREA)
        if self.blur_sigma_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), self.blur_sigma_px)
        gain, offset = self.lighting.at(t)
        image = (gain * image + offset) * 255.0
        noise_std = np.sqrt(self.read_noise ** 2 + self.shot_noise * np.clip(image, 0, None))
        image = image + rng.standard_normal(image.shape).astype(np.float32) * noise_std
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)

    def pose_of(self, obj: SceneObject, t: float) -> np.ndarray:
        """The true pose of ``obj`` in this camera's frame at ``t``."""
        return np.linalg.inv(self.trajectory(t)) @ obj.trajectory(t)

    def ideal_camera(self) -> tuple[np.ndarray, tuple[int, int]]:
        """The ideal pinhole camera (K, (w, h)) that sees everything the lens does."""
        if self._ideal is None:
            m = self.model
            border = np.concatenate([
                np.column_stack([np.arange(m.width), np.zeros(m.width)]),
                np.column_stack([np.arange(m.width), np.full(m.width, m.height - 1)]),
                np.column_stack([np.zeros(m.height), np.arange(m.height)]),
                np.column_stack([np.full(m.height, m.width - 1), np.arange(m.height)])])
            ideal = m.undistort(border, pixels=True)
            lo = np.floor(np.minimum(ideal.min(0), 0)) - 2
            hi = np.ceil(np.maximum(ideal.max(0), [m.width - 1, m.height - 1])) + 2
            K = m.K.copy()
            K[:2, 2] -= lo
            self._ideal = (K, (int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1))
        return self._ideal

    def _finer(self) -> np.ndarray:
        """Pixels -> the ``supersampling`` times finer grid's (pixel centres at integers)."""
        n = self.supersampling
        return np.array([[n, 0, (n - 1) / 2], [0, n, (n - 1) / 2], [0, 0, 1.0]])

    def _canvas(self) -> tuple[np.ndarray, tuple[int, int]]:
        """The ideal camera at the finer grid."""
        K, (w, h) = self.ideal_camera()
        return self._finer() @ K, (w * self.supersampling, h * self.supersampling)

    def _sensor_samples(self) -> tuple[np.ndarray, np.ndarray]:
        """Where each of the sensor's samples (the finer grid) lies in the canvas."""
        if self._sensor_map is None:
            m, n = self.model, self.supersampling
            finer = CameraModel(self._finer() @ m.K, m.dist, m.width * n, m.height * n)
            # in fixed point (1/32 of a fine sample), which cv2.remap reads 3x faster
            self._sensor_map = cv2.convertMaps(*finer.distortion_map(self._canvas()[0]),
                                               cv2.CV_16SC2)
        return self._sensor_map

    def _ideal_image(self, scene: list[SceneObject], t: float) -> np.ndarray:
        K, (w, h) = self._canvas()
        canvas = np.full((h, w), self.background, np.float32)
        poses = [(self.pose_of(o, t), o) for o in scene]
        for T, obj in sorted(poses, key=lambda p: -p[0][2, 3]):
            obj.drawable.draw(canvas, K, T)
        return canvas

    def _subframes(self, scene: list[SceneObject], t: float) -> int:
        """Instants to average over the exposure: about one per pixel the scene's origin
        points move during it (1 for a still scene)."""
        if self.exposure_s <= 0 or self.max_subframes <= 1 or not scene:
            return 1
        moved = 0.0
        for obj in scene:
            a = self.pose_of(obj, t - self.exposure_s / 2)[:3, 3]
            b = self.pose_of(obj, t + self.exposure_s / 2)[:3, 3]
            if a[2] > 0.02 and b[2] > 0.02:
                uv = self.model.project(np.array([a, b]))
                moved = max(moved, float(np.linalg.norm(uv[1] - uv[0])))
        return int(np.clip(math.ceil(moved), 1, self.max_subframes))


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """Write 8-bit frames losslessly: an ``.avi`` (FFV1) or, for a path without a suffix,
    a folder of ``frame_000000.png`` files.  Returns ``path``."""
    path = Path(path)
    if path.suffix == "":
        path.mkdir(parents=True, exist_ok=True)
        for i, f in enumerate(frames):
            cv2.imwrite(str(path / f"frame_{i:06d}.png"), f)
        return path
    if path.suffix.lower() != ".avi":
        raise InvalidInputError(f"{path}: write an .avi (lossless FFV1) or a folder (no suffix)")
    writer = None
    try:
        for f in frames:
            if writer is None:
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps,
                                         (f.shape[1], f.shape[0]), isColor=f.ndim == 3)
                if not writer.isOpened():
                    raise OSError(f"{path}: OpenCV cannot write FFV1 video here")
            writer.write(f)
    finally:
        if writer is not None:
            writer.release()
    return path
