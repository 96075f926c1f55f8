"""The time series of one measured edge: a bounded buffer of samples and where ``t`` falls.

The buffer answers "which two samples bracket ``t``, and how far between them": the
interpolation itself is done by the plan's kernel (:mod:`agent.srg.kernel`) on plain floats,
because per-call numpy overhead on 3- and 4-vectors costs more than the arithmetic; a
sample is therefore kept as one tuple of 7 floats, not as arrays.  ``t`` outside the
samples is extrapolated with a constant-velocity model (the same bracket, with a factor
outside [0, 1]) up to a limit, and refused beyond it with an error that says whether the
data for ``t`` was already dropped or has not arrived yet.
"""

from __future__ import annotations

from bisect import bisect_left

import numpy as np

from agent.errors import InvalidInputError
from agent.srg.errors import DataNotYetArrivedError, DataTooOldError, NoSamplesError

#: (index of the first sample, index of the second, factor, extrapolated seconds)
Bracket = tuple[int, int, float, float]


class SampleBuffer:
    """Samples of one edge ordered by time, at most ``max_samples`` and ``buffer_s`` long."""

    __slots__ = ("buffer_ns", "covs", "deltas", "max_samples", "name", "times", "values",
                 "with_cov")

    def __init__(self, name: str, buffer_s: float, max_samples: int) -> None:
        if not buffer_s > 0:
            raise InvalidInputError(f"buffer_s must be > 0, got {buffer_s!r}")
        if max_samples < 2:
            raise InvalidInputError(f"max_samples must be >= 2, got {max_samples!r}")
        self.name = name
        self.buffer_ns = int(buffer_s * 1e9)
        self.max_samples = max_samples
        # The lists are only ever changed in place: compiled plans hold references to them.
        self.times: list[int] = []
        #: (px, py, pz, qx, qy, qz, qw) of each sample
        self.values: list[tuple[float, ...]] = []
        self.covs: list[np.ndarray | None] = []
        #: rotation vector from sample i to sample i + 1 (slerp's log), filled on first use
        self.deltas: list[tuple[float, float, float] | None] = []
        #: how many samples carry a covariance (none: a plan skips looking for them)
        self.with_cov = 0

    def __len__(self) -> int:
        return len(self.times)

    @property
    def newest_ns(self) -> int | None:
        return self.times[-1] if self.times else None

    def add(self, t_ns: int, p: np.ndarray, q: np.ndarray, cov: np.ndarray | None) -> None:
        """Insert a sample; a sample at an existing time replaces it (a re-send)."""
        self.add_value(t_ns, tuple(p.tolist() + q.tolist()), cov)

    def add_value(self, t_ns: int, value: tuple[float, ...], cov: np.ndarray | None) -> None:
        """:meth:`add` of a sample's 7 floats (px, py, pz, qx, qy, qz, qw)."""
        times = self.times
        if not times or t_ns > times[-1]:
            times.append(t_ns)
            self.values.append(value)
            self.covs.append(cov)
            self.with_cov += cov is not None
            self.deltas.append(None)
            self._trim()
            return
        i = bisect_left(times, t_ns)
        if times[i] == t_ns:
            self.with_cov += (cov is not None) - (self.covs[i] is not None)
            self.values[i], self.covs[i] = value, cov
            self.deltas[i] = None
            if i:
                self.deltas[i - 1] = None
            return
        if t_ns < times[-1] - self.buffer_ns:
            return  # older than what the buffer keeps: it would be dropped at once
        times.insert(i, t_ns)
        self.values.insert(i, value)
        self.covs.insert(i, cov)
        self.with_cov += cov is not None
        self.deltas.insert(i, None)
        if i:
            self.deltas[i - 1] = None
        self._trim()

    def _trim(self) -> None:
        """Drop samples beyond the bounds, in batches (amortised O(1) per sample)."""
        times = self.times
        excess = len(times) - self.max_samples
        if excess <= 0 and times[0] >= times[-1] - self.buffer_ns - self.buffer_ns // 4:
            return
        cut = max(excess, bisect_left(times, times[-1] - self.buffer_ns))
        if cut > 0:
            if self.with_cov:
                self.with_cov -= sum(c is not None for c in self.covs[:cut])
            del times[:cut], self.values[:cut], self.covs[:cut], self.deltas[:cut]

    def bracket(self, t_ns: int, limit_s: float) -> Bracket:
        """The two samples around ``t`` and the interpolation factor between them.

        Raises ``NoSamplesError``, ``DataTooOldError`` or ``DataNotYetArrivedError``
        (``limit_s`` is how far beyond the samples constant-velocity extrapolation goes).
        """
        times = self.times
        n = len(times)
        if n == 0:
            raise NoSamplesError(self.name, t_ns)
        last = times[-1]
        if t_ns >= last:
            if t_ns == last:
                return n - 1, n - 1, 0.0, 0.0
            ahead = (t_ns - last) * 1e-9
            if ahead > limit_s:
                raise DataNotYetArrivedError(self.name, t_ns, last, limit_s)
            if n == 1:
                return 0, 0, 0.0, ahead
            t0 = times[-2]
            return n - 2, n - 1, (t_ns - t0) / (last - t0), ahead
        first = times[0]
        if t_ns < last - self.buffer_ns:
            raise DataTooOldError(self.name, t_ns, max(first, last - self.buffer_ns),
                             self.buffer_ns / 1e9)
        if t_ns <= first:
            if t_ns == first:
                return 0, 0, 0.0, 0.0
            behind = (first - t_ns) * 1e-9
            if behind > limit_s:
                raise DataTooOldError(self.name, t_ns, first, self.buffer_ns / 1e9)
            if n == 1:
                return 0, 0, 0.0, behind
            return 0, 1, (t_ns - first) / (times[1] - first), behind
        i = bisect_left(times, t_ns)
        t1 = times[i]
        if t1 == t_ns:
            return i, i, 0.0, 0.0
        t0 = times[i - 1]
        return i - 1, i, (t_ns - t0) / (t1 - t0), 0.0
