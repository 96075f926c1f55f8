"""RANSAC outlier elimination for ``A X = X B`` (Klinker, Bauer 2005, §3.4.3,
"Eliminating Outliers").

Hypotheses come from random minimal samples of two motions (as many as an all-inlier
sample needs at 99.9 % confidence, at least 50, at most ``iterations``); each is scored by
the median of the pairs' misfits (least median of squares), which needs no noise
threshold from the user and tolerates up to half of the motions being outliers.  The
consistent pairs are those whose misfit stays within ``threshold_factor`` times the median
misfit of the refit; X is then solved from them alone (the seed's step 4), twice, so the
final inlier set is judged against a fit that outliers did not pull.

A pair's misfit combines its two residuals into one length:
``sqrt(pos^2 + (L rot)^2)`` with ``L`` the median translation of the motions, the lever at
which a rotation error of the size ``rot`` displaces points by ``L rot``.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agent.errors import InvalidInputError
from services.alignment.solvers import (
    AlignmentError,
    DegenerateMotionError,
    MotionPairs,
    Pose,
    daniilidis,
    pair_residuals,
)

Solver = Callable[[MotionPairs], Pose]
_MIN_LEVER_M = 0.01
#: Floor of the misfit threshold, so noise-free data does not reject pairs over rounding.
_MIN_THRESHOLD_M = 1e-6


@dataclass(frozen=True)
class RansacResult:
    """The refit on the consistent pairs and which pairs those are."""

    pose: Pose
    inliers: np.ndarray  # bool (n,)
    threshold_m: float  # misfit threshold used (combined, metres)
    lever_m: float


def misfit(pairs: MotionPairs, x: Pose, lever_m: float) -> np.ndarray:
    """Combined residual of each pair in metres (module docstring)."""
    r = pair_residuals(pairs, x)
    return np.hypot(r.pos_m, lever_m * r.rot_rad)


def _iterations_needed(inlier_fraction: float, confidence: float = 0.999,
                       floor: int = 50) -> int:
    """Samples of two needed to draw an all-inlier sample with ``confidence`` (at least
    ``floor``: an all-inlier sample of two noisy motions is not yet a good hypothesis)."""
    p_good = min(max(inlier_fraction, 1e-3), 1.0 - 1e-9) ** 2
    return max(floor, int(np.ceil(np.log(1.0 - confidence) / np.log(1.0 - p_good))))


def ransac(pairs: MotionPairs, solver: Solver = daniilidis, iterations: int = 200,
           threshold_factor: float = 3.0, rng: np.random.Generator | None = None,
           refit: Solver | None = None) -> RansacResult:
    """Robust X from motion pairs that may contain outliers (module docstring).

    ``solver`` makes the hypotheses from two motions; ``refit`` (default: ``solver``)
    solves from the consistent pairs, e.g. a closed form followed by ``refine``.
    """
    refit = refit or solver
    n = len(pairs)
    if n < 3:
        raise AlignmentError(f"RANSAC needs at least 3 motion pairs, got {n}")
    if iterations < 1 or threshold_factor <= 0:
        raise InvalidInputError("RANSAC: iterations must be >= 1 and threshold_factor > 0")
    rng = rng if rng is not None else np.random.default_rng(0)
    lever = max(float(np.median(np.linalg.norm(pairs.pa, axis=-1))), _MIN_LEVER_M)
    best: Pose | None = None
    best_score = np.inf
    needed = iterations
    done = 0
    while done < min(iterations, needed):
        done += 1
        sample = rng.choice(n, size=2, replace=False)
        try:
            hypothesis = solver(pairs.subset(sample))
        except DegenerateMotionError:
            continue  # two motions about (nearly) parallel axes: no hypothesis
        e = misfit(pairs, hypothesis, lever)
        score = float(np.median(e))
        if score < best_score:
            best, best_score = hypothesis, score
            needed = _iterations_needed(float(np.mean(e <= threshold_factor * score)))
    if best is None:
        raise DegenerateMotionError(
            f"RANSAC: none of {iterations} samples of two motions had distinct rotation axes")
    pose, inliers, threshold = best, np.ones(n, dtype=bool), np.inf
    for _ in range(2):
        e = misfit(pairs, pose, lever)
        threshold = max(threshold_factor * float(np.median(e)), _MIN_THRESHOLD_M)
        inliers = e <= threshold
        if inliers.sum() < 2:
            raise AlignmentError(f"RANSAC: only {int(inliers.sum())} consistent motion pairs")
        pose = refit(pairs.subset(inliers))
    return RansacResult(pose, inliers, threshold, lever)
