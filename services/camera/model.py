"""A calibrated camera: pinhole ``K``, OpenCV's distortion, image size, pixel noise.

The model is exactly OpenCV's, so every camera tracker hands it to OpenCV unchanged
(``cv2.projectPoints``, ``cv2.solvePnP``, ``cv2.undistortPoints``).  Distortion takes any
of OpenCV's coefficient forms: 4 or 5 (k1 k2 p1 p2 [k3]), 8 (+ k4 k5 k6, rational),
12 (+ s1..s4, thin prism) or 14 (+ tauX tauY, tilted sensor); none means no distortion.

Files (:func:`load`, :meth:`CameraModel.save`):

* OpenCV's ``FileStorage`` calibration files, YAML (``%YAML:1.0``), JSON or XML, as
  OpenCV's calibration samples and ``uma calibrate camera`` write them: ``camera_matrix``,
  ``distortion_coefficients``, ``image_width``, ``image_height`` and optionally
  ``avg_reprojection_error`` (pixels, the calibration's RMS).
* ROS ``camera_info`` YAML (``camera_calibration``'s output, read only): ``image_width``,
  ``image_height``, ``camera_matrix.data``, ``distortion_coefficients.data``,
  ``distortion_model`` (``plumb_bob`` or ``rational_polynomial``).  It has no ``%YAML``
  line, which ``FileStorage`` needs, so the line is added and the text read from memory.

A file that is missing, unparsable, lacks a field or holds a wrong shape is a
:class:`CameraFileError` naming the file and the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from agent.errors import InvalidInputError, UmaError

#: distortion vector lengths OpenCV accepts
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)
#: the iterative undistortion's stop: OpenCV's default five iterations leave tenths of a
#: pixel at the corners of a wide-angle lens
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
_SUFFIXES = (".yaml", ".yml", ".json", ".xml")


class CameraFileError(UmaError):
    """A calibration file that cannot be read: says which file and what is wrong."""


def undistort_points(uv: Any, K: np.ndarray, dist: np.ndarray,
                     P: np.ndarray | None = None) -> np.ndarray:
    """Distorted pixels (n, 2) to ideal ones: normalised coordinates, or pixels of the
    camera matrix ``P``.  Iterates to 1e-10 (OpenCV 4 names the iterating variant
    ``undistortPointsIter``; OpenCV 5 folds it into ``undistortPoints``)."""
    pts = np.asarray(uv, np.float64).reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):
        out = cv2.undistortPointsIter(pts, K, dist, None, P, _UNDISTORT_CRITERIA)
    else:
        out = cv2.undistortPoints(pts, K, dist, R=None, P=P, criteria=_UNDISTORT_CRITERIA)
    return out.reshape(-1, 2)


@dataclass(frozen=True)
class CameraModel:
    """A camera's intrinsics.  ``pixel_std`` is the corner noise (pixels, per axis) the
    calibration measured, ``None`` if unknown; trackers estimate their own noise and use
    this only as a starting value."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    pixel_std: float | None = None
    name: str = ""
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, np.float64)
        dist = np.asarray(self.dist if self.dist is not None else (), np.float64).ravel()
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise InvalidInputError(f"camera matrix must be 3x3 and finite, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1 or np.any(K[1:, 0]) or K[2, 1]:
            raise InvalidInputError("camera matrix must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
                                    f"with fx, fy > 0, got {K.tolist()}")
        if dist.size not in DISTORTION_LENGTHS or not np.all(np.isfinite(dist)):
            raise InvalidInputError(
                f"distortion must have {', '.join(map(str, DISTORTION_LENGTHS))}"
                f" finite coefficients, got {dist.size}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InvalidInputError(f"image size must be positive, got {self.width}x{self.height}")
        if self.pixel_std is not None and not (0 <= self.pixel_std < math.inf):
            raise InvalidInputError(f"pixel_std must be >= 0, got {self.pixel_std}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def size(self) -> tuple[int, int]:
        """(width, height), the order OpenCV's functions take."""
        return self.width, self.height

    def project(self, points: Any, rvec: Any = None, tvec: Any = None) -> np.ndarray:
        """3D points (n, 3) in this camera's frame (or in an object frame at ``rvec``,
        ``tvec``) to distorted pixels (n, 2); pixel centres are integers."""
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        rvec = np.zeros(3) if rvec is None else np.asarray(rvec, np.float64)
        tvec = np.zeros(3) if tvec is None else np.asarray(tvec, np.float64)
        uv, _ = cv2.projectPoints(pts, rvec, tvec, self.K, self.dist)
        return uv.reshape(-1, 2)

    def undistort(self, uv: Any, pixels: bool = False) -> np.ndarray:
        """Distorted pixels (n, 2) to normalised image coordinates (x/z, y/z), or to the
        ideal pixels of the same ``K`` with ``pixels=True``."""
        return undistort_points(uv, self.K, self.dist, self.K if pixels else None)

    def ideal_pixels(self, uv: Any) -> np.ndarray:
        """:meth:`undistort` to ideal pixels, fast: inside the image by bilinear
        interpolation in a table of every pixel's offset to its ideal position
        (:meth:`ideal_offsets`; the offsets are smooth: within 5e-4 px of the iteration for
        a webcam's barrel distortion), outside it by the iteration.  Three times faster
        for the few hundred points of a frame's marker edges."""
        pts = np.asarray(uv, np.float64).reshape(-1, 2)
        table = self.ideal_offsets()
        x, y = pts[:, 0], pts[:, 1]
        inside = (x >= 0) & (y >= 0) & (x < self.width - 1) & (y < self.height - 1)
        if not inside.all():
            out = self.undistort(pts, pixels=True)
            out[inside] = self.ideal_pixels(pts[inside])
            return out
        x0, y0 = x.astype(np.intp), y.astype(np.intp)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        at = y0 * self.width + x0
        # the four neighbours' offsets in one gather (np.take: a fraction of the time of
        # indexing rows by an integer array)
        q = np.take(table, np.concatenate([at, at + 1, at + self.width, at + self.width + 1]),
                    axis=0).reshape(4, -1, 2)
        top = q[0] * (1 - fx) + q[1] * fx
        bottom = q[2] * (1 - fx) + q[3] * fx
        return pts + top + (bottom - top) * fy

    def ideal_offsets(self) -> np.ndarray:
        """Every pixel's offset (height * width, 2, row by row) to its ideal position: the
        table :meth:`ideal_pixels` interpolates in, built by the iteration on the first
        call (5 MB and about 0.1 s for 640x480: a tracker builds it when it starts, so
        that its first frame does not wait for it), then kept."""
        if "ideal_offsets" not in self._cache:
            uu, vv = np.meshgrid(np.arange(self.width, dtype=np.float64),
                                 np.arange(self.height, dtype=np.float64))
            grid = np.stack([uu.ravel(), vv.ravel()], -1)
            self._cache["ideal_offsets"] = self.undistort(grid, pixels=True) - grid
        return self._cache["ideal_offsets"]

    def distortion_map(self, K_ideal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For every pixel of this camera's (distorted) image, where it lies in an ideal
        pinhole image of camera matrix ``K_ideal``: the ``cv2.remap`` maps that turn an
        undistorted rendering into what this lens shows.  Cached per ``K_ideal``."""
        key = ("distortion_map", np.asarray(K_ideal, np.float64).tobytes())
        if key not in self._cache:
            uu, vv = np.meshgrid(np.arange(self.width, dtype=np.float64),
                                 np.arange(self.height, dtype=np.float64))
            grid = np.stack([uu.ravel(), vv.ravel()], -1)
            ideal = cv2.perspectiveTransform(self.undistort(grid).reshape(-1, 1, 2),
                                             np.asarray(K_ideal, np.float64)).reshape(-1, 2)
            maps = (ideal[:, 0].reshape(self.height, self.width).astype(np.float32),
                    ideal[:, 1].reshape(self.height, self.width).astype(np.float32))
            for old in [k for k in self._cache if k[0] == "distortion_map"]:
                del self._cache[old]
            self._cache[key] = maps
        return self._cache[key]

    def save(self, path: str | Path, **extra: float | int | str) -> Path:
        """Write an OpenCV calibration file (YAML, JSON or XML by the suffix); ``extra``
        scalar fields (e.g. ``views=24``) are written too."""
        path = Path(path)
        if path.suffix.lower() not in _SUFFIXES:
            raise CameraFileError(f"{path}: a calibration file ends in "
                                  f"{', '.join(_SUFFIXES)}")
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise CameraFileError(f"{path}: cannot be written")
        try:
            fs.write("image_width", self.width)
            fs.write("image_height", self.height)
            fs.write("camera_matrix", self.K)
            if self.dist.size:  # OpenCV cannot read back an empty matrix: none is none
                fs.write("distortion_coefficients", self.dist.reshape(1, -1))
            if self.pixel_std is not None:
                fs.write("avg_reprojection_error", float(self.pixel_std * math.sqrt(2)))
            if self.name:
                fs.write("camera_name", self.name)
            for k, v in extra.items():
                fs.write(k, v)
        finally:
            fs.release()
        return path


def load(path: str | Path) -> CameraModel:
    """A camera from an OpenCV calibration file or a ROS ``camera_info`` YAML file;
    :class:`CameraFileError` says what is wrong with a bad one."""
    path = Path(path)
    if not path.is_file():
        raise CameraFileError(f"calibration file {path} does not exist")
    if path.suffix.lower() not in _SUFFIXES:
        raise CameraFileError(f"{path}: not a calibration file (expected "
                              f"{', '.join(_SUFFIXES)})")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise CameraFileError(f"{path}: cannot be read ({exc})") from None
    if path.suffix.lower() in (".yaml", ".yml") and not text.lstrip().startswith("%YAML"):
        text = "%YAML:1.0\n---\n" + text  # ROS writes plain YAML; FileStorage needs the line
    fs = _open_memory(text, path)
    try:
        node = fs.getNode("camera_matrix")
        if node.isMap() and node.getNode("dt").empty():  # ROS: rows, cols, data; no dt
            return _from_ros(fs, path)
        return _from_opencv(fs, path)
    finally:
        fs.release()


def _open_memory(text: str, path: Path) -> cv2.FileStorage:
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as exc:
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else "unparsable"
        raise CameraFileError(f"{path}: not a valid YAML/JSON/XML file ({reason})") from None
    if not fs.isOpened():
        raise CameraFileError(f"{path}: not a valid YAML/JSON/XML file")
    return fs


def _from_opencv(fs: cv2.FileStorage, path: Path) -> CameraModel:
    K = _matrix(fs, "camera_matrix", path)
    dist_node = fs.getNode("distortion_coefficients")
    dist = np.zeros(0) if dist_node.empty() else _matrix(fs, "distortion_coefficients", path)
    rms = _optional_real(fs, "avg_reprojection_error")
    return _model(path, K=K, dist=dist, width=_integer(fs, "image_width", path),
                  height=_integer(fs, "image_height", path),
                  pixel_std=None if rms is None else rms / math.sqrt(2),
                  name=fs.getNode("camera_name").string() or "")


def _from_ros(fs: cv2.FileStorage, path: Path) -> CameraModel:
    model = fs.getNode("distortion_model").string() or "plumb_bob"
    if model not in ("plumb_bob", "rational_polynomial"):
        raise CameraFileError(f"{path}: distortion_model {model!r} is not OpenCV's "
                              "(plumb_bob or rational_polynomial)")
    K = _sequence(fs, "camera_matrix", path)
    if K.size != 9:
        raise CameraFileError(f"{path}: camera_matrix.data has {K.size} numbers, not 9")
    dist = np.zeros(0) if fs.getNode("distortion_coefficients").empty() \
        else _sequence(fs, "distortion_coefficients", path)
    return _model(path, K=K.reshape(3, 3), dist=dist, width=_integer(fs, "image_width", path),
                  height=_integer(fs, "image_height", path),
                  name=fs.getNode("camera_name").string() or "")


def _model(path: Path, **fields: Any) -> CameraModel:
    try:
        return CameraModel(**fields)
    except ValueError as exc:
        raise CameraFileError(f"{path}: {exc}") from None


def _matrix(fs: cv2.FileStorage, name: str, path: Path) -> np.ndarray:
    node = fs.getNode(name)
    if node.empty():
        raise CameraFileError(f"{path}: no {name}")
    m = node.mat()
    if m is None:
        raise CameraFileError(f"{path}: {name} is not an OpenCV matrix (rows, cols, dt, data)")
    return np.asarray(m, np.float64)


def _sequence(fs: cv2.FileStorage, name: str, path: Path) -> np.ndarray:
    node = fs.getNode(name).getNode("data")
    if node.empty() or not node.isSeq():
        raise CameraFileError(f"{path}: no {name}.data list")
    values = [node.at(i) for i in range(node.size())]
    if not all(v.isReal() or v.isInt() for v in values):
        raise CameraFileError(f"{path}: {name}.data holds something that is not a number")
    return np.array([v.real() for v in values], np.float64)


def _integer(fs: cv2.FileStorage, name: str, path: Path) -> int:
    node = fs.getNode(name)
    if node.empty() or not (node.isInt() or node.isReal()):
        raise CameraFileError(f"{path}: no {name} (a number of pixels)")
    return int(node.real())


def _optional_real(fs: cv2.FileStorage, name: str) -> float | None:
    node = fs.getNode(name)
    return None if node.empty() or not (node.isReal() or node.isInt()) else float(node.real())
