"""Pose streams, resampling at common times, and the coarse time offset between two trackers.

Two trackers stamp their samples with clocks that differ by a fixed offset (processing and
transport latency: tens to hundreds of ms).  Convention: ``offset_s`` is how much later b
stamps the same instant, ``t_b = t_a + offset_s``; pairs are formed from A at ``t`` and B
at ``t + offset_s``.

The angular speed ``|omega|`` of two rigidly connected bodies is the same at every instant
whatever their frames, so the cross-correlation of the two angular-speed signals peaks at
the offset.  That coarse estimate is refined jointly with X in ``pipeline`` by minimising
the ``A X = X B`` misfit over the offset.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.alignment.solvers import AlignmentError

#: Samples further apart than this are a gap; nothing is interpolated across it.
DEFAULT_MAX_GAP_S = 0.25
_CORRELATION_RATE_HZ = 1000.0
_GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0


@dataclass(frozen=True)
class PoseSeries:
    """A tracker's pose stream: times (s), positions (n, 3), xyzw quaternions (n, 4), and
    the covariances (n, 6, 6, geometry's convention) it published with them, if any.

    ``sensitivity`` (n, 6, m), if given: each pose's error (geometry's convention, as the
    covariance) per one standard deviation of each of m parameters that every sample
    shares (``parameters``, their names), e.g. an installation's tolerances.  The
    covariance includes their outer products; unlike it they say how the errors of two
    samples relate (``pipeline.shared_error_sensitivity``)."""

    t: np.ndarray
    position: np.ndarray
    quaternion: np.ndarray
    name: str = "stream"
    covariance: np.ndarray | None = None
    sensitivity: np.ndarray | None = None
    parameters: tuple[str, ...] = ()
    systematic: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float).reshape(-1)
        if not np.all(np.isfinite(t)):
            raise AlignmentError(f"{self.name}: non-finite timestamp")
        if len(t) < 2 or np.any(np.diff(t) <= 0):
            raise AlignmentError(f"{self.name}: needs >= 2 samples with strictly increasing "
                                 f"times, got {len(t)} samples")
        p = geo.check_vector(self.position, f"{self.name} position").reshape(-1, 3)
        q = geo.check_quaternion(self.quaternion, f"{self.name} quaternion").reshape(-1, 4)
        if not len(t) == len(p) == len(q):
            raise AlignmentError(f"{self.name}: {len(t)} times, {len(p)} positions, "
                                 f"{len(q)} quaternions; must be equal")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "quaternion", q)
        if self.covariance is not None:
            c = np.asarray(self.covariance, dtype=float)
            if c.shape != (len(t), 6, 6) or not np.all(np.isfinite(c)):
                raise AlignmentError(f"{self.name}: covariances must be {len(t)} finite 6x6 "
                                     f"matrices, got shape {c.shape}")
            object.__setattr__(self, "covariance", c)
        if self.sensitivity is not None:
            g = np.asarray(self.sensitivity, dtype=float)
            if (g.shape != (len(t), 6, len(self.parameters)) or not np.all(np.isfinite(g))
                    or self.covariance is None):
                raise AlignmentError(f"{self.name}: sensitivities must be {len(t)} finite 6 x "
                                     f"{len(self.parameters)} matrices (one column per "
                                     f"parameter) beside covariances, got shape {g.shape}")
            object.__setattr__(self, "sensitivity", g)
        if self.systematic is not None:
            c = np.asarray(self.systematic, dtype=float)
            if (c.shape != (len(t), 6, 6) or not np.all(np.isfinite(c))
                    or self.covariance is None):
                raise AlignmentError(f"{self.name}: systematic covariances must be {len(t)} "
                                     f"finite 6x6 matrices beside covariances, got shape "
                                     f"{c.shape}")
            object.__setattr__(self, "systematic", c)

    def __len__(self) -> int:
        return len(self.t)

    def at(self, times: np.ndarray, max_gap_s: float = DEFAULT_MAX_GAP_S,
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses at ``times`` (linear / slerp between the neighbouring samples).

        Returns positions, quaternions and a mask of the times that lie inside the stream
        and not in a gap; the poses at the other times are meaningless.
        """
        times = np.asarray(times, dtype=float).reshape(-1)
        k, alpha = self._bracket(times)
        valid = ((times >= self.t[0]) & (times <= self.t[-1])
                 & (self.t[k + 1] - self.t[k] <= max_gap_s))
        p, q = geo.interpolate(self.position[k], self.quaternion[k], self.position[k + 1],
                               self.quaternion[k + 1], alpha)
        return p, q, valid

    def noise_at(self, times: np.ndarray) -> np.ndarray | None:
        """The covariance (n, 6, 6) of each sample's own noise, its covariance less the
        ``systematic`` part, interpolated at ``times`` as ``at`` interpolates the poses:
        ``(1 - alpha)^2 C_k + alpha^2 C_k+1``.  None where the tracker does not say which
        part of its covariance persists: then its noise is unknown (``held_at`` holds the
        whole covariance, and X's covariance rests on the stations' bootstrap).

        Why: the noise of two samples is independent (what persists is the systematic
        part), so a pose interpolated between them has less of it than either sample, by
        the weights squared: two thirds on average between samples of equal noise."""
        if self.covariance is None or self.systematic is None:
            return None
        own = self.covariance - self.systematic
        k, alpha = self._bracket(np.asarray(times, dtype=float).reshape(-1))
        w = alpha[:, None, None]
        return (1.0 - w) ** 2 * own[k] + w ** 2 * own[k + 1]

    def _bracket(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The sample before each of ``times`` (the last but one at most) and the weight of
        the sample after it, in [0, 1]."""
        k = np.clip(np.searchsorted(self.t, times, side="right") - 1, 0, len(self.t) - 2)
        t0, t1 = self.t[k], self.t[k + 1]
        return k, np.clip((times - t0) / (t1 - t0), 0.0, 1.0)


    def covariance_at(self, times: np.ndarray) -> np.ndarray | None:
        """The published covariance of the sample nearest each of ``times`` (None if the
        stream has none): a covariance changes slowly, so no interpolation."""
        return None if self.covariance is None else self.covariance[self._nearest(times)]

    def held_at(self, times: np.ndarray) -> np.ndarray | None:
        """The part of the published covariance that persists from sample to sample, of the
        sample nearest each of ``times``: the ``systematic`` part where the tracker gives it,
        else the whole covariance (None if the stream has none).

        Why: a sample's own noise differs from station to station, so X's noise part
        counts it already (``noise_at``, or the stations' bootstrap); only an error that
        persists escapes it (``pipeline.held_error_covariance``)."""
        held = self.covariance if self.systematic is None else self.systematic
        return None if held is None else held[self._nearest(times)]

    def sensitivity_at(self, times: np.ndarray) -> np.ndarray | None:
        """The sensitivities of the sample nearest each of ``times`` (None if none)."""
        return None if self.sensitivity is None else self.sensitivity[self._nearest(times)]

    def _nearest(self, times: np.ndarray) -> np.ndarray:
        """Index of the sample nearest each of ``times``."""
        times = np.asarray(times, dtype=float).reshape(-1)
        k = np.clip(np.searchsorted(self.t, times), 1, len(self.t) - 1)
        return k - ((times - self.t[k - 1]) < (self.t[k] - times))


def angular_speed(series: PoseSeries) -> tuple[np.ndarray, np.ndarray]:
    """``|omega|`` (rad/s) between consecutive samples, stamped at their midpoints."""
    dt = np.diff(series.t)
    angle = geo.quat_angle(series.quaternion[:-1], series.quaternion[1:])
    return 0.5 * (series.t[:-1] + series.t[1:]), angle / dt


def coarse_offset(a: PoseSeries, b: PoseSeries, max_offset_s: float) -> tuple[float, float]:
    """Offset maximising the correlation of the angular speeds, and that correlation.

    Both speeds are resampled at 1 kHz on one grid (zero-mean, unit variance, zero outside
    their own stream) and correlated by FFT; the peak within ``[-max_offset_s,
    max_offset_s]`` is refined by a parabola through its neighbours.
    """
    if not max_offset_s > 0:
        raise InvalidInputError(f"max_offset_s must be positive, got {max_offset_s!r}")
    ta, wa = angular_speed(a)
    tb, wb = angular_speed(b)
    overlap = min(ta[-1], tb[-1]) - max(ta[0], tb[0])
    if overlap < 10 * max_offset_s:
        raise AlignmentError(
            f"{a.name} and {b.name} overlap for {max(overlap, 0.0):.3g} s; need at least "
            f"{10 * max_offset_s:.3g} s (10x the offset search range) to estimate the offset")
    step = 1.0 / _CORRELATION_RATE_HZ
    grid = np.arange(min(ta[0], tb[0]), max(ta[-1], tb[-1]), step)
    sa, sb = _standardised(grid, ta, wa), _standardised(grid, tb, wb)
    size = 1 << int(np.ceil(np.log2(2 * len(grid))))
    corr = np.fft.irfft(np.conj(np.fft.rfft(sa, size)) * np.fft.rfft(sb, size), size)
    max_lag = int(np.ceil(max_offset_s / step))
    lags = np.arange(-max_lag, max_lag + 1)
    scores = corr[lags % size] / (overlap / step)
    k = int(np.argmax(scores))
    shift = 0.0
    if 0 < k < len(lags) - 1:
        y0, y1, y2 = scores[k - 1: k + 2]
        denom = y0 - 2 * y1 + y2
        shift = 0.5 * (y0 - y2) / denom if denom < 0 else 0.0
    return float((lags[k] + shift) * step), float(scores[k])


def _standardised(grid: np.ndarray, t: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``w(t)`` on ``grid``, zero-mean and unit-variance inside ``t``'s span, 0 outside."""
    inside = (grid >= t[0]) & (grid <= t[-1])
    s = np.interp(grid, t, w)
    s = (s - s[inside].mean()) / (s[inside].std() + 1e-12)
    return np.where(inside, s, 0.0)


def golden_section(f: Callable[[float], float], lo: float, hi: float, tol: float,
                   ) -> float:
    """Minimiser of a unimodal ``f`` on ``[lo, hi]`` to within ``tol`` (golden section)."""
    c, d = hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo)
    fc, fd = f(c), f(d)
    while hi - lo > tol:
        if fc < fd:
            hi, d, fd = d, c, fc
            c = hi - _GOLDEN * (hi - lo)
            fc = f(c)
        else:
            lo, c, fc = c, d, fd
            d = lo + _GOLDEN * (hi - lo)
            fd = f(d)
    return 0.5 * (lo + hi)
