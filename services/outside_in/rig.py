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
    def stack_row(self) -> Array:
        """``R_cw`` (row by row), ``t_cw`` and ``focal_px`` in one row of 13: what a pose
        fit repeats for each marker this camera saw (``pose``)."""
        if "stack_row" not in self._cache:
            self._cache["stack_row"] = np.concatenate([self.R_cw.ravel(), self.t_cw,
                                                       [self.focal_px]])
        return self._cache["stack_row"]

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


class RigImages:
    """Where world points image in every camera of a rig at once: OpenCV's projection
    (``projectPoints``, equal to it within rounding) as a few numpy operations on all
    cameras together.  A tracker asks it for the same points in every camera several
    times a frame set (its claims, the windows, the cameras' health), where one OpenCV
    call and its wrappers per camera cost ten times the arithmetic.  Cameras whose
    distortion is not OpenCV's plain or rational model (thin prism, tilted sensor) are
    projected by OpenCV one by one."""

    def __init__(self, cameras: list[RigCamera]):
        self.cameras = list(cameras)
        self.R = np.array([c.R_cw for c in self.cameras])             # (c, 3, 3)
        self.Rt = self.R.transpose(0, 2, 1)
        self.t = np.array([c.t_cw for c in self.cameras])[:, None, :]  # (c, 1, 3)
        dist = np.zeros((len(self.cameras), 8))
        self.opencv = []   # cameras projected by OpenCV itself
        for i, c in enumerate(self.cameras):
            if c.dist.size in (0, 4, 5, 8):
                dist[i, :c.dist.size] = c.dist
            else:
                self.opencv.append(i)
        self.rational = bool(np.any(dist[:, 5:]))
        K = np.array([c.K for c in self.cameras])
        # per camera: k1 k2 p1 p2 k3 k4 k5 k6, fx fy cx cy skew
        self.lens = np.hstack([dist, K[:, [0, 1, 0, 1, 0], [0, 1, 2, 2, 1]]])[:, :, None]
        self.size = np.array([[c.width, c.height] for c in self.cameras], float)[:, None, :]

    def depth_and_pixels(self, points: Array, cams: Array | None = None
                         ) -> tuple[Array, Array]:
        """World points (n, 3) in the cameras ``cams`` (indices, default all): their
        depth along each optical axis (k, n) and distorted pixels (k, n, 2)."""
        if cams is None:
            Rt, t, lens = self.Rt, self.t, self.lens
        else:
            cams = np.asarray(cams, int)
            Rt, t, lens = self.Rt[cams], self.t[cams], self.lens[cams]
        X = points @ Rt + t
        z = X[..., 2]
        inv = 1.0 / np.where(z != 0, z, 1.0)
        x, y = X[..., 0] * inv, X[..., 1] * inv
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        a1 = 2 * x * y
        k1, k2, p1, p2, k3, k4, k5, k6, fx, fy, cx, cy, skew = lens.transpose(1, 0, 2)
        radial = 1 + k1 * r2 + k2 * r4 + k3 * r6
        if self.rational:
            radial = radial / (1 + k4 * r2 + k5 * r4 + k6 * r6)
        xd = x * radial + p1 * a1 + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * a1
        uv = np.empty((*z.shape, 2))
        uv[..., 0] = xd * fx + skew * yd + cx
        uv[..., 1] = yd * fy + cy
        if self.opencv:
            for row, i in enumerate(range(len(self.cameras)) if cams is None else cams.tolist()):
                if i in self.opencv:
                    uv[row] = self.cameras[i].project(points)
        return z, uv

    def inside(self, uv: Array, cams: Array | None = None, margin_px: float = 0.0) -> Array:
        """Which pixels (k, n, 2) lie inside their cameras' images (``RigCamera.visible``'s
        test)."""
        size = self.size if cams is None else self.size[np.asarray(cams, int)]
        return np.all((uv >= margin_px) & (uv <= size - 1 - margin_px), axis=-1)


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
