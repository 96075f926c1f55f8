"""Tracker alignment end to end: streams -> time offset -> stations -> pairs -> X.

``align_stations`` works on synchronous pose pairs (stations): it forms the motion pairs of
every two stations, selects them (angle threshold, axis criterion), eliminates outliers by
RANSAC, solves, and propagates the covariance from the stations' own noise (or, where the
trackers publish none, bootstraps it over the stations).  ``align_streams`` first
estimates the time offset of two free-running streams: coarsely from the angular speeds,
then jointly with X by minimising the ``A X = X B`` misfit over the offset (golden
section), and interpolates stream b at the stations' times.  Conventions: ``solvers``
(A, B, X) and ``timesync`` (offset).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.alignment.covariance import (
    Bootstrap,
    bootstrap_covariance,
    moved_poses,
    propagated_covariance,
    shared_shifts,
)
from services.alignment.robust import misfit, ransac
from services.alignment.selection import (
    Selection,
    angle_mask,
    angle_threshold,
    select_pairs,
)
from services.alignment.solvers import (
    AlignmentError,
    DegenerateMotionError,
    MotionPairs,
    Pose,
    Residuals,
    all_pairs,
    check_conditioning,
    daniilidis,
    pair_residuals,
    refine,
    relative_motions,
    tsai_lenz,
)
from services.alignment.timesync import PoseSeries, coarse_offset, golden_section

SOLVERS = {"daniilidis": daniilidis, "tsai-lenz": tsai_lenz}
WeightedSolver = Callable[..., Pose]
#: Half width (s) of the joint refinement window around the correlation estimate (moved
#: along if the minimum lies at its edge, at most _REFINE_MAX_SHIFTS times), its tolerance.
_REFINE_HALF_WIDTH_S = 0.02
_REFINE_MAX_SHIFTS = 5
_REFINE_TOL_S = 1e-4
#: Fraction of the largest misfits ignored by the offset cost (robust to outliers).
_REFINE_TRIM = 0.2
#: Stations used by the offset refinement, and the index gaps of the pairs formed from them
#: (varied gaps give both short and long motions without the cost of all combinations).
_REFINE_STATIONS = 240
_REFINE_GAPS = (5, 11, 23, 47)
#: Step (s) of the offset's parabola fit and of dX/d(offset): inside the range where a
#: pair's residual is linear in the offset, well above the refinement's tolerance.
_OFFSET_STEP_S = 0.002
#: Newton steps on the parabolas after the golden section (each step changes the pairs the
#: trim keeps, so it is repeated until the step is below the tolerance), and when to stop.
_NEWTON_STEPS = 4
_NEWTON_TOL_S = 1e-5


@dataclass(frozen=True)
class AlignmentOptions:
    """How to align; the defaults suit human-held trackers at 30-200 Hz."""

    method: str = "daniilidis"
    min_angle_rad: float | None = None  # None: from the motions' noise (selection)
    max_pairs: int | None = 1000
    max_stations: int = 40
    ransac: bool = True
    refine: bool = True
    ransac_iterations: int = 200
    bootstrap: int = 100
    estimate_offset: bool = True
    max_offset_s: float = 0.5
    offset_s: float = 0.0  # used as is when estimate_offset is False
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in SOLVERS:
            raise InvalidInputError(
                f"method must be one of {', '.join(SOLVERS)}, got {self.method!r}")
        if self.max_stations < 3:
            raise InvalidInputError(f"max_stations must be >= 3, got {self.max_stations}")
        if self.max_pairs is not None and self.max_pairs < 2:
            raise InvalidInputError(f"max_pairs must be >= 2, got {self.max_pairs}")


def solver_for(options: AlignmentOptions) -> WeightedSolver:
    """``f(pairs, weights=None) -> Pose``: the closed form, then ``refine`` if asked."""
    closed_form = SOLVERS[options.method]
    if not options.refine:
        return closed_form

    def refined(pairs: MotionPairs, weights: np.ndarray | None = None) -> Pose:
        return refine(pairs, closed_form(pairs, weights), weights)

    return refined


@dataclass(frozen=True)
class AlignmentResult:
    """X (pose of sensor_b in sensor_a), its covariance and how it was obtained."""

    position: np.ndarray
    quaternion: np.ndarray
    covariance: np.ndarray  # 6x6, geometry's left-perturbation convention
    time_offset_s: float  # t_b = t_a + offset
    method: str
    n_stations: int
    n_candidates: int  # motion pairs formed
    n_selected: int  # after angle threshold and axis criterion
    n_inliers: int  # after RANSAC
    axis_spread_rad: float
    axis_criterion: float
    residuals: Residuals = field(repr=False)  # of the inlier pairs
    #: station index pairs (i, j) of the inlier motions X was solved from
    pairs_ij: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 2), int))
    time_offset_std_s: float = 0.0  # the offset's uncertainty, in the covariance
    #: X's error (6, m; geometry's convention) per one std of each parameter the stations
    #: of stream a share (``PoseSeries.sensitivity``), in the covariance; (6, 0) if none
    shared_sensitivity: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((6, 0)))
    shared_parameters: tuple[str, ...] = ()
    #: the stations' bootstrap that ``covariance`` rests on (None: propagated from the
    #: stations' noise instead, ``covariance.propagated_covariance``)
    bootstrap: Bootstrap | None = field(repr=False, default=None)
    #: what ``covariance`` adds to the stations' noise part: the errors that differ from
    #: station to station by no noise of theirs (the offset's, the shared tolerances'
    #: draw, the held ones)
    added_covariance: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((6, 6)))

    @property
    def pose(self) -> Pose:
        return Pose(self.position, self.quaternion)

    @property
    def residual_rot_rad(self) -> float:
        """RMS rotation misfit of the inlier pairs."""
        return float(np.sqrt(np.mean(self.residuals.rot_rad ** 2)))

    @property
    def residual_pos_m(self) -> float:
        """RMS translation misfit of the inlier pairs."""
        return float(np.sqrt(np.mean(self.residuals.pos_m ** 2)))

    @property
    def pos_std_m(self) -> float:
        """RMS per-axis position standard deviation (trace of the position block / 3)."""
        c = geo.se3_to_decoupled(self.position, self.covariance)
        return float(np.sqrt(np.trace(c[:3, :3]) / 3.0))

    @property
    def rot_std_rad(self) -> float:
        """RMS per-axis rotation standard deviation."""
        return float(np.sqrt(np.trace(self.covariance[3:, 3:]) / 3.0))

    def summary(self) -> dict[str, Any]:
        """JSON-ready figures: the pose, its uncertainty and the fit's quality."""
        return {
            "position": self.position.tolist(), "quaternion": self.quaternion.tolist(),
            "pos_std_m": self.pos_std_m, "rot_std_rad": self.rot_std_rad,
            "time_offset_s": self.time_offset_s,
            "time_offset_std_s": self.time_offset_std_s, "method": self.method,
            "residual_rot_rad": self.residual_rot_rad, "residual_pos_m": self.residual_pos_m,
            "stations": self.n_stations, "pairs_candidate": self.n_candidates,
            "pairs_selected": self.n_selected, "pairs_inlier": self.n_inliers,
            "axis_spread_deg": float(np.degrees(self.axis_spread_rad)),
            "axis_criterion": self.axis_criterion,
        }


def _selected_motions(pa: np.ndarray, qa: np.ndarray, pb: np.ndarray, qb: np.ndarray,
                      options: AlignmentOptions) -> tuple[MotionPairs, np.ndarray, Selection]:
    """Motion pairs of all station pairs that pass the selection, with their indices."""
    ij = all_pairs(len(pa))
    motions = relative_motions(pa, qa, pb, qb, ij)
    selection = select_pairs(motions, options.min_angle_rad, options.max_pairs)
    if len(selection.index) < 2:
        raise DegenerateMotionError(
            f"only {len(selection.index)} of {len(motions)} motion pairs rotate by "
            f"{np.degrees(selection.min_angle_rad):.3g} to "
            f"{180 - np.degrees(selection.min_angle_rad):.3g} deg; move the trackers more")
    return motions.subset(selection.index), ij[selection.index], selection


@dataclass(frozen=True)
class Fit:
    """X from stations before its covariance: the pairs used and which were consistent."""

    pose: Pose
    motions: MotionPairs  # the selected motion pairs
    pairs_ij: np.ndarray  # their station indices (i, j)
    inliers: np.ndarray  # bool, over the selected pairs
    selection: Selection


def fit_stations(pa: np.ndarray, qa: np.ndarray, pb: np.ndarray, qb: np.ndarray,
                 options: AlignmentOptions, rng: np.random.Generator) -> Fit:
    """Select motion pairs, eliminate outliers (if ``options.ransac``) and solve."""
    if len(pa) < 3:
        raise AlignmentError(f"need at least 3 stations (2 motions), got {len(pa)}")
    solver = solver_for(options)
    motions, ij, selection = _selected_motions(pa, qa, pb, qb, options)
    check_conditioning(motions)  # refuse parallel axes before RANSAC samples them
    if options.ransac and len(motions) >= 3:
        found = ransac(motions, SOLVERS[options.method], options.ransac_iterations, rng=rng,
                       refit=solver)
        return Fit(found.pose, motions, ij, found.inliers, selection)
    return Fit(solver(motions), motions, ij, np.ones(len(motions), dtype=bool), selection)


def align_stations(pa: np.ndarray, qa: np.ndarray, pb: np.ndarray, qb: np.ndarray,
                   options: AlignmentOptions | None = None, time_offset_s: float = 0.0,
                   noise: tuple[np.ndarray, np.ndarray] | None = None) -> AlignmentResult:
    """X from synchronous pose pairs: ``(pa, qa)[k]`` = A_k and ``(pb, qb)[k]`` = B_k.

    X's covariance is propagated from ``noise``, each station's own noise covariance
    (n, 6, 6) of tracker a and of tracker b (``covariance.propagated_covariance``), where
    given; else, where the trackers publish no covariance, it is the bootstrap's over
    stations (``covariance.bootstrap_covariance``)."""
    options = options or AlignmentOptions()
    rng = np.random.default_rng(options.seed)
    fit = fit_stations(pa, qa, pb, qb, options, rng)
    inliers = fit.pairs_ij[fit.inliers]
    bootstrap = None
    if noise is None:
        bootstrap = bootstrap_covariance(pa, qa, pb, qb, inliers, fit.pose,
                                         solver_for(options), options.bootstrap, rng)
        covariance = bootstrap.covariance()
    else:
        covariance = propagated_covariance((pa, qa, pb, qb), inliers, fit.pose, *noise)
    return AlignmentResult(
        position=fit.pose.position, quaternion=fit.pose.quaternion,
        covariance=covariance, bootstrap=bootstrap,
        time_offset_s=time_offset_s, method=options.method, n_stations=len(pa),
        n_candidates=fit.selection.candidates, n_selected=len(fit.motions),
        n_inliers=int(fit.inliers.sum()), axis_spread_rad=fit.selection.axis_spread_rad,
        axis_criterion=fit.selection.axis_criterion,
        residuals=pair_residuals(fit.motions.subset(fit.inliers), fit.pose),
        pairs_ij=fit.pairs_ij[fit.inliers])


def station_times(a: PoseSeries, b: PoseSeries, offset_s: float, count: int,
                  margin: float = 0.0) -> np.ndarray:
    """Up to ``count`` of a's sample times at which b is defined too, one from each of
    ``count`` equal runs of those samples: the one whose covariance (its own noise where a
    says which part persists) has the run's median determinant, else the run's middle one.

    Why the median: a tracker widens a pose it cannot vouch for (the laser tracker's
    cover of a stray blob, 30-40 mm where its poses hold 0.2 mm), and X's covariance
    counts each station's noise in full, so one such station makes X claim far more error
    than it has; the least determinant instead would pick the tail of the covariances'
    own scatter, which claims less than its error. b must also be defined ``margin``
    seconds earlier and later (room for the offset refinement to move).
    """
    _, _, inside = b.at(a.t + offset_s)
    _, _, early = b.at(a.t + offset_s - margin)
    _, _, late = b.at(a.t + offset_s + margin)
    usable = np.flatnonzero(inside & early & late)
    if len(usable) < 3:
        raise AlignmentError(f"{a.name} and {b.name} have only {len(usable)} common instants "
                             f"at offset {offset_s * 1e3:.1f} ms")
    runs = np.array_split(usable, min(count, len(usable)))
    spread = _log_spread(a, usable)
    if spread is None:
        return a.t[[run[len(run) // 2] for run in runs]]
    return a.t[[run[_median_index(spread[run])] for run in runs]]


def _median_index(values: np.ndarray) -> int:
    """The index of ``values``' median (the lower of the middle two)."""
    return int(np.argsort(values, kind="stable")[(len(values) - 1) // 2])


def _log_spread(a: PoseSeries, samples: np.ndarray) -> np.ndarray | None:
    """Each sample's log determinant of its own noise (its covariance less the systematic
    part, or the whole where a does not split it), indexed by sample; inf where it is not
    positive definite; None where a publishes no covariance."""
    if a.covariance is None:
        return None
    own = a.covariance[samples]
    if a.systematic is not None:
        own = own - a.systematic[samples]
    sign, logdet = np.linalg.slogdet(own)
    out = np.full(len(a.t), np.inf)
    out[samples] = np.where(sign > 0, logdet, np.inf)
    return out


def _pair_misfits(a: PoseSeries, b: PoseSeries, times: np.ndarray, ij: np.ndarray,
                  solver: Any) -> Callable[[float], np.ndarray]:
    """The misfit of each pair ``ij`` under X solved at offset d, as a function of d."""
    pa, qa, _ = a.at(times)

    def misfits(d: float) -> np.ndarray:
        pb, qb, _ = b.at(times + d)
        motions = relative_motions(pa, qa, pb, qb, ij)
        return misfit(motions, solver(motions),
                      max(float(np.median(np.linalg.norm(motions.pa, axis=-1))), 0.01))

    return misfits


def _offset_cost(misfits: Callable[[float], np.ndarray]) -> Callable[[float], float]:
    """The offset refinement's cost: the trimmed mean square misfit at offset d."""
    def cost(d: float) -> float:
        e = misfits(d)
        return float(np.mean(np.sort(e)[:int(np.ceil((1.0 - _REFINE_TRIM) * len(e)))] ** 2))

    return cost


def _refinement_pairs(a: PoseSeries, b: PoseSeries, offset_s: float,
                      options: AlignmentOptions) -> tuple[np.ndarray, np.ndarray]:
    """The stations (times in a) and station pairs the offset refinement works on."""
    times = station_times(a, b, offset_s, _REFINE_STATIONS,
                          margin=_REFINE_HALF_WIDTH_S * (_REFINE_MAX_SHIFTS + 1))
    pa, qa, _ = a.at(times)
    pb, qb, _ = b.at(times + offset_s)
    ij = np.concatenate([np.stack([np.arange(len(times) - g), np.arange(g, len(times))], -1)
                         for g in _REFINE_GAPS if g < len(times)])
    motions = relative_motions(pa, qa, pb, qb, ij)
    ij = ij[angle_mask(motions, angle_threshold(motions, options.min_angle_rad))]
    if len(ij) < 2:
        raise DegenerateMotionError("the streams hardly rotate; cannot align their time offset")
    return times, ij


@dataclass(frozen=True)
class OffsetParabolas:
    """Near an offset ``d0``, each refinement pair's squared misfit as a parabola in the
    offset, ``e^2(d0 + s) ~ e^2(d0) + slope s + curve s^2 / 2``, for the pairs the
    refinement's trim keeps at ``d0``; fitted through ``d0`` and ``_OFFSET_STEP_S`` either
    side (a pair's residual is linear in the offset there)."""

    ij: np.ndarray  # station index pairs of the kept pairs
    slope: np.ndarray
    curve: np.ndarray

    def minimum(self, weights: np.ndarray | None = None) -> float:
        """The shift from ``d0`` that minimises the (weighted) sum of the parabolas."""
        w = np.ones(len(self.ij)) if weights is None else weights
        return float(-(w @ self.slope) / (w @ self.curve))


def offset_parabolas(a: PoseSeries, b: PoseSeries, offset_s: float,
                     options: AlignmentOptions) -> OffsetParabolas:
    """The refinement pairs' local model of the offset cost at ``offset_s``."""
    times, ij = _refinement_pairs(a, b, offset_s, options)
    misfits = _pair_misfits(a, b, times, ij, SOLVERS[options.method])
    h = _OFFSET_STEP_S
    lo, mid, hi = (misfits(offset_s + k * h) ** 2 for k in (-1, 0, 1))
    keep = np.argsort(mid)[:int(np.ceil((1.0 - _REFINE_TRIM) * len(mid)))]
    return OffsetParabolas(ij[keep], ((hi - lo) / (2 * h))[keep],
                           ((hi - 2 * mid + lo) / h ** 2)[keep])


def _golden_offset(a: PoseSeries, b: PoseSeries, coarse: float,
                   options: AlignmentOptions) -> float:
    """The minimum of the trimmed misfit within ``_REFINE_TOL_S``, searched from ``coarse``
    (the window follows the minimum if it lies at the window's edge)."""
    times, ij = _refinement_pairs(a, b, coarse, options)
    cost = _offset_cost(_pair_misfits(a, b, times, ij, SOLVERS[options.method]))
    centre = coarse
    for _ in range(_REFINE_MAX_SHIFTS):
        lo, hi = centre - _REFINE_HALF_WIDTH_S, centre + _REFINE_HALF_WIDTH_S
        refined = golden_section(cost, lo, hi, _REFINE_TOL_S)
        if lo + 2 * _REFINE_TOL_S < refined < hi - 2 * _REFINE_TOL_S:
            return refined
        centre = refined  # the minimum lies beyond the window: follow it
    raise AlignmentError(f"time offset: the misfit keeps falling beyond "
                         f"{abs(centre - coarse) * 1e3:.0f} ms from the correlation estimate "
                         f"{coarse * 1e3:.1f} ms; the streams may not move together")


def estimate_offset(a: PoseSeries, b: PoseSeries, options: AlignmentOptions,
                    ) -> tuple[float, float]:
    """The time offset (coarse by correlation, then refined jointly with X) and the coarse one.

    The refinement ends with Newton steps on the kept pairs' parabolas
    (``offset_parabolas``).  Why: the trimmed cost jumps wherever the trimmed set changes,
    so the golden section stops at a jump, farther from the minimum of the smooth model
    than the offset's own spread; ``offset_std`` is the spread of that model's minimum, so
    the estimate is that minimum (figures: docs/MEASUREMENTS.md).
    """
    coarse, _ = coarse_offset(a, b, options.max_offset_s)
    refined = _golden_offset(a, b, coarse, options)
    for _ in range(_NEWTON_STEPS):  # the kept set changes with the offset: iterate
        step = offset_parabolas(a, b, refined, options).minimum()
        if abs(step) > _REFINE_HALF_WIDTH_S:  # the parabolas do not hold that far: stay
            break
        refined += step
        if abs(step) < _NEWTON_TOL_S:
            break
    return refined, coarse


def offset_std(a: PoseSeries, b: PoseSeries, offset_s: float, options: AlignmentOptions,
               ) -> float:
    """Standard deviation (s) of a refined time offset, by bootstrap over stations.

    Why: the offset is estimated once and then held fixed, so every station's b is read at
    the same wrong instant and that error is common to all of them; the bootstrap over
    stations of X cannot see it.  A resample of the stations (pairs weighted ``c_i c_j`` as
    in ``covariance``) moves the minimum of the weighted sum of the pairs' parabolas
    (``offset_parabolas``), and the spread of those minima about the unweighted one is the
    offset's uncertainty.
    """
    model = offset_parabolas(a, b, offset_s, options)
    rng = np.random.default_rng([options.seed, 1])
    stations = np.unique(model.ij)
    centre = model.minimum()
    shifts = []
    for _ in range(options.bootstrap):
        counts = np.zeros(int(stations.max()) + 1)
        np.add.at(counts, rng.choice(stations, size=len(stations)), 1.0)
        w = counts[model.ij[:, 0]] * counts[model.ij[:, 1]]
        if w @ model.curve > 0:
            shifts.append(model.minimum(w) - centre)
    if len(shifts) < 2:
        return 0.0
    return float(np.sqrt(np.mean(np.square(shifts))))


def offset_covariance(b: PoseSeries, stations_a: tuple[np.ndarray, np.ndarray],
                      times: np.ndarray, result: AlignmentResult, std_s: float,
                      options: AlignmentOptions) -> np.ndarray:
    """What an offset error of ``std_s`` adds to X's covariance (geometry's convention).

    X is solved again from the same motion pairs with b read ``_OFFSET_STEP_S`` earlier and
    later; the central difference is dX/d(offset), and its outer product times the
    offset's variance the added covariance (first order).
    """
    if std_s == 0.0:
        return np.zeros((6, 6))
    solver = solver_for(options)
    ends = []
    for d in (-_OFFSET_STEP_S, _OFFSET_STEP_S):
        pb, qb, _ = b.at(times + result.time_offset_s + d)
        x = solver(relative_motions(*stations_a, pb, qb, result.pairs_ij))
        ends.append((x.position, x.quaternion))
    (p0, q0), (p1, q1) = ends
    dphi = geo.quat_to_rotvec(geo.quat_multiply(q1, geo.quat_conjugate(q0)))
    j = np.concatenate([p1 - p0, dphi]) / (2 * _OFFSET_STEP_S)
    return geo.decoupled_to_se3(result.position, np.outer(j, j) * std_s ** 2)


def held_error_covariance(p: np.ndarray, q: np.ndarray, covariances: np.ndarray | None,
                          ) -> np.ndarray:
    """A tracker's persistent covariances (n, 6, 6, world frame; ``PoseSeries.held_at``) at
    its stations ``(p, q)`` read as one error that holds in its sensor's frame for all of
    them: their mean in that frame (``Ad(T^-1) C Ad(T^-1)^T``).

    Why: an error ``E`` that stays with the sensor (``A_k -> A_k E``: a laser housing's
    beams, a marker body's geometry) cancels from every residual of ``A X = X B`` and moves
    X by exactly ``E``; no resampling of the stations can see it, so only the tracker's own
    account of its errors can.  A sample's own noise is no such error: X's noise part counts
    it (propagated or bootstrapped), so only the part the tracker calls systematic is held
    here; a tracker that does not say which part persists has its whole covariance read as
    held (conservative).
    """
    if covariances is None:
        return np.zeros((6, 6))
    Ad = geo.adjoint(*geo.inverse(p, q))
    return np.mean(Ad @ covariances @ np.swapaxes(Ad, -1, -2), axis=0)


def shared_error_sensitivity(stations: tuple[np.ndarray, ...], moved: dict[int, MotionPairs],
                             m: int, result: AlignmentResult,
                             options: AlignmentOptions) -> np.ndarray:
    """X's change (6, m; geometry's convention) per one std of each of the m parameters
    whose error every station of a shares, each station by its own sensitivity: ``moved``
    (:func:`moved_motions`) holds the motion pairs with the stations moved by each.

    Why: an error that differs from station to station but is the same in every recording
    (an installation's tolerance, seen through each station's geometry) is neither held
    (it does not cancel from the motions) nor noise (every resample of the stations holds
    the same draw of it, so their spread cannot show how that draw varies; what they see
    of it station by station comes out of their spread, ``covariance.shared_shifts``);
    the motions' geometry passes it to X, by several times its own size where the
    stations' errors differ along what the motions determine least.  X is solved again
    from the same motion pairs with every station of a moved by one std of the parameter
    (first order: the tolerances move a pose by a fraction of a milliradian)."""
    solver = solver_for(options)
    x0 = solver(relative_motions(*stations, result.pairs_ij))
    columns = np.zeros((m, 6))
    for j, motions in moved.items():
        x = solver(motions)
        dphi = geo.quat_to_rotvec(geo.quat_multiply(x.quaternion, geo.quat_conjugate(
            x0.quaternion)))
        columns[j, :3] = x.position - x0.position - np.cross(dphi, x0.position)  # rho
        columns[j, 3:] = dphi
    return columns.T


def moved_motions(stations: tuple[np.ndarray, ...], sensitivity: np.ndarray,
                  pairs_ij: np.ndarray) -> dict[int, MotionPairs]:
    """The motion pairs ``pairs_ij`` with every station of a moved by one std of parameter
    j (by its ``sensitivity`` (n, 6, m)), for each j that moves a station."""
    pa, qa, pb, qb = stations
    return {int(j): relative_motions(*moved_poses(pa, qa, sensitivity[:, :, j]), pb, qb,
                                     pairs_ij)
            for j in np.flatnonzero(np.any(sensitivity, axis=(0, 1)))}


def align_at_offset(a: PoseSeries, b: PoseSeries, offset_s: float, offset_std_s: float,
                    options: AlignmentOptions) -> AlignmentResult:
    """X from the streams' stations at a given offset whose uncertainty is ``offset_std_s``.

    X's covariance is the stations' own noise's (propagated from both streams' noise,
    ``PoseSeries.noise_at``, where both say which part of their covariance is noise; else
    the stations' bootstrap) plus the errors that no station's own noise holds: the
    offset's (``offset_covariance``), the errors a's stations share through parameters
    whose sensitivities a gives (``shared_error_sensitivity``), and each tracker's held
    error (``held_error_covariance``; of a's covariances what those parameters do not
    explain; b's moves X by ``X E_b X^-1``, hence its adjoint).  A bootstrap's part loses
    what the shared errors spread its resamples by (``covariance.shared_shifts``: counted
    whole already) and is scaled for an unbiased inverse of the whole
    (``covariance.inverse_unbiased``)."""
    times = station_times(a, b, offset_s, options.max_stations)
    pa, qa, _ = a.at(times)
    pb, qb, _ = b.at(times + offset_s)
    noise = (a.noise_at(times), b.noise_at(times + offset_s))
    result = align_stations(pa, qa, pb, qb, options, time_offset_s=offset_s,
                            noise=None if any(c is None for c in noise) else noise)
    ad_x = geo.adjoint(result.position, result.quaternion)
    held_a = a.held_at(times)
    shared = np.zeros((6, 0))
    bootstrap = result.bootstrap
    sensitivity = a.sensitivity_at(times)
    if sensitivity is not None and held_a is not None:
        held_a = held_a - sensitivity @ np.swapaxes(sensitivity, -1, -2)
        moved = moved_motions((pa, qa, pb, qb), sensitivity, result.pairs_ij)
        shared = shared_error_sensitivity((pa, qa, pb, qb), moved, sensitivity.shape[2],
                                          result, options)
        if moved and bootstrap is not None:
            bootstrap = replace(bootstrap, shared_shifts=shared_shifts(
                bootstrap, relative_motions(pa, qa, pb, qb, result.pairs_ij),
                list(moved.values()), result.pose))
    added = (offset_covariance(b, (pa, qa), times, result, offset_std_s, options)
             + shared @ shared.T + held_error_covariance(pa, qa, held_a)
             + ad_x @ held_error_covariance(pb, qb, b.held_at(times + offset_s)) @ ad_x.T)
    covariance = result.covariance + added if bootstrap is None else bootstrap.covariance(added)
    return replace(result, covariance=covariance, bootstrap=bootstrap,
                   added_covariance=added, time_offset_std_s=offset_std_s,
                   shared_sensitivity=shared, shared_parameters=a.parameters)


def align_streams(a: PoseSeries, b: PoseSeries,
                  options: AlignmentOptions | None = None) -> AlignmentResult:
    """X and the time offset from two free-running pose streams of rigidly joined sensors.
    A given offset (``options.estimate_offset`` False) counts as exact."""
    options = options or AlignmentOptions()
    if not options.estimate_offset:
        return align_at_offset(a, b, options.offset_s, 0.0, options)
    offset = estimate_offset(a, b, options)[0]
    return align_at_offset(a, b, offset, offset_std(a, b, offset, options), options)
