"""Bright blobs of an infrared image as sub-pixel marker centroids.

Thresholding, 8-connected components and the intensity-weighted centroid with its noise
std are the laser tracker's detector (``services.laser_camera.detection``: it labels only
the boxes holding bright pixels, and works in windows too); this module adds what markers
need beyond it: a size range, a roundness test (a retro-reflective ball images as a round
blob, a reflection on a rail or two touching markers do not), and windows around the
markers a prediction projects into the image, falling back to the whole frame when a
window cuts a blob.  Fragments are never merged: two markers close together must stay two.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.special import erfc

from agent.errors import InvalidInputError
from agent.runtime import compiled_twin
from services.laser_camera.detection import (
    AREA,
    FLUX,
    DetectorParams,
    check_gray8,
    detect_dots,
    detect_dots_in,
)
from services.outside_in import blob_model

Array = np.ndarray


@dataclass(frozen=True)
class BlobParams:
    """Thresholds of marker segmentation (DN of an 8-bit image, pixels)."""

    threshold: int = 50           # DN above which a pixel may belong to a marker
    min_area: int = 3             # pixels: smaller is a hot pixel or noise
    max_area: int = 600           # pixels: larger is a lamp or a window
    min_roundness: float = 0.8    # minor / major axis of the blob's intensity moments
    window_px: int = 10           # half size of a window around a predicted marker
    dark_level: float = 8.0       # DN of a dark pixel
    read_noise: float = 2.0       # DN, std of a dark pixel
    gain: float = 0.15            # DN per electron: shot noise variance = gain * signal
    floor_px: float = 0.005       # centroid error floor (pixel sampling, blob shape)
    locking_px: float = 0.05      # pixel locking of a small blob: this over its area, px
    locking_area: int = 8         # ... for blobs of fewer pixels than this
    crowd_px: float = 0.18        # centroid error from a neighbour's light, edges touching
    crowd_scale_px: float = 1.9   # ... falling off with the gap between the blobs' edges
    model_fit: bool = True        # centres by a ball's image fitted to the pixels
                                  # (``blob_model``), not the intensity-weighted centroid

    def __post_init__(self) -> None:
        if not 0 < self.threshold < 255:
            raise InvalidInputError(f"blob threshold must be in 1..254 DN, got {self.threshold}")
        if not 1 <= self.min_area <= self.max_area:
            raise InvalidInputError(f"need 1 <= min_area <= max_area, got {self.min_area}, "
                                    f"{self.max_area}")
        if not 0 <= self.min_roundness <= 1:
            raise InvalidInputError(f"min_roundness must be in [0, 1], got {self.min_roundness}")
        if not (self.floor_px >= 0 and self.locking_px >= 0):
            raise InvalidInputError(f"floor_px and locking_px must be >= 0, got "
                                    f"{self.floor_px}, {self.locking_px}")
        if self.window_px < 2:
            raise InvalidInputError(f"window_px must be >= 2, got {self.window_px}")

    def detector(self) -> DetectorParams:
        return DetectorParams(threshold=self.threshold, min_area=self.min_area,
                              max_area=self.max_area, merge_px=0.0,
                              dark_level=self.dark_level, read_noise=self.read_noise,
                              gain=self.gain, floor_px=self.floor_px)


@dataclass(frozen=True)
class Blobs:
    """Marker candidates of one image: pixel centroids and what was measured of each."""

    uv: Array         # (n, 2) distorted pixels, pixel centres at integers
    std_px: Array     # (n,) centroid noise std
    flux: Array       # (n,) summed intensity above the dark level
    area: Array       # (n,) pixels
    roundness: Array  # (n,) minor / major axis

    def __len__(self) -> int:
        return len(self.uv)

    @staticmethod
    def empty() -> Blobs:
        z = np.zeros(0)
        return Blobs(np.zeros((0, 2)), z, z, z, z)


def find_blobs(image: Array, params: BlobParams = BlobParams(),
               predicted_uv: Array | None = None) -> Blobs:
    """Round bright blobs of ``image``: in windows around ``predicted_uv`` (n, 2) when
    given, the whole frame when not or when a window cuts a blob."""
    check_gray8(image)
    windows = None
    if predicted_uv is not None and len(predicted_uv):
        uv = np.asarray(predicted_uv, float).reshape(-1, 2)
        # int() of each: toward zero; far outside the image is as good as 1e9 away
        centre = np.trunc(np.clip(uv[np.isfinite(uv).all(axis=1)], -1e9, 1e9)).astype(np.int64)
        r = params.window_px
        windows = np.hstack([centre - r, centre + r + 1])   # x0, y0, x1, y1
    segment = _segment if NATIVE is None else _segment_native
    found = segment(image, params, windows)
    if found is None:
        found = segment(image, params, None)
    refined, flux, area = found
    if len(refined) == 0:
        return Blobs.empty()
    refined[:, 2] = np.hypot(np.hypot(refined[:, 2], crowding_px(refined[:, :2], area, params)),
                             locking_px(area, params))
    keep = refined[:, 3] >= params.min_roundness
    if params.model_fit:
        _fit_models(image, refined, area, keep, params)
    refined = refined[keep]
    return Blobs(refined[:, :2].copy(), refined[:, 2].copy(), flux[keep], area[keep],
                 refined[:, 3].copy())


def _fit_models(image: Array, refined: Array, area: Array, keep: Array,
                params: BlobParams) -> None:
    """Replace the centroids and stds of the blobs ``keep`` of ``refined`` (``u, v, std,
    roundness`` rows) by the fitted ball images' (``blob_model``) where the fit was made
    and is the surer of the two (a blob that is no ball's image, a ring or a cut lamp,
    can leave the fit all but undetermined).  The fit's std needs neither the
    pixel-locking term (the model follows the blob's sampling) nor the crowding one (a
    neighbour's pixels are left out): on the simulated rig's marker images its errors
    over its stds are 0.97-1.03 (rms) for lone and crowded blobs alike."""
    uv, std, ok = blob_model.fit_centres(image, refined[:, :2], area, keep,
                                         params.dark_level, params.gain, params.read_noise)
    take = ok & (std < refined[:, 2])
    refined[take, :2] = uv[take]
    refined[take, 2] = std[take]


Segments = tuple[Array, Array, Array]


def _segment(image: Array, params: BlobParams, windows: Array | None) -> Segments | None:
    """Every blob of the whole image, or of the ``windows`` ((k, 4) ``x0, y0, x1, y1``;
    None when one cuts a blob): ``u, v, std, roundness`` (n, 4) refined (``_refine``), the
    detector's flux and area."""
    det = params.detector()
    if windows is None:
        rows = detect_dots(image, det)
    else:
        rows, whole = detect_dots_in(image, [tuple(b) for b in windows.tolist()], det)
        if not whole:
            return None
    refined = np.array([_refine(image, row, params) for row in rows]).reshape(-1, 4)
    return refined, rows[:, FLUX].copy(), rows[:, AREA].copy()


def _segment_native(image: Array, params: BlobParams, windows: Array | None
                    ) -> Segments | None:
    """``_segment`` by the compiled twin (``_blobs.c``): the same blobs, to the bit."""
    p = params
    rows, whole = NATIVE.find(
        np.ascontiguousarray(image), None if windows is None else np.ascontiguousarray(windows),
        p.threshold, p.min_area, p.max_area, p.dark_level, p.gain, 2.0 * p.read_noise,
        p.read_noise ** 2, 0.5 - 0.5 / np.pi, p.floor_px ** 2)
    if not whole:
        return None
    out = np.frombuffer(rows, np.float64).reshape(-1, 6)
    return out[:, :4].copy(), out[:, 4].copy(), out[:, 5].copy()


#: the compiled segmentation in use (tests set it to None to run the pure-Python one)
NATIVE: Any = compiled_twin("services.outside_in._blobs", "UMA_BLOBS_PURE_PYTHON")


def _refine(image: Array, row: Array, p: BlobParams) -> list[float]:
    """Centroid, its std and the roundness of one blob, from its bright pixels and the
    two-pixel rim around them.

    The detector's centroid weighs only the pixels above the threshold; for a marker of a
    few pixels that cut depends on where the blob falls within a pixel and biases the
    centroid by up to a tenth of a pixel.  The rim holds the blob's faint tails, so
    weighing it in (intensity above the dark level) removes most of that bias at the cost
    of a little read noise, which the std counts.  Roundness is the minor over major axis
    of the same intensity moments."""
    half = int(np.ceil(np.sqrt(row[AREA]))) + 3
    u, v = round(float(row[0])), round(float(row[1]))
    h, w = image.shape
    y0, y1 = max(v - half, 0), min(v + half + 1, h)
    x0, x1 = max(u - half, 0), min(u + half + 1, w)
    roi = image[y0:y1, x0:x1]
    bright = cv2.threshold(roi, p.threshold, 1, cv2.THRESH_BINARY)[1]
    _, labels = cv2.connectedComponents(bright, connectivity=8)
    own = labels[min(max(v - y0, 0), y1 - y0 - 1), min(max(u - x0, 0), x1 - x0 - 1)]
    # own == 0: the centroid fell between the pixels of a ring; take all bright pixels
    mine = bright if own == 0 else (labels == own).astype(np.uint8)
    # the rim stops short of other blobs' rims: a neighbour's tail would pull the centroid
    sel = cv2.dilate(mine, _RIM) & ~cv2.dilate(bright - mine, _RIM) & 1
    signal = np.subtract(roi, p.dark_level, dtype=np.float64)
    np.maximum(signal, 0.0, out=signal)
    signal *= sel
    m = cv2.moments(signal)
    flux = m["m00"]
    if flux <= 0:
        return [float(row[0]), float(row[1]), np.inf, 0.0]
    cu, cv_ = m["m10"] / flux, m["m01"] / flux
    # a rim pixel near the dark level is clipped at zero: max(n, 0) of read noise n keeps
    # (1/2 - 1/(2 pi)) of its variance
    read = np.where(signal > 2.0 * p.read_noise, 1.0, 0.5 - 0.5 / np.pi) * p.read_noise ** 2
    var_i = (signal * p.gain + read) * (sel & (roi < 255))
    mv = cv2.moments(var_i)
    r2 = (mv["m20"] + mv["m02"] - 2.0 * (cu * mv["m10"] + cv_ * mv["m01"])
          + (cu * cu + cv_ * cv_) * mv["m00"])
    std = float(np.sqrt(0.5 * r2 / flux ** 2 + p.floor_px ** 2))
    a, b, c = m["mu20"] / flux, m["mu02"] / flux, m["mu11"] / flux
    root = np.sqrt(max((a - b) ** 2 + 4 * c * c, 0.0))
    big, small = 0.5 * (a + b + root), 0.5 * (a + b - root)
    return [x0 + cu, y0 + cv_, std, float(np.sqrt(max(small, 0.0) / big)) if big > 0 else 0.0]


def crowding_px(uv: Array, area: Array, p: BlobParams) -> Array:
    """Each blob's centroid error (std, px) from its nearest neighbour's light.

    A marker's image a few pixels from another's (two markers of a body seen edge on, a
    marker passing a reflection) has the other's tail in its rim, or the rim cut short
    where the two meet: its centroid moves by up to a fifth of a pixel, several times
    its noise, and the same way in every frame while the two stay close.  The error
    falls off with the gap between the blobs' edges (their radii from their areas) as a
    Gaussian: ``crowd_px * exp(-gap^2 / (2 crowd_scale_px^2))``, measured on the
    simulated rig's marker images against their true centres.  Every blob found counts
    as a neighbour, round or not."""
    n = len(uv)
    if n < 2:
        return np.zeros(n)
    r = np.sqrt(np.asarray(area, float) / np.pi)
    gap = np.linalg.norm(uv[:, None, :] - uv[None, :, :], axis=2) - r[:, None] - r[None, :]
    np.fill_diagonal(gap, np.inf)
    g = np.maximum(gap.min(axis=1), 0.0)
    return p.crowd_px * np.exp(-0.5 * (g / p.crowd_scale_px) ** 2)


def locking_px(area: Array, p: BlobParams) -> Array:
    """Each blob's centroid error (std, px) from pixel locking: ``locking_px / area``
    for blobs of fewer than ``locking_area`` pixels, none for larger ones.

    A marker two or three pixels across has its intensity-weighted centroid pulled
    toward or away from the pixel grid by where it falls within a pixel (the weights of
    its few pixels and of its rim change in steps), up to 0.02 px: an error its noise
    model does not hold.  Measured on the simulated rig's isolated marker images of
    seeds 1-4 (their centroids against the true centres, outliers past 4 std left out):
    without this term and the floor, areas 3-4 erred 1.11 times the std reported, 5-7
    1.07 times, 8-13 1.06 and larger ones 1.01; with this term and the floor at 0.005
    px, 1.02, 1.02, 1.02 and 0.95, and on seeds 5-6 1.02, 1.01, 1.03 and 0.95."""
    a = np.asarray(area, float)
    return np.where(a < p.locking_area, p.locking_px / np.maximum(a, 1.0), 0.0)


#: the rim around a blob's bright pixels that holds its tails
_RIM = np.ones((5, 5), np.uint8)


def fit_centres(image: Array, uv: Array, half: int = 3) -> Array:
    """Centres (n, 2) of the blobs at ``uv`` by a least-squares fit of a ball's image --
    a disk of uniform brightness blurred by the lens, ``a erfc((d - r) / (sqrt 2 s)) / 2
    + b`` with amplitude, centre, radius, blur and background free -- to the ``2 half +
    1`` square around each, saturated pixels left out.

    The intensity-weighted centroid of a marker only two or three pixels wide depends on
    where it falls within a pixel (pixel locking: a few hundredths of a pixel); in one
    frame the noise hides that, in the average of many frames of a still marker it is
    what remains, so still scenes (the L-frame) are located by a fitted model.  A round
    Gaussian, the first such model, left 0.0056 px (rms per axis) on the simulated
    L-frame's 120-frame averages, a bias with the sub-pixel phase that more frames did
    not lower (0.0053 px at 480); the blurred disk leaves 0.0035 px there (0.0032 at
    480)."""
    img = np.asarray(image, np.float64)
    h, w = img.shape
    out = np.array(uv, np.float64).reshape(-1, 2)
    lower = [0.0, -np.inf, -np.inf, 0.05, 0.2, -np.inf]
    upper = [np.inf, np.inf, np.inf, 2.0 * half, float(half), np.inf]
    for k, (u, v) in enumerate(out.copy()):
        u0, v0 = round(float(u)), round(float(v))
        if not (half <= u0 < w - half and half <= v0 < h - half):
            continue
        patch = img[v0 - half:v0 + half + 1, u0 - half:u0 + half + 1]
        yy, xx = np.mgrid[v0 - half:v0 + half + 1, u0 - half:u0 + half + 1]
        ok = patch < 255

        def model(p: Array, xx: Array = xx, yy: Array = yy, patch: Array = patch,
                  ok: Array = ok) -> Array:
            a, cu, cv_, r, s, b = p
            d = np.hypot(xx - cu, yy - cv_)
            return (a * 0.5 * erfc((d - r) / (np.sqrt(2.0) * s)) + b - patch)[ok]

        start = [float(patch.max() - patch.min()), float(u), float(v), 1.0, 0.7,
                 float(patch.min())]
        sol = least_squares(model, start, x_scale=[10.0, 0.1, 0.1, 0.1, 0.1, 1.0],
                            bounds=(lower, upper))
        if sol.success and np.hypot(sol.x[1] - u, sol.x[2] - v) < 1.0:
            out[k] = sol.x[1:3]
    return out
