"""A pose stream's own noise at the alignment's stations (``PoseSeries.noise_at``): each
sample's covariance less its systematic part, and between two samples the noise the
interpolated pose has of them, which is less than either's."""

from __future__ import annotations

import numpy as np

from agent import geometry as geo
from services.alignment.covariance import moved_poses
from services.alignment.timesync import PoseSeries


def _covariances(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    """``n`` random positive definite 6 x 6 covariances, ``scale`` their size."""
    A = rng.normal(size=(n, 6, 6)) * scale
    return A @ np.swapaxes(A, 1, 2) + scale ** 2 * np.eye(6)


def _series(rng: np.random.Generator, systematic: bool = True) -> PoseSeries:
    """Two samples 33 ms apart, 2 cm and 3 degrees from each other, 1.5 m from the origin
    (where a rotation's error moves the position most), each with its own covariance and a
    smaller systematic part."""
    p = np.array([[1.2, -0.8, 0.4], [1.215, -0.79, 0.41]])
    q = np.array([geo.rotvec_to_quat([0.1, -0.2, 0.3]), geo.rotvec_to_quat([0.12, -0.19, 0.33])])
    own = _covariances(rng, 2, 1e-3)
    held = _covariances(rng, 2, 3e-4)
    return PoseSeries(np.array([0.0, 1 / 30]), p, q, "a", own + held,
                      systematic=held if systematic else None)


def test_at_a_sample_the_noise_is_its_covariance_less_its_systematic_part() -> None:
    s = _series(np.random.default_rng(1))
    own = s.covariance - s.systematic
    assert np.array_equal(s.noise_at(s.t), own)
    middle = s.noise_at(np.array([s.t.mean()]))[0]
    assert np.allclose(middle, 0.25 * (own[0] + own[1]), rtol=1e-12, atol=0)
    assert _series(np.random.default_rng(1), systematic=False).noise_at(s.t) is None
    assert PoseSeries(s.t, s.position, s.quaternion).noise_at(s.t) is None


def test_between_samples_the_noise_is_the_interpolated_poses_spread() -> None:
    """Two samples drawn with independent noise of their own covariances, interpolated as
    ``at`` does: the interpolated pose's error spreads as ``noise_at`` says (its whitened
    covariance the identity within the draws' scatter), at a third of the way and midway,
    where weights taken once instead of squared would claim twice the spread."""
    rng = np.random.default_rng(2)
    s = _series(rng)
    own = s.covariance - s.systematic
    draws = 20000
    roots = np.linalg.cholesky(own)
    for alpha in (1 / 3, 0.5):
        t = np.array([alpha * s.t[1]])
        truth_p, truth_q, _ = s.at(t)
        ends = [moved_poses(np.repeat(s.position[k:k + 1], draws, 0),
                            np.repeat(s.quaternion[k:k + 1], draws, 0),
                            rng.normal(size=(draws, 6)) @ roots[k].T) for k in (0, 1)]
        p, q = geo.interpolate(*ends[0], *ends[1], np.full(draws, alpha))
        phi = geo.quat_to_rotvec(geo.quat_multiply(q, geo.quat_conjugate(truth_q)))
        e = np.concatenate([p - truth_p - np.cross(phi, truth_p), phi], axis=1)
        claimed = np.linalg.cholesky(s.noise_at(t)[0])
        white = np.linalg.solve(claimed, np.linalg.solve(claimed, e.T @ e / draws).T)
        assert np.all(np.abs(np.linalg.eigvalsh(white) - 1.0) < 0.1), alpha
