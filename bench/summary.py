"""The one summary of timing samples that every benchmark reports.

Every benchmark here reports the same two figures of its samples, the median and the 99th
percentile; they are computed in this one place, one way (numpy's median and its default,
linearly interpolated, percentile), so that figures of different benchmarks compare.
The benchmarks run as ``python bench/NAME.py``, so this folder is ``sys.path[0]`` and they
import it as ``from summary import median_p99``.
"""

from __future__ import annotations

import json

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
