"""The fiducial tracker's compiled twin (services/fiducials/_kernels.c) against the numpy
code it mirrors: to rounding the fits, the Gauss-Newton and weighted steps, the side lines'
fits, the corners' covariance and the code cells' shift of thin sides' crossings; the edge
crossings to the bit; and the whole tracker's estimates on rendered frames, and a
bundle's on noisy corners."""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from services.camera.markers import dictionary, marker_corners
from services.camera.model import CameraModel
from services.camera.simulator import SimCamera
from services.fiducials import border, edges, pose
from services.fiducials.bodies import Body
from services.fiducials.simulate import tags, wandering, webcam
from services.fiducials.tracker import FiducialTracker

native = pytest.mark.skipif(pose.NATIVE is None or edges.NATIVE is None or border.NATIVE is None,
                            reason="the compiled fiducial kernels are not built")
K = np.array([[530.0, 0, 319.5], [0, 531.0, 241.5], [0, 0, 1]])


@pytest.fixture
def numpy_only(monkeypatch):
    """Runs the numpy code in the test's scope (the compiled twin set aside)."""
    def use_numpy() -> None:
        monkeypatch.setattr(pose, "NATIVE", None)
        monkeypatch.setattr(edges, "NATIVE", None)
        monkeypatch.setattr(border, "NATIVE", None)
    return use_numpy


def _stack(rng: np.random.Generator, m: int, n: int) -> tuple[np.ndarray, ...]:
    """``m`` objects of ``n`` points about 1 m in front of the camera, seen with pixel
    noise, and poses near (not at) the ones that made the images."""
    obj = rng.uniform(-0.1, 0.1, (m, n, 3)) * [1, 1, 0.2]
    R = np.stack([cv2.Rodrigues(rng.normal(0, 0.5, 3))[0] for _ in range(m)])
    t = np.column_stack([rng.uniform(-0.2, 0.2, (m, 2)), rng.uniform(0.6, 1.6, m)])
    X = obj @ np.swapaxes(R, 1, 2) + t[:, None]
    img = (X[..., :2] / X[..., 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    img += rng.normal(0, 0.3, img.shape)
    R0 = pose.exp_rotation(rng.normal(0, 0.03, (m, 3))) @ R
    return obj, img, R0, t + rng.normal(0, 0.01, (m, 3))


@native
@pytest.mark.parametrize("n", [4, 12])
def test_compiled_fits_and_steps_agree_with_numpy(numpy_only, n):
    obj, img, R0, t0 = _stack(np.random.default_rng(n), 9, n)
    # an object whose points all lie at its origin: its rotation is not fixed, the
    # normal equations are singular and neither takes a step
    obj[3] = 0.0
    root = np.random.default_rng(n + 1).normal(size=(9, 2 * n, 2 * n))
    information = root @ np.swapaxes(root, 1, 2) + 2 * n * np.eye(2 * n)
    compiled = pose.fits(obj, img, K, R0, t0)
    stepped, turned = pose.gauss_newton(obj, img, K, compiled)
    weighed = pose.reweigh(stepped, information)
    numpy_only()
    plain = pose.fits(obj, img, K, R0, t0)
    plain_stepped, plain_turned = pose.gauss_newton(obj, img, K, plain)
    plain_weighed = pose.reweigh(plain_stepped, information)
    for a, b in ((compiled, plain), (stepped, plain_stepped), (weighed, plain_weighed)):
        for field in ("R", "t", "residual", "jacobian"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=1e-11,
                                       atol=1e-11 * np.abs(getattr(b, field)).max())
    np.testing.assert_allclose(turned, plain_turned, rtol=1e-9, atol=1e-15)
    assert turned[3] == 0.0 and np.array_equal(stepped.R[3], R0[3])
    assert np.all(stepped.rss[np.arange(9) != 3] < compiled.rss[np.arange(9) != 3])


@native
def test_compiled_crossings_agree_with_numpy_to_the_bit(numpy_only):
    rng = np.random.default_rng(7)
    # 8-bit profiles: steps, ramps, several crossings, none, flat at the level
    profile = rng.integers(0, 256, (3, 4, 200, edges.STEPS)).astype(np.float64)
    profile[0] = np.sort(profile[0], axis=-1)
    profile[1, :, :50] = 128.0
    level = rng.integers(0, 256, profile.shape[:-1]) + rng.choice([0.0, 0.5], profile.shape[:-1])
    level[1, :, :50] = 128.0
    compiled = edges._crossings(profile, level)
    numpy_only()
    plain = edges._crossings(profile, level)
    assert np.isinf(plain).any() and np.isfinite(plain).any()
    assert np.array_equal(compiled, plain)


@native
def test_compiled_line_fits_locking_terms_and_corner_covariance_agree_with_numpy(numpy_only):
    rng = np.random.default_rng(11)
    n, k = 6, edges.SAMPLES
    corners = np.array([[0, 0], [40, 2], [42, 38], [-1, 40]], float) + rng.normal(0, 5, (n, 1, 2))
    side = corners[:, [1, 2, 3, 0]] - corners
    points = corners[:, :, None] + edges._SECOND * side[:, :, None] \
        + rng.normal(0, 0.2, (n, 4, k, 2))
    w = (rng.random((n, 4, k)) > 0.1).astype(float)
    w[0, 1] = 0.0  # a side without edge points: its line from the detected corners
    few = (w.sum(-1) < edges.MIN_POINTS)[..., None]

    def both() -> tuple[np.ndarray, ...]:
        mean, dev, direction = edges._lines(points, w)
        point = np.where(few, corners, mean)
        found, _ = edges._intersections(point, direction, corners, np.full((n, 4, 1), 5.0))
        taken, gains = edges._locking_terms(points, dev, direction, w, found)
        assert taken[..., 0].any()  # the locking's share taken out of some sides' scatter
        assert gains[..., 1].any()  # and its line gains, offset and turn
        return mean, dev, direction, taken, gains, edges._corner_covariance(
            found, point, direction, dev, w, few, taken)

    compiled = both()
    numpy_only()
    for a, b in zip(compiled, both(), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12 * np.abs(b).max())


@native
def test_compiled_code_crossing_bias_agrees_with_numpy(numpy_only, monkeypatch):
    # steep tags' sides 1.7-3 px across, crossed at their own middles and at the print's
    rng = np.random.default_rng(5)
    cells = border.code_cells(dictionary("apriltag36h11"))[[3, 17, 200, 511]]
    quad = np.array([[100, 100], [124, 103], [125, 121], [101, 118]], float)
    quads = np.stack([quad * [1, s] + rng.uniform(0, 50, 2) for s in (0.6, 0.8, 1.0, 1.2)])
    tag, side = np.repeat(np.arange(4), 4), np.tile(np.arange(4), 4)
    across = edges.cell_widths(quads, cells.shape[-1])[tag, side]
    offsets = rng.uniform(2.5, 4.0, (16, 1)) * edges._OFFS
    own = np.arange(16) % 3 > 0

    def bias() -> np.ndarray:
        return border.crossing_bias(quads[tag], cells[tag], side, edges._SECOND[::2], across,
                                    offsets, own)

    compiled = bias()
    monkeypatch.setattr(border, "NATIVE", None)
    plain = bias()
    assert np.abs(plain).max() > 0.01
    np.testing.assert_allclose(compiled, plain, rtol=0, atol=1e-12)


@native
def test_tracker_estimates_agree_with_the_numpy_code(numpy_only):
    # steep near tags (their thinnest sides from the border model) and far, nearly
    # fronto-parallel ones (the ambiguity covered, then decided by the track)
    rng = np.random.default_rng(3)
    camera = webcam(rng)
    trajectories = [wandering(rng, camera, (0.6, 1.5), 6.0, max_tilt_rad=1.3) for _ in range(4)] \
        + [wandering(rng, camera, (2.0, 3.0), 6.0, max_tilt_rad=0.3) for _ in range(4)]
    scene = tags("apriltag36h11", list(range(8)), 0.08, trajectories)
    sim = SimCamera(camera)
    frames = [sim.render(scene, k / 10, rng) for k in range(8)]

    def run() -> list:
        tracker = FiducialTracker(camera, "apriltag36h11", 0.08)
        return [e for k, f in enumerate(frames) for e in tracker.process(f, k * 100_000_000)]

    compiled = run()
    numpy_only()
    plain = run()
    assert len(compiled) == len(plain) >= 30
    assert {e.ambiguity for e in plain} == {"none", "covered", "history"}
    for a, b in zip(compiled, plain, strict=True):
        assert (a.name, a.ambiguity, a.markers) == (b.name, b.ambiguity, b.markers)
        for field in ("R", "t", "covariance", "sigma_px", "rms_px", "flip_probability"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=1e-9,
                                       atol=1e-12)


@native
def test_bundle_estimates_agree_with_the_numpy_code(numpy_only):
    # four tags on a plate at 2.5 m, tilted 0.15 rad: the two solutions judged by the
    # corners' joint covariance, the pose weighted by it
    plate = {i: marker_corners(0.08) + np.array([0.055 * dx, 0.055 * dy, 0.0])
             for i, (dx, dy) in enumerate([(-1, 1), (1, 1), (1, -1), (-1, -1)], start=20)}
    body = Body("plate", plate)
    rng = np.random.default_rng(4)
    frames = []
    R, t = cv2.Rodrigues(np.array([0.15, 0.0, 0.0]))[0], np.array([0.1, 0.05, 2.5])
    for _ in range(8):
        seen = {}
        for i, corners in plate.items():
            X = corners @ R.T + t
            seen[i] = X[:, :2] / X[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]] \
                + rng.normal(0, 0.05, (4, 2))
        frames.append(seen)
    noise = {i: 0.05 ** 2 * np.eye(8) for i in plate}
    camera = CameraModel(K, [], 640, 480, pixel_std=0.3)

    def run() -> list:
        tracker = FiducialTracker(camera, "apriltag36h11", None, bundles=[body])
        return [e for k, f in enumerate(frames) for e in tracker.estimate(f, k * 100_000_000,
                                                                          noise)]

    compiled = run()
    numpy_only()
    plain = run()
    assert len(compiled) == len(plain) == 8
    assert sum(np.isfinite(e.alternative_gap) for e in plain) >= 3  # two solutions judged
    for a, b in zip(compiled, plain, strict=True):
        assert (a.ambiguity, a.markers) == (b.ambiguity, b.markers)
        for field in ("R", "t", "covariance", "alternative_gap", "flip_probability"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=1e-9,
                                       atol=1e-12)


def test_the_numpy_code_is_forced_by_the_environment():
    out = subprocess.run([sys.executable, "-c", "from services.fiducials import border, edges, "
                          "pose; print(pose.NATIVE is None and edges.NATIVE is None "
                          "and border.NATIVE is None)"],
                         env=dict(os.environ, UMA_FIDUCIALS_PURE_PYTHON="1"),
                         capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "True"


def test_a_stack_of_other_sizes_is_refused():
    if pose.NATIVE is None:
        pytest.skip("the compiled fiducial kernels are not built")
    obj = np.ascontiguousarray(np.repeat(marker_corners(0.08)[None], 2, 0))
    R, t = np.tile(np.eye(3), (2, 1, 1)), np.tile([0.0, 0.0, 1.0], (2, 1))
    with pytest.raises(ValueError, match="inconsistent"):
        pose.NATIVE.fits(obj, np.zeros((2, 3, 2)), pose._intrinsics(K), R, t,
                         np.empty((2, 8)), np.empty((2, 8, 6)))
