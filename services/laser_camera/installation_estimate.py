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

import numpy as np

from agent.errors import InvalidInputError


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
        self._mean = np.zeros(0)
        self._cov = np.zeros((0, 0))
        self.accepted = 0
        self.refused = 0

    def _columns(self, names: list[str]) -> np.ndarray:
        """The state indices of ``names``, adding unseen ones at their prior."""
        new = [n for n in names if n not in self._index]
        if new:
            m, k = len(self.names), len(new)
            for n in new:
                self._index[n] = len(self.names)
                self.names.append(n)
            cov = np.eye(m + k)
            cov[:m, :m] = self._cov
            self._cov = cov
            self._mean = np.concatenate([self._mean, np.zeros(k)])
        return np.array([self._index[n] for n in names], dtype=int)

    def _innovation(self, z: np.ndarray, noise: np.ndarray, names: list[str], H: np.ndarray,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The state indices, every parameter's covariance with ``z`` (``P H^T``, (M, 2)),
        ``z``'s residual ``z - H mean`` and its covariance ``H P H^T + noise``."""
        idx = self._columns(names)
        v = z - H @ self._mean[idx]
        PHt = self._cov[:, idx] @ H.T
        return idx, PHt, v, H @ PHt[idx] + noise

    def innovation_chi2(self, z: np.ndarray, noise: np.ndarray, names: list[str],
                        H: np.ndarray) -> float:
        """Chi-square (2 dof) of ``z`` against what the estimate so far predicts for it
        (``update``'s gate, without taking it); NaN for a non-finite ``z``."""
        _, _, v, S = self._innovation(np.asarray(z, float), noise, names, np.asarray(H, float))
        return float(v @ np.linalg.solve(S, v))

    def update(self, z: np.ndarray, noise: np.ndarray, names: list[str], H: np.ndarray,
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
        _, PHt, v, S = self._innovation(z, noise, names, np.asarray(H, float))
        if not float(v @ np.linalg.solve(S, v)) <= self.gate_chi2:  # NaN: refused too
            self.refused += 1
            return False
        K = np.linalg.solve(S, PHt.T).T
        self._mean += K @ v
        # Joseph-free form, symmetrised: the gain is optimal and the update rank 2
        self._cov -= K @ PHt.T
        self._cov = 0.5 * (self._cov + self._cov.T)
        self.accepted += 1
        return True

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
