"""The fiducial tracker: covariance against Monte Carlo, the planar ambiguity never a
silent flip, edge-fitted corners, bundles, and the service end to end through a real agent
reading a generated video through cv2.VideoCapture."""

from __future__ import annotations

import copy
import functools
import math
import types

import cv2
import numpy as np
import pytest
from agent_helpers.harness import agent, poll, services_json, spawn
from conftest import endpoint, free_port

from agent import Client
from agent import geometry as geo
from services.camera.markers import dictionary, marker_corners, marker_image
from services.camera.model import CameraModel
from services.camera.simulator import (
    FAITHFUL,
    PlanarTarget,
    SceneObject,
    SimCamera,
    static,
    write_video,
)
from services.consistency import nees_figures
from services.fiducials import border, edges, image_fit, pose
from services.fiducials import tracker as fiducial_tracker
from services.fiducials.bodies import Body, BundleFileError, load_bundles
from services.fiducials.simulate import FACING, tags, wandering, webcam
from services.fiducials.tracker import FiducialTracker, branch_switch, side_offset_covariance

K = np.array([[530.0, 0, 319.5], [0, 530.0, 239.5], [0, 0, 1]])
IDEAL = CameraModel(K, [], 640, 480, pixel_std=0.3)
LENS = CameraModel(K, [-0.15, 0.03, 0.0003, -0.0002, 0.0], 640, 480, pixel_std=0.3)


def facing(tilt=(0.0, 0.0, 0.0), position=(0.0, 0.0, 1.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = FACING @ cv2.Rodrigues(np.asarray(tilt, float))[0]
    T[:3, 3] = position
    return T


def corners_of(T: np.ndarray, size=0.08) -> np.ndarray:
    return IDEAL.project(marker_corners(size) @ T[:3, :3].T + T[:3, 3])


def decoupled_error(T: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.concatenate([T[:3, 3] - t, cv2.Rodrigues(T[:3, :3] @ R.T)[0].ravel()])


def test_covariance_matches_monte_carlo_for_the_noise_it_is_given():
    T = facing((0.5, 0.3, 0.2), (0.1, -0.05, 0.8))
    obj, true = marker_corners(0.08), corners_of(T)
    rng = np.random.default_rng(0)
    errors, nees = [], []
    for _ in range(300):
        img = true + rng.normal(0, 0.3, true.shape)
        sols = pose.solve(obj, img, K, pose.square_candidates(img, 0.08, K))
        best = sols[0]
        e = decoupled_error(T, best.rotation, best.tvec)
        errors.append(e)
        nees.append(e @ np.linalg.solve(pose.covariance(pose.Fits.of([best]), [0.3])[0], e))
    empirical = np.cov(np.array(errors).T)
    claimed = pose.covariance(pose.Fits.of(sols[:1]), [0.3])[0]
    for block in (slice(0, 3), slice(3, 6)):
        ratio = np.trace(empirical[block, block]) / np.trace(claimed[block, block])
        assert 0.8 < ratio < 1.25, ratio
    assert 5.0 < np.mean(nees) < 7.2


def test_covariance_grows_with_the_measured_corner_noise():
    T = facing((0.3, 0.2, 0.0), (0.0, 0.0, 0.6))  # large: above the small-tag floor
    rng = np.random.default_rng(1)
    stds = {}
    for noise in (0.1, 0.8):
        tracker = FiducialTracker(IDEAL, "apriltag36h11", 0.08)
        for k in range(30):
            seen = {5: corners_of(T) + rng.normal(0, noise, (4, 2))}
            est = tracker.estimate(seen, k * 33_000_000)
        stds[noise] = (est[0].sigma_px, math.sqrt(np.trace(est[0].covariance[:3, :3])))
    assert stds[0.1][0] < 0.2 and 0.55 < stds[0.8][0] < 1.05  # estimated, not assumed
    assert stds[0.8][1] > 4 * stds[0.1][1]


def _ambiguous_view():
    """A small, far, nearly fronto-parallel tag: IPPE's two solutions fit alike."""
    return facing((0.08, 0.05, 0.0), (0.2, 0.1, 2.8))


def test_planar_ambiguity_is_covered_never_silent():
    T = _ambiguous_view()
    rng = np.random.default_rng(2)
    flagged = 0
    for _ in range(40):
        tracker = FiducialTracker(IDEAL, "apriltag36h11", 0.08)  # no history
        est = tracker.estimate({3: corners_of(T) + rng.normal(0, 0.3, (4, 2))}, 0)[0]
        e = decoupled_error(T, est.R, est.t)
        if est.ambiguity == "covered":
            flagged += 1
            assert math.isfinite(est.alternative_gap) and est.alternative_gap <= 16
        rot_m = e[3:] @ np.linalg.solve(est.covariance[3:, 3:], e[3:])
        assert rot_m < 16.3 or math.degrees(np.linalg.norm(e[3:])) < 5  # no silent flip
    assert flagged > 20


@pytest.mark.slow
def test_a_tag_facing_the_camera_whose_two_solutions_meet_is_no_silent_flip():
    """`uma eval fiducials --seed 117 --seconds 60`'s frames: at 29.4 s the tag, 2.98 m
    away and 2.8 degrees from facing the camera, gave one solution (both planar ones
    refined to one minimum), whose fit's covariance claimed its tilt to 1.9 degrees where
    it erred 5.1 (chi2(3) 18.3): a silent flip.  Its covariance holds the tilt anywhere
    within the solutions' meeting angle, and it is flagged covered."""
    from services.fiducials import evaluate as ev
    rng = np.random.default_rng(117)                 # as the eval draws it
    camera = webcam(rng)
    sim = SimCamera(camera, supersampling=FAITHFUL)
    traj = wandering(rng, camera, (ev.BINS[0], ev.BINS[-1]), 20.0)
    scene = tags(ev.FAMILY, [117], ev.SIZE_M, [traj])
    tracker = FiducialTracker(camera, ev.FAMILY, ev.SIZE_M)
    for k in range(295):
        est = tracker.process(sim.render(scene, k / 10, rng), k * 100_000_000)
    assert len(est) == 1 and not math.isfinite(est[0].alternative_gap)
    e, _, r_deg = ev._errors(traj(29.4), est[0].R, est[0].t)
    assert r_deg > 5 and est[0].ambiguity == "covered"
    assert e[3:] @ np.linalg.solve(est[0].covariance[3:, 3:], e[3:]) < ev.FLIP_CHI2


def test_a_covered_pose_claims_the_two_solutions_mixture_not_both_spreads():
    """Tilted 0.35 rad at 1.6 m, a frame's gap is 1-5: covered, and the chosen solution is
    the true one in nearly every frame.  The covariance is the mixture's second moment at
    the other's published chance: a flip still lies inside its 99.9 % region, and the
    likely case is not claimed twice over (the chosen spread plus the other's in full
    gives a mean NEES of 2.5 here)."""
    T = facing((0.35, 0.2, 0.0), (0.1, 0.05, 1.6))
    rng = np.random.default_rng(2)
    nees, chances = [], []
    for _ in range(200):
        tracker = FiducialTracker(IDEAL, "apriltag36h11", 0.08)  # no history
        est = tracker.estimate({3: corners_of(T) + rng.normal(0, 0.1, (4, 2))}, 0,
                               {3: 0.01 * np.eye(8)})[0]
        if est.ambiguity != "covered":
            continue
        e = decoupled_error(T, est.R, est.t)
        nees.append(e @ np.linalg.solve(est.covariance, e))
        chances.append(est.flip_probability)
        rot_m = e[3:] @ np.linalg.solve(est.covariance[3:, 3:], e[3:])
        assert rot_m < 16.3 or math.degrees(np.linalg.norm(e[3:])) < 5  # no silent flip
    assert len(nees) > 150 and 4.0 < np.mean(nees) < 6.5, np.mean(nees)
    assert 0.1 < np.mean(chances) < 0.3


def test_a_covered_pose_gives_an_unlikely_other_solution_at_least_the_floors_chance():
    """Where the evidence puts the other solution's chance near zero but the track has not
    decided, the covariance still holds it within sqrt(1 / COVERED_CHANCE_FLOOR) standard
    deviations: the chance is judged on a few pixels' residuals, a flip stays covered."""
    def solution(rotvec: tuple[float, float, float], t: tuple[float, float, float]):
        R = cv2.Rodrigues(np.array(rotvec, float))[0]
        return pose.Solution(R, np.array(t, float), 0.0, 4, np.zeros((8, 6)), np.zeros(8))

    chosen, other = solution((0.3, 0.0, 0.0), (0, 0, 1.0)), solution((-0.3, 0.0, 0.0), (0, 0, 1.0))
    d = pose.difference(chosen, other)
    tiny = 1e-8 * np.eye(6)
    for chance in (0.0, 0.01, 0.5):
        cov = fiducial_tracker._covered(tiny, chosen, [chosen, other], lambda s: tiny, chance)
        weight = max(chance, fiducial_tracker.COVERED_CHANCE_FLOOR)
        assert d @ np.linalg.lstsq(cov, d, rcond=None)[0] == pytest.approx(1 / weight, rel=1e-6)


def test_previous_frame_picks_the_solution_it_supports():
    rng = np.random.default_rng(3)
    for tilt, carries in (((0.7, 0.4, 0.0), True), ((0.08, 0.05, 0.0), False)):
        T = facing(tilt, (0.2, 0.1, 2.8))  # small and far: each frame's gap is under 1.5
        tracker = FiducialTracker(IDEAL, "apriltag36h11", 0.08)
        near = T.copy()
        near[:3, 3] = (0.1, 0.05, 0.5)  # the same attitude seen clearly, just before
        assert tracker.estimate({3: corners_of(near)}, 0)[0].ambiguity == "none"
        kinds = []
        for k in range(1, 10):
            est = tracker.estimate({3: corners_of(T) + rng.normal(0, 0.3, (4, 2))},
                                   k * 30_000_000)[0]
            kinds.append(est.ambiguity)
            if est.ambiguity == "history":  # the flipped solution lies 30-45 degrees off
                assert pose.rotation_angle(est.R, T[:3, :3]) < math.radians(20)
        # tilted 46 degrees, the clear frame's evidence carries over the next frames;
        # tilted 5 degrees, less than the noise alone seems to tilt it (16 degrees), the
        # pose may cross between the two solutions from frame to frame: covered
        if carries:
            assert kinds[:3] == ["history"] * 3 and set(kinds) <= {"history", "covered"}
        else:
            assert kinds == ["covered"] * 9, kinds


def test_weak_evidence_accumulates_over_frames():
    T = facing((0.35, 0.2, 0.0), (0.1, 0.05, 1.6))  # each frame's gap is 1-5
    for seed in range(3, 7):
        rng = np.random.default_rng(seed)
        tracker = FiducialTracker(IDEAL, "apriltag36h11", 0.08)
        kinds = []
        for k in range(8):
            est = tracker.estimate({3: corners_of(T) + rng.normal(0, 0.1, (4, 2))},
                                   k * 30_000_000)[0]
            kinds.append(est.ambiguity)
            assert est.alternative_gap <= 16
            assert pose.rotation_angle(est.R, T[:3, :3]) < math.radians(5)
        assert kinds[0] == "covered" and kinds[-4:] == ["history"] * 4, kinds


def test_a_history_pose_claims_its_own_solution_spread_not_the_other():
    """A pose the track's evidence decides (``history``, the other solution's chance a
    few percent at most) is as certain as its own fit: a covariance spanning the other
    solution as a mixture would not keep a flip to it within its 99.9 % region, and
    would be too wide for the likely case (mean NEES 4.8 here, under its band)."""
    T = facing((0.35, 0.2, 0.0), (0.1, 0.05, 1.6))  # each frame's gap is 1-5
    errors, covariances, chances = [], [], []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        tracker = FiducialTracker(IDEAL, "apriltag36h11", 0.08)
        for k in range(8):
            est = tracker.estimate({3: corners_of(T) + rng.normal(0, 0.1, (4, 2))},
                                   k * 30_000_000, {3: 0.01 * np.eye(8)})[0]
            if est.ambiguity == "history":
                errors.append(decoupled_error(T, est.R, est.t))
                covariances.append(est.covariance)
                chances.append(est.flip_probability)
    figures = nees_figures(np.array(errors), np.array(covariances))
    assert len(errors) > 150 and figures["within_bounds"], figures
    assert max(chances) < 1 / (1 + math.exp(3.0)) + 1e-9


def test_branch_switch_is_unlikely_where_the_solutions_lie_far_apart():
    deg = math.radians
    # (near, far, separation, turn, meet): a tilted tag, turning slowly
    assert branch_switch(deg(2), deg(60), deg(60), deg(3), deg(5)) < 1e-5
    assert branch_switch(deg(2), deg(20), deg(20), deg(4), deg(3)) < 1e-2
    # ... a small far one, which noise alone seems to tilt by 10 degrees: it may cross
    assert branch_switch(deg(2), deg(20), deg(20), deg(4), deg(10)) > 0.05
    assert branch_switch(deg(2), deg(4), deg(4), deg(3), deg(3)) > 0.2  # nearly meeting
    assert branch_switch(deg(2), deg(2), deg(2), deg(3), deg(3)) == 0.5


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_flip_probability_falls_with_evidence_only_where_the_branches_stay_apart(seed):
    rng = np.random.default_rng(seed)
    flips = {}
    for name, tilt in (("tilted", (0.6, 0.3, 0.0)), ("frontal", (0.02, 0.01, 0.0))):
        tracker = FiducialTracker(IDEAL, "apriltag36h11", 0.08)
        for k in range(8):  # turning slowly; each frame's own gap 0-6
            T = facing(np.add(tilt, (0.01 * k, 0.0, 0.0)), (0.1, 0.05, 1.6))
            est = tracker.estimate({3: corners_of(T) + rng.normal(0, 0.1, (4, 2))},
                                   k * 33_000_000)[0]
            if math.isfinite(est.alternative_gap):  # two solutions
                flips.setdefault(name, []).append(est.flip_probability)
        if name == "tilted":  # the evidence of the frames adds up, far past 2 % a frame
            assert est.ambiguity == "history" and flips[name][-1] < 1e-4, flips
            assert pose.rotation_angle(est.R, T[:3, :3]) < math.radians(5)
    # solutions a few degrees apart: the pose may cross between them from frame to frame
    assert len(flips["frontal"]) >= 4 and min(flips["frontal"]) > 0.1, flips


def test_edge_fitted_corners_beat_the_detectors_on_a_blurred_tag():
    cam = SimCamera(LENS, blur_sigma_px=1.0)
    T = facing((0.4, -0.3, 0.3), (0.05, 0.03, 1.0))
    scene = tags("apriltag36h11", [11], 0.08, [static(T)])
    image = cam.render(scene, 0.0, np.random.default_rng(4))
    true = LENS.undistort(LENS.project(marker_corners(0.08) @ T[:3, :3].T + T[:3, 3]),
                          pixels=True)
    tracker = FiducialTracker(LENS, "apriltag36h11", 0.08)
    raw, _, _ = tracker.detector.detectMarkers(image)
    detector_err = np.abs(LENS.undistort(raw[0].reshape(4, 2), pixels=True) - true).max()
    ours = edges.refine(image, np.asarray(raw).reshape(-1, 4, 2), 8, LENS)[0][0]
    assert np.abs(ours - true).max() < 0.3 < detector_err


def test_tracker_on_rendered_frames_is_accurate_and_honest():
    cam = SimCamera(LENS)
    T = facing((0.35, 0.2, 0.5), (-0.1, 0.05, 0.7))
    scene = tags("apriltag36h11", [2], 0.08, [static(T)])
    tracker = FiducialTracker(LENS, "apriltag36h11", 0.08)
    rng = np.random.default_rng(5)
    for k in range(10):
        est = tracker.process(cam.render(scene, 0.0, rng), k * 33_000_000)
    (e,) = est
    err = decoupled_error(T, e.R, e.t)
    assert np.linalg.norm(err[:3]) < 0.004 and math.degrees(np.linalg.norm(err[3:])) < 0.5
    assert e.name == "apriltag36h11-2" and e.ambiguity == "none"
    assert err @ np.linalg.solve(e.covariance, err) < 22.5  # chi2(6) 99.9 %


@pytest.mark.slow
def test_nees_of_rendered_moving_frames_is_inside_its_band():
    """The corners' joint covariance from the edge fits, propagated through the weighted
    pose, is neither too small nor too cautious on a webcam's blurred, noisy frames (each
    pixel its area's mean) of a moving tag."""
    rng = np.random.default_rng(7)
    camera = webcam(rng)
    traj = wandering(rng, camera, (0.6, 1.4), 6.0, max_tilt_rad=0.5)
    sim = SimCamera(camera, supersampling=FAITHFUL)
    tracker = FiducialTracker(camera, "apriltag36h11", 0.08)
    errors, covariances = [], []
    for k in range(60):
        t = k / 10
        (est,) = tracker.process(sim.render(tags("apriltag36h11", [4], 0.08, [traj]), t, rng),
                                 round(t * 1e9))
        if est.ambiguity == "none":
            errors.append(decoupled_error(traj(t), est.R, est.t))
            covariances.append(est.covariance)
    figures = nees_figures(np.array(errors), np.array(covariances))
    assert len(errors) >= 30 and figures["within_bounds"], figures


@pytest.mark.slow
def test_nees_of_far_rendered_frames_decided_by_the_track_is_inside_its_band():
    """At 1.5-2.4 m a tag's two solutions fit almost alike in every frame: the samples the
    track decides (``history``) claim their own solution's covariance, from corners whose
    sides' narrow cells and pixel locking are counted, and are neither too small nor too
    cautious (the ``covered`` ones carry a deliberate allowance for the other solution)."""
    rng = np.random.default_rng(13)
    camera = webcam(rng)
    traj = wandering(rng, camera, (1.5, 2.4), 6.0)
    sim = SimCamera(camera, supersampling=FAITHFUL)
    tracker = FiducialTracker(camera, "apriltag36h11", 0.08)
    scene = tags("apriltag36h11", [5], 0.08, [traj])
    errors, covariances = [], []
    for k in range(60):
        t = k / 10
        for est in tracker.process(sim.render(scene, t, rng), round(t * 1e9)):
            if est.ambiguity != "covered":
                errors.append(decoupled_error(traj(t), est.R, est.t))
                covariances.append(est.covariance)
    figures = nees_figures(np.array(errors), np.array(covariances))
    assert len(errors) >= 25 and figures["within_bounds"], figures


@pytest.mark.slow
@pytest.mark.parametrize("margin", [1, 3])
def test_a_steep_tags_corners_do_not_follow_its_thin_border(monkeypatch, margin):
    """A tag tilted 73 degrees from the line of sight at 1 m (its image's corners 38-143
    degrees): across its long sides the one-cell border is 2 px wide, and where a white
    cell follows it the blur lifts the profile's darkest sample.  Printed with a wide
    white margin, the edge points cross the middle of the tag's own black and white, not
    of each profile's extremes (which put a corner 0.6 px off); with a one-cell margin
    on a grey ground (as the eval's prints) the profile's own middle stays."""
    camera = webcam(np.random.default_rng(9))
    T = facing((-0.02, 0.88, 1.04), (0.42, -0.22, 1.02))
    side = 0.08 * (8 + 2 * margin) / 8
    scene = [SceneObject("tag", PlanarTarget(marker_image("apriltag36h11", 9, 12, margin),
                                             side, side), static(T))]
    image = SimCamera(camera, supersampling=FAITHFUL).render(scene, 0.0,
                                                             np.random.default_rng(1))
    true = camera.K @ (marker_corners(0.08) @ T[:3, :3].T + T[:3, 3]).T
    true = (true[:2] / true[2]).T
    raw, ids, _ = FiducialTracker(camera, "apriltag36h11", 0.08).detector.detectMarkers(image)
    assert ids is not None and ids.ravel().tolist() == [9]
    quads = np.asarray(raw).reshape(-1, 4, 2)
    ours = np.abs(edges.refine(image, quads, 8, camera)[0][0] - true).max()
    monkeypatch.setattr(edges, "PLATEAU_FALL", -1.0)  # every profile its own middle
    own_middle = np.abs(edges.refine(image, quads, 8, camera)[0][0] - true).max()
    if margin == 1:
        assert ours == own_middle < 0.35
    else:
        assert ours < 0.15 < 0.4 < own_middle


_CELLS = border.code_cells(dictionary("apriltag36h11"))


_STEEP_DRAWS = 3  # the most frames a test of the steep view asks for


def _steep_view(margin: int, blur_px: float, draws: int = 1):
    """A tag tilted 76 degrees from the line of sight at 1.3 m (the eval's seed 9 at
    1.9 s; across its long sides the one-cell border is 1.1 px wide), printed with
    ``margin`` white cells, rendered ``draws`` times with fresh sensor noise: the camera,
    the true pose, the true corners (ideal pixels) and the frames (read-only: the first
    ``draws`` of :func:`_steep_frames`, shared by the tests of this view)."""
    camera, T, true, frames = _steep_frames(margin, blur_px)
    return camera, T, true, list(frames[:draws])


@functools.cache
def _steep_frames(margin: int, blur_px: float):
    """:func:`_steep_view` with its ``_STEEP_DRAWS`` frames, rendered once per view (about
    2 s of CPU a frame at the faithful supersampling; the noise draws follow one another,
    so a test's first frames are the same with or without this cache)."""
    rng = np.random.default_rng(9)
    camera = webcam(rng)
    T = wandering(rng, camera, (0.5, 3.0), 10.0)(1.9)
    side = 0.08 * (8 + 2 * margin) / 8
    scene = [SceneObject("tag", PlanarTarget(marker_image("apriltag36h11", 9, 12, margin),
                                             side, side), static(T))]
    sim = SimCamera(camera, supersampling=FAITHFUL, blur_sigma_px=blur_px)
    true = camera.K @ (marker_corners(0.08) @ T[:3, :3].T + T[:3, 3]).T
    noise = np.random.default_rng(1)
    frames = tuple(sim.render(scene, 0.0, noise) for _ in range(_STEEP_DRAWS))
    true = (true[:2] / true[2]).T
    for array in (T, true, *frames):
        array.flags.writeable = False
    return camera, T, true, frames


@pytest.mark.slow
@pytest.mark.parametrize(("margin", "blur_px"), [(1, 0.6), (3, 0.8)])
def test_the_thinnest_borders_edges_come_from_the_decoded_tags_modelled_image(margin, blur_px):
    """Across the long sides of :func:`_steep_view`'s tag each profile's crossing moves
    with the code cells behind the border and the margin outside it.  With the tag's
    cells known, the modelled image's fit puts every corner nearer the truth: on a
    one-cell margin on grey under the simulated webcam's blur, and on a three-cell white
    margin under a blurrier lens (the fit estimates the blur itself)."""
    camera, _, true, (image,) = _steep_view(margin, blur_px)
    raw, ids, _ = FiducialTracker(camera, "apriltag36h11", 0.08).detector.detectMarkers(image)
    assert ids is not None and ids.ravel().tolist() == [9]
    quads = np.asarray(raw).reshape(-1, 4, 2)
    assert edges.cell_widths(quads.astype(float), 8).min() < edges.MODEL_CELL_PX
    crossing = np.abs(edges.refine(image, quads, 8, camera)[0][0] - true).max()
    modelled = np.abs(edges.refine(image, quads, 8, camera, _CELLS[[9]])[0][0] - true).max()
    assert modelled < 0.7 * crossing and modelled < 0.45, (modelled, crossing)


@pytest.mark.parametrize(("margin", "blur_px"), [(1, 0.6), (3, 0.8)])
def test_a_steep_tags_fitted_image_puts_its_corners_nearer_the_truth(margin, blur_px):
    """Over three noise draws, the edge fits (with the border model across the thin
    sides) leave a corner 0.2-0.3 px off; the fit of the whole modelled image puts every
    corner within 0.08 px, at most a third as far, and its covariance claims about that
    (8-dof NEES of the four corners under chi-square(8)'s 99.9 % point): on a one-cell
    margin on grey under the simulated webcam's blur, and on a three-cell white margin
    under a blurrier lens (the fit estimates the blur and the levels beyond the margin)."""
    camera, _, true, frames = _steep_view(margin, blur_px, 3)
    tracker = FiducialTracker(camera, "apriltag36h11", 0.08)
    found = 0
    for image in frames:
        raw, ids, _ = tracker.detector.detectMarkers(image)
        if ids is None:  # so steep a tag is not decoded under every noise draw
            continue
        found += 1
        assert ids.ravel().tolist() == [9]
        quads = np.asarray(raw, np.float64).reshape(-1, 4, 2)
        corners, _ = edges.refine(image, quads, 8, camera, _CELLS[[9]])
        assert edges.cell_widths(corners, 8).min() < image_fit.CELL_PX
        fitted = image_fit.fit(image, corners[0], _CELLS[9], camera)
        assert fitted is not None
        fit_corners, cov = fitted
        by_edges = np.hypot(*(corners[0] - true).T).max()
        by_image = np.hypot(*(fit_corners - true).T).max()
        assert by_image < 0.08 and by_image < by_edges / 3, (by_image, by_edges)
        error = (fit_corners - true).ravel()
        assert error @ np.linalg.solve(cov, error) < 26.1
    assert found >= 2


def test_a_tag_left_to_the_image_fit_skips_the_border_model_unless_the_fit_fails():
    """The tracker gives a tag under ``image_fit.CELL_PX`` the fit's corners started from
    its plain crossings (the border model and the code's correction are left out: the
    fit replaces their corners); where the fit is rejected (a lamp's glare on the glossy
    print beside the tag: the model, which has no glare, misfits), the border model's
    corners and their covariance, as :func:`edges.refine` with the tag's cells gives
    them."""
    camera, _, true, (image,) = _steep_view(1, 0.6)
    y, x = np.mgrid[:image.shape[0], :image.shape[1]]
    spot = true.mean(0) + np.array([-3.0, -12.0])
    glare = 500 * np.exp(-((x - spot[0]) ** 2 + (y - spot[1]) ** 2) / (2 * 6.0 ** 2))
    tracker = FiducialTracker(camera, "apriltag36h11", 0.08)
    for frame, kept in ((image, True), (np.clip(image + glare, 0, 255).astype(np.uint8), False)):
        raw, ids, _ = tracker.detector.detectMarkers(frame)
        assert ids.ravel().tolist() == [9]
        quads = np.asarray(raw, np.float64).reshape(-1, 4, 2)
        placed = edges.place(frame, quads, 8)
        assert image_fit.gate(edges.cell_widths(camera.ideal_pixels(placed).reshape(1, 4, 2),
                                                8))[0]
        crossed, _ = edges.refine(frame, quads, 8, camera, _CELLS[[9]], placed,
                                  np.array([False]))
        modelled, edge_cov = edges.refine(frame, quads, 8, camera, _CELLS[[9]])
        assert np.abs(crossed - modelled).max() > 0.05  # the border model moves them
        fitted = image_fit.fit(frame, crossed[0], _CELLS[9], camera)
        corners, cov = tracker.observe(frame)
        # a steep tag alone teaches no pixel locking, so the tracker's refine corrects none
        # and the bare edges.refine above is the one to compare with
        assert tracker._locking.weight == 0.0
        if kept:
            assert np.array_equal(corners[9], fitted[0]) and np.array_equal(cov[9], fitted[1])
            continue
        assert fitted is None
        in_image = modelled + (quads - camera.ideal_pixels(quads).reshape(quads.shape))
        gains = np.empty((1, 4, 2))
        edges.refine(frame, quads, 8, camera, _CELLS[[9]], gains=gains)
        assert np.array_equal(corners[9], modelled[0])
        assert np.array_equal(cov[9], fiducial_tracker.corner_covariance(
            edge_cov, modelled, in_image, 8, fiducial_tracker.LOCK_PX, gains)[0])


def test_the_tracker_fits_the_steep_tags_image_and_its_pose_follows(monkeypatch):
    """The tracker's position of :func:`_steep_view`'s tag from the fitted corners is
    several times nearer the truth than from the edge fits' (11 mm off: its short sides
    are a few px long), and its covariance still covers the error; a tag whose cells are
    wide is left to the edge fits."""
    camera, T, _, (image,) = _steep_view(1, 0.6)
    gate = image_fit.CELL_PX

    def position_error(cell_px: float) -> tuple[float, float]:
        monkeypatch.setattr(image_fit, "CELL_PX", cell_px)
        (est,) = FiducialTracker(camera, "apriltag36h11", 0.08).process(image, 0)
        e = est.t - T[:3, 3]
        return float(np.linalg.norm(e)), float(e @ np.linalg.solve(est.covariance[:3, :3], e))

    edge_mm, _ = position_error(0.0)
    fitted_mm, fitted_nees = position_error(gate)
    assert fitted_mm < edge_mm / 3 and fitted_mm < 0.004, (fitted_mm, edge_mm)
    assert fitted_nees < 16.3
    wide = np.array([[[100.0, 100.0], [160.0, 100.0], [160.0, 160.0], [100.0, 160.0]]])
    corners, _, fitted = image_fit.refine(image, wide, np.eye(8)[None],
                                          edges.cell_widths(wide, 8), _CELLS[[9]], camera)
    assert not fitted.any() and corners is wide
    # a degenerate quad (its corners on one line) is not fitted either, and raises nothing
    line = np.array([[[100.0, 100.0], [110.0, 100.0], [120.0, 100.0], [130.0, 100.0]]])
    corners, _, fitted = image_fit.refine(image, line, np.eye(8)[None], np.ones((1, 4)),
                                          _CELLS[[9]], camera)
    assert not fitted.any() and np.array_equal(corners, line)


def test_profiles_that_leave_the_tag_through_an_acute_corner_are_left_out():
    """Near a 25-degree corner of a steep tag's image a profile reaching 4 px inwards (0.8
    of a 40 px tag's cell) ends beyond the neighbouring side, in the blurred white outside
    it: left out of the line fit; none of a square's are."""
    square = np.array([[[100.0, 100.0], [140.0, 100.0], [140.0, 140.0], [100.0, 140.0]]])
    angle = math.radians(25)
    # a parallelogram, corners clockwise in the image: 25 degrees at corners 0 and 2
    side = 40 * np.array([math.cos(angle), math.sin(angle)])
    top = np.array([[100.0, 100.0], [140.0, 100.0]])
    sheared = np.concatenate([top, top[::-1] + side])[None]
    reach = np.full((1, 4, 1), 4.0)
    assert edges._clear_of_corners(edges._sides(square, 8), reach).all()
    clear = edges._clear_of_corners(edges._sides(sheared, 8), reach)[0]
    # side k runs from corner k to corner k + 1
    assert not clear[0, 0] and not clear[3, -1] and not clear[1, -1] and not clear[2, 0]
    assert clear[0, -1] and clear[1, 0] and clear[:, 3:-3].all()


def test_edge_points_that_crossed_a_neighbouring_cell_do_not_move_the_line():
    """A profile across a grazing tag's thin border can cross the edge of the cell behind
    it: such a point, a cell off the side, is left out of the line fit."""
    rng = np.random.default_rng(3)
    u = np.linspace(-10.0, 10.0, 20)
    points = np.zeros((1, 4, 20, 2))
    for k, angle in enumerate(np.arange(4) * np.pi / 2):
        d = np.array([np.cos(angle), np.sin(angle)])
        points[0, k] = u[:, None] * d + rng.normal(0, 0.05, (20, 1)) * d[::-1] * [-1, 1]
    normal = np.array([0.0, 1.0])  # side 0 runs along x
    points[0, 0, 13:16] += 2.1 * normal  # three points on a cell edge 2.1 px away
    w = np.ones((1, 4, 20))
    _, dev, direction = edges._lines(points, w)
    kept = edges._inliers(dev, direction, w, np.full((1, 4, 1), 2.1))
    assert kept[0, 0].tolist() == [1.0] * 13 + [0.0] * 3 + [1.0] * 4 and kept[0, 1:].all()
    before = edges._lines(points, w)[0][0, 0] @ normal
    after = edges._lines(points, kept)[0][0, 0] @ normal
    assert abs(after) < 0.05 < 0.2 < abs(before)


@pytest.mark.slow
def test_corner_covariance_of_the_edge_fits_matches_monte_carlo():
    """Without blur each edge point's noise is its own: the edge fits' covariance alone
    (before the tracker's allowance for blur-shared noise) is the corners' scatter."""
    cam = SimCamera(IDEAL, blur_sigma_px=0.0, read_noise=8.0)
    T = facing((0.3, -0.2, 0.1), (0.0, 0.0, 0.5))
    scene = tags("apriltag36h11", [9], 0.08, [static(T)])
    detector = FiducialTracker(IDEAL, "apriltag36h11", 0.08).detector
    rng = np.random.default_rng(8)
    corners, covs = [], []
    for _ in range(60):
        image = cam.render(scene, 0.0, rng)
        raw, _, _ = detector.detectMarkers(image)
        c, cov = edges.refine(image, np.asarray(raw).reshape(-1, 4, 2), 8, IDEAL)
        corners.append(c[0])
        covs.append(cov[0])
    scatter = np.var(np.array(corners), axis=0).sum(-1)  # (4,) per corner
    joint = np.mean(covs, axis=0)  # (8, 8): x, y of corner 0, 1, ...
    claimed = np.array([np.trace(joint[2 * i:2 * i + 2, 2 * i:2 * i + 2]) for i in range(4)])
    assert np.all((scatter / claimed > 0.4) & (scatter / claimed < 2.5)), scatter / claimed
    # the two corners of a side move with its line: across it, a shift moves them alike and
    # a turn oppositely (the turn's share is the larger: they are anti-correlated)
    c = np.array(corners)
    side = c.mean(axis=0)[1] - c.mean(axis=0)[0]
    normal = np.array([-side[1], side[0]]) / np.linalg.norm(side)
    across = c[:, :2] @ normal  # (samples, 2): corners 0 and 1 across side 0
    measured = np.corrcoef(across.T)[0, 1]
    block = joint[:4, :4]
    cov01 = np.array([[normal @ block[2 * i:2 * i + 2, 2 * j:2 * j + 2] @ normal
                       for j in range(2)] for i in range(2)])
    claimed_corr = cov01[0, 1] / np.sqrt(cov01[0, 0] * cov01[1, 1])
    assert measured < -0.3 and abs(claimed_corr - measured) < 0.3, (measured, claimed_corr)


def test_side_offsets_move_the_corners_as_their_lines_do():
    """The corners' covariance from the four sides' offsets and turns is the corners'
    scatter when the sides' lines are moved (their two ends by the offset, each end by
    the turn the other way) and intersected again; the sides with narrow cells across
    them (a tilted tag's long ones) are the less certain, and so is a side along a pixel
    axis (its edge points share one sub-pixel phase).  The short sides' cells, 3.3 px
    across, are wider than the code's correction takes: the code turns them."""
    quad = corners_of(facing((1.1, 0.0, 0.0), (0.0, 0.0, 1.6)))  # tilted 63 degrees
    cov = side_offset_covariance(quad[None], quad[None], 8)[0]
    centre = quad.mean(axis=0)
    normals = []
    for k in range(4):
        a, b = quad[k], quad[(k + 1) % 4]
        normal = np.array([b[1] - a[1], a[0] - b[0]]) / np.linalg.norm(b - a)
        normals.append(normal * np.sign(normal @ ((a + b) / 2 - centre)))
    side = np.roll(quad, -1, axis=0) - quad
    length = np.linalg.norm(side, axis=1)
    across = edges.cell_widths(quad[None], 8)[0]
    tau = fiducial_tracker.SIDE_A * np.exp(-across / fiducial_tracker.SIDE_SCALE_PX)
    rho = fiducial_tracker.SIDE_CORRELATION
    sweep = edges.SPAN * np.abs(side).min(axis=1)
    own = ((fiducial_tracker.LOCK_PX * np.sinc(sweep)) ** 2 / 2
           + (fiducial_tracker.EDGE_SHARE * across) ** 2)
    # pixel locking's slope along the span, carried out to the corners
    x = np.pi * np.maximum(sweep, 1e-6)
    slope = 12 * (np.sin(x) - x * np.cos(x)) / (2 * x ** 2) / (2 * edges.SPAN)
    code = np.where(across >= edges.CODE_CELL_PX, fiducial_tracker.CODE_TURN_A
                    * np.exp(-across / fiducial_tracker.CODE_TURN_SCALE_PX), 0.0)
    assert np.count_nonzero(code) == 2
    turns = (fiducial_tracker.LOCK_PX * slope) ** 2 / 2 + code ** 2
    rng = np.random.default_rng(2)
    n = 20000
    shifts = rng.multivariate_normal(
        np.zeros(4), np.outer(tau, tau) * (rho + (1 - rho) * np.eye(4)) + np.diag(own), n)
    turned = rng.normal(size=(n, 4)) * np.sqrt(turns)
    starts = quad + (shifts - turned)[..., None] * np.array(normals)  # (n, 4, 2)
    ends = np.roll(quad, -1, axis=0) + (shifts + turned)[..., None] * np.array(normals)
    moved = np.empty((n, 4, 2))
    for k in range(4):  # corner k: side k - 1's end, side k's start
        p, r = starts[:, k - 1], ends[:, k - 1] - starts[:, k - 1]
        q, s = starts[:, k], ends[:, k] - starts[:, k]
        u = ((q - p)[:, 0] * s[:, 1] - (q - p)[:, 1] * s[:, 0]) / (
            r[:, 0] * s[:, 1] - r[:, 1] * s[:, 0])
        moved[:, k] = p + u[:, None] * r
    scatter = np.cov((moved - quad).reshape(n, 8).T)
    assert np.allclose(scatter, cov, atol=0.05 * np.abs(cov).max()), (scatter, cov)
    turn = cv2.Rodrigues(np.array([0.0, 0.0, 0.2]))[0][:2, :2]
    turned = side_offset_covariance(quad[None], quad[None] @ turn.T, 8)[0]
    assert np.all(np.diag(turned) < np.diag(cov))  # no side along a pixel axis any more
    # the sides' offsets and turns read back from the corners' covariance: with no side
    # along a pixel axis, the long sides' offsets (narrow cells across them) are the larger,
    # the short sides' turns (the code behind their wider cells) the larger
    shift, turns_of, _ = fiducial_tracker._side_moves(quad[None] @ turn.T, 8)
    moves = np.linalg.inv(np.concatenate([shift[0], turns_of[0]], axis=1))
    std = np.sqrt(np.diag(moves @ turned @ moves.T))
    order = np.argsort(length)
    assert std[order[2:]].min() > 1.2 * std[order[:2]].max()
    assert std[4 + order[:2]].min() > 1.2 * std[4 + order[2:]].max()


def test_a_bundle_is_solved_from_all_its_corners(tmp_path):
    path = tmp_path / "b.toml"
    path.write_text("""
[[bundle]]
name = "cube"
[[bundle.marker]]
id = 1
size = 0.05
position = [0.0, 0.0, 0.025]
[[bundle.marker]]
id = 2
size = 0.05
position = [0.025, 0.0, 0.0]
rotation = [0.0, 1.5707963267948966, 0.0]
""")
    (cube,) = load_bundles(path, "apriltag36h11")
    T = facing((0.3, -0.5, 0.2), (0.0, 0.0, 0.9))
    rng = np.random.default_rng(6)
    seen = {i: IDEAL.project(c @ T[:3, :3].T + T[:3, 3]) + rng.normal(0, 0.2, (4, 2))
            for i, c in cube.corners.items()}
    tracker = FiducialTracker(IDEAL, "apriltag36h11", None, bundles=[cube])
    (est,) = tracker.estimate(seen, 0)
    single = FiducialTracker(IDEAL, "apriltag36h11", 0.05).estimate({1: seen[1]}, 0)[0]
    assert est.name == "cube" and est.markers == (1, 2)
    assert np.linalg.norm(decoupled_error(T, est.R, est.t)[:3]) < 0.003
    assert np.trace(est.covariance) < np.trace(single.covariance) / 2


@pytest.mark.slow
def test_eval_bundle_scene_reports_the_gain_over_its_most_accurate_tag():
    from services.fiducials.evaluate import _bundle

    rng = np.random.default_rng(3)
    camera = webcam(rng)
    out = _bundle(rng, camera, SimCamera(camera, supersampling=FAITHFUL), 6, 10.0)
    assert out["bundle_samples"] >= 4 and out["best_tag_samples"] >= 4
    assert out["best_tag_rms_mm"] <= out["single_rms_mm"]  # the least of the tags' errors
    assert out["best_gain_measured"] <= out["gain_measured"]
    assert out["best_gain_claimed"] == pytest.approx(
        out["best_tag_claimed_mm"] / out["bundle_claimed_mm"], rel=0.01)
    # the tag claimed most accurate claims the least gain; read strictly, the goal's share
    # against every tag is at most its share against either of these two
    assert out["prior_gain_claimed"] <= out["best_gain_claimed"]
    assert out["prior_tag"].startswith("apriltag36h11-")
    assert 0 < out["least_gain_share"] <= min(
        out["best_gain_measured"] / out["best_gain_claimed"],
        out["prior_gain_measured"] / out["prior_gain_claimed"]) + 0.002
    # the bundle's own 6-dof covariance against its errors, over its samples
    assert out["nees"]["dof"] == 6 and out["nees"]["mean"] > 0
    assert 0 < out["nees"]["effective_samples"] <= out["bundle_samples"]


def test_eval_bundle_scene_names_why_it_has_no_figures(monkeypatch):
    """A bundle scene in which no tag is found compares nothing and says so."""
    from services.fiducials import evaluate

    monkeypatch.setattr(evaluate.FiducialTracker, "observe", lambda self, image: ({}, {}))
    rng = np.random.default_rng(3)
    camera = webcam(rng, 160, 120)
    out = evaluate._bundle(rng, camera, SimCamera(camera), 1, 10.0)
    assert out == {"frames": 1, "bundle_samples": 0, "single_samples": 0,
                   "skipped": "the bundle was never solved from all four of its tags"}


def test_eval_bundle_scene_names_why_it_has_no_figures_when_no_tag_is_solved_alone(monkeypatch):
    """A bundle scene whose bundle is solved whole but none of whose tags is solved alone has
    nothing to compare the bundle with, and says so (not a mean over no samples)."""
    from services.fiducials import evaluate
    from services.fiducials.tracker import Estimate

    def bundle_only(self, seen, t_ns, noise=None):
        return [Estimate(b.name, t_ns, np.eye(3), np.array([0.0, 0.0, 1.5]), 1e-6 * np.eye(6),
                         0.05, 0.05, "none", tuple(b.corners), float("inf"))
                for b in self.bundles]

    monkeypatch.setattr(evaluate.FiducialTracker, "observe", lambda self, image: ({}, {}))
    monkeypatch.setattr(evaluate.FiducialTracker, "estimate", bundle_only)
    rng = np.random.default_rng(3)
    camera = webcam(rng, 160, 120)
    out = evaluate._bundle(rng, camera, SimCamera(camera), 2, 10.0)
    assert out == {"frames": 2, "bundle_samples": 2, "single_samples": 0,
                   "skipped": "no tag of the bundle was solved alone"}


def test_a_bundle_judges_its_planar_ambiguity_by_its_corners_covariance():
    """Four tags on a 19 cm plate at 2.5 m, tilted 0.15 rad: the two solutions' residuals
    differ by a few times a lone tag's corner floor (covered), but by hundreds of times
    the corners' own covariance, which the bundle has: it decides, on the true pose."""
    plate = {}
    for i, (dx, dy) in enumerate([(-1, 1), (1, 1), (1, -1), (-1, -1)], start=10):
        plate[i] = np.eye(4)
        plate[i][:2, 3] = (0.055 * dx, 0.055 * dy)
    body = Body("plate", {i: marker_corners(0.08) + T[:3, 3] for i, T in plate.items()})
    P = facing((0.15, 0.0, 0.0), (0.1, 0.05, 2.5))
    rng = np.random.default_rng(1)
    kinds = {"weighted": [], "bare": []}
    for _ in range(20):
        seen = {i: corners_of(P @ T) + rng.normal(0, 0.05, (4, 2)) for i, T in plate.items()}
        for kind, noise in (("weighted", {i: 0.05 ** 2 * np.eye(8) for i in plate}),
                            ("bare", None)):
            tracker = FiducialTracker(IDEAL, "apriltag36h11", None, bundles=[body])
            (est,) = tracker.estimate(seen, 0, noise)
            kinds[kind].append(est.ambiguity)
            assert pose.rotation_angle(est.R, P[:3, :3]) < math.radians(3)
    assert kinds["weighted"] == ["none"] * 20
    assert kinds["bare"].count("covered") >= 10


@pytest.mark.parametrize(("text", "reason"), [
    ("[[bundle]]\nname = 'x'\n", "no \\[\\[bundle.marker\\]\\]"),
    ("bundle = 3\n", "no \\[\\[bundle\\]\\] tables"),
    ("[[bundle]]\nname = 'a'\n[[bundle.marker]]\nid = 1\nsize = 0.05\n"
     "[[bundle]]\nname = 'b'\n[[bundle.marker]]\nid = 1\nsize = 0.05\n", "already in bundle"),
    ("[[bundle]]\nname = 'a'\n[[bundle.marker]]\nid = 1\nsize = -1\n", "size must be"),
    ("[[bundle\n", "not a TOML file"),
])
def test_bad_bundle_files_say_what_is_wrong(tmp_path, text, reason):
    path = tmp_path / "b.toml"
    path.write_text(text)
    with pytest.raises(BundleFileError, match=reason):
        load_bundles(path, "apriltag36h11")


def test_charuco_board_bundle_has_every_marker():
    from services.fiducials.bodies import charuco_body

    body = charuco_body("board", {"squares": [5, 4], "square": 0.04, "marker": 0.03},
                        "aruco4x4_50")
    assert isinstance(body, Body) and len(body.corners) == 10


def test_service_publishes_marker_poses_from_a_video(processes, realm, tmp_path):
    T = facing((0.3, -0.2, 0.4), (0.05, -0.02, 0.6))
    cam = SimCamera(LENS)
    scene = tags("apriltag36h11", [4], 0.08, [static(T)])
    rng = np.random.default_rng(7)
    # 30 s at 10 frames/s (30 noise draws, each shown ten times): still running when listed
    # on a loaded machine, where 8 s of video had ended and its ability was gone
    shots = [cam.render(scene, 0.0, rng) for _ in range(30)]
    video = write_video(tmp_path / "cam.avi", shots * 10, fps=10)
    calibration = LENS.save(tmp_path / "cam.yaml")
    ep = endpoint(free_port())
    agent(processes, realm, "host", ep)
    svc = spawn(processes, ["-m", "agent.cli", "service", "run", "fiducials", "--realm", realm,
                            "--agent", "host", "--connect", ep, "--source", str(video),
                            "--calibration", str(calibration), "--size", "0.08",
                            "--frame", "lab/cam1"])
    svc.wait_log("lab/cam1 -> markers/apriltag36h11-4")
    with Client(realm=realm, connect=[ep]) as client:
        got = poll(lambda: client.pose("lab/cam1", "markers/apriltag36h11-4"),
                   what="the marker's pose")
    R = geo.quat_to_matrix(np.asarray(got.quaternion, float))
    assert np.linalg.norm(got.position - T[:3, 3]) < 0.004
    assert pose.rotation_angle(R, T[:3, :3]) < math.radians(0.5)
    assert got.covariance is not None and np.all(np.diag(got.covariance) > 0)
    listed = services_json(realm, ep)
    (ability,) = [a for ag in listed["agents"] for s in ag["services"]
                  if s["service_id"] == "fiducials" for a in s["abilities"]]
    assert ability["edge"] == ["lab/cam1", "markers/apriltag36h11-4"]
    assert 0 < ability["attributes"]["pos_std_m"] < 0.01


def test_readme_example_tracks_a_simulated_tag():
    from agent_helpers.readme import readme_block, run_python

    done = run_python(readme_block("FiducialTracker(camera"), timeout=60)
    assert done.returncode == 0, done.stderr
    first = done.stdout.splitlines()[0]
    # facing the camera: its two planar solutions meet, its tilt told to second order only
    assert first.startswith("apriltag36h11-0 covered [ 100.") and first.endswith("mm")


class _Handle:
    def __init__(self, attrs: dict) -> None:
        self.advertised = [dict(attrs)]

    def update(self, **attrs: float) -> None:
        self.advertised.append(attrs)

    def publish_measurement(self, m: object) -> None:
        pass


def test_a_camera_that_loses_the_tag_advertises_it_lost_and_found_again():
    """So that a need preferring accuracy leaves a camera that no longer sees the tag
    (it would otherwise keep its last, good accuracy) and may come back."""
    import argparse

    from services.fiducials.service import LOST_FRAMES, LOST_STD_M, Publisher
    from services.fiducials.tracker import Estimate

    handles: list[_Handle] = []

    def ability(name: str, type: str, edge: tuple, **attrs: float) -> _Handle:
        handles.append(_Handle(attrs))
        return handles[-1]

    publish = Publisher(types.SimpleNamespace(ability=ability),
                        argparse.Namespace(name=[], prefix="markers", frame="lab/cam"))
    cov = np.diag([1e-6] * 3 + [1e-4] * 3)

    def frame(k: int, seen: bool) -> None:
        publish.frame(k * 33_000_000)
        if seen:
            publish(Estimate("apriltag36h11-1", k * 33_000_000, np.eye(3), np.ones(3), cov,
                             0.2, 0.2, "none", (1,), math.inf), 1)

    for k in range(10):
        frame(k, True)
    for k in range(10, 10 + LOST_FRAMES):  # missed: not yet lost
        frame(k, False)
    assert handles[0].advertised[-1].get("pos_std_m", 0) < 0.01
    frame(10 + LOST_FRAMES, False)
    assert handles[0].advertised[-1]["pos_std_m"] == LOST_STD_M
    assert handles[0].advertised[-1]["confidence"] == 0.0
    frame(11 + LOST_FRAMES, True)  # seen again: advertised at once
    assert handles[0].advertised[-1]["pos_std_m"] < 0.01


def test_the_code_cells_behind_a_thin_border_move_its_crossings_by_their_white():
    """Across a border 2 px wide under a webcam's blur, a code row behind it all white
    lifts the profile's darkest sample and moves the mid-level crossing outwards, all
    black inwards, against an average code's (what :func:`edges.refine` subtracts from
    the crossings of a decoded tag); across cells 5 px wide the code no longer reaches
    the crossing."""
    m = 8
    black = np.zeros((1, m, m))
    white = black.copy()
    white[0, 1:-1, 1:-1] = 1.0

    def bias(cells: np.ndarray, across_px: float) -> np.ndarray:
        quad = 100 + m * across_px * np.array([[[0.0, 0.0], [1, 0], [1, 1], [0, 1]]])
        reach = max(edges.REACH_MODULES * across_px, edges.REACH_MIN_PX)
        sides = np.arange(4)
        return border.crossing_bias(quad.repeat(4, 0), cells.repeat(4, 0), sides, edges._SECOND,
                                    np.full(4, across_px), np.full((4, 1), reach) * edges._OFFS,
                                    np.ones(4, bool))

    inner = slice(5, 15)  # clear of the border's own black cells at the side's ends
    assert np.all(bias(black, 2.0)[:, inner] < -0.02)
    assert np.all(bias(white, 2.0)[:, inner] > 0.01)
    spread = bias(white, 2.0)[:, inner] - bias(black, 2.0)[:, inner]
    assert np.all((spread > 0.08) & (spread < 0.3))
    assert np.abs(bias(black, 5.0)).max() < 0.01 and np.abs(bias(white, 5.0)).max() < 0.01


@pytest.mark.slow
def test_a_sides_crossings_are_corrected_for_the_code_behind_it():
    """The eval's seed 7 at 3 s: a tag 2.1 m away tilted 58 degrees, the cells 1.7 px
    across two of its sides.  Behind one of them the code row is black but for one cell:
    its crossings lie 0.08 px inside the true side (the darkest samples stay dark while
    the white margin outside is thin); corrected for its code, within 0.03 px."""
    rng = np.random.default_rng(7)
    camera = webcam(rng)
    T = wandering(rng, camera, (0.5, 3.0), 10.0)(3.0)
    image = SimCamera(camera, supersampling=FAITHFUL).render(
        tags("apriltag36h11", [7], 0.08, [static(T)]), 0.0, np.random.default_rng(1))
    true = camera.K @ (marker_corners(0.08) @ T[:3, :3].T + T[:3, 3]).T
    true = (true[:2] / true[2]).T
    raw, ids, _ = FiducialTracker(camera, "apriltag36h11", 0.08).detector.detectMarkers(image)
    assert ids is not None and ids.ravel().tolist() == [7]
    quads = np.asarray(raw, np.float64).reshape(-1, 4, 2)
    cells = border.code_cells(dictionary("apriltag36h11"))[[7]]
    assert np.rot90(cells[0], 2)[1].sum() == 1  # side 2: one white cell behind it

    def offset(corners: np.ndarray, k: int) -> float:
        a, b = true[k], true[(k + 1) % 4]
        along = (b - a) / np.linalg.norm(b - a)
        normal = np.array([along[1], -along[0]])  # outwards
        return float(((corners[k] - a) @ normal + (corners[(k + 1) % 4] - b) @ normal) / 2)

    crossed = edges.refine(image, quads, 8, camera)[0][0]
    corrected = edges.refine(image, quads, 8, camera, cells)[0][0]
    assert offset(crossed, 2) < -0.05
    assert abs(offset(corrected, 2)) < 0.03


def test_a_bundles_markers_share_their_tag_wide_side_offsets():
    """Two tilted markers of one bundle (cells 2.5 px across their long sides): their
    corners' joint covariance keeps each marker's own block and couples the two by their
    tag-wide side offsets (seen alike, they look smaller or larger together), so the mean
    of the two scales is no more certain than ``TAG_CORRELATION`` lets it be: it is not
    averaged away.  A marker steep enough for the image fit shares nothing."""
    quads = np.stack([corners_of(facing((0.8, 0.0, 0.0), (x, 0.0, 1.5))) for x in (-0.1, 0.1)])
    edge_fits = 0.02 ** 2 * np.eye(8)  # what each marker's own edge fits add
    blocks = list(side_offset_covariance(quads, quads, 8) + edge_fits)
    joint = fiducial_tracker.bundle_covariance(blocks, list(quads), 8)
    scale = fiducial_tracker.tag_scale(quads, 8)
    rho = fiducial_tracker.TAG_CORRELATION
    assert np.allclose(joint[:8, :8], blocks[0]) and np.allclose(joint[8:, 8:], blocks[1])
    assert np.allclose(joint[:8, 8:], rho * np.outer(scale[0], scale[1]))
    assert np.linalg.eigvalsh(joint).min() > -1e-12
    # the two markers' scales (their corners on their own scale modes, in standard
    # deviations), averaged: independent, the shared part would halve; it keeps rho of it
    mean = np.concatenate(scale / np.einsum("ij,ij->i", scale, scale)[:, None]) / 2
    independent = mean @ np.block([[blocks[0], np.zeros((8, 8))],
                                   [np.zeros((8, 8)), blocks[1]]]) @ mean
    assert np.isclose(mean @ joint @ mean - independent, rho / 2)
    steep = np.stack([quads[0], corners_of(facing((1.1, 0.0, 0.0), (0.1, 0.0, 2.0)))])
    assert edges.cell_widths(steep, 8)[1].min() < image_fit.CELL_PX
    blocks = list(side_offset_covariance(steep, steep, 8) + edge_fits)
    assert not fiducial_tracker.bundle_covariance(blocks, list(steep), 8)[:8, 8:].any()


def _side_offsets_along_x(turn_deg: float, side_px: float, shifts: np.ndarray,
                          locking: edges.Locking | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A tag ``side_px`` px across facing the ideal camera (blur 0.6 px, each pixel
    integrated over its area, no noise), turned ``turn_deg`` in its plane and moved along
    x by ``shifts`` px: its two nearly vertical sides' x offsets from the truth (refined
    with ``locking``) and their true x."""
    cam = SimCamera(IDEAL, blur_sigma_px=0.6, read_noise=0.0, shot_noise=0.0,
                    supersampling=FAITHFUL)
    detector = FiducialTracker(IDEAL, "apriltag36h11", 0.08).detector
    z = K[0, 0] * 0.08 / side_px
    err, where = [], []
    for shift in shifts:
        T = facing((0.0, 0.0, math.radians(turn_deg)), ((0.3 + shift) * z / K[0, 0], 0.0, z))
        image = cam.render(tags("apriltag36h11", [9], 0.08, [static(T)]), 0.0,
                           np.random.default_rng(0))
        raw, _, _ = detector.detectMarkers(image)
        got = edges.refine(image, np.asarray(raw).reshape(-1, 4, 2), 8, IDEAL,
                           locking=locking)[0][0]
        true = corners_of(T)
        for a, b in ((1, 2), (3, 0)):  # the right and left sides
            err.append((got[a, 0] + got[b, 0] - true[a, 0] - true[b, 0]) / 2)
            where.append((true[a, 0] + true[b, 0]) / 2)
    return np.array(err), np.array(where)


def _locking_amplitude(err: np.ndarray, where: np.ndarray) -> float:
    s = np.sin(2 * np.pi * where)
    return float(err @ s / (s @ s))


@pytest.mark.parametrize("side_px", [25.0, 42.6, 71.0])
def test_pixel_locking_pulls_edges_towards_the_pixel_borders_at_every_sample_spacing(side_px):
    """A side along a pixel axis, each pixel integrated over its area: its crossings, the
    chords between pixel centres of a blurred step, lie off the edge towards the border
    between the pixels, ``A sin(2π x)`` with ``A`` > 0, whether the profiles' samples lie
    0.21, 0.36 or 0.59 px apart (sides of 25, 42.6 and 71 px)."""
    err, where = _side_offsets_along_x(0.0, side_px, np.arange(8) / 8)
    amplitude = _locking_amplitude(err, where)
    assert 0.03 < amplitude < 0.1, amplitude


@pytest.mark.slow
def test_the_cameras_pixel_locking_is_learnt_from_its_frames_and_taken_out():
    """The sides of a tag turned 5 degrees sweep several pixels across their axis: their
    scatter teaches the camera's locking amplitude, which then takes the locking out of
    the sides of a tag along the axes (whose points share one phase, so that it moves
    their whole line and teaches nothing)."""
    along_axes = edges.Locking()
    _side_offsets_along_x(0.0, 42.6, np.arange(4) / 4, along_axes)
    assert along_axes.amplitude == 0.0 and along_axes.spread == edges.LOCK_PRIOR_PX
    locking = edges.Locking()
    _side_offsets_along_x(5.0, 42.6, np.arange(4) / 4, locking)
    assert 0.04 < locking.amplitude < 0.08 and locking.spread < 0.005
    shifts = np.arange(8) / 8
    before = _locking_amplitude(*_side_offsets_along_x(0.0, 42.6, shifts))
    err, where = _side_offsets_along_x(0.0, 42.6, shifts, locking)
    assert abs(_locking_amplitude(err, where)) < 0.3 * before, (before, err)


def test_a_frame_teaches_the_cameras_locking_once_when_a_tags_image_fit_is_rejected(
        monkeypatch):
    """A tag whose image fit is rejected has its edges fitted again (with the border
    model); its sides have taught the camera's pixel locking in the frame's first pass
    already, and teach nothing the second time."""
    cam = SimCamera(IDEAL, blur_sigma_px=0.6, read_noise=0.0, shot_noise=0.0,
                    supersampling=FAITHFUL)
    z = K[0, 0] * 0.08 / 42.6
    T = facing((0.0, 0.0, math.radians(5.0)), (0.3 * z / K[0, 0], 0.0, z))
    image = cam.render(tags("apriltag36h11", [9], 0.08, [static(T)]), 0.0,
                       np.random.default_rng(0))
    monkeypatch.setattr(image_fit, "gate", lambda across: np.ones(len(across), bool))
    monkeypatch.setattr(image_fit, "refine", lambda gray, corners, cov, *_: (
        corners, cov, np.zeros(len(corners), bool)))
    tracker = FiducialTracker(IDEAL, "apriltag36h11", 0.08)
    tracker.observe(image)
    raw, _, _ = tracker.detector.detectMarkers(image)
    quads = np.asarray(raw, np.float64).reshape(-1, 4, 2)
    once = edges.Locking()
    edges.refine(image, quads, 8, IDEAL, _CELLS[[9]], edges.place(image, quads, 8),
                 np.array([False]), once)
    assert once.weight > 0  # the turned tag's sides teach
    assert (tracker._locking.evidence, tracker._locking.weight) == (once.evidence, once.weight)


def test_once_the_camera_has_learnt_its_locking_the_covariance_carries_what_is_left():
    """A tag turned 5 degrees teaches the camera its pixel locking; a tag along the axes
    then has its sides corrected, and its corners' covariance carries ``LOCK_LEFT_PX`` of
    locking (the learnt amplitude's spread being smaller), not the prior's ``LOCK_PX``
    that a camera which has learnt nothing carries."""
    cam = SimCamera(IDEAL, blur_sigma_px=0.6, read_noise=0.0, shot_noise=0.0,
                    supersampling=FAITHFUL)
    z = K[0, 0] * 0.08 / 42.6

    def frame(turn_deg: float, shift_px: float) -> np.ndarray:
        T = facing((0.0, 0.0, math.radians(turn_deg)), ((0.3 + shift_px) * z / K[0, 0], 0.0, z))
        return cam.render(tags("apriltag36h11", [9], 0.08, [static(T)]), 0.0,
                          np.random.default_rng(0))

    along = frame(0.0, 0.25)
    fresh = FiducialTracker(IDEAL, "apriltag36h11", 0.08)
    learnt = FiducialTracker(IDEAL, "apriltag36h11", 0.08)
    learnt.observe(frame(5.0, 0.0))
    assert learnt._locking.spread < fiducial_tracker.LOCK_LEFT_PX
    raw, _, _ = learnt.detector.detectMarkers(along)
    quads = np.asarray(raw, np.float64).reshape(-1, 4, 2)
    for tracker, lock_px in ((fresh, fiducial_tracker.LOCK_PX),
                             (learnt, fiducial_tracker.LOCK_LEFT_PX)):
        gains = np.empty((len(quads), 4, 2))
        ideal, edge_cov = edges.refine(along, quads, 8, IDEAL, _CELLS[[9]],
                                       locking=copy.copy(tracker._locking), gains=gains)
        _, cov = tracker.observe(along)  # the ideal camera: no lens offset
        np.testing.assert_allclose(cov[9], fiducial_tracker.corner_covariance(
            edge_cov, ideal, ideal, 8, lock_px, gains)[0], rtol=1e-12, atol=0)


def test_the_locking_sine_is_taken_out_of_the_edge_fits_scatter_not_their_noise():
    """A side 5 degrees off a pixel axis sweeps several pixels across it: its points lie off
    its line by the locking's ``A sin(2π x)`` (which its line averages out) and their noise.
    The corners' covariance pools the noise alone: the sine and cosine fitted out of each
    such side, two dof each; a side along the axis (all its points at one phase) and a side
    with too few points keep their scatter whole."""
    rng = np.random.default_rng(3)
    noise, amplitude, n, k = 0.04, 0.05, 200, edges.SAMPLES
    turn = math.radians(5.0)
    square = np.array([[0, 0], [40, 0], [40, 40], [0, 40]], float)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    corners = square @ rotation.T + [100.3, 200.7]
    side = corners[[1, 2, 3, 0]] - corners
    normal = side[:, ::-1] * [-1.0, 1.0] / 40
    points = (corners[:, None] + edges._SECOND * side[:, None])[None] \
        + rng.normal(0, noise, (n, 4, k, 1)) * normal[None, :, None]
    axis = np.array([1, 0, 1, 0])  # the image axis nearer each side's normal
    phase = np.take_along_axis(points, axis[None, :, None, None], -1)[..., 0]
    points += (amplitude * np.sin(2 * np.pi * phase))[..., None] * np.eye(2)[axis][None, :, None]
    w = np.ones((n, 4, k))
    mean, dev, direction = edges._lines(points, w)
    few = np.zeros((n, 4, 1), bool)
    taken = edges._locking_scatter(points, dev, direction, w)
    assert np.all(taken[..., 1] == 2.0)
    cov = edges._corner_covariance(corners[None].repeat(n, 0), mean, direction, dev, w, few,
                                   taken)
    whole = edges._corner_covariance(corners[None].repeat(n, 0), mean, direction, dev, w, few,
                                     np.zeros_like(taken))
    # the pooled variance, read off the covariance's scale: the noise's, not the sine's too
    normal_fit = direction[..., ::-1] * [-1.0, 1.0]
    across = np.einsum("nksc,nkc->nks", dev, normal_fit)
    s2_whole = (across ** 2).sum((1, 2)) / (w.sum(-1) - 2).sum(-1)
    s2 = s2_whole * cov[:, 0, 0] / whole[:, 0, 0]
    # (what is left over the noise: the sine's second order, its phase read off points it
    # has moved itself)
    assert 0.97 < np.mean(s2) / noise ** 2 < 1.1 and np.mean(s2_whole) > 1.6 * noise ** 2
    # along an axis every point of a side shares one phase: nothing to fit there; nor on a
    # side with too few points
    flat = points.copy()
    coordinate = np.take_along_axis(flat, axis[None, :, None, None], -1)
    np.put_along_axis(flat, axis[None, :, None, None], coordinate.mean(2, keepdims=True), -1)
    _, dev, direction = edges._lines(flat, w)
    assert not edges._locking_scatter(flat, dev, direction, w).any()
    few_points = w.copy()
    few_points[:, :, edges.LOCK_FIT_POINTS - 1:] = 0.0
    _, dev, direction = edges._lines(points, few_points)
    assert not edges._locking_scatter(points, dev, direction, few_points).any()


def test_a_sides_points_that_sample_the_locking_at_one_phase_carry_it_whole():
    """Twenty points along a side 17 degrees off a pixel axis, spaced so that each steps
    about a whole pixel across it, all see the locking at nearly one phase: it moves the
    line by its whole amplitude (gain near 1, at that angle the fade's), however far the side
    sweeps across the axis; spaced so that their phases spread over a period, it averages
    out (gain near 0), as the continuum's ``sinc(sweep)`` says for both."""
    angle = math.radians(17.0)
    direction = np.array([math.cos(angle), math.sin(angle)])

    def gains(step: float) -> np.ndarray:
        u = (np.arange(20) - 9.5) * step
        points = 100.0 + u[:, None] * direction  # x along the side, y across its axis
        edge = points[None, None].repeat(4, 1)
        dev = (points - points.mean(0))[None, None].repeat(4, 1)
        w = np.ones((1, 4, 20))
        corners = np.array([[[0.0, 0.0], [60.0, 0.0], [60.0, 60.0], [0.0, 60.0]]])
        return edges._locking_gains(edge, dev, np.broadcast_to(direction, (1, 4, 2)), w,
                                    corners)[0, 0]

    fade = float(np.interp(17.0, edges.LOCK_FADE_DEG, edges.LOCK_FADE))
    aliased = gains(1.0 / math.sin(angle))  # a whole pixel across the axis per point
    spread = gains(1.05 / 20 / math.sin(angle) * 20)  # 1.05 px a point: phases spread
    assert aliased[0] == pytest.approx(fade, rel=1e-6)
    assert spread[0] < 0.1 * fade
