"""Movement-pair selection (Klinker, Bauer 2005, §3.4.3, after Tsai-Lenz and Schmidt et al.).

Motions taken in temporal order differ little, and small rotations have axes dominated by
noise.  Two filters: the angle threshold ``theta <= alpha <= pi - theta`` (near pi the
rotation axis flips sign under noise and the dual quaternions of a and b may disagree in
sign), then Schmidt's axis criterion (eq. 3.12): keep the subset whose rotation axes are
least parallel, i.e. with the smallest sum of ``|a_ij . a_kl|``.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.alignment.solvers import MotionPairs, axis_spread

#: Default angle threshold of the preselection (Klinker, Bauer 2005: "a threshold angle theta").
DEFAULT_MIN_ANGLE_RAD = np.radians(5.0)


def angle_mask(pairs: MotionPairs, min_angle_rad: float = DEFAULT_MIN_ANGLE_RAD) -> np.ndarray:
    """Motions whose rotation angle lies in ``[theta, pi - theta]`` (both sensors)."""
    if not 0.0 <= min_angle_rad < np.pi / 2:
        raise ValueError(f"min_angle_rad must lie in [0, pi/2), got {min_angle_rad!r}")
    ok = np.ones(len(pairs), dtype=bool)
    for q in (pairs.qa, pairs.qb):
        angle = 2.0 * np.arctan2(np.linalg.norm(q[:, :3], axis=-1), q[:, 3])
        ok &= (angle >= min_angle_rad) & (angle <= np.pi - min_angle_rad)
    return ok


def axis_criterion(axes: np.ndarray) -> float:
    """Schmidt's eq. 3.12 averaged: mean ``|a_i . a_j|`` over distinct pairs (0 is best)."""
    n = len(axes)
    if n < 2:
        return 1.0
    dots = np.abs(axes @ axes.T)
    return float((dots.sum() - np.trace(dots)) / (n * (n - 1)))


def greedy_axis_selection(axes: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` axes chosen greedily to keep the sum of ``|a_i . a_j|`` small.

    Exact minimisation of eq. 3.12 over subsets is combinatorial; adding at each step the
    axis least parallel (in sum) to those already chosen is the usual approximation.
    Starts from the axis least parallel to all others.
    """
    n = len(axes)
    if count >= n:
        return np.arange(n)
    dots = np.abs(axes @ axes.T)
    chosen = np.zeros(n, dtype=bool)
    load = np.zeros(n)  # sum of |a_i . a_j| over chosen j, for every candidate i
    first = int(np.argmin(dots.sum(axis=1)))
    order = [first]
    chosen[first] = True
    load += dots[first]
    for _ in range(count - 1):
        nxt = int(np.argmin(np.where(chosen, np.inf, load)))
        order.append(nxt)
        chosen[nxt] = True
        load += dots[nxt]
    return np.sort(np.array(order))


@dataclass(frozen=True)
class Selection:
    """Which motions were kept, and how well they condition X."""

    index: np.ndarray  # indices into the candidate motions
    candidates: int
    passed_angle: int
    axis_spread_rad: float
    axis_criterion: float


def select_pairs(pairs: MotionPairs, min_angle_rad: float = DEFAULT_MIN_ANGLE_RAD,
                 max_pairs: int | None = None) -> Selection:
    """Angle-threshold preselection, then (if more than ``max_pairs`` pass) eq. 3.12."""
    passed = np.flatnonzero(angle_mask(pairs, min_angle_rad))
    axes = pairs.axes_a[passed]
    keep = passed
    if max_pairs is not None and len(passed) > max_pairs:
        keep = passed[greedy_axis_selection(axes, max_pairs)]
        axes = pairs.axes_a[keep]
    return Selection(keep, len(pairs), len(passed), axis_spread(axes), axis_criterion(axes))
