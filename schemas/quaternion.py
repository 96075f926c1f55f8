"""Unit quaternions (x, y, z, w) on the wire: how far a norm may be off, and the one check.

Light to import (no numpy, no pydantic): the pure geometry imports it too.
"""

from __future__ import annotations

import math

#: Largest accepted deviation of a quaternion's norm from 1 before it is refused, not
#: normalised. Rounding in text, float32 and msgpack stays far below it; a quaternion
#: off by more is a bug upstream and must not be silently repaired.
QUAT_NORM_TOL = 1e-3


def unit_norm(x: float, y: float, z: float, w: float) -> float:
    """The norm of a quaternion that is a unit one within ``QUAT_NORM_TOL`` (divide by it to
    renormalise); ``ValueError`` saying so otherwise."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(n - 1.0) > QUAT_NORM_TOL:
        raise ValueError(f"quaternion: norm {n:.6g} is not 1 (tolerance {QUAT_NORM_TOL:g}); "
                         "quaternions are x, y, z, w")
    return n
