"""Is a reported covariance honest?  NEES of a run and the 95 % band of its mean.

The mean NEES of k independent d-dof errors lies in ``chi2(d k) / k``'s 95 % interval when
the covariance is honest.  A tracker's errors are not independent from frame to frame:
the installation's imperfections (a housing's beam errors, a bent screen, a camera turned
since calibration) hold for a whole run.  The errors' autocorrelation, taken about zero --
the mean an honest, unbiased tracker's error has, so that an error which stays the same
for the whole run counts as the single sample it is -- gives the effective number of
independent samples ``k = n / tau`` (``tau`` the largest integrated autocorrelation time
of the error's components, Geyer's initial positive sequence).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.stats import chi2


def nees_figures(errors: np.ndarray, covariances: np.ndarray) -> dict[str, Any]:
    """Errors (n, d) with their covariances (n, d, d): mean NEES, its 95 % band for the
    effective sample count, the share of single NEES inside chi2(d)'s two-sided 95 %
    interval (0.95 when honest), and whether the mean lies inside its band."""
    e = np.asarray(errors, float)
    n, d = e.shape
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(covariances, e[..., None])[..., 0])
    tau = max(autocorrelation_time_about_zero(e[:, j]) for j in range(d))
    k = n / tau
    lo, hi = (float(x) for x in chi2.ppf([0.025, 0.975], d * k) / k)
    lo_1, hi_1 = chi2.ppf([0.025, 0.975], d)
    mean = float(np.mean(nees))
    return {"mean": round(mean, 3), "dof": d, "effective_samples": round(k, 2),
            "bounds_95": [round(lo, 3), round(hi, 3)],
            "share_inside_single_95": round(float(np.mean((nees >= lo_1) & (nees <= hi_1))), 4),
            "within_bounds": bool(lo <= mean <= hi)}


def autocorrelation_time_about_zero(x: np.ndarray) -> float:
    """Integrated autocorrelation time (samples, 1..n) of a series whose mean should be 0:
    ``1 + 2 sum rho_k`` with the autocorrelation taken about zero, summed over pairs
    ``rho_2m + rho_2m+1`` while they stay positive."""
    x = np.asarray(x, float)
    n = x.size
    if n < 4 or not np.any(x):
        return 1.0
    f = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n] / (n - np.arange(n))  # unbiased per lag
    rho = acf / acf[0]
    tau = -1.0
    for m in range(n // 2):
        pair = rho[2 * m] + rho[2 * m + 1]
        if pair <= 0:
            break
        tau += 2.0 * pair
    return float(min(max(1.0, tau), n))
