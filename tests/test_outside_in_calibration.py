"""Wand calibration of an outside-in rig: the wand found in blobs, the bundle adjustment
against the simulated truth, and `uma calibrate rig` end to end on generated videos read
back through the camera layer's capture path."""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest

from agent.daemon.settings import check_static_edge
from agent.errors import UmaError
from services.outside_in.calibration import (
    CalibrationError,
    Wand,
    calibrate_rig,
    static_blobs,
    wand_in_image,
)
from services.outside_in.rigfile import load_rig
from services.outside_in.simulator import SimConfig, Simulation


def test_wand_is_found_in_order_among_static_blobs() -> None:
    sim = Simulation(seed=2, config=SimConfig(n_cameras=2))
    cam = sim.cameras[0]
    wand = Wand()
    ends = np.array([[0.1, -0.2, 1.0], [0.1, 0.3, 1.3]])
    u = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
    X = ends[0] + np.array(wand.distances)[:, None] * u
    uv = cam.project(X)
    static = np.array([[100.0, 100.0], [500.0, 400.0]])
    shuffled = np.vstack([static, uv[::-1]])
    found = wand_in_image(shuffled, cam.model, static, wand)
    assert found is not None and np.allclose(found, uv)
    assert wand_in_image(uv[:2], cam.model, static, wand) is None          # two blobs
    bent = uv.copy()
    bent[1] += [0.0, 5.0]
    assert wand_in_image(bent, cam.model, static, wand) is None            # not a line


def test_static_blobs_are_those_in_most_frames() -> None:
    rng = np.random.default_rng(0)
    frames = [np.vstack([[[50.0, 60.0]], rng.uniform(0, 600, (3, 2))]) for _ in range(40)]
    found = static_blobs(frames)
    assert found.shape == (1, 2) and np.allclose(found[0], [50, 60])


def test_wand_distances_must_tell_its_ends_apart() -> None:
    with pytest.raises(ValueError, match="off"):
        Wand((0.0, 0.25, 0.5))


def test_too_few_wand_frames_are_refused_with_the_camera_named() -> None:
    sim = Simulation(seed=1, config=SimConfig(n_cameras=2))
    obs = np.full((30, 2, 3, 2), np.nan)
    obs[:5] = 1.0
    with pytest.raises(CalibrationError, match="cam0, cam1"):
        calibrate_rig([c.model for c in sim.cameras], obs, [])


@pytest.mark.slow
def test_uma_calibrate_rig_on_generated_videos(tmp_path, capsys) -> None:
    """Videos written by the simulator, read back by Capture: the rig's shape within a
    millimetre and 0.05 deg, its world frame within the L-frame's reach, the covariance
    of the right size, the files usable by the tracker and by agents."""
    from agent.cli.main import main
    out = tmp_path / "rig.toml"
    static = tmp_path / "static.toml"
    code = main(["calibrate", "rig", "--sim", "3", "--cameras", "4", "--frames", "90",
                 "--videos", str(tmp_path / "v"), "-o", str(out), "--agent-config",
                 str(static), "--json"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert report["max_shape_pos_error_mm"] < 1.5
    assert report["max_shape_rot_error_deg"] < 0.05
    assert report["max_world_pos_error_mm"] < 15
    for c in report["cameras"].values():
        assert c["world_pos_error_mm"] < 4 * max(c["pos_std_mm"], 0.1)
    assert 0.01 < report["rms_px"] < 0.08
    assert 0.75 < report["rms_over_noise"] < 1.25     # the residuals are the noise
    cams, covs, _ = load_rig(out)
    assert len(cams) == 4 and covs.shape == (4, 6, 6)
    edges = tomllib.loads(static.read_text())["static"]
    assert [check_static_edge(e, i)["child"] for i, e in enumerate(edges)] == [
        f"lab/cam{i}" for i in range(4)]


def test_uma_calibrate_rig_names_what_is_missing(tmp_path) -> None:
    import argparse

    from services.outside_in.cli import _sources
    from services.outside_in.commands import _rig_arguments
    p = argparse.ArgumentParser()
    _rig_arguments(p)
    args = p.parse_args(["--wand-video", "a=a.avi", "--wand-video", "b=b.avi",
                         "--lframe-video", "a=la.avi", "--intrinsics", "a=a.yaml"])
    with pytest.raises(UmaError, match="'b' lacks --lframe-video, --intrinsics"):
        _sources(args)
    with pytest.raises(SystemExit):
        p.parse_args(["--wand-video", "nofile"])


def test_body_from_points_keeps_the_steady_markers_near_each_other() -> None:
    from services.outside_in.bodies import body_from_points
    from services.outside_in.simulator import standard_bodies
    rng = np.random.default_rng(3)
    truth = standard_bodies()[1].markers + np.array([0.2, 0.1, 1.2])
    frames = []
    for _ in range(30):
        pts = [truth + rng.normal(0, 2e-4, truth.shape),
               np.array([[1.5, -1.2, 0.3]]),                      # a reflection's ghost
               rng.uniform(-1, 1, (2, 3))]                       # passing ghosts
        frames.append(np.vstack(pts)[rng.permutation(len(truth) + 3)])
    body, scatter = body_from_points("wand", frames)
    assert len(body.markers) == 4 and scatter < 5e-4
    assert np.allclose(np.sort(body.signature), np.sort(standard_bodies()[1].signature),
                       atol=5e-4)
    with pytest.raises(UmaError, match="three at least"):
        body_from_points("none", [rng.uniform(-1, 1, (3, 3)) for _ in range(10)])


def test_uma_calibrate_body_adds_a_body_and_warns_of_a_twin(tmp_path, capsys) -> None:
    from agent.cli.main import main
    from services.outside_in.bodies import load_bodies
    from services.outside_in.rigfile import save_rig
    sim = Simulation(seed=1, config=SimConfig(n_cameras=4))
    rig = save_rig(tmp_path / "rig.toml", sim.cameras, np.zeros((4, 6, 6)), "lab/world",
                   "lab", 0.03)
    out = tmp_path / "bodies.toml"
    for name in ("wand", "twin"):
        assert main(["calibrate", "body", name, "--rig", str(rig), "--sim", "1",
                     "--sim-body", "wand", "--frames", "20", "--bodies", str(out),
                     "--json"]) == 0
    captured = capsys.readouterr()
    last = json.loads(captured.out.strip().splitlines()[-1])
    assert last["not_distinguishable_from"] == ["wand"]
    assert "warning: twin and wand" in captured.err
    bodies = load_bodies(out)
    assert [b.name for b in bodies] == ["wand", "twin"]
    assert np.allclose(bodies[0].signature, sim.bodies[1].signature, atol=1e-3)


@pytest.mark.slow
def test_wand_frames_one_camera_saw_do_not_derail_the_adjustment() -> None:
    """Wand images projected from the truth (0.03 px noise), some frames seen by one
    camera only -- one in twenty with 8 cameras at the volume's edges -- and the L-frame:
    the rig comes out within a millimetre of the truth (frames one camera saw have no
    triangulated start and had left the adjustment far off or not finite)."""
    from services.outside_in.calibration import LFRAME
    from services.outside_in.simulator import WandWave
    rng = np.random.default_rng(3)
    sim = Simulation(seed=4, config=SimConfig(n_cameras=4))
    wave = WandWave(seed=4)
    obs = np.full((150, 4, 3, 2), np.nan)
    for f in range(len(obs)):
        X = wave.markers(f / 20)
        for c, cam in enumerate(sim.cameras):
            if np.all(cam.visible(X, margin_px=3)):
                obs[f, c] = cam.project(X) + rng.normal(0, 0.03, (3, 2))
    for f in range(0, len(obs), 10):          # the reference camera, and another, alone
        seen = np.nonzero(~np.isnan(obs[f, :, 0, 0]))[0]
        keep = seen[(f // 10) % len(seen)] if len(seen) else None
        obs[f, [c for c in range(4) if c != keep]] = np.nan
    lframe = [cam.project(LFRAME.markers) + rng.normal(0, 0.003, (4, 2))
              for cam in sim.cameras]
    cal = calibrate_rig([c.model for c in sim.cameras], obs, [lframe], sigma_px=0.03,
                        lframe_averaged=100)
    for est, true in zip(cal.cameras, sim.cameras, strict=True):
        assert np.linalg.norm(est.position - true.position) < 0.001
    # the views used, frame for frame as recorded (the report matches them to the truth)
    assert cal.wand_obs.shape == obs.shape
    assert np.all(np.isnan(cal.wand_obs[::10, :, 0, 0]))
