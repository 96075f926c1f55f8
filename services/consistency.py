"""Is a reported covariance honest?  NEES of a run and the 95 % band of its mean.

The mean NEES of k independent d-dof errors lies in ``chi2(d k) / k``'s 95 % interval when
the covariance is honest.  A tracker's errors are not independent from frame to frame:
the installation's imperfections (a housing's beam errors, a bent screen, a camera turned
since calibration) hold for a whole run.  The errors' autocorrelation, taken about zero --
the mean an honest, unbiased tracker's error has, so that an error which stays the same
for the whole run counts as the single sample it is -- gives the effective number of
independent samples ``k = n / tau`` (``tau`` the largest integrated autocorrelation time
of the error's components, Geyer's initial positive sequence).

Runs that share an error known only through its covariance -- every dead-reckoning run of
one calibration shares that calibration's error -- are dependent in a way the reported
covariances describe exactly: ``shared_error_effective_runs`` takes the variance of the
runs' mean NEES from them, and the band is the chi-square with the same mean and variance
(Satterthwaite, "An approximate distribution of estimates of variance components",
Biometrics Bulletin 1946).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.stats import chi2

from agent.errors import InvalidInputError


def nees_figures(errors: np.ndarray, covariances: np.ndarray) -> dict[str, Any]:
    """Errors (n, d) with their covariances (n, d, d): mean NEES, its 95 % band for the
    effective sample count, the share of single NEES inside chi2(d)'s two-sided 95 %
    interval (0.95 when honest), and whether the mean lies inside its band."""
    e = np.asarray(errors, float)
    n, d = e.shape
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(covariances, e[..., None])[..., 0])
    tau = max(autocorrelation_time(e[:, j], about="zero") for j in range(d))
    k = n / tau
    lo, hi = mean_nees_band_95(d, k)
    lo_1, hi_1 = chi2.ppf([0.025, 0.975], d)
    mean = float(np.mean(nees))
    return {"mean": round(mean, 3), "dof": d, "effective_samples": round(k, 2),
            "bounds_95": [round(lo, 3), round(hi, 3)],
            "share_inside_single_95": round(float(np.mean((nees >= lo_1) & (nees <= hi_1))), 4),
            "within_bounds": bool(lo <= mean <= hi)}


def mean_nees_band_95(dof: int, effective_samples: float) -> tuple[float, float]:
    """The 95 % interval of the mean NEES of ``effective_samples`` independent ``dof``-dof
    errors with honest covariances: ``chi2(dof k) / k``'s 2.5 % and 97.5 % quantiles."""
    k = float(effective_samples)
    lo, hi = chi2.ppf([0.025, 0.975], dof * k) / k
    return float(lo), float(hi)


def shared_error_effective_runs(covariances: np.ndarray, sensitivities: np.ndarray,
                                shared_cov: np.ndarray) -> float:
    """Effective number of independent runs in the mean NEES of runs whose errors
    ``y_r = S_r c + n_r`` share one draw ``c ~ N(0, shared_cov)`` (m-dim) on top of
    independent ``n_r``, each reported with its full covariance ``covariances[r]``
    (d x d, ``S_r shared_cov S_r^T`` included); ``sensitivities`` are the ``S_r`` (n, d, m).

    The mean NEES is a Gaussian quadratic form: with ``W_r`` the inverse covariances,
    ``Var(sum_r y_r^T W_r y_r) = 2 sum_{r,s} tr(W_r K_rs W_s K_sr)`` (``K_rs`` the
    cross-covariances), which is ``2 d`` per run plus, between runs,
    ``2 sum_{r != s} tr(U_r C U_s C)`` with ``U_r = S_r^T W_r S_r``.  Returned is the
    ``k`` for which ``chi2(d k) / k`` has that variance (``n`` when nothing is shared):
    the shared part counts once, not once per run.
    """
    cov = np.asarray(covariances, float)
    S = np.asarray(sensitivities, float)
    C = np.asarray(shared_cov, float)
    n, d = cov.shape[:2]
    WS = np.linalg.solve(cov, S)  # (n, d, m)
    V = np.einsum("rdi,rdj,jk->rik", S, WS, C)  # U_r C
    T = V.sum(axis=0)
    between = np.einsum("ij,ji->", T, T) - np.einsum("rij,rji->", V, V)
    var_sum = 2.0 * d * n + 2.0 * between
    return float(2.0 * d * n * n / var_sum)


def shared_error_nees_figures(nees: np.ndarray, covariances: np.ndarray,
                              sensitivities: np.ndarray, shared_cov: np.ndarray | None,
                              ) -> dict[str, Any]:
    """Mean NEES of runs (``nees``, each with its full ``covariances``) that share an error
    (``sensitivities``, ``shared_cov``: see ``shared_error_effective_runs``; None: nothing
    shared) against the 95 % band that counts the shared error once, and against the
    narrower band of as many independent runs."""
    nees = np.asarray(nees, float)
    n, d = np.shape(covariances)[:2]
    k = float(n) if shared_cov is None else shared_error_effective_runs(
        covariances, sensitivities, shared_cov)
    mean = float(nees.mean())
    lo, hi = mean_nees_band_95(d, k)
    lo_i, hi_i = mean_nees_band_95(d, n)
    return {"mean": mean, "effective_runs": k, "bounds_95": [lo, hi],
            "within_bounds": bool(lo <= mean <= hi),
            "bounds_95_independent_runs": [lo_i, hi_i],
            "within_bounds_independent_runs": bool(lo_i <= mean <= hi_i)}


def autocorrelation_time(x: np.ndarray, about: str) -> float:
    """Integrated autocorrelation time (samples, 1..n) of a series: ``1 + 2 sum rho_k``,
    summed over pairs ``rho_2m + rho_2m+1`` while they stay positive (Geyer's initial
    positive sequence, which stops before the noisy tail of the estimate takes over).

    ``about="zero"``: for errors whose mean should be 0, taken about zero, each lag's
    products averaged over the ``n - k`` of them, so that an error which stays the same for
    the whole run keeps ``rho_k`` at 1 and counts as the single sample it is.
    ``about="mean"``: for fluctuations about the series' own mean (a NEES series, whose
    mean is what is being judged), centred first and with the usual ``1/n`` weighting of
    every lag, whose tapering keeps the sequence positive definite as Geyer's rule needs.
    """
    if about not in ("zero", "mean"):
        raise InvalidInputError(f"about must be 'zero' or 'mean', got {about!r}")
    x = np.asarray(x, float)
    n = x.size
    if about == "mean":
        x = x - np.mean(x)
    if n < 4 or not np.any(x):
        return 1.0
    f = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n]
    if about == "zero":
        acf = acf / (n - np.arange(n))  # unbiased per lag
    rho = acf / acf[0]
    tau = -1.0  # rho_0 counted once: 1 + 2 * sum_{k>=1} = 2 * sum_{k>=0} - 1
    for m in range(n // 2):
        pair = rho[2 * m] + rho[2 * m + 1]
        if pair <= 0:
            break
        tau += 2.0 * pair
    return float(min(max(1.0, tau), n))
