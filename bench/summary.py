"""The one summary of timing samples that every benchmark reports.

Every benchmark here reports the same two figures of its samples, the median and the 99th
percentile; they are computed in this one place, one way (numpy's median and its default,
linearly interpolated, percentile), so that figures of different benchmarks compare.
The benchmarks run as ``python bench/NAME.py``, so this folder is ``sys.path[0]`` and they
import it as ``from summary import median_p99``.
"""

from __future__ import annotations

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
    """The CPU the figures were measured on (``/proc/cpuinfo`` model name): absolute timings
    compare only on the same CPU, so every benchmark prints it next to its ratios."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"
