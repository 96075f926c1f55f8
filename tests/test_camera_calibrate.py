"""`uma calibrate camera` on simulated ChArUco boards of known intrinsics, and the
printable marker sheets of `uma markers print`."""

from __future__ import annotations

import json
import math
import re
import struct
import zlib

import cv2
import numpy as np
import pytest

from agent.cli.main import main
from services.camera import calibrate as cal
from services.camera.markers import (
    board_in_target,
    board_target,
    charuco_board,
    dictionary,
    sheet,
    write_pdf,
    write_png,
)
from services.camera.model import CameraModel, load
from services.camera.simulator import (
    FAITHFUL,
    SceneObject,
    SimCamera,
    pose_matrix,
    static,
    write_video,
)

TRUTH = CameraModel(np.array([[612.0, 0, 318.2], [0, 609.5, 242.7], [0, 0, 1]]),
                    [-0.21, 0.06, 0.0012, -0.0008, -0.01], 640, 480)
BOARD = charuco_board((9, 6), 0.04, 0.02)


def board_poses(rng, n, distance=(0.45, 0.75), centre_only=False):
    """Board poses facing the camera, tilted 0.2-0.6 rad about both axes, centred on
    random image points (the whole image, or its middle)."""
    lo, hi = ([280, 200], [360, 280]) if centre_only else ([60, 60], [580, 420])
    for _ in range(n):
        u, v = rng.uniform(lo, hi)
        T = pose_matrix((math.pi, 0, 0),
                        rng.uniform(*distance) * np.linalg.solve(TRUTH.K, [u, v, 1]))
        tilt = rng.choice([-1, 1], 2) * rng.uniform(0.2, 0.6, 2)
        T[:3, :3] = T[:3, :3] @ cv2.Rodrigues(np.array([*tilt, rng.uniform(-0.3, 0.3)]))[0]
        yield T


def render_board_views(seed, n, board=BOARD, supersampling=FAITHFUL, **kw):
    """(frames, true corner noise in px) of ``n`` simulated views of ``board``: the noise
    of what the detector measures, the RMS of the detected corners against the true
    corners' projections over the views a calibration keeps (both axes, the unit of
    OpenCV's RMS).  Rendered as a sensor integrates light (``FAITHFUL``) by default:
    sampled at the pixels' centres alone, the corners lock to the pixel grid by about
    0.04 px (RMS)."""
    rng = np.random.default_rng(seed)
    cam, target = SimCamera(TRUTH, supersampling=supersampling), board_target(board)
    detector = cv2.aruco.CharucoDetector(board)
    frames, views, truth = [], [], {}
    for T in board_poses(rng, n, **kw):
        image = cam.render([SceneObject("board", target, static(T))], 0.0, rng)
        frames.append(image)
        view = cal.detect_view(detector, image, len(frames))
        if view is not None:
            Tb = T @ board_in_target(board)
            pts = board.getChessboardCorners()[view.ids] @ Tb[:3, :3].T + Tb[:3, 3]
            views.append(view)
            truth[view.index] = TRUTH.project(pts)
    kept, _ = cal.select_views(views, TRUTH.size)
    if not kept:
        return frames, math.nan
    e = np.concatenate([v.corners - truth[v.index] for v in kept])
    return frames, float(np.sqrt((e ** 2).sum(1).mean()))


@pytest.fixture(scope="module")
def board_video(tmp_path_factory):
    frames, noise = render_board_views(seed=1, n=36)
    path = write_video(tmp_path_factory.mktemp("cal") / "board.avi", frames, fps=10)
    return path, noise


def check_intrinsics(summary, noise_px):
    """The goal: focal lengths within 0.3 %, principal point within 1 px, and both
    OpenCV's RMS and the corners' noise the calibration reports (the RMS with the fit's
    degrees of freedom counted) within 10 % of the detected corners' true error."""
    K = TRUTH.K
    assert abs(summary["fx"] / K[0, 0] - 1) < 0.003
    assert abs(summary["fy"] / K[1, 1] - 1) < 0.003
    assert abs(summary["cx"] - K[0, 2]) < 1.0
    assert abs(summary["cy"] - K[1, 2]) < 1.0
    assert abs(summary["noise_px"] / noise_px - 1) < 0.10
    assert abs(summary["rms_px"] / noise_px - 1) < 0.10


@pytest.mark.slow
def test_uma_calibrate_camera_recovers_known_intrinsics(board_video, tmp_path, capsys):
    path, noise = board_video
    out = tmp_path / "cam.yaml"
    code = main(["calibrate", "camera", "--source", str(path), "--squares", "9x6",
                 "--square", "0.04", "-o", str(out), "--json"])
    summary = json.loads(capsys.readouterr().out)
    assert (code, summary["verdict"], summary["reasons"]) == (0, "good", [])
    check_intrinsics(summary, noise)
    written = load(out)
    np.testing.assert_allclose(written.K[0, 0], summary["fx"])
    assert written.pixel_std == pytest.approx(summary["noise_px"] / math.sqrt(2))
    assert summary["std"]["fx"] > 0 and summary["uncovered"] == []


@pytest.mark.slow
def test_the_detectors_own_error_is_absorbed_like_independent_noise():
    """The detected corners' error is mostly the detector's own (the same views rendered
    without sensor noise, refined from the same start), and the fit (9 intrinsics, 6 per
    view, linearised at the truth) absorbs about as much of it as of independent noise,
    p / 2n, so the RMS stays within 10 % of that error: no marker edge reaches a corner's
    window to pull corners smoothly across a view."""
    rng, quiet_rng = np.random.default_rng(107), np.random.default_rng(0)
    cam = SimCamera(TRUTH, supersampling=FAITHFUL)
    quiet = SimCamera(TRUTH, supersampling=FAITHFUL, read_noise=0.0, shot_noise=0.0)
    target, detector = board_target(BOARD), cv2.aruco.CharucoDetector(BOARD)
    own, measured, jacobians = [], [], []
    for T in board_poses(rng, 36):
        scene = [SceneObject("board", target, static(T))]
        image = cam.render(scene, 0.0, rng)
        corners, ids, markers, _ = detector.detectBoard(image)
        if ids is None or len(ids) < cal.MIN_CORNERS:
            continue
        outlines = [np.reshape(m, (4, 2)).astype(np.float64) for m in markers]
        Tb = T @ board_in_target(BOARD)
        uv, J = cv2.projectPoints(BOARD.getChessboardCorners()[ids.ravel()].astype(np.float64),
                                  cv2.Rodrigues(Tb[:3, :3])[0], Tb[:3, 3], TRUTH.K, TRUTH.dist)
        start, uv = corners.reshape(-1, 2), uv.reshape(-1, 2)
        measured.append(cal.refine_corners(image, start, outlines) - uv)
        own.append(cal.refine_corners(quiet.render(scene, 0.0, quiet_rng), start, outlines) - uv)
        jacobians.append(J[:, :15])  # rvec, tvec, f, c, 5 distortion coefficients
    J = np.zeros((sum(len(j) for j in jacobians), 9 + 6 * len(jacobians)))
    row = 0
    for k, j in enumerate(jacobians):
        J[row:row + len(j), :9] = j[:, 6:]
        J[row:row + len(j), 9 + 6 * k:15 + 6 * k] = j[:, :6]
        row += len(j)
    fit = np.linalg.qr(J)[0]
    own_e, sensor_e = np.concatenate(own), np.concatenate(measured) - np.concatenate(own)
    assert np.sqrt((sensor_e ** 2).sum(1).mean()) < np.sqrt((own_e ** 2).sum(1).mean())
    absorbed = np.sum((fit.T @ own_e.ravel()) ** 2) / np.sum(own_e ** 2)
    assert absorbed < J.shape[1] / J.shape[0] + 0.03


def test_corner_noise_counts_the_fits_degrees_of_freedom():
    """Corners at their true projections plus independent noise of a known std: OpenCV's
    RMS falls short of that noise by the fit's parameters (9 intrinsics, 6 per view),
    the reported corner noise does not."""
    rng = np.random.default_rng(0)
    sigma = 0.1  # px per axis
    corners3d = BOARD.getChessboardCorners()
    views = []
    for i, T in enumerate(board_poses(rng, 30)):
        Tb = T @ board_in_target(BOARD)
        uv = TRUTH.project(corners3d @ Tb[:3, :3].T + Tb[:3, 3])
        seen = np.flatnonzero(((uv >= 0) & (uv < TRUTH.size)).all(1))
        ids = np.sort(rng.choice(seen, 20, replace=False))
        views.append(cal.View(i, ids, uv[ids] + rng.normal(0, sigma, (len(ids), 2))))
    result = cal.calibrate(views, BOARD, TRUTH.size, len(views))
    assert (result.corners, result.parameters) == (600, 9 + 6 * 30)
    true_noise = sigma * math.sqrt(2)
    assert result.noise_px / true_noise == pytest.approx(1, abs=0.04)
    assert result.rms_px / true_noise == pytest.approx(math.sqrt(1 - 189 / 1200), abs=0.04)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [*range(2, 11), *range(101, 111)])
def test_calibration_goals_hold_on_more_seeds(seed):
    frames, noise = render_board_views(seed, n=36)
    detector = cv2.aruco.CharucoDetector(BOARD)
    views = [v for i, f in enumerate(frames)
             if (v := cal.detect_view(detector, f, i)) is not None]
    kept, dup = cal.select_views(views, TRUTH.size)
    result = cal.calibrate(kept, BOARD, TRUTH.size, len(views), dup)
    assert result.verdict == "good", result.reasons
    check_intrinsics(result.summary(), noise)


def test_views_of_the_image_centre_only_need_more_views(tmp_path, capsys):
    small = charuco_board((5, 4), 0.04, 0.02)
    frames, _ = render_board_views(seed=5, n=12, board=small, supersampling=1,
                                   distance=(0.6, 0.7), centre_only=True)
    path = write_video(tmp_path / "centre.avi", frames, fps=10)
    code = main(["calibrate", "camera", "--source", str(path), "--squares", "5x4", "--square",
                 "0.04", "-o", str(tmp_path / "c.yaml")])
    text = capsys.readouterr().out
    assert code == 3
    assert "verdict: needs more views" in text
    assert re.search(r"no corners seen in the image's top-left, top, top-right, left, right, "
                     r"bottom-left, bottom, bottom-right", text)


def test_subpixel_windows_stay_clear_of_the_markers():
    corners = np.array([[100.0, 100.0], [130.0, 100.0], [100.0, 140.0]])
    # a fifth of the distance to the nearest other corner (30, 30 and 40 px)
    assert cal.subpix_windows(corners, []).tolist() == [6, 6, 8]
    # a marker 6 px from the first corner and 5 px from the second in the window's square
    # measure: their windows end 2 px short of it
    marker = np.array([[106.0, 95.0], [126.0, 95.0], [126.0, 75.0], [106.0, 75.0]])
    assert cal.subpix_windows(corners, [marker]).tolist() == [4, 3, 8]


def test_near_duplicate_views_are_dropped():
    rng = np.random.default_rng(0)
    T = next(board_poses(rng, 1))
    cam, target = SimCamera(TRUTH), board_target(BOARD)
    detector = cv2.aruco.CharucoDetector(BOARD)
    views = []
    for i in range(4):  # the board held still: only the sensor noise changes
        image = cam.render([SceneObject("b", target, static(T))], 0.0, rng)
        views.append(cal.detect_view(detector, image, i))
    kept, duplicates = cal.select_views(views, TRUTH.size)
    assert (len(kept), duplicates) == (1, 3)


def test_bad_calibrate_arguments_say_what_is_wrong(tmp_path, capsys):
    assert main(["calibrate", "camera", "--source", str(tmp_path / "none.avi")]) == 1
    assert "neither a device index" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["calibrate", "camera", "--source", "x", "--squares", "9by6"])
    assert "COLSxROWS" in capsys.readouterr().err


def test_printed_png_carries_its_dpi_and_exact_tag_size(tmp_path):
    dpi = 200.0
    image = sheet("apriltag36h11", [0, 1, 2], 0.05, dpi=dpi)
    data = write_png(tmp_path / "tags.png", image, dpi).read_bytes()
    at = data.index(b"pHYs")
    ppm_x, ppm_y, unit = struct.unpack(">IIB", data[at + 4:at + 13])
    assert (ppm_x, ppm_y, unit) == (round(dpi / 0.0254), round(dpi / 0.0254), 1)
    back = cv2.imread(str(tmp_path / "tags.png"), cv2.IMREAD_GRAYSCALE)
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary("apriltag36h11")).detectMarkers(back)
    assert sorted(ids.ravel().tolist()) == [0, 1, 2]
    side_px = np.linalg.norm(corners[0][0, 1] - corners[0][0, 0])
    assert side_px / dpi * 25.4 == pytest.approx(50.0, abs=0.3)  # mm on paper


def test_printed_pdf_is_a_page_of_the_sheets_physical_size(tmp_path):
    image = sheet("aruco4x4_50", [3], 0.04, dpi=100, page="letter")
    data = write_pdf(tmp_path / "t.pdf", image, 100).read_bytes()
    assert data.startswith(b"%PDF-1.4") and data.rstrip().endswith(b"%%EOF")
    box = re.search(rb"/MediaBox \[0 0 ([\d.]+) ([\d.]+)\]", data)
    assert float(box[1]) == pytest.approx(215.9 / 25.4 * 72, abs=0.5)  # letter, points
    xref = int(data.rsplit(b"startxref\n", 1)[1].split()[0])
    offsets = [int(line[:10]) for line in data[xref:].split(b"\n")[3:8]]
    for n, off in enumerate(offsets, 1):
        assert data[off:].startswith(b"%d 0 obj" % n)
    start = data.index(b"stream\n", data.index(b"/Subtype /Image")) + len(b"stream\n")
    pixels = zlib.decompress(data[start:data.index(b"\nendstream", start)])
    np.testing.assert_array_equal(np.frombuffer(pixels, np.uint8).reshape(image.shape), image)
