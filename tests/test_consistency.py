"""services.consistency: the autocorrelation time and shared errors behind NEES bands."""

import numpy as np
import pytest

from services.consistency import autocorrelation_time, shared_error_effective_runs


def _ar1(a: float, n: int, rng: np.random.Generator) -> np.ndarray:
    w = rng.standard_normal(n)
    x = np.empty_like(w)
    x[0] = w[0]
    for k in range(1, n):
        x[k] = a * x[k - 1] + w[k]
    return x


@pytest.mark.parametrize("about", ["mean", "zero"])
def test_autocorrelation_time_of_known_series(about):
    """White noise has tau = 1; an AR(1) series x_k = a x_k-1 + w_k has (1 + a) / (1 - a)."""
    rng = np.random.default_rng(3)
    assert autocorrelation_time(rng.standard_normal(20000), about) == pytest.approx(1.0, abs=0.1)
    a = 0.9
    assert autocorrelation_time(_ar1(a, 50000, rng), about) == pytest.approx((1 + a) / (1 - a),
                                                                            rel=0.15)


def test_a_constant_error_is_one_sample_about_zero_and_nothing_about_its_mean():
    """About zero, an error that holds for the whole run counts once (tau = n); about its
    own mean, a constant has nothing to correlate."""
    assert autocorrelation_time(np.full(10, 0.3), about="zero") == 10.0
    assert autocorrelation_time(np.ones(10), about="mean") == 1.0


def test_an_offset_makes_the_two_differ():
    """White noise on a constant offset: correlated for ever about zero, white about its
    mean."""
    x = 1.0 + np.random.default_rng(4).standard_normal(2000)
    assert autocorrelation_time(x, about="mean") == pytest.approx(1.0, abs=0.2)
    assert autocorrelation_time(x, about="zero") > 100


def test_about_must_be_named():
    with pytest.raises(ValueError, match="about must be 'zero' or 'mean'"):
        autocorrelation_time(np.ones(10), about="median")


def test_shared_error_effective_runs_matches_monte_carlo():
    """Runs sharing one Gaussian error: the variance of their mean NEES is that of
    chi2(d k) / k with the k returned (20 runs of 6 dof sharing a 5-dim error)."""
    rng = np.random.default_rng(0)
    n, d, m = 20, 6, 5
    S = 0.5 * rng.standard_normal((n, d, m))
    P = rng.uniform(0.5, 2.0, (n, d))
    C = np.diag(rng.uniform(0.5, 2.0, m))
    cov = np.einsum("ri,ij->rij", P, np.eye(d)) + np.einsum("rij,jk,rlk->ril", S, C, S)
    k = shared_error_effective_runs(cov, S, C)
    assert 1.0 < k < n
    assert shared_error_effective_runs(cov, np.zeros_like(S), C) == pytest.approx(n)
    draws = 4000
    c = rng.standard_normal((draws, m)) @ np.linalg.cholesky(C).T
    y = np.einsum("rij,tj->tri", S, c) + np.sqrt(P) * rng.standard_normal((draws, n, d))
    mean = np.einsum("tri,tri->t", y, np.linalg.solve(cov, y[..., None])[..., 0]) / n
    assert mean.mean() == pytest.approx(d, rel=0.05)
    assert mean.var() == pytest.approx(2 * d / k, rel=0.1)
