"""Cameras behind IVY's screens: a pinhole with OpenCV's radial/tangential distortion.

Each camera sits outside the cube behind one screen (or one half of the floor/ceiling in
the thesis' eight-camera layout) and looks at it (Hogue 2003, §5.1).  The model is exactly
OpenCV's (``K``, ``dist = [k1, k2, p1, p2, k3]``), so the tracker's ``cv2.undistortPoints``
inverts the simulator's projection; ``project`` is a numpy copy of ``cv2.projectPoints``
(cross-checked in the tests) because it runs for a handful of points per frame.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.camera.model import undistort_points
from services.installation.ivy import Wall

IMAGE_WIDTH = 640
IMAGE_HEIGHT = 480


@dataclass(frozen=True)
class Camera:
    """A calibrated-by-construction camera: the ground truth the tracker must estimate."""

    name: str
    wall: str
    #: the part of the wall's screen (X0, X1, Y0, Y1, metres) this camera is responsible for
    region: tuple[float, float, float, float]
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (5,) k1, k2, p1, p2, k3
    R_cw: np.ndarray  # (3, 3) world -> camera rotation
    center: np.ndarray  # (3,) optical centre in world
    width: int = IMAGE_WIDTH
    height: int = IMAGE_HEIGHT
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (n, 3) in camera coordinates (z along the optical axis)."""
        return (np.atleast_2d(points) - self.center) @ self.R_cw.T

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (n, 3) to distorted pixel coordinates (n, 2); pixel centres are
        integers (OpenCV convention).  Points behind the camera give NaN."""
        pc = self.to_camera(points)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = pc[:, 0] / z
            y = pc[:, 1] / z
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        uv = np.column_stack([self.K[0, 0] * xd + self.K[0, 1] * yd + self.K[0, 2],
                              self.K[1, 1] * yd + self.K[1, 2]])
        uv[z <= 0] = np.nan
        return uv

    def in_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Which pixel positions (n, 2) lie inside the image, ``margin_px`` from its border."""
        uv = np.atleast_2d(uv)
        u, v = uv[:, 0], uv[:, 1]
        with np.errstate(invalid="ignore"):  # NaN compares False: outside
            return (u >= margin_px - 0.5) & (u <= self.width - 0.5 - margin_px) \
                & (v >= margin_px - 0.5) & (v <= self.height - 0.5 - margin_px)

    def pixel_rays(self, supersample: int = 1) -> np.ndarray:
        """Unit viewing rays in world coordinates, (h*s, w*s, 3), for sub-pixel sample
        centres; used to render calibration patterns exactly through the distortion."""
        key = ("rays", supersample)
        if key not in self._cache:
            s = supersample
            offs = (np.arange(s) + 0.5) / s - 0.5
            us = (np.arange(self.width)[:, None] + offs).ravel()
            vs = (np.arange(self.height)[:, None] + offs).ravel()
            uu, vv = np.meshgrid(us, vs)
            xn = undistort_points(np.stack([uu.ravel(), vv.ravel()], -1), self.K, self.dist)
            rays_c = np.column_stack([xn, np.ones(len(xn))])
            rays_c /= np.linalg.norm(rays_c, axis=1, keepdims=True)
            self._cache.clear()  # one resolution at a time: a 2x ray grid is 30 MB
            self._cache[key] = (rays_c @ self.R_cw).reshape(len(vs), len(us), 3)
        return self._cache[key]

    def screen_to_image_jacobian(self, wall: Wall, xy: np.ndarray,
                                 step_m: float = 1e-4) -> np.ndarray:
        """d(pixel)/d(screen X, Y) at a screen point (2x2): the local affine map that
        shapes a laser spot's footprint into its image."""
        xy = np.asarray(xy, float)
        pts = xy + step_m * np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
        uv = self.project(wall.to_world(pts))
        return np.column_stack([(uv[0] - uv[1]), (uv[2] - uv[3])]) / (2 * step_m)


def place_camera(name: str, wall: Wall, region: tuple[float, float, float, float],
                 rng: np.random.Generator, distance_m: float = 2.2,
                 fill: float = 0.9) -> Camera:
    """A camera behind ``wall`` framing ``region`` (screen coordinates), slightly
    misaligned, with individual intrinsics and barrel distortion (a real installation)."""
    x0, x1, y0, y1 = region
    centre_xy = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    centre = wall.to_world(centre_xy)[0]
    ex, ey, n = wall.rotation.T
    long_axis, long_len, short_len = (ex, x1 - x0, y1 - y0) if x1 - x0 >= y1 - y0 \
        else (ey, y1 - y0, x1 - x0)
    # focal length so the region fills `fill` of the image along its tighter dimension
    f = fill * min(IMAGE_WIDTH / long_len, IMAGE_HEIGHT / short_len) * distance_m
    f *= 1 + rng.uniform(-0.02, 0.02)
    K = np.array([[f, 0, IMAGE_WIDTH / 2 - 0.5 + rng.uniform(-8, 8)],
                  [0, f * (1 + rng.uniform(-0.003, 0.003)),
                   IMAGE_HEIGHT / 2 - 0.5 + rng.uniform(-8, 8)],
                  [0, 0, 1]])
    dist = np.array([rng.uniform(-0.14, -0.08), rng.uniform(0.0, 0.03),
                     rng.uniform(-5e-4, 5e-4), rng.uniform(-5e-4, 5e-4), 0.0])
    # looking in through the screen from outside, slightly tilted and rolled
    z = -n + rng.normal(0, 0.015, 3)
    z /= np.linalg.norm(z)
    x = long_axis - (long_axis @ z) * z
    x /= np.linalg.norm(x)
    roll = rng.normal(0, 0.01)
    y = np.cross(z, x)
    x, y = np.cos(roll) * x + np.sin(roll) * y, -np.sin(roll) * x + np.cos(roll) * y
    C = centre + n * distance_m + rng.normal(0, 0.02, 3)
    return Camera(name, wall.name, region, K, dist, np.vstack([x, y, z]), C)
