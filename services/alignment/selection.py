"""Movement-pair selection (Klinker, Bauer 2005, §3.4.3, after Tsai-Lenz and Schmidt et al.).

Motions taken in temporal order differ little, and small rotations have axes dominated by
noise.  Two filters: the angle threshold ``theta <= alpha <= pi - theta`` (near pi the
rotation axis flips sign under noise and the dual quaternions of a and b may disagree in
sign), then Schmidt's axis criterion (eq. 3.12): keep the subset whose rotation axes are
least parallel, i.e. with the smallest sum of ``|a_ij . a_kl|``.

The threshold ``theta`` follows the noise unless given (``noise_angle_threshold``): a
motion's axis is noise only when its angle is comparable to the angle noise, and the
measured realistic installation showed that a fixed 5 degrees drops pairs that still carry
information (``noise_angle_threshold``'s docstring).

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent.errors import InvalidInputError
from services.alignment.solvers import MotionPairs, axis_spread

#: A fixed angle threshold (Klinker, Bauer 2005: "a threshold angle theta"): what the
#: service asks of motions before it solves (readiness), not the solver's selection.
DEFAULT_MIN_ANGLE_RAD = np.radians(5.0)
#: The noise-derived threshold is this many robust standard deviations of the angle noise.
NOISE_ANGLE_SIGMAS = 3.0


def noise_angle_threshold(pairs: MotionPairs, sigmas: float = NOISE_ANGLE_SIGMAS) -> float:
    """``sigmas`` times the robust std (1.4826 MAD about 0) of ``alpha_A - alpha_B``.

    Why: ``A = X B X^-1`` makes the two motions' rotation angles equal, so their
    difference is the pair's angle noise, measured without X (as Tsai and Lenz (1989) and
    Park and Martin (1994) use the invariance).  A motion's axis is noise only when its
    angle is within a few of those; the linear solvers' equations (Daniilidis' dual
    quaternions, Tsai-Lenz's modified Rodrigues vectors) have the same noise at every angle
    and small rotations add translation rows that constrain R_X, so a larger threshold only
    drops information.
    """
    d = _angles(pairs.qa) - _angles(pairs.qb)
    return float(min(sigmas * 1.4826 * np.median(np.abs(d)), np.pi / 2 - 1e-9))


def angle_threshold(pairs: MotionPairs, min_angle_rad: float | None) -> float:
    """``min_angle_rad`` as given, or the noise's threshold (``noise_angle_threshold``) if
    None."""
    return noise_angle_threshold(pairs) if min_angle_rad is None else min_angle_rad


def _angles(q: np.ndarray) -> np.ndarray:
    """Rotation angles (rad, [0, pi]) of canonical quaternions."""
    return 2.0 * np.arctan2(np.linalg.norm(q[:, :3], axis=-1), q[:, 3])


def angle_mask(pairs: MotionPairs, min_angle_rad: float = DEFAULT_MIN_ANGLE_RAD) -> np.ndarray:
    """Motions whose rotation angle lies in ``[theta, pi - theta]`` (both sensors)."""
    if not 0.0 <= min_angle_rad < np.pi / 2:
        raise InvalidInputError(f"min_angle_rad must lie in [0, pi/2), got {min_angle_rad!r}")
    ok = np.ones(len(pairs), dtype=bool)
    for q in (pairs.qa, pairs.qb):
        angle = _angles(q)
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
    min_angle_rad: float  # the angle threshold applied


def select_pairs(pairs: MotionPairs, min_angle_rad: float | None = None,
                 max_pairs: int | None = None) -> Selection:
    """Angle-threshold preselection, then (if more than ``max_pairs`` pass) eq. 3.12.

    ``min_angle_rad`` None: the threshold follows the noise (``noise_angle_threshold``).
    """
    min_angle_rad = angle_threshold(pairs, min_angle_rad)
    passed = np.flatnonzero(angle_mask(pairs, min_angle_rad))
    axes = pairs.axes_a[passed]
    keep = passed
    if max_pairs is not None and len(passed) > max_pairs:
        keep = passed[greedy_axis_selection(axes, max_pairs)]
        axes = pairs.axes_a[keep]
    return Selection(keep, len(pairs), len(passed), axis_spread(axes), axis_criterion(axes),
                     min_angle_rad)
