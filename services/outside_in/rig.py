"""The cameras of an outside-in rig: a camera model (``services.camera``) and a pose.

A camera's pose is the SRG edge ``world -> camera`` (``position``, ``quaternion``: camera
axes in world coordinates, OpenCV's axes: x right, y down, z along the optical axis).
Projection is the model's (OpenCV's ``projectPoints``); observations are brought to
undistorted normalised coordinates once (``normalize``), where triangulation and
refinement are plain pinhole geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from agent import geometry as geo
from services.camera.model import CameraModel

Array = np.ndarray


@dataclass(frozen=True)
class RigCamera:
    """One calibrated camera of a rig: intrinsics and its pose in the world."""

    name: str
    model: CameraModel
    position: Array          # (3,) optical centre in world
    quaternion: Array        # (4,) x, y, z, w: camera axes in world
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @staticmethod
    def of(name: str, K: Array, dist: Array, position: Array, quaternion: Array,
           width: int = 640, height: int = 480) -> RigCamera:
        return RigCamera(name, CameraModel(K, dist, width, height, name=name),
                         np.asarray(position, float), np.asarray(quaternion, float))

    @property
    def K(self) -> Array:  # noqa: N802 (OpenCV's name)
        return self.model.K

    @property
    def dist(self) -> Array:
        return self.model.dist

    @property
    def width(self) -> int:
        return self.model.width

    @property
    def height(self) -> int:
        return self.model.height

    @property
    def R_cw(self) -> Array:  # noqa: N802 (the rotation's usual name)
        """World -> camera rotation."""
        if "R_cw" not in self._cache:
            self._cache["R_cw"] = geo.quat_to_matrix(self.quaternion).T
        return self._cache["R_cw"]

    @property
    def t_cw(self) -> Array:
        """World -> camera translation: ``x_c = R_cw x_w + t_cw``."""
        if "t_cw" not in self._cache:
            self._cache["t_cw"] = -self.R_cw @ np.asarray(self.position, float)
        return self._cache["t_cw"]

    @property
    def rvec(self) -> Array:
        if "rvec" not in self._cache:
            self._cache["rvec"] = cv2.Rodrigues(self.R_cw)[0].ravel()
        return self._cache["rvec"]

    @property
    def focal_px(self) -> float:
        """Mean focal length: the scale from normalised coordinates to pixels."""
        return 0.5 * float(self.K[0, 0] + self.K[1, 1])

    @property
    def projection(self) -> Array:
        """``[R_cw | t_cw]`` (3, 4): the projection of normalised coordinates."""
        return np.hstack([self.R_cw, self.t_cw[:, None]])

    def to_camera(self, points: Array) -> Array:
        """World points (n, 3) in camera coordinates."""
        return np.atleast_2d(points) @ self.R_cw.T + self.t_cw

    def project(self, points: Array) -> Array:
        """World points (n, 3) to distorted pixels (n, 2)."""
        return self.model.project(points, self.rvec, self.t_cw)

    def visible(self, points: Array, margin_px: float = 0.0) -> Array:
        """Which world points lie in front of the camera and inside its image."""
        pts = np.atleast_2d(points)
        front = self.to_camera(pts)[:, 2] > 0.05
        uv = self.project(pts)
        inside = ((uv[:, 0] >= margin_px) & (uv[:, 0] <= self.width - 1 - margin_px)
                  & (uv[:, 1] >= margin_px) & (uv[:, 1] <= self.height - 1 - margin_px))
        return front & inside

    def normalize(self, uv: Array) -> Array:
        """Distorted pixels (n, 2) to undistorted normalised coordinates (n, 2)."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        if len(uv) == 0:
            return uv.copy()
        return self.model.undistort(uv)

    def moved(self, position: Array, quaternion: Array) -> RigCamera:
        """The same camera at another pose."""
        return RigCamera(self.name, self.model, np.asarray(position, float),
                         np.asarray(quaternion, float))


def look_at(eye: Array, target: Array, up: Array = (0.0, 0.0, 1.0)) -> Array:
    """Quaternion of a camera at ``eye`` looking at ``target`` with image-up near ``up``."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return geo.matrix_to_quat(np.column_stack([x, y, z]))
