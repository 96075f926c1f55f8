"""The one summary of timing samples that every benchmark reports.

Every benchmark here reports the same two figures of its samples, the median and the 99th
percentile; they are computed in this one place, one way (numpy's median and its default,
linearly interpolated, percentile), so that figures of different benchmarks compare.
The benchmarks run as ``python bench/NAME.py``, so this folder is ``sys.path[0]`` and they
import it as ``from summary import median_p99``.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
from numpy.typing import ArrayLike


def median_p99(samples: ArrayLike, unit: str) -> dict[str, float]:
    """Median and 99th percentile of ``samples``, keyed ``median_<unit>`` and ``p99_<unit>``.

    ``samples`` are already in ``unit`` (e.g. ``"ms"``, ``"us"``); ``unit`` only names the
    keys.  Raises ``ValueError`` if there are no samples.
    """
    a = np.asarray(samples, dtype=float).ravel()
    if a.size == 0:
        raise ValueError(f"median_p99: no samples to summarise (unit {unit!r})")
    return {f"median_{unit}": float(np.median(a)), f"p99_{unit}": float(np.percentile(a, 99))}


def cpu_model() -> str:
    """The CPU the figures were measured on (``/proc/cpuinfo``'s model name, and the count
    of CPUs this process may use): figures of different machines do not compare."""
    import os

    try:
        with open("/proc/cpuinfo") as f:
            name = next((line.split(":", 1)[1].strip() for line in f
                         if line.startswith("model name")), "unknown")
    except OSError:
        name = "unknown"
    return f"{name} ({len(os.sched_getaffinity(0))} CPUs)"


def report(figures: dict[str, object], as_json: bool) -> None:
    """Print a benchmark's figures one per line (floats to 3 decimals) and, with
    ``as_json``, all of them as one JSON object on the last line (``--json``)."""
    for k, v in figures.items():
        print(f"{k:40s} {v:.3f}" if isinstance(v, float) else f"{k:40s} {v}")
    if as_json:
        print(json.dumps(figures))


def contour_centroids(img: np.ndarray, threshold: float, dark_level: float,
                      min_area: int = 0) -> np.ndarray:
    """The plain OpenCV anchor of the blob and dot detectors: findContours on the
    thresholded image, each contour's intensity centroid above the dark level."""
    _, mask = cv2.threshold(img, threshold, 255, cv2.THRESH_BINARY)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        x, y, w, h = cv2.boundingRect(c)
        roi = img[y:y + h, x:x + w].astype(np.float32) - dark_level
        roi[mask[y:y + h, x:x + w] == 0] = 0
        m = cv2.moments(roi)
        if m["m00"] > 0 and cv2.countNonZero(mask[y:y + h, x:x + w]) >= min_area:
            out.append((x + m["m10"] / m["m00"], y + m["m01"] / m["m00"]))
    return np.array(out).reshape(-1, 2)

