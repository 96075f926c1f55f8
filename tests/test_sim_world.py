"""The simulated IVY world: walls (eq. 5.40), cameras (OpenCV's model), laser hits, rendering,
ground truth and its refusal of bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agent import geometry as geo
from services.installation.ivy import CUBE_SIDE_M, WALL_NAMES, make_walls
from services.installation.laser_housing import LABELS
from services.sim import mounts
from services.sim.render import checkerboard, render_plane_pattern
from services.sim.world import IvyWorld, WorldConfig


@pytest.fixture(scope="module")
def world() -> IvyWorld:
    return IvyWorld(seed=2, ideal=True)


def test_walls_follow_eq_5_40_and_cover_the_cube() -> None:
    walls = make_walls()
    assert set(walls) == set(WALL_NAMES)
    rng = np.random.default_rng(0)
    for w in walls.values():
        assert np.allclose(w.rotation.T @ w.rotation, np.eye(3))
        assert np.linalg.det(w.rotation) == pytest.approx(1.0)
        xy = rng.uniform(0, w.screen_side_m, (10, 2))
        pts = w.to_world(xy)
        # x = R [X, Y, Pi]^T - T, on the face of the cube
        manual = (w.rotation @ np.column_stack([xy, np.full(10, w.plane_distance)]).T).T \
            - w.translation
        assert np.allclose(pts, manual)
        assert np.allclose(pts @ w.normal, CUBE_SIDE_M / 2)
        assert np.allclose(w.to_screen(pts), xy)
        centre = w.to_world([[w.screen_side_m / 2] * 2])[0]
        assert np.allclose(centre, w.normal * CUBE_SIDE_M / 2)
    with pytest.raises(ValueError, match="screen side"):
        make_walls(screen_side_m=3.0)


def test_camera_projection_equals_opencv(world: IvyWorld) -> None:
    rng = np.random.default_rng(1)
    for cam in world.cameras:
        wall = world.walls[cam.wall]
        pts = wall.to_world(rng.uniform(0, wall.screen_side_m, (50, 2)))
        rvec, _ = cv2.Rodrigues(cam.R_cw)
        ref, _ = cv2.projectPoints(pts, rvec, -cam.R_cw @ cam.center, cam.K, cam.dist)
        assert np.abs(cam.project(pts) - ref[:, 0]).max() < 1e-9
        # each camera sees its whole screen
        corners = wall.to_world([[0, 0], [0, 2.29], [2.29, 0], [2.29, 2.29]])
        assert cam.in_image(cam.project(corners)).all()


def test_beams_obey_the_housing_geometry(world: IvyWorld) -> None:
    t = np.linspace(0, 30, 40)
    ps, qs = world.rig_pose(t)
    for p, q in zip(ps, qs, strict=True):
        hits = world.laser_hits(p, q)
        P = {k: hits[k].point for k in LABELS}
        # P0 lies on line P1P2; P3P0 . P1P2 = P4P0 . P1P2 = P3P0 . P4P0 = 0 (fig. 5.4)
        d12 = P[2] - P[1]
        assert np.linalg.norm(np.cross(p - P[1], d12)) < 1e-9
        assert abs((P[3] - p) @ d12) < 1e-9 and abs((P[4] - p) @ d12) < 1e-9
        assert abs((P[3] - p) @ (P[4] - p)) < 1e-9
        for h in hits.values():
            assert np.isclose(np.abs(h.point).max(), CUBE_SIDE_M / 2)


def test_rig_pose_is_head_pose_times_the_mounting(world: IvyWorld) -> None:
    t = np.array([0.0, 1.5, 7.25])
    ph, qh = world.trajectory.pose(t)
    pr, qr = world.rig_pose(t)
    pe, qe = geo.compose(ph, qh, *mounts.HEAD_TO_LASER_RIG)
    assert np.allclose(pr, pe) and np.allclose(qr, qe)


def test_render_is_deterministic_and_realistic(world: IvyWorld) -> None:
    a, b = world.render(2.5), world.render(2.5)
    other = IvyWorld(seed=2, ideal=True).render(2.5)
    for name, img in a.images.items():
        assert img.dtype == np.uint8 and img.shape == (480, 640)
        assert np.array_equal(img, b.images[name]) and np.array_equal(img, other.images[name])
        dark = np.median(img)
        assert 4 <= dark <= 12  # notch filter: a dark frame
    # head-on spots saturate (thesis §5.2); every visible diode shows up in some image
    peaks = [a.images[c][round(uv[1]), round(uv[0])]
             for c, pts in a.image_points.items() for uv in pts.values()]
    assert len(peaks) == len(a.visible_labels) and max(peaks) == 255
    assert not np.array_equal(world.render(2.6).images["front"], a.images["front"])


def _subpixel_corner_errors_px(img: np.ndarray, pattern: tuple[int, int],
                               true_uv: np.ndarray) -> np.ndarray:
    """Distance (px) from each corner OpenCV finds in ``img`` to the nearest true corner."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, found = cv2.findChessboardCorners(img, pattern, flags=flags)
    assert ok
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-4)
    found = cv2.cornerSubPix(img, found, (5, 5), (-1, -1), criteria).reshape(-1, 2)
    assert len(found) == len(true_uv)
    return np.linalg.norm(found[:, None] - true_uv[None], axis=2).min(axis=1)


@pytest.mark.slow
def test_calibration_patterns_put_corners_where_they_project(world: IvyWorld) -> None:
    """The lens blur is applied before sampling: a hard edge point-sampled 2x2 per pixel and
    blurred afterwards moved sub-pixel corners by up to 0.35 px, and every calibration made
    from such images carried a 1-3 mm error field over the screens into the tracker."""
    cam = world.camera("front")
    img, pattern, xy = world.screen_board("front")
    err = _subpixel_corner_errors_px(img, pattern, cam.project(world.walls["front"].to_world(xy)))
    assert np.sqrt(np.mean(err ** 2)) < 0.04 and err.max() < 0.07, (err.mean(), err.max())
    # a board held obliquely: the blur's extent on the board differs along its two axes
    square, (na, nb) = 0.06, (10, 7)
    R_board = cam.R_cw.T @ geo.rodrigues(np.radians([30.0, -25.0, 10.0]))
    a_w, b_w = R_board[:, 0], R_board[:, 1]
    origin = cam.center + cam.R_cw.T @ [0.0, 0.0, 1.0] - 0.5 * square * (na * a_w + nb * b_w)
    img = render_plane_pattern(cam, origin, a_w, b_w,
                               checkerboard(square, (na, nb), border_m=square))
    ii, jj = np.meshgrid(np.arange(1, na), np.arange(1, nb))
    corners = origin + square * (ii.reshape(-1, 1) * a_w + jj.reshape(-1, 1) * b_w)
    err = _subpixel_corner_errors_px(img, (na - 1, nb - 1), cam.project(corners))
    assert np.sqrt(np.mean(err ** 2)) < 0.04 and err.max() < 0.07, (err.mean(), err.max())


def test_eight_camera_layout_splits_floor_and_ceiling() -> None:
    w = IvyWorld(n_cameras=8, seed=1)
    names = [c.name for c in w.cameras]
    assert len(names) == 8 and {"floor1", "floor2", "ceiling1", "ceiling2"} <= set(names)
    # a spot on the seam is seen by both cameras of the split screen
    p = np.array([0.0, 0.0, 0.0])
    q = geo.quat_identity()
    frame = w.render(0.0, pose=(p, q))
    seen = [c for c, pts in frame.image_points.items() if 4 in pts]
    assert sorted(seen) == ["ceiling1", "ceiling2"]


@pytest.mark.parametrize("kwargs, msg", [({"n_cameras": 7}, "n_cameras")])
def test_bad_configuration_is_refused(kwargs, msg) -> None:
    with pytest.raises(ValueError, match=msg):
        IvyWorld(**kwargs)


def test_bad_poses_are_refused(world: IvyWorld) -> None:
    q = geo.quat_identity()
    with pytest.raises(ValueError, match="outside the cube"):
        world.laser_hits([2.0, 0, 0], q)
    with pytest.raises(ValueError, match="unit quaternion"):
        world.laser_hits([0, 0, 0], [0, 0, 0, 2.0])
    with pytest.raises(ValueError, match="non-finite"):
        world.render(0.0, pose=([np.nan, 0, 0], q))
    with pytest.raises(ValueError, match="no camera"):
        world.camera("nope")


def test_installation_imperfections_are_applied_when_asked() -> None:
    from services.installation.ivy import screen_displacement

    ideal = IvyWorld(seed=2, ideal=True)
    rough = IvyWorld(seed=2, config=WorldConfig.ideal(housing_error_deg=0.2,
                                                      housing_offset_m=0.002,
                                                      screen_bulge_m=0.005))
    p, q = ideal.rig_pose(3.0)
    a, b = ideal.laser_hits(p[0], q[0]), rough.laser_hits(p[0], q[0])
    for k in LABELS:
        off, d = rough.beams[k]
        angle = np.degrees(np.arccos(np.clip(d @ ideal.beams[k][1], -1, 1)))
        assert 0 < angle < 1.5 and 0 < np.linalg.norm(off) < 0.01
        assert 0 < np.linalg.norm(a[k].point - b[k].point) < 0.05
        # the hit lies on the bent fabric: inside the wall's plane by the displacement
        wall = rough.walls[b[k].wall]
        depth = wall.plane_distance - b[k].point @ wall.normal
        bend = screen_displacement(wall, b[k].screen_xy, rough.bulge_m[wall.name])
        assert depth == pytest.approx(bend, abs=1e-9)
        assert np.allclose(ideal.beams[k][0], 0) and a[k].point @ ideal.walls[a[k].wall].normal \
            == pytest.approx(CUBE_SIDE_M / 2)
    with pytest.raises(ValueError, match="must be >= 0"):
        WorldConfig(screen_bulge_m=-1.0)


@pytest.mark.slow
def test_realistic_default_shows_moving_content_and_keeps_the_calibration_images() -> None:
    """The default world: projected content behind the notch filter (below the detector's
    threshold, moving), cameras turned a little since calibration, imperfections drawn from
    ``imperfection_seed`` without touching what calibration sees."""
    real, ideal = IvyWorld(seed=2), IvyWorld(seed=2, ideal=True)
    a, b = real.render(1.0, pose=real.rig_pose(1.0)), ideal.render(1.0, pose=real.rig_pose(1.0))
    name = "front"
    lit = np.median(a.images[name]) - np.median(b.images[name])
    assert 2 < lit < 30 and np.percentile(a.images[name], 99) < 40  # dim, not black
    later = real.render(1.5, pose=real.rig_pose(1.0)).images[name]
    assert np.mean(np.abs(later.astype(int) - a.images[name])) > 1  # the content moves
    turned = [np.degrees(geo.quat_angle(geo.matrix_to_quat(c.R_cw), geo.matrix_to_quat(t.R_cw)))
              for c, t in zip(real.cameras, real._tracking, strict=True)]
    assert all(0 < x < 0.1 for x in turned)
    other = IvyWorld(seed=2, imperfection_seed=5)
    assert not np.allclose(other.beams[1][1], real.beams[1][1])
    assert np.array_equal(other.screen_board(name)[0], real.screen_board(name)[0])
    assert np.array_equal(other.cameras[0].R_cw, real.cameras[0].R_cw)
    with pytest.raises(ValueError, match="not both"):
        IvyWorld(ideal=True, config=WorldConfig())
