"""The covariance of an estimated X: propagated from the stations' own noise where both
trackers publish covariances, else by bootstrap over stations.

Why not first-order propagation of the pair residuals as if independent: motion pairs are
formed from all combinations of stations, so each station's measurement noise enters many
pairs and the pair residuals are strongly correlated.  Treating them as independent (the
Gauss-Newton ``(J^T W J)^-1``) understates the uncertainty by roughly the square root of
the number of pairs per station.  Both ways here keep that correlation.
``propagated_covariance`` moves each station by its own noise and sums what each moves X
by (the pairs that share a station move together): the covariance is computed from the
trackers' accounts of their noise, not estimated, so it has no scatter of its own.
``bootstrap_covariance`` resamples the *stations* (the independent measurements) with
replacement and re-solves: it needs no noise model, which is what it is for (a tracker
that publishes no covariance), but its spread is an estimate from some 40 stations whose
own scatter makes X's NEES heavier-tailed than chi-square(6) (``inverse_unbiased`` makes
its inverse unbiased, not its tails right).

Result in ``agent.geometry``'s convention: 6x6 over the left perturbation
``X_true = Exp(xi) X``, ``xi = [rho (m), phi (rad)]`` in sensor_a's frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.alignment.solvers import (
    AlignmentError,
    DegenerateMotionError,
    MotionPairs,
    Pose,
    linearised_residuals,
    relative_motions,
)

WeightedSolver = Callable[[MotionPairs, np.ndarray], Pose]
#: fewest resamples whose 6-dof covariance has an unbiased inverse (``_inverse_unbiased``)
MIN_RESAMPLES = 9
_DOF = 6


@dataclass(frozen=True)
class Bootstrap:
    """The resamples' spread of X about the estimate (6x6, geometry's convention), the
    counts its inverse's bias rests on, and the resamples themselves."""

    spread: np.ndarray
    stations: int
    resamples: int  # the solvable ones
    pairs_ij: np.ndarray  # the station index pairs of the motions X was solved from
    counts: np.ndarray  # (resamples, stations): how often each solvable resample drew each
    #: (resamples, 6, m): each resample's shift of X under each of m errors that every
    #: recording shares, one std each (``shared_shifts``)
    shared_shifts: np.ndarray = field(default_factory=lambda: np.zeros((0, 6, 0)))

    @property
    def shared(self) -> np.ndarray:
        """What ``spread`` holds of the shared errors, averaged over their draws."""
        e = self.shared_shifts
        return np.einsum("bim,bjm->ij", e, e) / max(len(e) - 1, 1)

    @property
    def weights(self) -> np.ndarray:
        """(resamples, pairs): each motion pair's weight in each solvable resample."""
        return self.counts[:, self.pairs_ij[:, 0]] * self.counts[:, self.pairs_ij[:, 1]]

    def covariance(self, added: np.ndarray | None = None) -> np.ndarray:
        """X's covariance: the spread less its ``shared`` part (counted in ``added``), scaled
        so that the inverse of the whole is unbiased, plus ``added`` (6x6, the same
        convention), what the stations' resamples cannot see, computed rather than
        estimated from their noise (``inverse_unbiased``)."""
        added = np.zeros((6, 6)) if added is None else added
        noise = _less(self.spread, self.shared, np.sqrt(2.0 / (self.stations - 1)))
        return noise * inverse_unbiased(noise, added, self.stations, self.resamples,
                                        self.shared_shifts) + added


def _less(spread: np.ndarray, part: np.ndarray, resolution: float) -> np.ndarray:
    """``spread - part``, in no direction below ``resolution`` times the spread there
    (in the spread's own metric, so that units and coordinates do not matter).

    Why: ``part`` is an average over the draws of what it removes; where one draw left
    less than average, the difference falls below what the spread can resolve (its
    relative standard error, ``sqrt(2 / nu)`` for a Wishart estimate), and a variance set
    to zero there would make any error in that direction infinitely unlikely."""
    root = np.linalg.cholesky(spread)
    w, v = np.linalg.eigh(np.linalg.solve(root, np.linalg.solve(root, part).T))
    r = root @ v
    return (r * np.clip(1.0 - w, resolution, None)) @ r.T


def moved_poses(p: np.ndarray, q: np.ndarray, xi: np.ndarray,
                ) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``(p, q)`` moved by the left perturbations ``xi`` (n, 6; geometry's
    convention): ``dp = rho + phi x p``, ``q <- Exp(phi) q``."""
    phi = xi[:, 3:]
    return p + xi[:, :3] + np.cross(phi, p), geo.quat_multiply(geo.rotvec_to_quat(phi), q)


def propagated_covariance(stations: tuple[np.ndarray, ...], pairs_ij: np.ndarray, x: Pose,
                          noise_a: np.ndarray, noise_b: np.ndarray) -> np.ndarray:
    """X's covariance from each station's own noise (``noise_a``, ``noise_b``: (n, 6, 6)
    per station of each tracker, geometry's convention), to first order through the
    refinement's objective at ``x`` (``solvers.refine``): ``sum_s K_s Sigma_s K_s^T``,
    ``K_s = -H^-1 J^T dr/dz_s`` the implicit function's derivative of X by station s's
    pose, ``H = J^T J``.

    Each station is moved by each column of a root of its covariance, alone: every pair
    it belongs to moves with it, which keeps the correlation of the pairs that share a
    station exactly.  The stations' noise must be independent from station to station;
    what they share (a tracker's held error, an installation's tolerances) is the
    caller's to add."""
    pa, qa, pb, qb = stations
    ij = np.asarray(pairs_ij, dtype=int).reshape(-1, 2)
    n = len(pa)
    r0, J, scale = linearised_residuals(relative_motions(pa, qa, pb, qb, ij), x)
    gradient = np.zeros((n, 6, 2 * _DOF))  # d(J^T r) per station and root column
    for side, noise in enumerate((noise_a, noise_b)):
        root = _root(noise)
        for k in range(_DOF):
            moved = list(stations)
            moved[2 * side:2 * side + 2] = moved_poses(*stations[2 * side:2 * side + 2],
                                                       root[:, :, k])
            both = [np.concatenate([s, m]) for s, m in zip(stations, moved, strict=True)]
            for end in (0, 1):  # move the pairs' first stations, then their second ones
                shifted = ij.copy()
                shifted[:, end] += n
                dr = linearised_residuals(relative_motions(*both, shifted), x, scale)[0] - r0
                np.add.at(gradient[:, :, _DOF * side + k], ij[:, end],
                          np.einsum("pki,pk->pi", J, dr))
    shift = np.linalg.solve(np.einsum("pki,pkj->ij", J, J), gradient)  # (n, 6, columns)
    return np.einsum("sik,sjk->ij", shift, shift)


def _root(covariances: np.ndarray) -> np.ndarray:
    """``L`` with ``L L^T = C`` for each of the (n, 6, 6) ``covariances``; a tracker's
    covariance less its systematic part may fall a rounding error below zero in some
    direction, which counts as zero."""
    w, v = np.linalg.eigh(0.5 * (covariances + np.swapaxes(covariances, -1, -2)))
    return v * np.sqrt(np.clip(w, 0.0, None))[:, None, :]


def bootstrap_covariance(pa: np.ndarray, qa: np.ndarray, pb: np.ndarray, qb: np.ndarray,
                         pairs_ij: np.ndarray, x: Pose, solver: WeightedSolver,
                         resamples: int = 100, rng: np.random.Generator | None = None,
                         ) -> Bootstrap:
    """X's spread over ``resamples`` solves on stations drawn with replacement.

    ``pairs_ij`` are the station index pairs that the estimate used; in a resample a pair
    counts ``c_i * c_j`` times, ``c`` being how often each station was drawn.
    """
    if resamples < MIN_RESAMPLES:
        raise InvalidInputError(
            f"bootstrap needs at least {MIN_RESAMPLES} resamples, got {resamples}")
    rng = rng if rng is not None else np.random.default_rng(0)
    ij = np.asarray(pairs_ij, dtype=int).reshape(-1, 2)
    stations = np.unique(ij)
    motions = relative_motions(pa, qa, pb, qb, ij)
    deltas, drawn = [], []
    for _ in range(resamples):
        counts = np.zeros(int(stations.max()) + 1)
        np.add.at(counts, rng.choice(stations, size=len(stations)), 1.0)
        w = counts[ij[:, 0]] * counts[ij[:, 1]]
        used = w > 0
        try:
            xk = solver(motions.subset(used), w[used])
        except DegenerateMotionError:
            continue  # this resample lost the axis spread; it says nothing about X's spread
        dp = xk.position - x.position
        dphi = geo.quat_to_rotvec(geo.quat_multiply(xk.quaternion,
                                                    geo.quat_conjugate(x.quaternion)))
        deltas.append(np.concatenate([dp, dphi]))
        drawn.append(counts)
    if len(deltas) < max(2, resamples // 2):
        raise AlignmentError(f"bootstrap: only {len(deltas)} of {resamples} resamples were "
                             "solvable; the motions barely determine X")
    D = np.array(deltas)
    decoupled = D.T @ D / (len(D) - 1)  # spread about the estimate itself, not the mean
    _inverse_unbiased(len(stations), len(D))  # refuse too few stations or resamples here
    return Bootstrap(geo.decoupled_to_se3(x.position, decoupled), len(stations), len(D), ij,
                     np.array(drawn))


def shared_shifts(bootstrap: Bootstrap, motions: MotionPairs, moved: list[MotionPairs],
                  x: Pose) -> np.ndarray:
    """(resamples, 6, m): each resample's shift of X (geometry's convention) under each of
    m errors that every recording shares, less the whole estimate's shift: ``moved`` are
    ``motions`` with every station moved by one std of one such parameter each (first
    order: the refinement's Gauss-Newton step at ``x``).  Their spread, summed over the
    parameters, is what the bootstrap's spread holds of those errors on average over
    their draws (``Bootstrap.shared``).

    Why: such an error (an installation's tolerance seen through each station's pose)
    differs from station to station, so the resamples see it as noise and spread X by it,
    while X's covariance counts it whole as the parameters' (``shared_error_sensitivity``):
    counted twice, by this much on average over the parameters' draws."""
    r0, J, scale = linearised_residuals(motions, x)
    jtj = np.einsum("pki,pkj->pij", J, J)
    jtr = np.stack([np.einsum("pki,pk->pi", J, linearised_residuals(m, x, scale)[0] - r0)
                    for m in moved], axis=-1)  # (pairs, 6, parameters)
    whole = -np.linalg.solve(jtj.sum(0), jtr.sum(0))
    w = bootstrap.weights
    each = -np.linalg.solve(np.einsum("bp,pij->bij", w, jtj), np.einsum("bp,pim->bim", w, jtr))
    return each - whole


def inverse_unbiased(spread: np.ndarray, added: np.ndarray, stations: int,
                     resamples: int, shifts: np.ndarray | None = None) -> float:
    """The factor ``k`` on the bootstrap's ``spread`` S that makes the inverse of
    ``k S + added`` unbiased, to second order in S's dispersion:
    ``k = 1 + (f(nu_s) f(nu_b) - 1) (tr P^2 + (tr P)^2) / (7 tr P)``,
    ``P = C^-1/2 S C^-1/2`` S's share of ``C = S + added``.

    Why: only S is estimated from the stations' noise; ``added`` (the offset's, the shared
    tolerances', the held errors) is computed from the trackers' own accounts and does not
    scatter with that noise.  For an S that scatters like a Wishart estimate with ``nu``
    degrees of freedom, ``E[(S - Sigma) A (S - Sigma)] = (Sigma A Sigma + tr(A Sigma)
    Sigma) / nu``, so the mean NEES of an honest error against ``k S + added`` is
    ``6 - (k - 1) tr P + (tr P^2 + (tr P)^2) / nu``, which is 6 at the ``k`` above (with
    ``1 / nu`` read from the exact factor of the whole-S case, ``f - 1 ~ 7 / nu``).  With
    nothing added (``P = I``) it is ``f(nu_s) f(nu_b)`` (``_inverse_unbiased``); with S
    half of the covariance it is about half as far from 1: scaling S by the whole factor
    there makes X's covariance conservative.  P is read from S itself (plug-in).

    Where S had the shared errors' average part taken out (``shifts``, as in
    ``shared_shifts``: ``Q(theta) = sum_jl theta_j theta_l C_jl``, ``C_jl`` the shifts'
    spread between parameters j and l, was in it and ``E[Q]`` came out), S also errs by
    ``Q(theta) - E[Q]``; for standard normal ``theta``, ``E[(Q - E Q) A (Q - E Q)] =
    sum_jl C_jl A C_jl + C_jl A C_lj``, which adds ``sum_jl tr(G_jl G_jl + G_jl G_jl^T)``,
    ``G_jl = C^-1/2 C_jl C^-1/2``, to the mean NEES, and to ``(k - 1) tr P`` likewise.
    """
    f = _inverse_unbiased(stations, resamples)
    c = spread + added
    share = np.linalg.solve(c, spread)  # C^-1 S, similar to P
    tr, tr2 = float(np.trace(share)), float(np.trace(share @ share))
    if tr <= 0.0:
        return f
    excess = (f - 1.0) * (tr2 + tr ** 2) / (_DOF + 1)
    if shifts is not None and shifts.size:
        white = np.linalg.solve(np.linalg.cholesky(c), shifts)  # C^-1/2 e, per resample
        g = np.einsum("bim,bjn->mnij", white, white) / (len(shifts) - 1)
        excess += float(np.einsum("mnij,mnji->", g, g) + np.einsum("mnij,mnij->", g, g))
    return 1.0 + excess / tr


def _inverse_unbiased(stations: int, resamples: int, dof: int = _DOF) -> float:
    """``f(nu_s) f(nu_b)``, ``f(nu) = nu / (nu - d - 1)``, ``nu_s = stations - 1``,
    ``nu_b = resamples - 1``: the factor that makes the inverse of the bootstrap's
    covariance unbiased.

    Why: consumers use the inverse (NEES, a filter's gain, the SRG's error functions), and
    the inverse of an estimate is biased high: for a Wishart estimate with ``nu`` degrees
    of freedom, ``E[S^-1] = f(nu) Sigma^-1`` (Hotelling's T^2).  The bootstrap's covariance
    is two nested estimates: the ideal bootstrap (every resample) rests on the stations,
    and the finite resamples are a Monte Carlo estimate of that, so
    ``E[S_B^-1] = E[E[S_B^-1 | S]] = f(nu_b) E[S^-1] = f(nu_b) f(nu_s) Sigma^-1``.
    docs/MEASUREMENTS.md has the check of this against Monte Carlo draws.
    """
    nu_s, nu_b = stations - 1, resamples - 1
    if nu_s <= dof + 1:
        raise AlignmentError(f"the covariance of X needs at least {dof + 3} stations, got "
                             f"{stations}")
    if nu_b <= dof + 1:
        raise AlignmentError(f"the covariance of X needs at least {dof + 3} solvable "
                             f"bootstrap resamples, got {resamples}")
    return nu_s / (nu_s - dof - 1) * nu_b / (nu_b - dof - 1)
