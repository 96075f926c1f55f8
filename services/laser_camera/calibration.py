"""Calibration of the laser-dot cameras (Hogue 2003, §5.4) and its file format.

Per camera, three steps of the thesis:

1. intrinsics (§5.4.1): ``cv2.calibrateCamera`` on checkerboard views held in front of
   the camera -- focal lengths, principal point, radial/tangential distortion;
2. image -> screen (§5.4.1, eqs. 5.19-5.37): a checkerboard projected onto the screen
   (known corner positions in screen metres), corners found with sub-pixel accuracy,
   undistorted, and the homography fitted by the normalised DLT (``homography``), cross-
   checked against ``cv2.findHomography``;
3. screen -> world (§5.4.3, eq. 5.40): the wall's rotation, translation and plane
   distance, measured when the display was built.

The thesis' second extrinsic step (a homography for the camera moving while a notch filter
is screwed on, §5.4.2) is not simulated: the simulated cameras have no filter to fit.
A dark frame gives the sensor's dark level and noise for the detector.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from agent.errors import InvalidInputError
from services.camera.model import undistort_points
from services.installation.ivy import Wall
from services.laser_camera.detection import DetectorParams
from services.laser_camera.homography import (
    apply_homography,
    dlt_homography,
    homography_scale,
)

FORMAT_VERSION = 1
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-4)


@dataclass
class CameraCalibration:
    """Everything the tracker knows about one camera."""

    name: str
    wall: Wall
    K: np.ndarray  # (3, 3) intrinsics
    dist: np.ndarray  # (5,) k1, k2, p1, p2, k3
    H: np.ndarray  # (3, 3) undistorted pixel -> screen metres
    width: int = 640
    height: int = 480
    detector: DetectorParams = field(default_factory=DetectorParams)
    #: quality figures from the calibration run (reprojection errors etc.)
    quality: dict = field(default_factory=dict)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (n, 2) to ideal (undistorted) pixels of the same camera."""
        return undistort_points(uv, self.K, self.dist, self.K)

    def image_to_screen(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (n, 2) to screen coordinates (n, 2), metres (eq. 5.39)."""
        return apply_homography(self.H, self.undistort(uv))

    def screen_sigma_m(self, default: float) -> float:
        """Per-axis error (1 sigma) of the image -> screen map after calibration: the
        corners' residual RMS (per axis) scaled by sqrt(8 / n), the share of the noise an
        8-parameter fit to n corners passes on to its predictions."""
        rms, n = self.quality.get("screen_rms_m"), self.quality.get("corners")
        if not rms or not n or n <= 8:
            return default
        return float(rms / math.sqrt(2) * math.sqrt(8 / n))

    def centre_world(self) -> np.ndarray:
        """The camera's optical centre in world coordinates (3,), from its intrinsics and
        its screen homography: ``H^-1 = s K [r1 r2 t]`` (Zhang's plane pose), the centre
        ``-R^T t`` in the screen's frame (x, y on the screen, z along the outward
        normal), then eq. 5.40.  The tracker needs it to know how a camera turned since
        calibration, or a bent screen seen at an angle, moves a dot."""
        M = np.linalg.solve(self.K, np.linalg.inv(self.H))
        M /= 0.5 * (np.linalg.norm(M[:, 0]) + np.linalg.norm(M[:, 1]))
        if M[2, 2] < 0:  # the screen lies in front of the camera
            M = -M
        r1, r2, t = M[:, 0], M[:, 1], M[:, 2]
        c = -np.column_stack([r1, r2, np.cross(r1, r2)]).T @ t
        w = self.wall
        return w.rotation @ np.array([c[0], c[1], w.plane_distance + c[2]]) - w.translation

    def metres_per_pixel(self, uv_undistorted: np.ndarray) -> np.ndarray:
        """Linear scale of the image -> screen map at (undistorted) image points (n, 2)."""
        return homography_scale(self.H, uv_undistorted)

    def to_dict(self) -> dict:
        d = self.detector
        return {"name": self.name, "wall": self.wall.to_dict(), "K": self.K.tolist(),
                "dist": self.dist.tolist(), "H": self.H.tolist(),
                "width": self.width, "height": self.height,
                "detector": {"threshold": d.threshold, "min_area": d.min_area,
                             "max_area": d.max_area, "merge_px": d.merge_px,
                             "dark_level": d.dark_level, "read_noise": d.read_noise,
                             "gain": d.gain, "floor_px": d.floor_px},
                "quality": self.quality}

    @classmethod
    def from_dict(cls, d: dict) -> CameraCalibration:
        name = d.get("name", "?")
        try:
            K = _matrix(d["K"], (3, 3), f"camera {name}: K")
            dist = _matrix(d["dist"], (5,), f"camera {name}: dist")
            H = _matrix(d["H"], (3, 3), f"camera {name}: H")
            return cls(str(name), Wall.from_dict(d["wall"]), K, dist, H,
                       int(d.get("width", 640)), int(d.get("height", 480)),
                       DetectorParams(**d.get("detector", {})), dict(d.get("quality", {})))
        except KeyError as exc:
            raise InvalidInputError(f"camera {name}: calibration lacks {exc}") from None
        except TypeError as exc:
            raise InvalidInputError(f"camera {name}: bad calibration entry ({exc})") from None


@dataclass
class Calibration:
    """The calibration of all cameras of a display."""

    cameras: list[CameraCalibration]
    #: where it came from (e.g. the simulated installation it was made for)
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.cameras:
            raise InvalidInputError("calibration has no cameras")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise InvalidInputError(f"calibration: duplicate camera names in {names}")

    def camera(self, name: str) -> CameraCalibration:
        for c in self.cameras:
            if c.name == name:
                return c
        raise InvalidInputError(f"no camera {name!r} in the calibration "
                                f"(cameras: {', '.join(c.name for c in self.cameras)})")

    def save(self, path: str | Path) -> None:
        data = {"format": "uma-laser-camera-calibration", "version": FORMAT_VERSION,
                "meta": self.meta, "cameras": [c.to_dict() for c in self.cameras]}
        Path(path).write_text(json.dumps(data, indent=1))

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        p = Path(path)
        try:
            data = json.loads(p.read_text())
        except OSError as exc:
            raise InvalidInputError(f"cannot read calibration file {p}: {exc.strerror}") from None
        except json.JSONDecodeError as exc:
            raise InvalidInputError(f"calibration file {p} is not JSON ({exc})") from None
        if not isinstance(data, dict) or data.get("format") != "uma-laser-camera-calibration":
            raise InvalidInputError(f"{p} is not a uma laser-camera calibration file")
        if data.get("version") != FORMAT_VERSION:
            raise InvalidInputError(f"{p}: calibration format version {data.get('version')} "
                                    f"unsupported (this build reads {FORMAT_VERSION})")
        meta = data.get("meta", {})
        if not isinstance(meta, dict):
            raise InvalidInputError(f"{p}: 'meta' must be a map")
        cameras = data.get("cameras", [])
        if not isinstance(cameras, list) or not all(isinstance(c, dict) for c in cameras):
            raise InvalidInputError(f"{p}: 'cameras' must be a list of maps")
        return cls([CameraCalibration.from_dict(c) for c in cameras], meta)


# --------------------------------------------------------------------------- procedures


def calibrate_intrinsics(views: list[tuple[np.ndarray, np.ndarray]],
                         pattern: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, float]:
    """K, distortion and RMS reprojection error (px) from checkerboard views, each an
    image and the board's 3-D inner-corner coordinates."""
    obj_pts, img_pts = [], []
    size = None
    for img, obj in views:
        corners = find_corners(img, pattern)
        if corners is None:
            continue
        obj_pts.append(obj.astype(np.float32))
        img_pts.append(corners.astype(np.float32).reshape(-1, 1, 2))
        size = img.shape[::-1]
    if len(obj_pts) < 3:
        raise InvalidInputError(f"intrinsic calibration: the board was found in {len(obj_pts)} of "
                                f"{len(views)} views; need at least 3")
    rms, K, dist, _, _ = cv2.calibrateCamera(obj_pts, img_pts, size, None, None,
                                             flags=cv2.CALIB_FIX_K3)
    return K, dist.ravel()[:5], float(rms)


def find_corners(img: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners (n, 2) of a checkerboard, OpenCV's order, or None."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(img, pattern, flags=flags)
    if not ok:
        return None
    corners = cv2.cornerSubPix(img, corners, (5, 5), (-1, -1), _SUBPIX_CRITERIA)
    return corners.reshape(-1, 2).astype(np.float64)


def order_board_corners(corners: np.ndarray, pattern: tuple[int, int], img: np.ndarray,
                        rear_view: bool = True) -> np.ndarray:
    """Reorder detected corners to the board's own row-major order.

    OpenCV may walk the grid from any of its four ends.  Of the four readings, the right
    one (a) maps the board with the handedness of the view -- a camera behind a rear-
    projection screen sees it mirrored (``rear_view``; a mirror in the light path flips it
    back) -- and (b) predicts the colours of the squares: board
    square (i, j) is black when i + j is even.  With one odd and one even square count both
    tests together leave exactly one reading.
    """
    w, h = pattern
    grid = corners.reshape(h, w, 2)
    best, best_score = None, -1.0
    for flip_k in (False, True):
        for flip_l in (False, True):
            g = grid[:, ::-1] if flip_k else grid
            g = g[::-1] if flip_l else g
            # handedness: cross product of the board's +a and +b directions in the image
            da, db = g[0, -1] - g[0, 0], g[-1, 0] - g[0, 0]
            cross = da[0] * db[1] - da[1] * db[0]
            # screen X x Y is the outward normal; seen from outside (rear view) the board
            # turns clockwise in the image (cross < 0, image y pointing down)
            if (cross < 0) != rear_view:
                continue
            centres = 0.25 * (g[:-1, :-1] + g[1:, :-1] + g[:-1, 1:] + g[1:, 1:])
            ll, kk = np.mgrid[0:h - 1, 0:w - 1]
            expect_dark = (kk + ll) % 2 == 0
            vals = img[np.rint(centres[..., 1]).astype(int), np.rint(centres[..., 0]).astype(int)]
            dark = vals < np.median(vals)
            score = float(np.mean(dark == expect_dark))
            if score > best_score:
                best, best_score = g, score
    if best is None or best_score < 0.9:
        raise InvalidInputError("screen board: cannot tell the board's orientation (square colours "
                                f"agree at best {best_score:.0%}); is rear_view set right?")
    return best.reshape(-1, 2)


def calibrate_screen(cam_K: np.ndarray, cam_dist: np.ndarray, img: np.ndarray,
                     pattern: tuple[int, int], corners_xy: np.ndarray,
                     rear_view: bool = True) -> tuple[np.ndarray, dict]:
    """Image -> screen homography from a projected checkerboard and its quality figures."""
    corners = find_corners(img, pattern)
    if corners is None:
        raise InvalidInputError(f"screen board: no {pattern[0]}x{pattern[1]} checkerboard found")
    corners = order_board_corners(corners, pattern, img, rear_view)
    und = undistort_points(corners, cam_K, cam_dist, cam_K)
    H = dlt_homography(und, corners_xy)
    H_cv, _ = cv2.findHomography(und, corners_xy, 0)
    resid = np.linalg.norm(apply_homography(H, und) - corners_xy, axis=1)
    probe = und[:: max(1, len(und) // 10)]
    diff_cv = np.abs(apply_homography(H, probe) - apply_homography(H_cv, probe)).max()
    return H, {"screen_rms_m": float(np.sqrt(np.mean(resid ** 2))),
               "screen_max_m": float(resid.max()), "corners": len(corners),
               "dlt_vs_opencv_m": float(diff_cv)}


def sensor_noise(dark: np.ndarray) -> tuple[float, float]:
    """Dark level and read noise (DN) of a dark frame, robust to stuck pixels."""
    v = dark.astype(np.float64).ravel()
    med = float(np.median(v))
    mad = float(np.median(np.abs(v - med)))
    return med, max(1.4826 * mad, 0.5)


def calibrate_sim(world, n_views: int = 8, seed: int = 0) -> Calibration:
    """Calibrate every camera of a simulated ``IvyWorld`` from its rendered calibration
    images -- the same procedure as on the real display, with rendered pictures."""
    pattern = (9, 6)
    cams = []
    for cam in world.cameras:
        K, dist, rms = calibrate_intrinsics(world.intrinsic_views(cam.name, n_views, seed),
                                            pattern)
        img, board_pattern, corners_xy = world.screen_board(cam.name)
        H, quality = calibrate_screen(K, dist, img, board_pattern, corners_xy)
        dark_level, read_noise = sensor_noise(world.dark_frame(cam.name, seed))
        quality["intrinsic_rms_px"] = rms
        cams.append(CameraCalibration(
            cam.name, world.walls[cam.wall], K, dist, H, cam.width, cam.height,
            DetectorParams(dark_level=dark_level, read_noise=read_noise), quality))
    return Calibration(cams, {"sim": world.installation})


def sim_calibration(world, cache: str | Path | None = None) -> Calibration:
    """The calibration of a simulated world, from ``cache`` if that file was made for the
    same installation, else calibrated (10-20 s) and written to ``cache``."""
    if cache is not None and Path(cache).exists():
        cal = Calibration.load(cache)
        if cal.meta.get("sim") == world.installation:
            return cal
    cal = calibrate_sim(world)
    if cache is not None:
        cal.save(cache)
    return cal


def _matrix(v, shape: tuple[int, ...], name: str) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InvalidInputError(f"{name}: expected finite values of shape {shape}, got {a.shape}")
    return a
