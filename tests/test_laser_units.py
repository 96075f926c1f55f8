"""Laser-dot tracker pieces against exact data: DLT vs OpenCV, dot detection, the pose
solver, the 24 labelings, temporal coherence, gating and the no-pose corner cases."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agent import geometry as geo
from services.installation.ivy import intersect_beam, make_walls, on_active_area, screen_to_world
from services.installation.laser_housing import BEAM_DIRECTIONS, LABELS
from services.laser_camera import pose as pose_module
from services.laser_camera.detection import (
    DetectorParams,
    _component_stats,
    detect_dots,
    detect_dots_in,
)
from services.laser_camera.homography import (
    apply_homography,
    dlt_homography,
    homography_jacobian,
    homography_scale,
    normalising_transform,
)
from services.laser_camera.pose import (
    PERMUTATIONS,
    candidate_poses,
    frame_from_points,
    labeling_errors,
    reflection,
)
from services.laser_camera.tracker import (
    LabeledDots,
    LaserTracker,
    NoPose,
    PoseEstimate,
    TrackerParams,
    WorldDots,
    _ScreenMap,
    clipped_spot_bias,
)
from services.sim.render import SensorModel
from services.sim.world import IvyWorld, WorldConfig

RNG_SEED = 1234


def random_rig_pose(rng: np.random.Generator, upright: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
    p = rng.uniform(-0.8, 0.8, 3)
    if upright:
        r = np.radians(rng.uniform([-25, -25, -180], [25, 25, 180]))
        q = geo.quat_multiply(geo.rotvec_to_quat([0, 0, r[2]]),
                              geo.rotvec_to_quat([r[0], r[1], 0]))
    else:
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
    return p, q


def exact_hits(world: IvyWorld, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    hits = world.laser_hits(p, q)
    return np.array([hits[k].point for k in LABELS])


def world_dots(points: np.ndarray, std: float = 1e-3) -> WorldDots:
    n = len(points)
    return WorldDots(np.asarray(points, float).reshape(-1, 3), np.full(n, std), ["w"] * n,
                     np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (n, 1, 1)), ["c"] * n)


@pytest.fixture(scope="module")
def world() -> IvyWorld:
    return IvyWorld(seed=3, ideal=True)


# ------------------------------------------------------------------ homography (eqs 5.19-5.37)


def test_dlt_equals_opencv_on_exact_data() -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(20):
        H0 = np.array([[0.004, 2e-4, -1.2], [1e-4, -0.0041, 1.1], [1e-5, 2e-6, 1.0]])
        H0[:2] += rng.normal(0, 1e-4, (2, 3))
        H0[2, :2] += rng.normal(0, 1e-5, 2)
        src = rng.uniform([0, 0], [640, 480], (int(rng.integers(4, 40)), 2))
        dst = apply_homography(H0, src)
        H = dlt_homography(src, dst)
        H_cv, _ = cv2.findHomography(src, dst, 0)
        assert np.abs(H - H_cv).max() < 1e-6
        assert np.abs(H - H0).max() < 1e-9 * np.abs(H0).max()


def test_normalisation_centres_and_scales() -> None:
    pts = np.random.default_rng(1).uniform(100, 600, (30, 2))
    T = normalising_transform(pts)
    n = np.column_stack([pts, np.ones(30)]) @ T.T
    assert np.allclose(n[:, :2].mean(0), 0, atol=1e-12)
    assert np.linalg.norm(n[:, :2], axis=1).mean() == pytest.approx(np.sqrt(2))


def test_homography_jacobian_matches_finite_differences() -> None:
    H = np.array([[0.004, 2e-4, -1.2], [1e-4, -0.0041, 1.1], [1e-5, 2e-6, 1.0]])
    x, e = np.array([120.0, 300.0]), 1e-4
    steps = e * np.eye(2)
    num = (apply_homography(H, x + steps) - apply_homography(H, x[None])).T / e
    assert np.allclose(homography_jacobian(H, x), num, rtol=1e-4)


@pytest.mark.parametrize("src, dst, msg", [
    (np.zeros((3, 2)), np.zeros((3, 2)), "at least 4"),
    ([[0, 0], [1, 0], [2, 0], [3, 0], [4, 0]], np.random.default_rng(0).random((5, 2)),
     "degenerate"),
    ([[0, 0], [1, 0], [0, 1], [np.nan, 1]], np.ones((4, 2)), "non-finite"),
    (np.ones((4, 2)), np.ones((4, 2)), "coincide"),
    (np.random.default_rng(0).random((5, 2)), np.random.default_rng(1).random((4, 2)),
     "destination"),
])
def test_dlt_refuses_bad_input(src, dst, msg) -> None:
    with pytest.raises(ValueError, match=msg):
        dlt_homography(src, dst)


# ------------------------------------------------------------------ detection (§5.2.1)


def test_detection_is_subpixel_on_noise_free_renders() -> None:
    quiet = WorldConfig.ideal(sensor=SensorModel(read_noise_dn=0.0, gain_dn_per_e=0.0,
                                                 stuck_pixels=0),
                              exposure_s=0.0, distractor_rate=0.0)
    w = IvyWorld(seed=5, config=quiet)
    rng = np.random.default_rng(RNG_SEED)
    errors = []
    for _ in range(25):
        frame = w.render(0.0, pose=random_rig_pose(rng))
        for cam, truth in frame.image_points.items():
            dots = detect_dots(frame.images[cam], DetectorParams(read_noise=0.0, gain=0.0))
            for uv in truth.values():
                d = np.hypot(*(dots[:, :2] - uv).T)
                # spots clipped by the screen's edge are biased by design; the tracker
                # drops them (edge guard), so judge only unclipped ones
                if d.min() < 2.0:
                    errors.append(d.min())
    errors = np.array(errors)
    assert len(errors) > 50
    assert np.quantile(errors, 0.98) < 0.1, errors.max()


def _blob(img: np.ndarray, u: float, v: float, sigma: float, peak: float) -> None:
    vv, uu = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    g = peak * np.exp(-((uu - u) ** 2 + (vv - v) ** 2) / (2 * sigma ** 2))
    np.add(img, g, out=img)


def test_detection_std_covers_the_pixels_flipping_across_the_threshold() -> None:
    """A dim spot drawn 400 times with the sensor noise the detector assumes: its
    centroids spread as the reported std says, which holds the pixels that the noise puts
    in or out of the spot (without them the reported variance was a twelfth of the
    spread's)."""
    p = DetectorParams(floor_px=0.0)
    rng = np.random.default_rng(RNG_SEED)
    clean = np.full((40, 40), p.dark_level)
    _blob(clean, 20.3, 19.6, 1.3, 90.0)
    found, stds = [], []
    for _ in range(400):
        noisy = clean + rng.normal(0.0, 1.0, clean.shape) * np.sqrt(
            p.read_noise ** 2 + p.gain * (clean - p.dark_level))
        dots = detect_dots(np.clip(np.rint(noisy), 0, 255).astype(np.uint8), p)
        assert len(dots) == 1
        found.append(dots[0, :2])
        stds.append(dots[0, 4])
    spread = np.mean(np.var(np.array(found), axis=0))
    assert 0.8 < spread / np.mean(np.square(stds)) < 1.25


def test_detection_merges_fragments_and_ignores_hot_pixels() -> None:
    img = np.full((480, 640), 8.0)
    _blob(img, 100.3, 200.7, 1.0, 400)
    _blob(img, 300.0, 100.0, 0.8, 300)
    _blob(img, 303.5, 100.0, 0.8, 300)  # a second fragment of the same spot
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    img[50, 50] = 255  # stuck pixel
    dots = detect_dots(img)
    assert len(dots) == 2
    dots = dots[np.argsort(dots[:, 0])]
    assert np.hypot(dots[0, 0] - 100.3, dots[0, 1] - 200.7) < 0.1  # saturated, point-sampled
    assert np.hypot(dots[1, 0] - 301.75, dots[1, 1] - 100.0) < 0.1
    assert detect_dots(np.zeros((480, 640), np.uint8)).shape == (0, 5)


def _full_frame_components(img: np.ndarray, p: DetectorParams) -> np.ndarray:
    """Reference: every component's (u, v, flux, area) from labelling the whole frame."""
    _, mask = cv2.threshold(img, p.threshold, 255, cv2.THRESH_BINARY)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    vv, uu = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    rows = []
    for k in range(1, n):
        if p.min_area <= stats[k, 4] <= p.max_area:
            s = np.where(labels == k, np.maximum(img - p.dark_level, 0.0), 0.0)
            rows.append([(s * uu).sum() / s.sum(), (s * vv).sum() / s.sum(), s.sum(),
                         stats[k, 4]])
    return np.array(rows).reshape(-1, 4)


def test_banded_labelling_finds_what_full_frame_labelling_finds() -> None:
    rng = np.random.default_rng(RNG_SEED)
    p = DetectorParams(merge_px=0.0)  # compare components, not merged spots
    for _ in range(10):
        img = np.full((120, 160), 8.0)
        for u, v in rng.uniform([0, 0], [160, 120], (12, 2)):  # some touch, some at edges
            _blob(img, u, v, rng.uniform(0.6, 2.5), rng.uniform(60, 400))
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        img[rng.integers(0, 120, 5), rng.integers(0, 160, 5)] = 200  # hot pixels
        img[40:60, 30] = img[40, 30:50] = 250  # an L: one component spanning rows and columns
        ours, ref = detect_dots(img, p), _full_frame_components(img, p)
        assert len(ours) == len(ref)
        ours = ours[np.lexsort(ours[:, :2].T)]
        ref = ref[np.lexsort(ref[:, :2].T)]
        np.testing.assert_allclose(ours[:, :4], ref, rtol=1e-12, atol=1e-9)


def test_component_statistics_are_opencvs() -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(300):  # sparse to dense masks: one component, several, none
        shape = tuple(rng.integers(1, 60, 2))
        mask = (rng.random(shape) < rng.uniform(0, 0.4)).view(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8,
                                                               ltype=cv2.CV_32S)
        assert _component_stats(mask, labels, n) == stats[1:].tolist()


def test_a_clipped_spots_bias_is_its_cut_centroids_offset() -> None:
    """``clipped_spot_bias``: a Gaussian spot (std ``edge_std_m * sqrt(pi / 2)``) cut by a
    straight edge has its centroid pulled inwards; given where that centroid lies, the
    bias is how far the spot's centre lies from it (sampled here on a fine grid), capped
    at ``edge_std_m`` -- a dot 8 mm inside a screen's edge is not 4 mm uncertain."""
    edge_std = 0.004
    sigma = edge_std * np.sqrt(np.pi / 2)
    u = np.linspace(-0.06, 0.06, 24001)
    for centre in (-0.002, 0.0, 0.003, 0.006, 0.009, 0.012):
        w = np.exp(-0.5 * ((u - centre) / sigma) ** 2) * (u >= 0)
        centroid = float(np.sum(w * u) / np.sum(w))
        expected = min(edge_std, centroid - centre)
        assert clipped_spot_bias(centroid, edge_std) == pytest.approx(expected, abs=2e-5)
    assert clipped_spot_bias(0.008, edge_std) < 0.001
    assert clipped_spot_bias(0.0, edge_std) == edge_std


def test_the_trackers_plain_float_screen_map_is_the_shared_numpy_one() -> None:
    """The tracker maps each dot image -> screen -> world on floats (``_ScreenMap``); it must
    say what eqs. 5.39-5.40's numpy functions say: the same point, the same std (pixel std
    through the homography's scale, calibration and edge terms), the same bend, the same
    edge term, and None exactly off the active area."""
    rng = np.random.default_rng(RNG_SEED)
    p = TrackerParams()
    for wall in make_walls().values():
        side = wall.screen_side_m
        pixels = np.array([[0, 0], [640, 0], [0, 480], [640, 480]], float)
        corners = np.array([[0, 0], [side, 0], [0, side], [side, side]])
        H = dlt_homography(pixels + rng.normal(0, 15, (4, 2)), corners)
        m = _ScreenMap(tuple(H.ravel().tolist()), tuple(wall.rotation.ravel().tolist()),
                       tuple(wall.translation.tolist()), wall.plane_distance, side, 0.001)
        uv = rng.uniform(-40, 680, (200, 2))  # some beyond the screen's image
        xy = apply_homography(H, uv)
        on = on_active_area(xy, side)
        inside = np.minimum(xy, side - xy).min(axis=1)
        edge = np.where(on_active_area(xy, side, p.edge_guard_m), 0.0,
                        [clipped_spot_bias(d, p.edge_std_m) for d in inside])
        std = np.sqrt((0.3 * homography_scale(H, uv)) ** 2 + 0.001 ** 2 + edge ** 2)
        u = 2 * xy / side - 1
        bend = np.maximum(0, 1 - u[:, 0] ** 2) * np.maximum(0, 1 - u[:, 1] ** 2)
        world = screen_to_world(xy, wall.rotation, wall.translation, wall.plane_distance)
        assert 0 < on.sum() < len(uv)
        for k, (x, y) in enumerate(uv.tolist()):
            dot = m.world_dot(x, y, 0.3, p)
            assert (dot is not None) == on[k]
            if dot is not None:
                np.testing.assert_allclose(dot[0], world[k], rtol=1e-12, atol=1e-12)
                assert dot[1:] == pytest.approx((std[k], bend[k], edge[k]), rel=1e-12,
                                                abs=1e-15)


def test_detection_in_windows_is_detection_in_full_where_the_windows_are() -> None:
    img = np.full((480, 640), 8.0)
    for u, v in ((100.3, 200.7), (120.0, 204.0), (400.0, 300.0), (600.0, 50.0)):
        _blob(img, u, v, 1.0, 300)
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    full = detect_dots(img)
    # two overlapping windows around the close pair (joined, not counted twice), one more
    dots, whole = detect_dots_in(img, [(80, 180, 130, 230), (100, 180, 150, 230),
                                       (380, 280, 420, 320)])
    assert whole and len(dots) == 3
    np.testing.assert_allclose(dots[np.argsort(dots[:, 0])], full[np.argsort(full[:, 0])][:3])
    # a window clipped by the image is whole; one cutting a spot is not
    assert detect_dots_in(img, [(580, -20, 660, 80)])[1]
    assert not detect_dots_in(img, [(401, 280, 440, 320)])[1]
    assert detect_dots_in(img, [(200, 200, 240, 240)])[0].shape == (0, 5)


@pytest.mark.parametrize("bad", [{"roi_half_px": -1}, {"roi_refresh_s": -0.1}])
def test_negative_window_parameters_are_refused(bad) -> None:
    with pytest.raises(ValueError, match="roi_half_px and roi_refresh_s must be >= 0"):
        TrackerParams(**bad)


@pytest.mark.parametrize("bad", [np.zeros((480, 640)), np.zeros((4, 4, 3), np.uint8), None])
def test_detection_refuses_non_gray8(bad) -> None:
    with pytest.raises(ValueError, match="uint8"):
        detect_dots(bad)


# ------------------------------------------------------------------ pose (§5.3)


def test_housing_geometry_is_fig_5_4() -> None:
    d = BEAM_DIRECTIONS
    assert np.allclose(d[1], -d[2])
    assert d[3] @ d[1] == 0 and d[4] @ d[1] == 0 and d[3] @ d[4] == 0
    assert np.cross(d[1], d[3]) @ d[4] > 0  # n = P0P1 x P0P3 points along beam 4


def test_pose_solver_is_exact_for_random_poses(world: IvyWorld) -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(200):
        p, q = random_rig_pose(rng)
        P0, R = frame_from_points(exact_hits(world, p, q))
        assert np.linalg.norm(P0 - p) < 1e-9
        assert geo.quat_angle(geo.matrix_to_quat(R), q) < 1e-9


def test_every_permutation_labels_correctly_or_as_the_reflection(world: IvyWorld) -> None:
    rng = np.random.default_rng(RNG_SEED + 1)
    for _ in range(30):
        p, q = random_rig_pose(rng)
        P = exact_hits(world, p, q)
        for perm in PERMUTATIONS:
            shown = P[perm]  # shown[j] is the hit of diode perm[j] + 1
            truth_order = tuple(int(np.flatnonzero(perm == k)[0]) for k in range(4))
            cands = candidate_poses(shown, max_error=1e-6)
            assert {c.order for c in cands[:2]} == {truth_order, reflection(truth_order)}
            right = next(c for c in cands if c.order == truth_order)
            assert geo.quat_angle(right.quaternion, q) < 1e-9
            mirror = next(c for c in cands if c.order == reflection(truth_order))
            assert np.degrees(geo.quat_angle(mirror.quaternion, q)) == pytest.approx(180, abs=1e-6)
            assert np.linalg.norm(mirror.position - p) < 1e-9  # same P0, eq. 5.8


def test_wrong_labelings_score_high(world: IvyWorld) -> None:
    p, q = random_rig_pose(np.random.default_rng(7), upright=True)
    eps = np.sort(labeling_errors(exact_hits(world, p, q)))
    assert eps[1] < 1e-9 and eps[2] > 0.05


def test_degenerate_points_give_no_frame() -> None:
    with pytest.raises(ValueError, match=r"P1 and P2|line P1P2"):
        frame_from_points(np.zeros((4, 3)))
    assert candidate_poses(np.zeros((4, 3)), 1.0) == []
    assert candidate_poses(np.outer(np.arange(4.0), [1, 0, 0]), 1.0) == []


# ------------------------------------------------------------------ tracker (§5.3.1)


def make_tracker() -> LaserTracker:
    # solve() works on world dots, needs no cameras; exact dots: an ideal installation
    return LaserTracker(calibration=None, params=TrackerParams.ideal())


def test_initialisation_picks_the_upright_solution_and_coherence_keeps_it(world) -> None:
    tr = make_tracker()
    t_arr = np.arange(0, 6, 1 / 15)
    p_all, q_all = world.rig_pose(t_arr)
    rng = np.random.default_rng(3)
    for t, p, q in zip(t_arr, p_all, q_all, strict=True):
        P = exact_hits(world, p, q)[rng.permutation(4)]
        res = tr.solve(world_dots(P), float(t))
        assert isinstance(res, PoseEstimate), res
        assert geo.quat_angle(res.quaternion, q) < 1e-6
        for k, pt in res.dots.items():
            assert np.allclose(pt, world.laser_hits(p, q)[k].point)
    assert tr.counts["pose"] == len(t_arr)


def test_upside_down_start_is_refused(world) -> None:
    p = np.zeros(3)
    q = geo.rotvec_to_quat([np.pi, 0, 0])  # rolled over: neither solution is upright
    res = make_tracker().solve(world_dots(exact_hits(world, p, q)), 0.0)
    assert isinstance(res, NoPose) and res.reason == "not_upright"


def test_too_few_dots_and_distractors(world) -> None:
    p, q = random_rig_pose(np.random.default_rng(11), upright=True)
    P = exact_hits(world, p, q)
    tr = make_tracker()
    res = tr.solve(world_dots(P[:3]), 0.0)
    assert isinstance(res, NoPose) and res.reason == "too_few_dots" and res.n_dots == 3
    distractor = np.array([[1.22, 0.3, -0.2]])
    res = tr.solve(world_dots(np.vstack([P, distractor])), 0.1)
    assert isinstance(res, PoseEstimate) and geo.quat_angle(res.quaternion, q) < 1e-6
    res = tr.solve(world_dots(np.vstack([P[:3], distractor])), 0.2)
    assert isinstance(res, NoPose) and res.reason == "no_consistent_labeling"
    res = tr.solve(world_dots(np.zeros((0, 3))), 0.3)
    assert isinstance(res, NoPose) and res.reason == "too_few_dots"
    res = tr.solve(world_dots(np.random.default_rng(0).random((9, 3))), 0.4)
    assert isinstance(res, NoPose) and res.reason == "too_many_dots"
    assert tr.counts["too_few_dots"] == 2 and tr.counts["pose"] == 1


def test_gating_refuses_impossible_jumps(world) -> None:
    p = np.array([0.1, -0.2, 0.3])
    q = geo.rotvec_to_quat([0.0, 0.1, 0.4])
    tr = make_tracker()
    assert tr.solve(world_dots(exact_hits(world, p, q)), 0.0).ok
    q2 = geo.quat_multiply(geo.rotvec_to_quat([0, 0, np.radians(60)]), q)
    res = tr.solve(world_dots(exact_hits(world, p, q2)), 1 / 30)  # 1800 deg/s
    assert isinstance(res, NoPose) and res.reason == "gated_jump"
    res = tr.solve(world_dots(exact_hits(world, p + np.array([0.3, 0, 0]), q)), 2 / 30)  # 4.5 m/s
    assert isinstance(res, NoPose) and res.reason == "gated_jump"
    # after the coherence window the tracker re-initialises and accepts the new pose
    res = tr.solve(world_dots(exact_hits(world, p, q2)), 1.0)
    assert isinstance(res, PoseEstimate) and res.reinitialised


def test_beam_into_an_edge_or_parallel_to_a_wall_gives_no_pose(world) -> None:
    # facing a vertical edge: beam 3 (backwards) runs into the corner between two walls
    p = np.array([0.0, 0.0, 0.3])
    q = geo.rotvec_to_quat([0, 0, np.radians(45)])
    hits = world.laser_hits(p, q)
    assert not hits[3].on_screen
    frame = world.render(0.0, pose=(p, q))
    assert 3 not in frame.visible_labels
    dots = frame.visible_labels
    P = np.array([hits[k].point for k in sorted(dots)])
    res = make_tracker().solve(world_dots(P), 0.0)
    assert isinstance(res, NoPose) and res.reason == "too_few_dots"
    # a beam parallel to walls meets the wall it points at; no division by zero anywhere
    walls = make_walls()
    hit = intersect_beam(walls, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    assert hit.wall == "ceiling" and hit.cos_incidence == 1.0
    hit = intersect_beam(walls, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    assert hit.wall == "front" and np.isclose(hit.point[1], 1.0)


def test_covariance_is_a_valid_pose_covariance(world) -> None:
    p, q = random_rig_pose(np.random.default_rng(2), upright=True)
    res = make_tracker().solve(world_dots(exact_hits(world, p, q), std=1e-3), 0.0)
    assert isinstance(res, PoseEstimate)
    C = geo.check_covariance(res.covariance)
    dec = geo.se3_to_decoupled(res.position, C)
    assert 1e-7 < dec[0, 0] < 1e-4 and 1e-8 < dec[3, 3] < 1e-4


@pytest.mark.slow
def test_installation_tolerances_make_the_covariance_honest(world) -> None:
    """Across many housings and screens drawn with the tolerances the tracker is told, the
    pose errors they cause have the covariance the tracker reports (mean NEES ~ 6); with
    dots this sharp the errors are the installation's alone, and so is the covariance: its
    systematic part says the same."""
    from services.sim import world as sim_world

    cfg = WorldConfig.ideal(housing_error_deg=0.05, housing_offset_m=0.001,
                            screen_bulge_m=0.004)
    tr = LaserTracker(None, TrackerParams.ideal(housing_dir_std_rad=np.radians(0.05),
                                                housing_offset_std_m=0.001,
                                                screen_bulge_std_m=0.004))
    rng = np.random.default_rng(RNG_SEED)
    nees, nees_sys = [], []
    for s in range(300):
        world.beams, world.bulge_m = sim_world._imperfections(cfg, s)
        p, q = random_rig_pose(rng, upright=True)
        hits = [world.laser_hits(p, q)[k] for k in LABELS]
        if not all(h.on_screen for h in hits):
            continue
        walls = [world.walls[h.wall] for h in hits]
        u = [2 * h.screen_xy / w.screen_side_m - 1 for h, w in zip(hits, walls, strict=True)]
        # the cameras see the bent fabric and the calibration puts it on the wall's plane
        on_plane = [h.point + (w.plane_distance - h.point @ w.normal) * w.normal
                    for h, w in zip(hits, walls, strict=True)]
        dots = WorldDots(np.array(on_plane), np.full(4, 1e-6),
                         [w.name for w in walls], np.array([w.rotation[:, :2].T for w in walls]),
                         ["c"] * 4, np.array([(1 - a ** 2) * (1 - b ** 2) for a, b in u]))
        tr.reset()
        res = tr.solve(dots, 0.0)
        if getattr(res, "reason", "") == "unconfirmed_labeling":  # a start: confirmed next
            res = tr.solve(dots, 1 / 30)
        if getattr(res, "reason", "") == "not_upright":  # a head upside down: no init
            continue
        assert isinstance(res, PoseEstimate), res
        e = np.concatenate([p - res.position, geo.quat_to_rotvec(
            geo.quat_multiply(q, geo.quat_conjugate(res.quaternion)))])
        C = geo.se3_to_decoupled(res.position, res.covariance)
        nees.append(e @ np.linalg.solve(C, e))
        S = geo.se3_to_decoupled(res.position, res.systematic)
        nees_sys.append(e @ np.linalg.solve(S, e))
    world.beams, world.bulge_m = sim_world._imperfections(world.config, world.install_seed)
    assert len(nees) > 100
    assert 4.8 < np.mean(nees) < 7.2, (np.mean(nees), len(nees))
    assert np.mean(nees) <= np.mean(nees_sys) < 1.01 * np.mean(nees)


def test_dots_seen_by_two_overlapping_cameras_are_merged() -> None:
    from services.laser_camera.tracker import _merge_duplicates

    axes = np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (3, 1, 1))
    d = WorldDots(np.array([[0.1, 0.2, 1.22], [0.104, 0.2, 1.22], [0.5, 0.2, 1.22]]),
                  np.array([1e-3, 2e-3, 1e-3]), ["ceiling", "ceiling", "ceiling"], axes,
                  ["ceiling1", "ceiling2", "ceiling2"])
    m = _merge_duplicates(d, 0.03)
    assert len(m.points) == 2
    assert m.points[0][0] == pytest.approx(0.1 + 0.004 * 0.2)  # inverse-variance weights
    assert m.std_m[0] == pytest.approx(1 / np.sqrt(1e6 + 0.25e6))
    other_wall = WorldDots(d.points[:2], d.std_m[:2], ["ceiling", "front"], axes[:2],
                           ["ceiling1", "front"])
    assert len(_merge_duplicates(other_wall, 0.03).points) == 2


def test_service_measures_and_readvertises_its_attributes() -> None:
    from services.laser_camera import service

    class Out:
        def __init__(self) -> None:
            self.updates: list[dict] = []

        def update(self, **kw) -> None:
            self.updates.append(kw)

    perf = service._Performance()
    est = PoseEstimate(0.0, np.zeros(3), geo.quat_identity(), np.diag([1e-6] * 3 + [4e-6] * 3),
                       {}, {}, 0.0, 4, False)
    two_dots = LabeledDots(0.0, [1, 3], np.zeros((2, 3)), np.ones(2), np.ones(2), True)
    for i in range(20):  # a pose in 3 of 4 frame sets, labeled dots in all but one
        perf.add(0.01, est if i % 4 else NoPose(0.0, "too_few_dots", 3),
                 None if i == 0 else two_dots)
        perf.times[-1] = i / 30.0  # as if taken at 30 Hz
    a = perf.attributes(30.0)
    assert a["confidence"] == pytest.approx(0.75)
    assert a["frequency_hz"] == pytest.approx(30 * 0.75, rel=1e-6)
    assert a["latency_s"] == pytest.approx(0.01)
    assert a["pos_std_m"] == pytest.approx(1e-3) and a["rot_std_rad"] == pytest.approx(2e-3)
    d = perf.dot_attributes(30.0)
    assert d["confidence"] == pytest.approx(0.95) and "pos_std_m" not in d
    assert d["frequency_hz"] == pytest.approx(30 * 0.95, rel=1e-6)
    out = service._Outputs(Out(), Out(), a, d)
    service._maybe_update(out, perf, 30.0)
    assert not out.pose.updates and not out.dots.updates  # nothing drifted
    perf.latency.extend([0.05] * 40)  # the median latency is now 50 ms
    service._maybe_update(out, perf, 30.0)
    assert out.pose.updates == [out.pose_attrs] and out.pose_attrs["latency_s"] == 0.05
    assert out.dots.updates == [out.dot_attrs] and out.dot_attrs["latency_s"] == 0.05


def test_model_error_is_added_to_the_covariance(world) -> None:
    from services.laser_camera.tracker import TrackerParams

    p, q = random_rig_pose(np.random.default_rng(2), upright=True)
    dots = world_dots(exact_hits(world, p, q), std=1e-3)
    plain = make_tracker().solve(dots, 0.0)
    tr = LaserTracker(None, TrackerParams.ideal(model_pos_std_m=0.002, model_rot_std_rad=0.001))
    inflated = tr.solve(dots, 0.0)
    a = geo.se3_to_decoupled(plain.position, plain.covariance)
    b = geo.se3_to_decoupled(inflated.position, inflated.covariance)
    assert np.allclose(b - a, np.diag([4e-6] * 3 + [1e-6] * 3), atol=1e-12)
    # an error the dots cannot show does not average out over frames: it is systematic
    assert not np.any(plain.systematic)
    assert np.allclose(geo.se3_to_decoupled(inflated.position, inflated.systematic),
                       np.diag([4e-6] * 3 + [1e-6] * 3), atol=1e-12)
    with pytest.raises(ValueError, match=">= 0"):
        TrackerParams(model_rot_std_rad=-1.0)


def test_advertised_rate_stays_positive_when_no_frame_gave_a_pose() -> None:
    """A warm-up without a single pose (no dots seen yet) must not advertise 0 Hz, which
    the ability schema refuses and which stopped the service in a loaded CI run."""
    from schemas.models import Attributes
    from services.laser_camera.service import MIN_RATE_HZ, _Performance

    perf = _Performance()
    for k in range(10):
        perf.times.append(100.0 + k / 30)
        perf.latency.append(0.004)
        perf.got_pose.append(False)
    attrs = perf.attributes(30.0)
    assert attrs["frequency_hz"] == MIN_RATE_HZ and attrs["confidence"] == 0.0
    Attributes(**attrs)  # valid for the ability it is advertised on
    perf.got_pose[-1] = True
    assert perf.attributes(30.0)["frequency_hz"] == pytest.approx(3.0)


def test_warm_up_waits_for_a_first_pose_but_not_forever() -> None:
    from services.laser_camera import service as ls

    pose = PoseEstimate.__new__(PoseEstimate)  # only its type matters here
    none = [(k, None, None) for k in range(ls.WARMUP_FRAMES)]
    assert not ls._warmed_up([*none[:-2], (8, pose, None)])  # too few frames for a rate
    assert ls._warmed_up([*none[:-1], (9, pose, None)])
    assert not ls._warmed_up(none)  # no pose yet: keep waiting
    assert ls._warmed_up([(k, None, None) for k in range(ls.MAX_WARMUP_FRAMES)])


def test_simulated_cameras_skip_the_frames_an_overrun_missed() -> None:
    from services.laser_camera.service import next_frame_time

    assert next_frame_time(1.0, 0.05, 1.01) == pytest.approx(1.05)  # on time: next frame
    # 120 ms late: the frames at 1.05 and 1.10 are gone, the next one is at 1.15, not now
    assert next_frame_time(1.0, 0.05, 1.12) == pytest.approx(1.15)
    assert next_frame_time(1.0, 0.0, 5.0) == 1.0  # a capture paces itself


@pytest.mark.skipif(pose_module.KERNELS is None, reason="the laser kernels are not built")
def test_the_compiled_labelings_and_frames_are_numpys(monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled labelings (eps, P0, rays of all 24), frames of labeled hits and
    rotations are numpy's (to 1e-15 of the largest; the same bits where numpy's einsum
    sums as on x86-64), the degenerate ones too: coincident points (eps inf) and P3 on
    the line P1P2 (no frame: NaN)."""
    rng = np.random.default_rng(3)
    sets = [rng.normal(size=(4, 3)) for _ in range(20)]
    sets += [np.array([[0.0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 1, 0]]),
             np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 0, 1]])]
    hits = np.array(sets)
    v1, v3 = rng.normal(size=(30, 3)), rng.normal(size=(30, 3))
    v3[0] = 0.0

    def everything() -> list[np.ndarray]:
        out = [a for points in sets for a in pose_module._labelings(points)]
        return out + list(pose_module.frames_from_points(hits)) + [pose_module._rotations(v1, v3)]

    compiled = everything()
    monkeypatch.setattr(pose_module, "KERNELS", None)
    for got, want in zip(compiled, everything(), strict=True):
        assert got.shape == want.shape
        same = np.isfinite(want)
        assert np.array_equal(np.isfinite(got), same)
        assert np.array_equal(got[~same], want[~same], equal_nan=True)
        assert np.abs(got[same] - want[same]).max() <= 1e-15 * np.abs(want[same]).max()
    eps_coincident, R, rotations = compiled[3 * 20], compiled[-2], compiled[-1]
    assert np.isinf(eps_coincident).any() and np.isnan(R[-1]).all()
    assert np.isnan(rotations[0]).all() and np.isfinite(rotations[1:]).all()


@pytest.mark.skipif(pose_module.KERNELS is None, reason="the laser kernels are not built")
def test_the_compiled_frames_refuse_arrays_of_the_wrong_kind() -> None:
    """A stack of the wrong size or type raises a ValueError naming the laser kernel."""
    k = pose_module.KERNELS
    with pytest.raises(ValueError, match="laser kernel"):
        k.frames(np.zeros((2, 4, 3)), np.empty((1, 3)), np.empty((2, 3, 3)))
    with pytest.raises(ValueError, match="laser kernel"):
        k.labelings(np.zeros((4, 3)), pose_module.PERMUTATIONS.astype(float), np.empty(24),
                    np.empty((24, 3)), np.empty((24, 4, 3)))
    with pytest.raises(ValueError, match="laser kernel"):
        k.labelings(np.zeros((4, 3)), pose_module.PERMUTATIONS + 1, np.empty(24),
                    np.empty((24, 3)), np.empty((24, 4, 3)))
