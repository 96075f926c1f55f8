"""The fusion eval's reset figure: after each (re)start the error must stay within the
error of the optical pose the filter started from plus what its covariance claims (its
99.73 % ellipsoid along the error); a start that runs away is reported as unbounded."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent import geometry as geo
from services.fusion import evaluate as fe
from services.fusion.ekf import FusionStats
from services.sim.trajectory import HeadTrajectory

RATE_HZ = 300.0


def recording(traj: HeadTrajectory, starts: list[float], drift_rad_s: float,
              std_rad: float = math.radians(0.2)) -> fe.Recording:
    """A run whose output follows the truth but turns away from it at ``drift_rad_s``
    after each start, claiming ``std_rad`` per axis; optical poses exact at 15 Hz."""
    t = np.arange(0.0, 6.0, 1 / RATE_HZ)
    p, q = traj.pose(t)
    since = t - np.array([max([s for s in starts if s <= x], default=0.0) for x in t])
    turn = np.zeros((t.size, 3))
    turn[:, 2] = drift_rad_s * since
    q_out = geo.quat_multiply(geo.rotvec_to_quat(turn), q)
    cov = np.tile(np.diag([1e-6] * 3 + [std_rad ** 2] * 3), (t.size, 1, 1))
    t_opt = np.arange(0.0, 6.0, 1 / fe.OPTICAL_HZ)
    p_opt, q_opt = traj.pose(t_opt)
    return fe.Recording(t, p, q_out, cov, p, q_out, t_opt, p_opt, q_opt, 0.0, FusionStats(),
                        {}, np.zeros(0), {}, np.array(starts))


def test_a_start_that_converges_is_bounded_and_one_that_runs_away_is_not() -> None:
    traj = HeadTrajectory(seed=1)
    calm = recording(traj, [0.1, 3.0], drift_rad_s=math.radians(0.05))
    f = fe.reset_figures(calm, traj)
    assert f["starts"] == 2 and f["bounded"], f
    assert f["worst_orientation_deg"] < 0.11 and f["worst_orientation_excess_deg"] < 0
    wild = recording(traj, [0.1, 3.0], drift_rad_s=math.radians(13))  # 26 deg in 2 s
    f = fe.reset_figures(wild, traj)
    assert not f["bounded"] and f["worst_orientation_deg"] > 20, f
    assert f["worst_orientation_excess_deg"] > 19
    assert not f["largest_axis_3_sigma"]["bounded"]


def test_the_bound_is_the_covariance_s_claim_along_the_error() -> None:
    """The covariance's 99.73 % ellipsoid, not a sphere of three of its largest axis's
    standard deviations: along the largest axis an error of 3.5 sigma is inside what the
    covariance claims (3.76 sigma) and beyond the sphere; along a small axis one of 5 of
    that axis's sigma is beyond the claim and well inside the sphere."""
    traj = HeadTrajectory(seed=1)
    sigma = np.radians([0.02, 0.02, 0.2])   # world axes: z the largest
    for axis, k, claim_ok in ((2, 3.5, True), (0, 5.0, False)):
        rec = recording(traj, [0.1], drift_rad_s=0.0)
        turn = np.zeros((rec.t.size, 3))
        turn[:, axis] = np.where(rec.t > 1.0, k * sigma[axis], 0.0)
        _, q = traj.pose(rec.t)
        rec.q[:] = geo.quat_multiply(geo.rotvec_to_quat(-turn), q)
        rec.cov[:, 3:, 3:] = np.diag(sigma**2)
        f = fe.reset_figures(rec, traj)
        assert f["bounded"] == claim_ok, f
        assert f["largest_axis_3_sigma"]["bounded"] == (k * sigma[axis] < 3 * sigma[2]), f


def test_a_gaussian_error_leaves_the_claim_at_its_rate_whatever_the_covariance() -> None:
    """``claim_reach`` is the reach of the ellipsoid chi-square(3) puts 99.73 % inside:
    errors drawn from their covariance lie beyond it 0.27 % of the time for round and
    flat covariances alike (the largest axis's 3 sigma: 0.27-2.9 %)."""
    rng = np.random.default_rng(11)
    n = 100_000
    for lam in ([1.0, 1.0, 1.0], [0.01, 0.3, 1.0], [1e-6, 1e-6, 1.0]):
        axes = np.linalg.qr(rng.standard_normal((3, 3)))[0]
        cov = axes @ np.diag(lam) @ axes.T
        e = rng.standard_normal((n, 3)) @ np.linalg.cholesky(cov).T
        beyond = np.linalg.norm(e, axis=1) > fe.claim_reach(e, np.broadcast_to(cov, (n, 3, 3)))
        assert np.mean(beyond) == pytest.approx(0.0027, abs=4 * math.sqrt(0.0027 / n))


def test_a_run_that_never_started_reports_no_reset() -> None:
    traj = HeadTrajectory(seed=1)
    rec = recording(traj, [], drift_rad_s=0.0)
    f = fe.reset_figures(rec, traj)
    assert f == {"starts": 0, "window_s": fe.RESET_WINDOW_S}


def test_the_gaussian_share_beyond_3_sigma_is_chi_square_for_a_3d_error() -> None:
    """The reference of the reset bound's test: 1-D's 0.27 % for one dominant axis,
    chi-square(3) beyond 9 (2.9 %) for three equal ones, and in between otherwise."""
    from scipy.stats import chi2

    lam = np.array([[1e-12, 1e-12, 1.0], [2.0, 2.0, 2.0], [0.3, 0.5, 1.0]])
    share = fe.gaussian_share_beyond_3_sigma(lam)
    assert share[0] == pytest.approx(chi2.sf(9.0, 1), rel=1e-3)
    assert share[1] == pytest.approx(chi2.sf(9.0, 3), rel=5e-3)
    z = np.random.default_rng(3).standard_normal((2_000_000, 3))
    assert share[2] == pytest.approx(np.mean(z**2 @ lam[2] > 9.0), rel=0.03)


def test_errors_heavier_than_their_covariance_show_beyond_3_sigma() -> None:
    """Errors drawn from their own covariance meet the Gaussian share; the same errors a
    fifth larger than the covariance claims lie beyond it several times as often."""
    rng = np.random.default_rng(5)
    n = 20_000
    axes = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    cov = np.broadcast_to(axes @ np.diag([0.2, 0.6, 1.0]) @ axes.T, (n, 3, 3))
    e = rng.standard_normal((n, 3)) @ np.linalg.cholesky(cov[0]).T
    honest = fe.beyond_3_sigma(e, cov)
    expected = honest["gaussian_share"]
    assert 0.004 < expected < 0.01
    assert honest["share"] == pytest.approx(expected, abs=4 * math.sqrt(expected / n))
    heavy = fe.beyond_3_sigma(1.2 * e, cov)
    assert heavy["gaussian_share"] == expected and heavy["share"] > 3 * expected


@pytest.mark.parametrize("rho", [0.6, 0.9, 0.95, 0.99, 1.0])
def test_the_gaussian_share_is_exact_for_every_ratio_of_the_axes(rho: float) -> None:
    """Against one-dimensional integrals of two cases with a closed inner probability (one
    smaller axis of ratio ``rho``, the other none; both ``rho``): an axis near the largest
    puts the end of the integrand's support where a rule over all z would cross it."""
    from scipy.integrate import quad
    from scipy.special import erf
    from scipy.stats import norm

    def beyond(inside_given_z3) -> float:
        return 1.0 - quad(lambda z: norm.pdf(z) * inside_given_z3(9.0 - z * z), -3.0, 3.0,
                          epsabs=1e-14, epsrel=1e-12)[0]

    one = beyond(lambda a: erf(math.sqrt(a / (2.0 * rho))))
    two = beyond(lambda a: 1.0 - math.exp(-a / (2.0 * rho)))
    share = fe.gaussian_share_beyond_3_sigma(np.array([[0.0, rho, 1.0], [rho, rho, 1.0]]))
    assert share == pytest.approx([one, two], rel=1e-4)
