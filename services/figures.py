"""Figures of a series of errors or latencies, as the demo and the offline evaluations print
them: median, p99, RMS and max."""

from __future__ import annotations

import numpy as np


def error_stats(x: list[float] | np.ndarray, scale: float = 1.0) -> dict[str, float] | None:
    """``{median, p99, rms, max}`` of ``x * scale``; None for an empty series."""
    if len(x) == 0:
        return None
    a = np.asarray(x, dtype=float) * scale
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)),
            "rms": float(np.sqrt(np.mean(a * a))), "max": float(a.max())}
