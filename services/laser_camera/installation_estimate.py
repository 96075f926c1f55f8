"""The installation's errors estimated online from the fourth beam's miss.

Four dots on their walls hold eight coordinates for the pose's six; the two left over,
where the fourth dot lies off beam 4 of the pose the other three fix (the miss), are
mostly the installation's error: the housing's beams, the screens' bend, the cameras' turn
since calibration and each camera's screen map, all held for the whole run.  Each frame set
sees that error through another geometry, so frame set by frame set the misses pin down
the parameters the dots move with, and each pose can be corrected by what is known so far.

``InstallationEstimate`` is a Kalman filter over named parameters, each in units of
its own standard deviation with a prior N(0, 1), so a parameter no miss has seen yet keeps
its tolerance and a pose that depends on it keeps its covariance.  A frame set enters as
its miss, the miss's noise and its sensitivity to every parameter; a miss that the estimate
so far does not explain within its covariance (chi-square, 2 dof) is refused, not absorbed:
a stray blob or a clipped spot moves one frame set's miss, not the installation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from agent.errors import InvalidInputError
from agent.runtime import compiled_twin


class InstallationEstimate:
    """Held parameters (each N(0, 1) a priori, in units of its tolerance) estimated from
    linear observations ``z = H theta + noise``: the fourth beam's misses.

    Kept as mean and covariance, each observation a rank-2 Kalman update touching the
    parameters it sees: a run holds some 90 parameters and an update costs tens of
    microseconds, where inverting an information matrix of that size each frame set costs
    a millisecond."""

    def __init__(self, gate_chi2: float):
        if not gate_chi2 > 0:
            raise InvalidInputError("the estimate's chi-square gate must be positive")
        self.gate_chi2 = gate_chi2
        self.names: list[str] = []
        self._index: dict[str, int] = {}
        #: the state indices of each sequence of names asked for (``_columns``): a tracker
        #: asks for the same few dozen names, in the same order, frame set after frame set
        self._indices: dict[tuple[str, ...], np.ndarray] = {}
        self._mean = np.zeros(0)
        self._cov = np.zeros((0, 0))
        self._root: np.ndarray | None = None  # ``root``'s, until the covariance changes
        self.accepted = 0
        self.refused = 0

    def _columns(self, names: Sequence[str]) -> np.ndarray:
        """The state indices of ``names``, adding unseen ones at their prior (read-only:
        shared by every call with the same names; an estimate only appends parameters, so
        a name's index never changes)."""
        key = tuple(names)
        idx = self._indices.get(key)
        if idx is not None:
            return idx
        new = [n for n in dict.fromkeys(key) if n not in self._index]
        if new:
            m, k = len(self.names), len(new)
            for n in new:
                self._index[n] = len(self.names)
                self.names.append(n)
            cov = np.eye(m + k)
            cov[:m, :m] = self._cov
            self._cov = cov
            self._mean = np.concatenate([self._mean, np.zeros(k)])
            self._root = None
        idx = np.array([self._index[n] for n in key], dtype=int)
        idx.flags.writeable = False
        self._indices[key] = idx
        return idx

    def _innovation(self, z: np.ndarray, noise: np.ndarray, names: Sequence[str],
                    H: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The state indices, every parameter's covariance with ``z`` (``P H^T``, (M, 2)),
        ``z``'s residual ``z - H mean`` and its covariance ``H P H^T + noise``."""
        idx = self._columns(names)
        v = z - H @ self._mean[idx]
        PHt = self._cov[:, idx] @ H.T
        return idx, PHt, v, H @ PHt[idx] + noise

    def innovation_chi2(self, z: np.ndarray, noise: np.ndarray, names: Sequence[str],
                        H: np.ndarray) -> tuple[float, np.ndarray]:
        """Chi-square (2 dof) of ``z`` against what the estimate so far predicts for it
        (``update``'s gate, without taking it; NaN for a non-finite ``z`` or a residual
        covariance that is not positive definite, a ``noise`` that is not a covariance),
        and the covariance it is taken under (2, 2): what a change of ``z`` must exceed to
        show."""
        if KERNELS is not None:
            S = np.empty((2, 2))
            chi2 = self._kalman(z, noise, names, H, S, -math.inf)
            return chi2, S
        _, _, v, S = self._innovation(np.asarray(z, float), noise, names, np.asarray(H, float))
        return _chi2(v, _covariance_inverse2(S)), S

    def update(self, z: np.ndarray, noise: np.ndarray, names: Sequence[str], H: np.ndarray,
               ) -> bool:
        """Take the observation ``z`` (its ``noise`` covariance; ``H`` (2, len(names)): dz
        per one std of each named parameter, one column each) if its innovation passes the
        gate; whether it did.  Names and one array, not a dict of columns: the tracker
        builds ``H`` as one array product, and a dict taken apart again each frame set
        costs more than the update's arithmetic."""
        z = np.asarray(z, float)
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(noise))):
            self.refused += 1
            return False
        if KERNELS is not None:  # the same steps, compiled
            taken = self._kalman(z, noise, names, H, np.empty((2, 2)), self.gate_chi2) \
                <= self.gate_chi2  # NaN: refused too
        else:
            taken = self._take(z, noise, names, np.asarray(H, float))
        if taken:
            self._root = None
            self.accepted += 1
        else:
            self.refused += 1
        return taken

    def _take(self, z: np.ndarray, noise: np.ndarray, names: Sequence[str],
              H: np.ndarray) -> bool:
        """``update``'s gate and update in numpy: whether ``z`` passed and was taken."""
        _, PHt, v, S = self._innovation(z, noise, names, H)
        Sinv = _covariance_inverse2(S)
        if not _chi2(v, Sinv) <= self.gate_chi2:  # NaN: refused too
            return False
        self._mean += PHt @ Sinv.T @ v
        # Joseph-free form (the gain is optimal), its rank-2 part P H^T S^-1 H P taken as
        # Y Y^T (Y = P H^T G, G G^T = S^-1): a product with its own transpose is exactly
        # symmetric, so the covariance stays so without a pass to symmetrise it
        Y = PHt @ _root2(Sinv)
        self._cov -= Y @ Y.T
        return True

    def _kalman(self, z: np.ndarray, noise: np.ndarray, names: Sequence[str], H: np.ndarray,
                S: np.ndarray, gate: float) -> float:
        """The compiled innovation (its covariance into ``S``) and its chi-square, the
        update taken in place where that is at most ``gate``.  The kernel reads contiguous
        float64 buffers only: ``z``, ``H`` and ``noise`` are made so, as numpy takes any."""
        idx = self._columns(names)  # first: a new name grows the mean and covariance
        return KERNELS.kalman(idx, np.ascontiguousarray(H, float), np.ascontiguousarray(z, float),
                              np.ascontiguousarray(noise, float), self._cov, self._mean, S, gate)

    def rows(self, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The state indices of ``names`` (adding unseen ones at their prior), their
        estimate and their rows of the whole covariance (len(names), len(self.names)): a
        pose corrected by the estimate takes its own parameters' covariance and their
        covariance with every parameter from the same rows."""
        idx = self._columns(names)
        return idx, self._mean[idx], self._cov[idx]

    def root(self) -> np.ndarray:
        """``L`` with ``L L^T`` the whole remaining covariance (``names``' order), lower
        triangular (Cholesky) where rounding leaves the covariance positive definite;
        kept until the covariance changes (a refused miss leaves it as it was)."""
        if self._root is None:
            try:
                self._root = np.linalg.cholesky(self._cov)
            except np.linalg.LinAlgError:  # a parameter pinned down to 1e-8 of its tolerance
                w, V = np.linalg.eigh(self._cov)
                self._root = V * np.sqrt(np.maximum(w, 0.0))
        return self._root

    def mean(self, names: list[str]) -> np.ndarray:
        """The estimate of each named parameter (in stds; 0 if never seen)."""
        return np.array([self._mean[self._index[n]] if n in self._index else 0.0
                         for n in names])

    def covariance(self, names: list[str]) -> np.ndarray:
        """The estimate's remaining covariance over ``names`` (identity where unseen)."""
        if names == self.names:
            return self._cov.copy()
        idx = self._columns(names)
        return self._cov[np.ix_(idx, idx)]

    def std(self, name: str) -> float:
        """The remaining standard deviation of one parameter (1 if never seen)."""
        i = self._index.get(name)
        return 1.0 if i is None else float(np.sqrt(self._cov[i, i]))


#: the compiled twin of the innovation and update (None: the numpy code runs)
KERNELS: Any = compiled_twin("services.laser_camera._kernels", "UMA_LASER_PURE_PYTHON")


def _covariance_inverse2(S: np.ndarray) -> np.ndarray:
    """The inverse of a 2 x 2 covariance in closed form; NaN throughout where it is not
    positive definite or not finite, so the chi-square from it is NaN and the gate refuses:
    an update through an indefinite ``S`` would grow the covariance (and ``_root2`` has no
    real root of it).  ``np.linalg.solve`` on a 2 x 2 costs more in its argument handling
    than the arithmetic."""
    (a, b), (c, d) = S.tolist()
    det = a * d - b * c
    if not (a > 0.0 and det > 0.0 and math.isfinite(det)):
        return np.full((2, 2), np.nan)
    return np.array([[d, -b], [-c, a]]) / det


def _root2(A: np.ndarray) -> np.ndarray:
    """``G`` lower triangular with ``G G^T`` the symmetric part of a positive definite 2 x 2
    matrix ``A`` (Cholesky, in closed form)."""
    (a, b), (c, d) = A.tolist()
    g00 = math.sqrt(a)
    g10 = 0.5 * (b + c) / g00
    return np.array([[g00, 0.0], [g10, math.sqrt(max(d - g10 * g10, 0.0))]])


def _chi2(v: np.ndarray, Sinv: np.ndarray) -> float:
    """``v^T S^-1 v`` of a residual ``v`` (2,) given ``S^-1``."""
    return float(v @ Sinv @ v)
