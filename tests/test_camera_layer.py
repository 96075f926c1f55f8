"""The shared camera layer: calibration files, undistortion, capture of generated videos
through cv2.VideoCapture, and the simulator's geometry against OpenCV's detector."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from agent.errors import InvalidInputError
from services.camera.capture import Capture, CaptureError
from services.camera.model import CameraFileError, CameraModel, load
from services.camera.simulator import (
    FAITHFUL,
    PlanarTarget,
    SceneObject,
    SimCamera,
    pose_matrix,
    static,
    write_video,
)

K = np.array([[612.0, 0.4, 318.2], [0, 609.5, 242.7], [0, 0, 1]])
DISTORTIONS = {
    0: [],
    5: [-0.21, 0.06, 0.0012, -0.0008, -0.01],
    8: [-0.21, 0.06, 0.0012, -0.0008, -0.01, 0.02, -0.01, 0.005],
    12: [-0.21, 0.06, 0.0012, -0.0008, -0.01, 0.02, -0.01, 0.005, 1e-3, -1e-4, 2e-4, 1e-4],
    14: [-0.21, 0.06, 0.0012, -0.0008, -0.01, 0.02, -0.01, 0.005, 1e-3, -1e-4, 2e-4, 1e-4,
         0.01, -0.005],
}

ROS_CAMERA_INFO = """\
image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [612.0, 0.4, 318.2, 0, 609.5, 242.7, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.21, 0.06, 0.0012, -0.0008, -0.01]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [612.0, 0, 318.2, 0, 0, 609.5, 242.7, 0, 0, 0, 1, 0]
"""


@pytest.mark.parametrize("n", sorted(DISTORTIONS))
@pytest.mark.parametrize("suffix", [".yaml", ".json", ".xml"])
def test_calibration_file_round_trip(tmp_path, n, suffix):
    cam = CameraModel(K, DISTORTIONS[n], 640, 480, pixel_std=0.21, name="cam1")
    back = load(cam.save(tmp_path / f"cam{suffix}", views=12))
    np.testing.assert_array_equal(back.K, cam.K)
    np.testing.assert_array_equal(back.dist, cam.dist)
    assert (back.width, back.height, back.name) == (640, 480, "cam1")
    assert back.pixel_std == pytest.approx(0.21)


def test_ros_camera_info_is_read(tmp_path):
    path = tmp_path / "ost.yaml"
    path.write_text(ROS_CAMERA_INFO)
    cam = load(path)
    np.testing.assert_array_equal(cam.K, K)
    np.testing.assert_array_equal(cam.dist, DISTORTIONS[5])
    assert (cam.size, cam.name, cam.pixel_std) == ((640, 480), "narrow_stereo", None)


@pytest.mark.parametrize(("text", "reason"), [
    ("%YAML:1.0\n---\nimage_width: 640\n", "no camera_matrix"),
    ("camera_matrix: [1, 2", "not a valid"),
    (ROS_CAMERA_INFO.replace("data: [612.0, 0.4, 318.2, 0, 609.5, 242.7, 0, 0, 1]",
                             "data: [612.0, 0.4]"), "has 2 numbers, not 9"),
    (ROS_CAMERA_INFO.replace("plumb_bob", "equidistant"), "not OpenCV's"),
    (ROS_CAMERA_INFO.replace("image_height: 480\n", ""), "no image_height"),
    (ROS_CAMERA_INFO.replace("-0.01]", "-0.01, 0.2]"), "distortion must have"),
])
def test_malformed_files_say_what_is_wrong(tmp_path, text, reason):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(CameraFileError, match=reason):
        load(path)


def test_missing_and_misnamed_files(tmp_path):
    with pytest.raises(CameraFileError, match="does not exist"):
        load(tmp_path / "none.yaml")
    (tmp_path / "cam.txt").write_text("x")
    with pytest.raises(CameraFileError, match="not a calibration file"):
        load(tmp_path / "cam.txt")


@pytest.mark.parametrize("n", [5, 8, 14])
def test_undistortion_matches_opencv_and_inverts_projection(n):
    cam = CameraModel(K, DISTORTIONS[n], 640, 480)
    rng = np.random.default_rng(n)
    uv = rng.uniform([0, 0], [639, 479], (200, 2))
    ours = cam.undistort(uv)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    ref = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), K, cam.dist, None, None,
                                  criteria).reshape(-1, 2)
    np.testing.assert_allclose(ours, ref, atol=1e-12)
    back = cam.project(np.column_stack([ours, np.ones(len(ours))]))
    np.testing.assert_allclose(back, uv, atol=1e-6)
    ideal = cam.undistort(uv, pixels=True)
    np.testing.assert_allclose(ideal, ours @ K[:2, :2].T + K[:2, 2], atol=1e-9)


def _marker_scene(rotvec, position, marker_px=80):
    aruco = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    tex = cv2.aruco.generateImageMarker(aruco, 7, marker_px, borderBits=1)
    tex = cv2.copyMakeBorder(tex, 10, 10, 10, 10, cv2.BORDER_CONSTANT, value=255)
    return aruco, SceneObject("tag", PlanarTarget(tex, 0.10, 0.10),
                              static(pose_matrix(rotvec, position)))


def test_rendered_marker_corners_lie_where_the_model_projects_them():
    cam = SimCamera(CameraModel(K, DISTORTIONS[5], 640, 480))
    aruco, obj = _marker_scene((np.pi + 0.3, 0.25, 0.1), (0.15, -0.1, 0.6))
    image = cam.render([obj], 0.0, np.random.default_rng(3))
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, ids, _ = cv2.aruco.ArucoDetector(aruco, params).detectMarkers(image)
    assert ids is not None and ids.ravel().tolist() == [7]
    s = 0.04  # the marker is 8 cm inside a 10 cm print
    T = obj.trajectory(0.0)
    true = cam.model.project(np.array([[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]])
                             @ T[:3, :3].T + T[:3, 3])
    assert np.abs(corners[0].reshape(4, 2) - true).max() < 0.5


def _edge_crossings(supersampling: int) -> np.ndarray:
    """Row by row, how far a print's black-to-white edge crosses its mid-level from where
    the model projects it: a half-black print, tilted 60 degrees so that a pixel spans
    more of its texture across the edge than along it; no noise, no lens."""
    tex = np.full((120, 120), 255, np.uint8)
    tex[:, :60] = 0
    cam = SimCamera(CameraModel(K, [], 640, 480), read_noise=0.0, shot_noise=0.0,
                    supersampling=supersampling)
    T = pose_matrix((np.pi, 0.0, 0.0), (0.013, 0.0, 0.9)) @ pose_matrix((0.0, 1.05, 0.03))
    image = cam.render([SceneObject("print", PlanarTarget(tex, 0.12, 0.12), static(T))], 0.0,
                       np.random.default_rng(0)).astype(float)
    black, white = 0.08 * 255, 0.93 * 255
    ends = cam.model.project(np.array([[0.0, 0.04, 0], [0.0, -0.04, 0]]) @ T[:3, :3].T
                             + T[:3, 3])
    errors = []
    ends = ends[np.argsort(ends[:, 1])]
    middle = (black + white) / 2
    for v in range(int(ends[0, 1]) + 2, int(ends[1, 1]) - 1):
        u_true = np.interp(v, ends[:, 1], ends[:, 0])
        left = int(u_true) - 3
        row = image[v, left:left + 8]
        i = int(np.argmax(row >= middle))
        errors.append(left + i - 1 + (middle - row[i - 1]) / (row[i] - row[i - 1]) - u_true)
    return np.array(errors)


def test_pixels_integrate_their_area_so_tilted_edges_do_not_lock_to_the_grid():
    centres, faithful = _edge_crossings(1), _edge_crossings(FAITHFUL)
    assert len(centres) > 20
    assert np.sqrt(np.mean(faithful ** 2)) < 0.5 * np.sqrt(np.mean(centres ** 2))
    assert np.abs(faithful).max() < 0.1


def test_supersampling_is_a_whole_number():
    with pytest.raises(InvalidInputError, match="supersampling"):
        SimCamera(CameraModel(K, [], 640, 480), supersampling=0)


def test_motion_blur_averages_more_instants_when_the_target_moves_fast():
    cam = SimCamera(CameraModel(K, DISTORTIONS[5], 640, 480), exposure_s=0.01)
    _, still = _marker_scene((np.pi, 0, 0), (0, 0, 1))
    moving = SceneObject("tag", still.drawable, lambda t: pose_matrix((np.pi, 0, 0),
                                                                      (2.0 * t, 0, 1)))
    assert cam._subframes([still], 0.5) == 1
    assert cam._subframes([moving], 0.5) == cam.max_subframes  # 2 m/s at 1 m: 12 px
    rng = np.random.default_rng(0)
    sharp, blurred = cam.render([still], 0.0, rng), cam.render([moving], 0.0, rng)
    assert np.abs(np.diff(blurred.astype(float), axis=1)).max() < \
        np.abs(np.diff(sharp.astype(float), axis=1)).max()


@pytest.mark.parametrize("name", ["sim.avi", "frames"])
def test_generated_video_reads_back_through_capture(tmp_path, name):
    cam = SimCamera(CameraModel(K, DISTORTIONS[5], 160, 120))
    _, obj = _marker_scene((np.pi, 0, 0), (0, 0, 0.6))
    moving = SceneObject("tag", obj.drawable,
                         lambda t: pose_matrix((np.pi, 0, 0), (0.1 * t, 0, 0.6)))
    rng = np.random.default_rng(5)
    frames = [cam.render([moving], i / 20, rng) for i in range(6)]
    path = write_video(tmp_path / name, frames, fps=20)
    before = time.time_ns()
    with Capture(path, fps=20, gray=True) as cap:  # a folder has no rate of its own
        got = list(cap.frames())
        assert cap.clock == "file-mapped"
    assert [f.seq for f in got] == list(range(6))
    for f, ref in zip(got, frames, strict=True):
        np.testing.assert_array_equal(f.image, ref)  # lossless
    t = np.array([f.t_ns for f in got])
    np.testing.assert_allclose(np.diff(t), 50e6, atol=1e5)
    assert before - 1e9 < t[0] <= time.time_ns()


def test_capture_is_bounded_and_paced(tmp_path):
    frames = [np.full((8, 8), i * 20, np.uint8) for i in range(5)]
    path = write_video(tmp_path / "v.avi", frames, fps=50)
    start = time.monotonic()
    with Capture(path, pace=True, max_frames=3) as cap:
        got = list(cap)
    assert [f.seq for f in got] == [0, 1, 2]
    assert time.monotonic() - start >= 0.035  # held back to 20 ms per frame


def test_sources_that_cannot_be_opened_say_so(tmp_path):
    with pytest.raises(CaptureError, match="neither a device index"):
        Capture(tmp_path / "missing.avi")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CaptureError, match="holds no images"):
        Capture(tmp_path / "empty")
    (tmp_path / "junk.avi").write_bytes(b"not a video")
    with pytest.raises(CaptureError, match="cannot open video file"):
        Capture(tmp_path / "junk.avi")


def test_ideal_pixels_by_table_agree_with_the_iteration_inside_and_outside_the_image():
    cam = CameraModel(K, [-0.16, 0.02, 0.0003, -0.0001, 0.0], 640, 480)
    rng = np.random.default_rng(2)
    inside = rng.uniform([0, 0], [638.9, 478.9], (500, 2))
    outside = np.array([[-3.0, 10.0], [650.0, 200.0], [100.0, 479.5]])
    pts = np.concatenate([inside, outside])
    exact = cam.undistort(pts, pixels=True)
    got = cam.ideal_pixels(pts)
    assert np.abs(got - exact).max() < 5e-4
    np.testing.assert_array_equal(got[-3:], exact[-3:])
