"""Laser dot detection in one 8-bit image (Hogue 2003, §5.2.1, listings 5.1-5.4).

The thesis labels bright pixels in one pass, accumulates intensity-weighted sums per
label (eqs. 5.1-5.3), divides (5.4-5.5) and merges candidates closer than ``delta_x``.
Here OpenCV does the pass: a binary threshold and ``connectedComponentsWithStats`` label
the bright pixels in C; the weighted sums are then taken only inside each component's
bounding box, so the Python work scales with the number of dots, not pixels.  Weights are
intensities minus the sensor's dark level, which removes the pull of the threshold's cut
towards the geometric centre of the region.  Fragments of one spot (a smeared or clipped
spot can break apart) closer than ``merge_px`` are merged with intensity weights.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: columns of the detector's output rows
U, V, FLUX, AREA, STD = range(5)


@dataclass(frozen=True)
class DetectorParams:
    """Thresholds of the detector; the sensor terms come from the calibration dark frame."""

    threshold: int = 40  # DN above which a pixel may belong to a laser dot
    min_area: int = 2  # smaller components are hot pixels
    max_area: int = 4000  # larger ones are not laser dots (stray light)
    merge_px: float = 6.0  # fragments closer than this belong to one dot (thesis delta_x)
    dark_level: float = 8.0  # DN of a dark pixel
    read_noise: float = 1.5  # DN, std of a dark pixel
    gain: float = 0.1  # DN per electron: shot noise variance = gain * signal
    floor_px: float = 0.02  # systematic centroid error (sampling, saturation)

    def __post_init__(self) -> None:
        if not 0 < self.threshold < 255:
            raise ValueError(f"threshold must be in 1..254 DN, got {self.threshold}")
        if self.min_area < 1 or self.max_area < self.min_area:
            raise ValueError("need 1 <= min_area <= max_area")
        if self.merge_px < 0:
            raise ValueError("merge_px must be >= 0")


def detect_dots(image: np.ndarray, params: DetectorParams = DetectorParams()) -> np.ndarray:
    """Sub-pixel laser dots in a grayscale image: rows ``(u, v, flux, area, std_px)``.

    ``u, v`` are distorted pixel coordinates (pixel centres at integers), ``flux`` the
    summed intensity above the dark level, ``std_px`` the centroid's standard deviation
    from sensor noise (with a floor for systematic effects).
    """
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError("image must be a 2-D uint8 array (grayscale, 8 bit), got "
                         f"{getattr(image, 'dtype', type(image))} "
                         f"{getattr(image, 'shape', '')}")
    _, mask = cv2.threshold(image, params.threshold, 255, cv2.THRESH_BINARY)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8,
                                                           ltype=cv2.CV_32S)
    rows = []
    for k in range(1, n):
        x, y, w, h, area = stats[k]
        if area < params.min_area or area > params.max_area:
            continue
        rows.append(_centroid(image[y:y + h, x:x + w], labels[y:y + h, x:x + w] == k,
                              x, y, int(area), params))
    if not rows:
        return np.zeros((0, 5))
    return _merge(np.array(rows), params)


def _centroid(roi: np.ndarray, sel: np.ndarray, x0: int, y0: int, area: int,
              p: DetectorParams) -> list[float]:
    """Intensity-weighted centroid (eqs. 5.1-5.5) of one component and its noise std."""
    signal = np.where(sel, roi.astype(np.float64) - p.dark_level, 0.0)
    np.maximum(signal, 0.0, out=signal)
    flux = float(signal.sum())
    us = np.arange(x0, x0 + roi.shape[1], dtype=np.float64)
    vs = np.arange(y0, y0 + roi.shape[0], dtype=np.float64)
    u = float(signal.sum(axis=0) @ us) / flux
    v = float(signal.sum(axis=1) @ vs) / flux
    # var(u_hat) = sum (u_i - u)^2 var(I_i) / flux^2; saturated pixels carry no noise
    var_i = np.where(sel & (roi < 255), p.read_noise ** 2 + p.gain * signal, 0.0)
    r2 = (us[None, :] - u) ** 2 + (vs[:, None] - v) ** 2
    var = 0.5 * float((r2 * var_i).sum()) / flux ** 2
    return [u, v, flux, float(area), float(np.sqrt(var + p.floor_px ** 2))]


def _merge(rows: np.ndarray, p: DetectorParams) -> np.ndarray:
    """Merge candidates closer than ``merge_px`` (fragments of one spot), flux-weighted."""
    if len(rows) < 2 or p.merge_px <= 0:
        return rows
    group = np.arange(len(rows))
    for i in range(len(rows)):
        for j in range(i + 1, len(rows)):
            if np.hypot(*(rows[i, :2] - rows[j, :2])) < p.merge_px:
                group[group == group[j]] = group[i]
    out = []
    for g in np.unique(group):
        r = rows[group == g]
        w = r[:, FLUX] / r[:, FLUX].sum()
        out.append([w @ r[:, U], w @ r[:, V], r[:, FLUX].sum(), r[:, AREA].sum(),
                    float(np.sqrt((w ** 2) @ r[:, STD] ** 2))])
    return np.array(out)
