"""Tracker alignment AX = XB: solvers, selection, RANSAC, time offset, files."""

from __future__ import annotations

import tomllib
from dataclasses import replace

import numpy as np
import pytest

from agent import geometry as geo
from agent.daemon.settings import check_static_edge
from services.alignment import opencv_reference, records
from services.alignment.pipeline import (
    AlignmentOptions,
    align_at_offset,
    align_stations,
    align_streams,
    estimate_offset,
    fit_stations,
    offset_parabolas,
    offset_std,
)
from services.alignment.robust import ransac
from services.alignment.selection import (
    angle_mask,
    axis_criterion,
    greedy_axis_selection,
    noise_angle_threshold,
    select_pairs,
)
from services.alignment.simulate import (
    StreamConfig,
    add_pose_noise,
    corrupt,
    random_pose,
    simulate_streams,
)
from services.alignment.solvers import (
    AlignmentError,
    DegenerateMotionError,
    MotionPairs,
    Pose,
    all_pairs,
    daniilidis,
    pair_residuals,
    refine,
    relative_motions,
    tsai_lenz,
)
from services.alignment.timesync import PoseSeries
from services.sim import mounts

LASER = Pose(*mounts.HEAD_TO_LASER_RIG)


def _stations(seed: int, n: int = 8, noise: tuple[float, float] = (0.0, 0.0),
              ) -> tuple[tuple[np.ndarray, ...], Pose]:
    """Random stations A_k and B_k = Y A_k X (optionally noisy), and the true X."""
    rng = np.random.default_rng(seed)
    x, y = random_pose(rng, 0.3), random_pose(rng, 2.0)
    pa = rng.uniform(-1, 1, (n, 3))
    qa = geo.rotvec_to_quat(rng.normal(0, 1.0, (n, 3)))
    pb, qb = geo.compose(*geo.compose(y.position, y.quaternion, pa, qa), *x)
    pb, qb = add_pose_noise(pb, qb, *noise, rng)
    return (pa, qa, pb, qb), x


def _trajectory_stations(seed: int, n: int) -> tuple[tuple[np.ndarray, ...], Pose]:
    """Noisy stations along the simulated head trajectory (1 mm, 0.1 deg per pose)."""
    rng = np.random.default_rng(seed)
    x, world_b = random_pose(rng, 0.2), random_pose(rng, 2.0)
    a, b = simulate_streams(seed, LASER, x, world_b, StreamConfig(seconds=40.0, rate_b_hz=60.0))
    pick = np.linspace(0, len(a) - 1, n).astype(int)
    stations = (a.position[pick], a.quaternion[pick], *b.at(a.t[pick])[:2])
    return stations, x


def _err(pose: Pose, truth: Pose) -> tuple[float, float]:
    dp, dr = geo.pose_error(pose.position, pose.quaternion, *truth)
    return float(dp), float(dr)


# --------------------------------------------------------------------------- solvers


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noise_free_solvers_recover_x_and_agree_with_opencv(seed: int) -> None:
    stations, x = _stations(seed)
    motions = relative_motions(*stations, all_pairs(len(stations[0])))
    for solve, cv_method in ((tsai_lenz, "tsai"), (daniilidis, "daniilidis")):
        ours = solve(motions)
        assert max(_err(ours, x)) < 1e-9, solve.__name__
        cv = opencv_reference.calibrate_hand_eye(*stations, cv_method)
        assert max(_err(ours, cv)) < 1e-9, f"{solve.__name__} vs cv2 {cv_method}"
        assert max(_err(refine(motions, ours), x)) < 1e-9
        r = pair_residuals(motions, ours)
        assert r.rot_rad.max() < 1e-9 and r.pos_m.max() < 1e-9


def test_pipeline_on_noise_free_trajectory_recovers_x() -> None:
    times = np.linspace(0.0, 30.0, 25)
    ph, qh = geo.compose(*mounts.HEAD_TO_LASER_RIG, *_head(times))
    x = Pose(*geo.compose(*geo.inverse(*mounts.HEAD_TO_LASER_RIG), *mounts.HEAD_TO_ACCEL_RIG))
    pb, qb = geo.compose(*geo.compose(np.array([1.0, -2.0, 0.5]),
                                      geo.rotvec_to_quat([0.3, -1.0, 2.0]), ph, qh), *x)
    for method in ("daniilidis", "tsai-lenz"):
        result = align_stations(ph, qh, pb, qb, AlignmentOptions(method=method, bootstrap=10))
        assert max(_err(result.pose, x)) < 1e-9, method
        assert result.n_inliers == result.n_selected  # no pair rejected
        assert np.abs(result.covariance).max() < 1e-15


def _head(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from services.sim.trajectory import HeadTrajectory
    return HeadTrajectory(3).pose(times)


def test_refinement_converges_to_one_optimum_as_good_as_the_best_closed_form() -> None:
    closed = {name: [] for name in ("tsai_lenz", "daniilidis")}
    refined = []
    for seed in range(12):
        stations, x = _trajectory_stations(seed, n=40)
        motions = relative_motions(*stations, all_pairs(40))
        motions = motions.subset(angle_mask(motions))
        ends = []
        for solve in (tsai_lenz, daniilidis):
            start = solve(motions)
            closed[solve.__name__].append(_err(start, x))
            ends.append(refine(motions, start))
        assert max(_err(ends[0], ends[1])) < 1e-8  # same minimum from either start
        refined.append(_err(ends[1], x))
    best = np.minimum(*(np.mean(v, axis=0) for v in closed.values()))
    after = np.mean(refined, axis=0)
    assert after[0] <= best[0] and after[1] <= best[1]
    assert after[0] < 4e-3 and after[1] < np.radians(0.25)


# --------------------------------------------------------------------------- degenerate


def _about_z(n: int, noise: float = 0.0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(7)
    pa = rng.uniform(-1, 1, (n, 3))
    qa = geo.rotvec_to_quat(np.outer(rng.uniform(-2, 2, n), [0, 0, 1.0]))
    x = random_pose(rng, 0.2)
    pb, qb = geo.compose(pa, qa, *x)
    return (pa, qa, *add_pose_noise(pb, qb, noise, noise, rng))


@pytest.mark.parametrize("noise", [0.0, 1e-4])
def test_parallel_rotation_axes_are_refused(noise: float) -> None:
    stations = _about_z(10, noise)
    motions = relative_motions(*stations, all_pairs(10))
    for solve in (tsai_lenz, daniilidis):
        with pytest.raises(DegenerateMotionError, match="parallel"):
            solve(motions)
    with pytest.raises(DegenerateMotionError, match="parallel"):
        align_stations(*stations, AlignmentOptions(bootstrap=10))


def test_fewer_than_two_motions_are_refused() -> None:
    stations, _ = _stations(0, n=3)
    one = relative_motions(*stations, [[0, 1]])
    for solve in (tsai_lenz, daniilidis):
        with pytest.raises(DegenerateMotionError, match="at least 2"):
            solve(one)
    with pytest.raises(AlignmentError, match="at least 3 stations"):
        align_stations(*(s[:2] for s in stations))
    assert issubclass(AlignmentError, ValueError)


def test_pure_translations_are_refused() -> None:
    rng = np.random.default_rng(3)
    pa = rng.uniform(-1, 1, (12, 3))
    qa = np.tile(geo.rotvec_to_quat([0.1, 0.2, 0.3]), (12, 1))
    pb, qb = geo.compose(pa, qa, *random_pose(rng, 0.2))
    pb, qb = add_pose_noise(pb, qb, 1e-3, np.radians(0.1), rng)
    motions = relative_motions(pa, qa, pb, qb, all_pairs(12))
    for solve in (tsai_lenz, daniilidis):
        with pytest.raises(DegenerateMotionError, match="pure translations"):
            solve(motions)
    with pytest.raises(DegenerateMotionError, match="rotate by"):
        align_stations(pa, qa, pb, qb)


def test_nan_and_non_unit_poses_are_refused() -> None:
    (pa, qa, pb, qb), _ = _stations(1)
    bad = pb.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="B position: non-finite"):
        relative_motions(pa, qa, bad, qb, all_pairs(8))
    with pytest.raises(ValueError, match="B position"):
        align_stations(pa, qa, bad, qb)
    with pytest.raises(ValueError, match="not a unit quaternion"):
        relative_motions(pa, qa * 1.1, pb, qb, all_pairs(8))
    with pytest.raises(ValueError, match="non-finite"):
        PoseSeries(np.arange(8.0), pa, np.where(np.eye(8, 4) > 0, np.nan, qa), "a")
    with pytest.raises(AlignmentError, match="strictly increasing"):
        PoseSeries(np.zeros(8), pa, qa, "a")
    with pytest.raises(AlignmentError, match="different numbers"):
        MotionPairs(pa, qa, pb[:3], qb[:3])


# --------------------------------------------------------------------------- selection


def test_angle_threshold_and_axis_criterion() -> None:
    axes = np.array([[0, 0, 1.0]] * 6 + [[1.0, 0, 0], [0, 1.0, 0]])
    chosen = greedy_axis_selection(axes, 3)
    assert {6, 7} <= set(chosen.tolist())  # the two axes not parallel to the rest
    assert axis_criterion(axes[[0, 6, 7]]) == pytest.approx(0.0)
    assert axis_criterion(axes[:3]) == pytest.approx(1.0)
    angles = np.radians([1.0, 20.0, 90.0, 175.0])
    q = geo.rotvec_to_quat(angles[:, None] * [0.0, 0.6, 0.8])
    motions = MotionPairs(np.zeros((4, 3)), q, np.zeros((4, 3)), q)
    assert angle_mask(motions, np.radians(10)).tolist() == [False, True, True, False]
    stations, _ = _stations(2, n=12)
    sel = select_pairs(relative_motions(*stations, all_pairs(12)), max_pairs=20)
    assert len(sel.index) == 20 and sel.candidates == 66
    assert sel.axis_spread_rad > np.radians(30)


def test_the_angle_threshold_follows_the_noise() -> None:
    """Without a given threshold, pairs are dropped only when their rotation is within a few
    noise standard deviations of none or of half a turn (the angles of A and B differ only
    by noise), so the default keeps more pairs than 5 degrees would; a given threshold is
    applied as given."""
    stations, _ = _stations(7, n=25, noise=(0.001, np.radians(0.1)))
    motions = relative_motions(*stations, all_pairs(25))
    threshold = noise_angle_threshold(motions)
    assert np.radians(0.05) < threshold < np.radians(2.0)
    assert select_pairs(motions).min_angle_rad == threshold
    assert select_pairs(motions, np.radians(5.0)).min_angle_rad == np.radians(5.0)
    noisier = relative_motions(*_stations(7, n=25, noise=(0.001, np.radians(0.4)))[0],
                               all_pairs(25))
    assert noise_angle_threshold(noisier) > 2 * threshold
    fit = fit_stations(*stations, AlignmentOptions(ransac=False, refine=False),
                       np.random.default_rng(0))
    kept = angle_mask(motions, threshold).sum()
    assert len(fit.motions) == kept > angle_mask(motions, np.radians(5.0)).sum()
    exact = relative_motions(*_stations(7, n=25)[0], all_pairs(25))
    assert noise_angle_threshold(exact) < 1e-6  # no noise: only rotations of 0 are dropped


# --------------------------------------------------------------------------- RANSAC


def test_ransac_rejects_outlier_stations() -> None:
    (pa, qa, pb, qb), x = _stations(11, n=30, noise=(0.001, np.radians(0.1)))
    pb_bad, qb_bad, bad = corrupt(pb, qb, 0.2, np.random.default_rng(4))
    ij = all_pairs(30)
    motions = relative_motions(pa, qa, pb_bad, qb_bad, ij)
    keep = angle_mask(motions)
    motions, ij = motions.subset(keep), ij[keep]
    found = ransac(motions, daniilidis, rng=np.random.default_rng(0),
                   refit=lambda m: refine(m, daniilidis(m)))
    touches_bad = bad[ij[:, 0]] | bad[ij[:, 1]]
    assert not np.any(found.inliers & touches_bad)  # every corrupted pair rejected
    assert found.inliers[~touches_bad].mean() > 0.9  # and few good ones lost
    clean = _err(refine(motions.subset(~touches_bad), daniilidis(motions.subset(~touches_bad))),
                 x)
    robust = _err(found.pose, x)
    assert robust[0] < 1.5 * clean[0] + 1e-4 and robust[1] < 1.5 * clean[1] + 1e-5
    plain = _err(daniilidis(motions), x)
    assert plain[1] > 10 * robust[1]  # without RANSAC the outliers do damage


# --------------------------------------------------------------------------- time offset


@pytest.mark.parametrize("offset_s", [0.0, 0.037, 0.094])
def test_time_offset_is_recovered_within_2_ms(offset_s: float) -> None:
    rng = np.random.default_rng(int(offset_s * 1e3))
    x, world_b = random_pose(rng, 0.2), random_pose(rng, 2.0)
    a, b = simulate_streams(int(offset_s * 1e3), LASER, x, world_b,
                            StreamConfig(seconds=30.0, offset_s=offset_s))
    estimate, coarse = estimate_offset(a, b, AlignmentOptions())
    assert abs(estimate - offset_s) < 2e-3
    assert abs(coarse - offset_s) < 10e-3


def test_the_offset_estimate_is_the_minimum_its_std_describes() -> None:
    """offset_std is the spread of the minimum of the kept pairs' parabolas, so the
    estimate must sit at that minimum: the step the parabolas still ask for is small next
    to the std (the golden section alone stopped where the trimmed cost jumps)."""
    rng = np.random.default_rng(8)
    x, world_b = random_pose(rng, 0.2), random_pose(rng, 2.0)
    a, b = simulate_streams(8, LASER, x, world_b, StreamConfig(seconds=30.0, offset_s=0.03))
    options = AlignmentOptions(bootstrap=30)
    estimate, _ = estimate_offset(a, b, options)
    std = offset_std(a, b, estimate, options)
    assert abs(offset_parabolas(a, b, estimate, options).minimum()) < 0.5 * std
    assert abs(estimate - 0.03) < 4 * std


def test_streams_end_to_end_with_covariance() -> None:
    rng = np.random.default_rng(21)
    x, world_b = random_pose(rng, 0.2), random_pose(rng, 2.0)
    a, b = simulate_streams(21, LASER, x, world_b, StreamConfig(seconds=30.0, offset_s=0.05))
    result = align_streams(a, b, AlignmentOptions(bootstrap=30))
    dp, dr = _err(result.pose, x)
    assert dp < 1e-2 and dr < np.radians(0.4)
    assert abs(result.time_offset_s - 0.05) < 2e-3
    C = geo.se3_to_decoupled(result.position, geo.check_covariance(result.covariance))
    d = np.concatenate([x.position - result.position, geo.quat_to_rotvec(
        geo.quat_multiply(x.quaternion, geo.quat_conjugate(result.quaternion)))])
    assert d @ np.linalg.solve(C, d) < 22.46  # chi-square(6) 99.9 %: the covariance is honest


def test_too_short_overlap_is_refused() -> None:
    rng = np.random.default_rng(0)
    a, b = simulate_streams(0, LASER, random_pose(rng, 0.2), random_pose(rng, 1.0),
                            StreamConfig(seconds=3.0))
    with pytest.raises(AlignmentError, match="overlap"):
        estimate_offset(a, b, AlignmentOptions())


# --------------------------------------------------------------------------- files


def test_pose_pair_csv_round_trip_and_errors(tmp_path) -> None:
    rng = np.random.default_rng(0)
    a, b = simulate_streams(0, LASER, random_pose(rng, 0.2), random_pose(rng, 1.0),
                            StreamConfig(seconds=2.0, rate_a_hz=50.0, rate_b_hz=50.0))
    path = tmp_path / "pairs.csv"
    records.write_pose_pairs(path, a, b)
    a2, b2 = records.read_pose_pairs(path)
    for s, s2 in ((a, a2), (b, b2)):
        assert np.array_equal(s.t, s2.t) and np.array_equal(s.position, s2.position)
        assert np.allclose(s.quaternion, s2.quaternion, rtol=0, atol=1e-15)
    lines = path.read_text().splitlines()
    (tmp_path / "nan.csv").write_text("\n".join([*lines[:3], lines[3].replace(
        lines[3].split(",")[5], "nan", 1), *lines[4:]]))
    with pytest.raises(AlignmentError, match=r"nan.csv:4: qa_y is nan"):
        records.read_pose_pairs(tmp_path / "nan.csv")
    (tmp_path / "hdr.csv").write_text(lines[0].replace("qb_w", "w") + "\n" + lines[1])
    with pytest.raises(AlignmentError, match=r"missing column.*qb_w"):
        records.read_pose_pairs(tmp_path / "hdr.csv")
    (tmp_path / "txt.csv").write_text(lines[0] + "\n" + lines[1].replace(
        lines[1].split(",")[0], "noon", 1))
    with pytest.raises(AlignmentError, match=r"txt.csv:2: t_a is not a number"):
        records.read_pose_pairs(tmp_path / "txt.csv")
    with pytest.raises(AlignmentError, match="cannot read"):
        records.read_pose_pairs(tmp_path / "absent.csv")


def test_calibration_file_is_an_agent_static_edge(tmp_path) -> None:
    (pa, qa, pb, qb), _ = _stations(3, n=15, noise=(0.001, np.radians(0.1)))
    result = align_stations(pa, qa, pb, qb, AlignmentOptions(bootstrap=20))
    path = tmp_path / "calib.toml"
    records.write_calibration(path, result, "marvin/laser_rig", "marvin/accel_rig")
    data = tomllib.loads(path.read_text())
    edge = check_static_edge(data["static"][0], 0)  # the agent's own config check
    assert edge["parent"] == "marvin/laser_rig" and edge["child"] == "marvin/accel_rig"
    assert np.allclose(edge["position"], result.position, atol=0, rtol=0)
    assert np.allclose(edge["quaternion"], result.quaternion, atol=1e-15)
    assert edge["pos_std_m"] == pytest.approx(result.pos_std_m)
    assert edge["rot_std_rad"] == pytest.approx(result.rot_std_rad)
    with pytest.raises(AlignmentError, match="cannot be written"):
        records.calibration_toml(result, 'a"b', "c")


def test_the_offset_uncertainty_is_in_the_covariance() -> None:
    """The offset is estimated once and then held fixed: its error is common to every
    station, which the stations' own noise cannot show, so align_streams adds what it
    does to X (dX/d offset times the offset's variance) to the covariance."""
    rng = np.random.default_rng(5)
    x, world_b = random_pose(rng, 0.2), random_pose(rng, 1.0)
    a, b = simulate_streams(21, LASER, x, world_b, StreamConfig(seconds=30.0, offset_s=0.05))
    options = AlignmentOptions(bootstrap=30)
    result = align_streams(a, b, options)
    assert 0.0 < result.time_offset_std_s < 2e-3
    assert abs(result.time_offset_s - 0.05) < 4 * result.time_offset_std_s + 1e-4
    alone = align_at_offset(a, b, result.time_offset_s, 0.0, options)
    added = result.added_covariance - alone.added_covariance
    assert np.allclose(result.covariance - alone.covariance, added, rtol=1e-9, atol=0)
    assert np.trace(added) > 0
    assert np.linalg.eigvalsh(added).min() > -1e-12 * np.trace(added)  # one direction, PSD
    assert np.linalg.matrix_rank(added, tol=1e-9 * np.trace(added)) == 1
    assert result.summary()["time_offset_std_s"] == result.time_offset_std_s


def _nees_of(result, x: Pose) -> float:
    d = np.concatenate([x.position - result.position, geo.quat_to_rotvec(geo.quat_multiply(
        x.quaternion, geo.quat_conjugate(result.quaternion)))])
    return float(d @ np.linalg.solve(geo.se3_to_decoupled(result.position, result.covariance),
                                     d))


@pytest.mark.slow
def test_a_trackers_held_error_is_in_the_covariance() -> None:
    """An error that stays with sensor a (``A_k -> A_k E``: a housing's beams) cancels from
    every residual and moves X by E, so no bootstrap over stations sees it; the tracker's
    published covariance is its account of it, and X's covariance must carry it."""
    rng = np.random.default_rng(8)
    x, world_b = random_pose(rng, 0.2), random_pose(rng, 1.0)
    a, b = simulate_streams(4, LASER, x, world_b, StreamConfig(seconds=30.0, offset_s=0.02))
    held = np.diag([2e-3 ** 2] * 3 + [np.radians(0.3) ** 2] * 3)  # in sensor a's frame
    e = np.array([2e-3, -2e-3, 2e-3, *np.radians([0.3, -0.3, 0.3])])  # one std per axis
    p, q = geo.compose(a.position, a.quaternion, e[:3], geo.rotvec_to_quat(e[3:]))
    Ad = geo.adjoint(p, q)
    published = Ad @ held @ np.swapaxes(Ad, -1, -2)  # the tracker's world-frame covariance
    options = AlignmentOptions(bootstrap=30)
    honest = align_streams(PoseSeries(a.t, p, q, "a", published), b, options)
    silent = align_streams(PoseSeries(a.t, p, q, "a"), b, options)  # the old covariance
    assert _nees_of(honest, x) < 16.8  # chi2(6) 99 %
    assert _nees_of(silent, x) > 50


def test_only_the_part_a_tracker_calls_systematic_is_held() -> None:
    """A sample's own noise differs from station to station, so the bootstrap counts it; a
    tracker that says which part of its covariance persists (``systematic``) has only that
    part held, not its noise again; without it the whole covariance is held."""
    rng = np.random.default_rng(8)
    x, world_b = random_pose(rng, 0.2), random_pose(rng, 1.0)
    a, b = simulate_streams(4, LASER, x, world_b, StreamConfig(seconds=30.0, offset_s=0.02))
    n = len(a)
    held = np.broadcast_to(np.diag([1e-6] * 3 + [1e-7] * 3), (n, 6, 6))
    noise = np.broadcast_to(np.diag([4e-6] * 3 + [3e-6] * 3), (n, 6, 6))
    options = AlignmentOptions(bootstrap=30, estimate_offset=False, offset_s=0.02)

    def added(series: PoseSeries) -> np.ndarray:
        return align_streams(series, b, options).added_covariance

    told = added(PoseSeries(a.t, a.position, a.quaternion, "a", held + noise, systematic=held))
    assert np.allclose(told, added(PoseSeries(a.t, a.position, a.quaternion, "a", held)),
                       rtol=1e-9, atol=0)
    untold = added(PoseSeries(a.t, a.position, a.quaternion, "a", held + noise))
    assert np.trace(untold) > 3 * np.trace(told)
    with pytest.raises(AlignmentError, match="systematic covariances must be"):
        PoseSeries(a.t, a.position, a.quaternion, "a", held + noise, systematic=held[1:])


@pytest.mark.slow
def test_an_error_the_stations_share_through_parameters_is_in_the_covariance() -> None:
    """An error that differs from station to station but comes from parameters every
    station shares (here sensor a's rotation read 2 % too large about each axis: its error
    grows with how far the rig turned) neither cancels like a held error nor varies like
    noise; given each sample's sensitivity to the parameters, X's covariance carries what
    the motions make of it, where reading the same covariances as held misses it."""
    rng = np.random.default_rng(0)
    x, world_b = random_pose(rng, 0.2), random_pose(rng, 1.0)
    a, b = simulate_streams(4, LASER, x, world_b, StreamConfig(
        seconds=30.0, offset_s=0.02, pos_std_m=2e-4, rot_std_rad=np.radians(0.02)))
    turn = geo.quat_to_rotvec(geo.quat_multiply(a.quaternion,
                                                geo.quat_conjugate(a.quaternion[0])))
    S = np.zeros((len(a), 6, 3))  # per one std of each parameter
    S[:, :3] = 0.005 * turn[:, :, None] * np.eye(3)
    S[:, 3:] = 0.02 * turn[:, :, None] * np.eye(3)
    e = S @ rng.normal(size=3)  # one draw of the parameters, shared by every sample
    p = a.position + e[:, :3] + np.cross(e[:, 3:], a.position)
    q = geo.quat_multiply(geo.rotvec_to_quat(e[:, 3:]), a.quaternion)
    published = S @ np.swapaxes(S, 1, 2) + 1e-12 * np.eye(6)
    options = AlignmentOptions(bootstrap=30, estimate_offset=False, offset_s=0.02)
    shared = align_streams(PoseSeries(a.t, p, q, "a", published, S, ("x", "y", "z")), b,
                           options)
    held = align_streams(PoseSeries(a.t, p, q, "a", published), b, options)
    assert _nees_of(shared, x) < 12.6  # chi2(6) 95 %
    assert _nees_of(held, x) > 50
    assert shared.shared_parameters == ("x", "y", "z")
    assert shared.shared_sensitivity.shape == (6, 3) and held.shared_sensitivity.shape == (6, 0)
    with pytest.raises(AlignmentError, match="sensitivities must be"):
        PoseSeries(a.t, p, q, "a", published, S, ("x", "y"))


def test_published_covariances_are_checked() -> None:
    t = np.arange(4.0)
    p, q = np.zeros((4, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (4, 1))
    with pytest.raises(AlignmentError, match="covariances must be 4 finite 6x6"):
        PoseSeries(t, p, q, "a", np.zeros((3, 6, 6)))
    assert PoseSeries(t, p, q, "a", np.zeros((4, 6, 6))).covariance_at([1.4, 1.6])[0].shape \
        == (6, 6)


@pytest.mark.slow
def test_the_propagated_covariance_is_xs_spread_over_the_stations_noise() -> None:
    """X's covariance propagated from each station's own noise (both trackers', each
    station alone, so that the pairs sharing a station move together) is the covariance
    of X over draws of that noise: 400 draws on 12 stations give a mean NEES near 6 and a
    spread that whitens to the identity; the pairs read as independent (the Gauss-Newton
    covariance of their residuals) understate it several times over."""
    from services.alignment.covariance import propagated_covariance
    from services.alignment.pipeline import solver_for
    from services.alignment.solvers import linearised_residuals

    truth, x = _stations(4, n=12)
    n, noise = len(truth[0]), (0.001, np.radians(0.1))
    J = np.tile(np.eye(6), (n, 1, 1))
    decoupled = np.diag([noise[0] ** 2] * 3 + [noise[1] ** 2] * 3)
    rng = np.random.default_rng(2)
    ij = all_pairs(n)
    solver = solver_for(AlignmentOptions())

    def draw() -> tuple[np.ndarray, ...]:
        return (*add_pose_noise(*truth[:2], *noise, rng), *add_pose_noise(*truth[2:], *noise,
                                                                           rng))

    def shift(pose: Pose) -> np.ndarray:
        dphi = geo.quat_to_rotvec(geo.quat_multiply(x.quaternion,
                                                    geo.quat_conjugate(pose.quaternion)))
        return np.concatenate([x.position - pose.position - np.cross(dphi, pose.position),
                               dphi])

    stations = draw()
    estimate = solver(relative_motions(*stations, ij))
    noise_of = []
    for p in (stations[0], stations[2]):
        J[:, :3, 3:] = geo.skew(p)
        noise_of.append(J @ decoupled @ np.swapaxes(J, 1, 2))
    C = propagated_covariance(stations, ij, estimate, *noise_of)
    # Gauss-Newton from an estimate within the noise converges in three steps
    e = np.array([shift(refine(relative_motions(*draw(), ij), estimate, iterations=3))
                  for _ in range(400)])
    nees = np.einsum("di,di->d", e, np.linalg.solve(C, e.T).T)
    assert np.mean(nees) == pytest.approx(6.0, abs=0.6)
    root = np.linalg.cholesky(C)
    white = np.linalg.solve(root, np.linalg.solve(root, e.T @ e / len(e)).T)
    assert np.all(np.abs(np.linalg.eigvalsh(white) - 1.0) < 0.35)
    r, Jr, _ = linearised_residuals(relative_motions(*stations, ij), estimate)
    independent = np.linalg.inv(np.einsum("pki,pkj->ij", Jr, Jr)) * np.mean(r ** 2)
    assert np.trace(np.linalg.solve(C, independent)) < 0.5 * 6


@pytest.mark.slow
def test_the_bootstraps_factor_makes_the_nested_estimates_inverse_unbiased() -> None:
    """The bootstrap's covariance estimates from 40 stations an ideal bootstrap that 100
    resamples estimate again: with the factor of both, the mean NEES of an error drawn from
    the true covariance is 6; with the stations' alone it is ~6.5 (measured on the
    alignment itself: 6.43, se 0.25).  Where a computed covariance is added, the factor
    shrinks with the estimate's share and the mean NEES stays 6."""
    from services.alignment.covariance import _inverse_unbiased, inverse_unbiased

    rng = np.random.default_rng(5)
    stations, resamples, draws = 40, 100, 20000
    A = rng.normal(size=(6, 6))
    sigma = A @ A.T + 0.5 * np.eye(6)

    def estimated(cov: np.ndarray, nu: int) -> np.ndarray:
        """``draws`` Wishart estimates of ``cov`` (6x6, or one per draw) with ``nu`` dof."""
        L = np.linalg.cholesky(cov)
        z = rng.normal(size=(draws, nu, 6))
        return L @ (np.einsum("dni,dnj->dij", z, z) / nu) @ np.swapaxes(L, -1, -2)

    ideal = estimated(sigma, stations - 1)  # the bootstrap over every resample
    estimate = estimated(ideal, resamples - 1)  # its Monte Carlo estimate
    e = rng.normal(size=(draws, 6)) @ np.linalg.cholesky(sigma).T
    nees = np.einsum("di,di->d", e, np.linalg.solve(estimate, e[..., None])[..., 0])
    both, stations_only = _inverse_unbiased(stations, resamples), 39 / 32
    assert np.mean(nees) / both == pytest.approx(6.0, abs=0.15)
    assert np.mean(nees) / stations_only > 6.3
    with pytest.raises(AlignmentError, match="at least 9 solvable bootstrap resamples"):
        _inverse_unbiased(stations, 8)
    assert inverse_unbiased(estimate[0], np.zeros((6, 6)), stations, resamples) \
        == pytest.approx(both, rel=1e-12)
    # half of the covariance computed, not estimated (an installation's shared tolerances):
    # the factor of the whole-estimate case on the estimated half makes it conservative
    added = sigma
    e = rng.normal(size=(draws, 6)) @ np.linalg.cholesky(sigma + added).T
    k = np.array([inverse_unbiased(s, added, stations, resamples) for s in estimate])
    assert np.all((k > 1.0) & (k < both))

    def mean_nees(factor: np.ndarray | float) -> float:
        c = np.asarray(factor)[..., None, None] * estimate + added
        return float(np.mean(np.einsum("di,di->d", e, np.linalg.solve(c, e[..., None])[..., 0])))

    assert mean_nees(k) == pytest.approx(6.0, abs=0.15)
    assert mean_nees(both) < 5.75


def test_the_nees_band_counts_the_installation_error_the_trials_share() -> None:
    """``uma eval alignment``'s band of a seed's mean NEES: as many trials as there are when
    nothing is shared; towards one trial when the shared installation error dominates."""
    from services.alignment.evaluate import _covariance_figures
    rng = np.random.default_rng(3)

    def trials(shared_scale: float) -> list[dict]:
        out = []
        for _ in range(50):
            p = rng.uniform(-0.2, 0.2, 3)
            S = np.eye(6)
            S[:3, 3:] = -geo.skew(p)
            own = np.diag([1e-6] * 3 + [1e-7] * 3)
            shared = shared_scale * own
            per_std = S @ np.sqrt(shared)  # X's error per one std of each shared parameter
            out.append({"nees": float(rng.chisquare(6)), "consistency": {
                "covariance": S @ (own + shared) @ S.T,
                "sensitivity": {f"parameter {j}": per_std[:, j] for j in range(6)}}})
        return out
    alone = _covariance_figures(trials(0.0))
    assert alone["effective_runs"] == pytest.approx(50)
    assert alone["bounds_95"] == pytest.approx(alone["bounds_95_independent_runs"])
    held = _covariance_figures(trials(100.0))
    assert 1.0 <= held["effective_runs"] < 1.2
    assert held["bounds_95"][1] > 2 * held["bounds_95_independent_runs"][1]


def test_a_seeds_share_comes_with_its_wilson_interval() -> None:
    """``uma eval alignment``'s share inside chi2(6)'s bound carries Wilson's 95 % interval
    over the seed's trials: 13 of 17 cannot tell a share of 0.85 from one of 0.6."""
    from services.alignment.evaluate import _covariance_figures, _wilson_95
    assert _wilson_95(13, 17) == pytest.approx([0.527, 0.904], abs=1e-3)
    assert _wilson_95(95, 100) == pytest.approx([0.888, 0.978], abs=1e-3)
    rng = np.random.default_rng(5)
    trials = [{"nees": float(x), "consistency": {"covariance": np.eye(6), "sensitivity": {}}}
              for x in rng.chisquare(6, 40)]
    f = _covariance_figures(trials)
    inside = sum(t["nees"] <= 12.592 for t in trials)
    assert f["within_chi2_95_fraction (ideal 0.95)"] == inside / 40
    assert f["within_chi2_95_fraction_wilson_95"] == _wilson_95(inside, 40)


def test_an_honest_seeds_share_spreads_wider_when_its_trials_share_the_installation() -> None:
    """The share of trials inside chi2(6)'s 95 % bound that an honest covariance falls
    below in 5 % of the cases: a binomial's over 100 independent trials (0.91), far lower
    when most of each trial's error is the installation's one draw."""
    from services.alignment.evaluate import _honest_share_quantile
    rng = np.random.default_rng(4)
    n = 100
    base = np.array([np.diag(rng.uniform(0.5, 2.0, 6)) for _ in range(n)])
    alone = _honest_share_quantile(base, np.zeros((n, 6, 3)))
    assert alone == pytest.approx(0.91, abs=0.011)
    S = rng.normal(size=(n, 6, 3))  # three tolerances, each trial its own sensitivity
    shared = _honest_share_quantile(base + S @ np.swapaxes(S, 1, 2), S)
    assert shared < 0.85


def test_the_bootstraps_share_of_a_shared_error_is_what_its_resamples_make_of_it() -> None:
    """An error that every recording shares but that differs between stations (here a
    scale error of sensor a's rotations, per parameter) spreads the resamples as noise
    would, and X's covariance counts it whole already; ``Bootstrap.shared``, the resamples'
    spread of X's shift under each parameter (first order), matches solving each resample
    again with the stations moved.  The covariance takes it out of the spread, in no
    direction below the spread's resolution."""
    from services.alignment.covariance import (
        _inverse_unbiased,
        _less,
        bootstrap_covariance,
        inverse_unbiased,
        shared_shifts,
    )
    from services.alignment.pipeline import moved_motions, solver_for
    from services.alignment.solvers import relative_motions

    stations, _ = _stations(11, n=20, noise=(0.001, np.radians(0.1)))
    pa, qa = stations[:2]
    turn = geo.quat_to_rotvec(qa)
    sensitivity = np.zeros((len(pa), 6, 3))
    sensitivity[:, :3] = 0.002 * turn[:, :, None] * np.eye(3)
    sensitivity[:, 3:] = 0.005 * turn[:, :, None] * np.eye(3)
    options = AlignmentOptions(bootstrap=20)
    solver = solver_for(options)
    ij = np.array([(i, j) for i in range(len(pa)) for j in range(i + 1, len(pa))])
    motions = relative_motions(*stations, ij)
    estimate = solver(motions)
    boot = bootstrap_covariance(*stations, ij, estimate, solver, 20, np.random.default_rng(1))
    moved = list(moved_motions(stations, sensitivity, ij).values())

    def shift(pairs: MotionPairs, w: np.ndarray | None, origin: Pose) -> np.ndarray:
        xk = solver(pairs, w)
        dphi = geo.quat_to_rotvec(geo.quat_multiply(xk.quaternion,
                                                    geo.quat_conjugate(origin.quaternion)))
        return np.concatenate([xk.position - origin.position
                               - np.cross(dphi, origin.position), dphi])

    whole = [shift(m, None, estimate) for m in moved]
    exact = np.zeros((6, 6))
    for w in boot.weights:
        used = w > 0
        xb = solver(motions.subset(used), w[used])
        for m, s in zip(moved, whole, strict=True):
            e = shift(m.subset(used), w[used], xb) - s
            exact += np.outer(e, e) / (boot.resamples - 1)
    assert np.allclose(boot.covariance(),
                       boot.spread * _inverse_unbiased(boot.stations, boot.resamples), rtol=1e-12)
    boot = replace(boot, shared_shifts=shared_shifts(boot, motions, moved, estimate))
    # first order: each resample also re-weighs translation against rotation (4 % here)
    assert np.linalg.norm(boot.shared - exact) < 0.1 * np.linalg.norm(exact)
    floor = np.sqrt(2.0 / (boot.stations - 1))
    assert np.allclose(_less(boot.spread, 2.0 * boot.spread, floor), floor * boot.spread)
    noise = _less(boot.spread, boot.shared, floor)
    k = boot.covariance()[0, 0] / noise[0, 0]
    assert np.allclose(boot.covariance(), k * noise, rtol=1e-12)
    assert k > inverse_unbiased(noise, np.zeros((6, 6)), boot.stations, boot.resamples)


@pytest.mark.slow
def test_the_covariance_is_not_conservative_where_shared_errors_dominate() -> None:
    """60 recordings of one motion, each with its own station noise and its own draw of
    three shared parameters (sensor a's rotations read too large, as in the test above,
    here larger than the noise): the mean NEES of X against its covariance is near 6,
    where the bootstrap's spread taken whole with the whole-estimate factor (the shared
    errors counted twice, the factor on what is computed) stays conservative."""
    from services.alignment.covariance import _inverse_unbiased

    rng = np.random.default_rng(0)
    x, world_b = random_pose(rng, 0.2), random_pose(rng, 1.0)
    config = StreamConfig(seconds=20.0, offset_s=0.02, pos_std_m=5e-4,
                          rot_std_rad=np.radians(0.05))
    nees, whole = [], []
    for k in range(60):
        a, b = simulate_streams(100 + k, LASER, x, world_b, config)
        turn = geo.quat_to_rotvec(geo.quat_multiply(a.quaternion,
                                                    geo.quat_conjugate(a.quaternion[0])))
        S = np.zeros((len(a), 6, 3))
        S[:, :3] = 0.001 * turn[:, :, None] * np.eye(3)
        S[:, 3:] = 0.004 * turn[:, :, None] * np.eye(3)
        e = S @ np.random.default_rng([7, k]).normal(size=3)
        p = a.position + e[:, :3] + np.cross(e[:, 3:], a.position)
        q = geo.quat_multiply(geo.rotvec_to_quat(e[:, 3:]), a.quaternion)
        result = align_streams(  # b publishes no covariance: X's rests on the bootstrap
            PoseSeries(a.t, p, q, "a", S @ np.swapaxes(S, 1, 2) + 1e-12 * np.eye(6), S,
                       ("x", "y", "z")), replace(b, covariance=None, systematic=None),
            AlignmentOptions(bootstrap=30, estimate_offset=False, offset_s=0.02, seed=k))
        boot = result.bootstrap
        nees.append(_nees_of(result, x))
        whole.append(_nees_of(replace(result, covariance=boot.spread * _inverse_unbiased(
            boot.stations, boot.resamples) + result.added_covariance), x))
    assert 5.6 < np.mean(nees) < 7.5
    assert np.mean(whole) < 5.6
