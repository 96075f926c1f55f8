"""Intrinsic calibration from a ChArUco board: views, coverage, OpenCV's estimate, verdict.

1. **Views** (:func:`detect_view`): ``cv2.aruco.CharucoDetector.detectBoard`` finds the
   board's chessboard corners from the markers around them, ``cv2.cornerSubPix`` refines
   them (:func:`refine_corners`); a view needs
   ``MIN_CORNERS`` corners that are not on one line (``checkCharucoCornersCollinear``).
2. **Selection** (:func:`select_views`): a view that shows the same corners within
   ``min_shift`` of the image diagonal of a view already kept adds almost nothing but
   weight (a video of a board held still): it is rejected as a near-duplicate.
3. **Estimate** (:func:`calibrate`): ``cv2.calibrateCameraExtended``: intrinsics, the RMS
   reprojection error, each parameter's standard deviation and each view's error.  The
   RMS is OpenCV's: the plain mean over the corners, which the fit has pulled towards
   them; the corners' own noise is estimated with the fit's degrees of freedom counted
   (:func:`corner_noise`), and that is the noise the camera model carries.
4. **Coverage and verdict**: corners are counted in a 3x3 grid of the image; distortion is
   only known where corners were seen, so every cell must hold some.  The verdict is
   "good" or "needs more views" with the reasons (too few distinct views, the cells not
   covered by name, an uncertain focal length or principal point, a high RMS).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.camera.model import CameraModel

MIN_CORNERS = 6
MIN_VIEWS = 8
GRID = 3
MIN_CORNERS_PER_CELL = 4
#: acceptance: focal length to 0.3 % at 3 sigma, principal point to 1 px at 2 sigma
MAX_FOCAL_REL_STD = 0.001
MAX_CENTRE_STD_PX = 0.5
MAX_RMS_PX = 1.0
#: how far (px) a corner's cornerSubPix window ends short of a marker (:func:`subpix_windows`)
SUBPIX_MARGIN_PX = 2.0
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
CELL_NAMES = (("top-left", "top", "top-right"), ("left", "centre", "right"),
              ("bottom-left", "bottom", "bottom-right"))
STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
             "s1", "s2", "s3", "s4", "tau_x", "tau_y")


@dataclass(frozen=True)
class View:
    """One image's detected board corners."""

    index: int
    ids: np.ndarray  # (n,) chessboard corner ids
    corners: np.ndarray  # (n, 2) pixels


@dataclass
class Result:
    """A calibration and what it says about itself."""

    model: CameraModel | None
    rms_px: float  # OpenCV's: sqrt(sum of squared residuals / corners), per corner
    std: dict[str, float]
    views_seen: int
    views_used: int
    duplicates: int
    coverage: np.ndarray  # (GRID, GRID) corners per cell
    verdict: str
    reasons: list[str] = field(default_factory=list)
    per_view_rms_px: list[float] = field(default_factory=list)
    noise_px: float = math.nan  # the corners' noise estimated from the residuals, per corner
    corners: int = 0
    parameters: int = 0  # estimated: intrinsics not held fixed, and six per view

    @property
    def uncovered(self) -> list[str]:
        return [CELL_NAMES[r][c] for r in range(GRID) for c in range(GRID)
                if self.coverage[r, c] < MIN_CORNERS_PER_CELL]

    def summary(self) -> dict:
        """JSON-ready figures."""
        m = self.model
        return {"verdict": self.verdict, "reasons": self.reasons, "rms_px": self.rms_px,
                "noise_px": self.noise_px, "corners": self.corners,
                "parameters": self.parameters,
                "views_seen": self.views_seen, "views_used": self.views_used,
                "near_duplicates_rejected": self.duplicates, "uncovered": self.uncovered,
                "coverage_corners": self.coverage.tolist(),
                "fx": None if m is None else m.K[0, 0], "fy": None if m is None else m.K[1, 1],
                "cx": None if m is None else m.K[0, 2], "cy": None if m is None else m.K[1, 2],
                "dist": None if m is None else m.dist.tolist(), "std": self.std}


def detect_view(detector: cv2.aruco.CharucoDetector, image: np.ndarray, index: int,
                ) -> View | None:
    """The board's corners in ``image``, or ``None`` when too few are seen to help."""
    corners, ids, markers, _ = detector.detectBoard(image)
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    board = detector.getBoard()
    if board.checkCharucoCornersCollinear(ids):
        return None
    outlines = [np.asarray(m, np.float64).reshape(4, 2) for m in markers or ()]
    return View(index, ids.ravel().astype(int),
                refine_corners(image, corners.reshape(-1, 2), outlines))


def refine_corners(image: np.ndarray, corners: np.ndarray,
                   markers: Iterable[np.ndarray] = ()) -> np.ndarray:
    """Chessboard corners refined by ``cv2.cornerSubPix`` to 1e-4 px.  ``detectBoard``'s
    own refinement stops at 0.1 px and leaves a bias of about 0.05 % in the board's scale
    on simulated boards, 0.3 % in the focal length after calibration; this removes it.
    Each corner's window (:func:`subpix_windows`) stays clear of the markers beside it: a
    marker's edge inside the window pulls the corner, by up to 1-2 px on a tilted board."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    pts = np.asarray(corners, np.float32).reshape(-1, 2)
    out = pts.copy()
    halves = subpix_windows(pts, list(markers))
    for half in np.unique(halves):
        sel = halves == half
        out[sel] = cv2.cornerSubPix(gray, pts[sel].reshape(-1, 1, 2).copy(),
                                    (int(half), int(half)), (-1, -1),
                                    _SUBPIX_CRITERIA).reshape(-1, 2)
    return out.astype(np.float64)


def subpix_windows(corners: np.ndarray, markers: list[np.ndarray]) -> np.ndarray:
    """Each corner's ``cornerSubPix`` half-window (px): a fifth of its distance to the
    nearest other corner, and clear of every marker outline ((4, 2) corners, pixels) by
    ``SUBPIX_MARGIN_PX`` (the gradient's kernel and the optics' blur reach that far), in
    the window's own (square) measure; between 2 and 8 px."""
    pts = np.asarray(corners, np.float64).reshape(-1, 2)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(d, np.inf)
    half = 0.2 * d.min(1) if len(pts) > 1 else np.full(len(pts), 8.0)
    if markers:
        t = np.linspace(0.0, 1.0, 16, endpoint=False)[:, None]
        edge = np.concatenate([m + t[:, None] * (np.roll(m, -1, axis=0) - m)
                               for m in markers]).reshape(-1, 2)
        square = np.abs(pts[:, None] - edge[None]).max(axis=2).min(axis=1)
        half = np.minimum(half, square - SUBPIX_MARGIN_PX)
    return np.clip(np.floor(half), 2, 8).astype(int)


def select_views(views: Iterable[View], size: tuple[int, int], min_shift: float = 0.05,
                 ) -> tuple[list[View], int]:
    """The views kept and the number of near-duplicates rejected (see the module)."""
    limit = min_shift * math.hypot(*size)
    kept: list[View] = []
    duplicates = 0
    for v in views:
        if any(_same_view(v, k, limit) for k in kept):
            duplicates += 1
        else:
            kept.append(v)
    return kept, duplicates


def _same_view(a: View, b: View, limit_px: float) -> bool:
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if len(common) < 0.8 * max(len(a.ids), len(b.ids)):
        return False
    return float(np.median(np.linalg.norm(a.corners[ia] - b.corners[ib], axis=1))) < limit_px


def coverage(views: Iterable[View], size: tuple[int, int]) -> np.ndarray:
    """Corners seen per cell of a ``GRID`` x ``GRID`` division of the image."""
    grid = np.zeros((GRID, GRID), int)
    w, h = size
    for v in views:
        col = np.clip((v.corners[:, 0] / w * GRID).astype(int), 0, GRID - 1)
        row = np.clip((v.corners[:, 1] / h * GRID).astype(int), 0, GRID - 1)
        np.add.at(grid, (row, col), 1)
    return grid


def calibrate(views: list[View], board: cv2.aruco.CharucoBoard, size: tuple[int, int],
              views_seen: int, duplicates: int = 0, flags: int = 0) -> Result:
    """Calibrate from the kept ``views`` and judge the result."""
    cover = coverage(views, size)
    if len(views) < 3:
        return Result(None, math.nan, {}, views_seen, len(views), duplicates, cover,
                      "needs more views",
                      [f"only {len(views)} usable views of the board (at least {MIN_VIEWS})"])
    obj, img = [], []
    for v in views:
        o, i = board.matchImagePoints(v.corners.reshape(-1, 1, 2).astype(np.float32),
                                      v.ids.reshape(-1, 1))
        obj.append(o.astype(np.float32))
        img.append(i.astype(np.float32))
    rms, K, dist, _, _, std_in, _, per_view = cv2.calibrateCameraExtended(
        obj, img, size, None, None, flags=flags)
    dist = dist.ravel()
    std = {n: float(s) for n, s in zip(STD_NAMES, std_in.ravel()[:4 + dist.size],
                                       strict=False)}
    corners = sum(len(v.ids) for v in views)
    parameters = int(np.count_nonzero(std_in)) + 6 * len(views)
    noise = corner_noise(float(rms), corners, parameters)
    model = CameraModel(K, dist, size[0], size[1], pixel_std=noise / math.sqrt(2))
    result = Result(model, float(rms), std, views_seen, len(views), duplicates, cover, "good",
                    per_view_rms_px=[float(e) for e in per_view.ravel()], noise_px=noise,
                    corners=corners, parameters=parameters)
    result.reasons = _reasons(result)
    if result.reasons:
        result.verdict = "needs more views"
    return result


def corner_noise(rms_px: float, corners: int, parameters: int) -> float:
    """The corners' noise (per corner, both axes, the unit of the RMS) from a fit's RMS:
    the residuals of ``2 * corners`` coordinates that fitted ``parameters`` have
    ``2 * corners - parameters`` degrees of freedom, so their mean square is that much
    below the noise's (the fit follows the noise in as many directions as it has
    parameters).  For 36 views of 25-30 corners the RMS is 0.93-0.95 of the noise."""
    m = 2 * corners
    return rms_px * math.sqrt(m / (m - parameters)) if m > parameters else math.nan


def _reasons(r: Result) -> list[str]:
    out = []
    if r.views_used < MIN_VIEWS:
        out.append(f"only {r.views_used} distinct views (at least {MIN_VIEWS}): move or tilt "
                   "the board between them")
    if r.uncovered:
        out.append("no corners seen in the image's " + ", ".join(r.uncovered) +
                   ": show the board there too")
    assert r.model is not None
    K = r.model.K
    rel_f = max(r.std["fx"] / K[0, 0], r.std["fy"] / K[1, 1])
    if rel_f > MAX_FOCAL_REL_STD:
        out.append(f"focal length uncertain ({100 * rel_f:.2f} % std, at most "
                   f"{100 * MAX_FOCAL_REL_STD:.2f} %): add views with the board tilted")
    c_std = max(r.std["cx"], r.std["cy"])
    if c_std > MAX_CENTRE_STD_PX:
        out.append(f"principal point uncertain ({c_std:.2f} px std, at most "
                   f"{MAX_CENTRE_STD_PX} px): add tilted views near the image's edges")
    if r.rms_px > MAX_RMS_PX:
        out.append(f"RMS {r.rms_px:.2f} px is high (at most {MAX_RMS_PX} px): blurred "
                   "frames, a wrong square size or a board that is not flat")
    return out
