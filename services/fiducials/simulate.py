"""Simulated scenes for the fiducial tracker's tests, eval, bench and demo: a webcam-like
camera and printed tags moving smoothly in front of it (ground truth known)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from services.camera.markers import marker_target
from services.camera.model import CameraModel
from services.camera.simulator import SceneObject, Trajectory

#: a tag faces the camera when its z axis points back at it: turned by pi about x
FACING = np.diag([1.0, -1.0, -1.0])


def webcam(rng: np.random.Generator, width: int = 640, height: int = 480) -> CameraModel:
    """A 640x480 camera of about 62 degrees horizontal field of view with the barrel
    distortion of a cheap lens, calibrated (``pixel_std`` 0.3 px)."""
    f = 530.0 * width / 640 * (1 + rng.uniform(-0.02, 0.02))
    K = np.array([[f, 0, (width - 1) / 2 + rng.uniform(-6, 6)],
                  [0, f * (1 + rng.uniform(-0.003, 0.003)), (height - 1) / 2 + rng.uniform(-6, 6)],
                  [0, 0, 1]])
    dist = [rng.uniform(-0.2, -0.08), rng.uniform(0.0, 0.05), rng.uniform(-5e-4, 5e-4),
            rng.uniform(-5e-4, 5e-4), 0.0]
    return CameraModel(K, dist, width, height, pixel_std=0.3)


def wandering(rng: np.random.Generator, camera: CameraModel, depth: tuple[float, float],
              period_s: float, max_tilt_rad: float = 0.7, fill: float = 0.7) -> Trajectory:
    """A smooth path in front of the camera (its frame): the depth sweeps ``depth`` and
    back every ``period_s``, the image position wanders within ``fill`` of the field of
    view, the tag tilts up to ``max_tilt_rad`` and spins slowly."""
    phases = rng.uniform(0, 2 * math.pi, 6)
    rates = rng.uniform(0.6, 1.4, 6) * 2 * math.pi / period_s
    half_w = fill * (camera.width / 2) / camera.K[0, 0]
    half_h = fill * (camera.height / 2) / camera.K[1, 1]
    z0, z1 = depth

    def at(t: float) -> np.ndarray:
        s = [math.sin(r * t + p) for r, p in zip(rates, phases, strict=True)]
        z = z0 + (z1 - z0) * (0.5 - 0.5 * math.cos(2 * math.pi * t / period_s))
        T = np.eye(4)
        tilt = cv2.Rodrigues(np.array([max_tilt_rad * s[2], max_tilt_rad * s[3], 0.0]))[0]
        spin = cv2.Rodrigues(np.array([0.0, 0.0, 1.5 * s[4]]))[0]
        T[:3, :3] = FACING @ tilt @ spin
        T[:3, 3] = (z * half_w * s[0], z * half_h * s[1], z)
        return T

    return at


def tags(family: str, ids: Sequence[int], size_m: float,
         trajectories: Sequence[Trajectory]) -> list[SceneObject]:
    """Printed tags (with their quiet zone) along the given trajectories."""
    return [SceneObject(f"{family}-{i}", marker_target(family, i, size_m), traj)
            for i, traj in zip(ids, trajectories, strict=True)]
