"""What ``uma calibrate rig`` and ``uma calibrate body`` do (grammar in ``commands.py``)."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.errors import UmaError
from services.camera.capture import Capture
from services.camera.model import load as load_camera
from services.camera.simulator import write_video
from services.outside_in.blobs import BlobParams, find_blobs, fit_centres
from services.outside_in.bodies import (
    body_from_points,
    distinguishable,
    dump_bodies,
    load_bodies,
)
from services.outside_in.calibration import (
    LFRAME,
    RigCalibration,
    Wand,
    calibrate_rig,
    wand_observations,
)
from services.outside_in.pose import absolute_orientation
from services.outside_in.rigfile import load_rig, save_rig, static_edges
from services.outside_in.simulator import (
    SimConfig,
    Simulation,
    WandWave,
    blocked,
    static_scene,
)
from services.outside_in.triangulation import match_and_triangulate

Array = np.ndarray
#: wand frame sets per second the simulation records (a wand needs no more)
SIM_WAND_HZ = 20
#: seconds of the still L-frame the simulation records, at the cameras' own rate (what a
#: real recording of "a second or two" holds; its frames are averaged)
SIM_LFRAME_S = 1.0


def calibrate_rig_command(args: argparse.Namespace) -> int:
    try:
        wand = Wand(args.wand)
    except ValueError as exc:
        raise UmaError(f"--wand: {exc}") from None
    truth = None
    if args.sim is not None:
        if not 20 <= args.frames <= 100_000 or not 2 <= args.cameras <= 16:
            raise UmaError(f"--frames must be 20 or more and --cameras 2-16, got "
                           f"{args.frames} and {args.cameras}")
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(args.videos or tmp)
            sim = simulate_recordings(args.sim, args.cameras, args.frames, folder, wand)
            truth = sim.cameras
            cal = calibrate_from_files(_sim_sources(folder, sim), wand, args.refine_intrinsics)
            noise = wand_noise_px(sim, WandWave(wand.distances, seed=args.sim), cal.wand_obs)
    else:
        cal = calibrate_from_files(_sources(args), wand, args.refine_intrinsics)
    save_rig(args.output, cal.cameras, cal.covariances, args.world, args.site, cal.rms_px)
    if args.agent_config:
        Path(args.agent_config).write_text(
            "# world -> camera edges of 'uma calibrate rig'\n"
            + static_edges(cal.cameras, cal.covariances, args.world, args.site))
    report = rig_report(cal, truth)
    if truth is not None:
        report["simulated_noise_px"] = round(noise, 4)
        report["rms_over_noise"] = round(cal.rms_px / noise, 3)
    if args.json:
        print(json.dumps(report))
    else:
        _print(report, args.output)
    return 0


def _sources(args: argparse.Namespace) -> dict[str, tuple[str, str, str]]:
    """NAME -> (wand video, L-frame video, intrinsics file), every camera complete."""
    wand, lf, intr = (dict(args.wand_video), dict(args.lframe_video), dict(args.intrinsics))
    names = set(wand) | set(lf) | set(intr)
    if len(names) < 2:
        raise UmaError("give two cameras at least: --wand-video, --lframe-video and "
                       "--intrinsics NAME=FILE for each (or --sim SEED)")
    for n in sorted(names):
        missing = [o for o, d in (("--wand-video", wand), ("--lframe-video", lf),
                                  ("--intrinsics", intr)) if n not in d]
        if missing:
            raise UmaError(f"camera {n!r} lacks {', '.join(missing)}")
    return {n: (wand[n], lf[n], intr[n]) for n in sorted(names)}


def _sim_sources(folder: Path, sim: Simulation) -> dict[str, tuple[str, str, str]]:
    return {c.name: (str(folder / f"{c.name}.wand.avi"), str(folder / f"{c.name}.lframe.avi"),
                     str(folder / f"{c.name}.yaml")) for c in sim.cameras}


def simulate_recordings(seed: int, n_cameras: int, n_frames: int, folder: Path,
                        wand: Wand) -> Simulation:
    """Render a simulated rig's wand and L-frame videos and intrinsics files into
    ``folder``; returns the simulation (its cameras are the truth)."""
    folder.mkdir(parents=True, exist_ok=True)
    sim = Simulation(seed=seed, config=SimConfig(n_cameras=n_cameras))
    wave = WandWave(wand.distances, seed=seed).scene(sim)
    still = static_scene(sim, LFRAME.markers)
    stride = round(sim.config.rate_hz / SIM_WAND_HZ)
    for c, cam in enumerate(sim.cameras):
        cam.model.save(folder / f"{cam.name}.yaml")
        write_video(folder / f"{cam.name}.wand.avi",
                    (sim.render(c, stride * i, wave).image for i in range(n_frames)),
                    SIM_WAND_HZ)
        write_video(folder / f"{cam.name}.lframe.avi",
                    (sim.render(c, 10**6 + i, still).image
                     for i in range(round(SIM_LFRAME_S * sim.config.rate_hz))),
                    sim.config.rate_hz)
    return sim


def wand_noise_px(sim: Simulation, wave: WandWave, obs: Array) -> float:
    """The simulated wand images' true centroid error (px, rms per axis): each observed
    marker against the true camera's projection of the true wand at that frame."""
    stride = round(sim.config.rate_hz / SIM_WAND_HZ)
    errors = []
    for f in range(len(obs)):
        for c, cam in enumerate(sim.cameras):
            if not np.isnan(obs[f, c, 0, 0]):
                t = sim.exposure_time(c, stride * f)
                errors.append(obs[f, c] - cam.project(wave.markers(t)))
    return float(np.sqrt(np.mean(np.square(errors))))


def calibrate_from_files(sources: dict[str, tuple[str, str, str]], wand: Wand,
                         refine_intrinsics: bool) -> RigCalibration:
    """Read every camera's recordings through the capture path and calibrate."""
    names = list(sources)
    models = []
    for n in names:
        m = load_camera(sources[n][2])
        models.append(type(m)(m.K, m.dist, m.width, m.height, m.pixel_std, n))
    wand_frames = matched_blobs([sources[n][0] for n in names])
    lframe_blobs, averaged = still_blobs([sources[n][1] for n in names])
    obs = wand_observations(models, wand_frames, wand)
    return calibrate_rig(models, obs, [lframe_blobs], wand, intrinsics=refine_intrinsics,
                         lframe_averaged=averaged)


#: DN above which a pixel of an averaged still image may belong to a marker: its noise is
#: a few tenths of a DN, so markers far too faint for one frame's threshold are found
STILL_THRESHOLD_DN = 20


def still_blobs(paths: list[str], max_frames: int = 600) -> tuple[list[Array], int]:
    """Blob pixels of recordings of a still scene (the L-frame on the floor), one array
    per camera, and the fewest frames averaged in any.  Each recording's frames are
    averaged into one image before segmentation: the noise falls by the square root of
    their number, so the far markers, near one frame's threshold and found in that frame
    only when its noise lifts them above it (which biases their centroids), are found in
    every camera with a lower threshold, and located by a fitted model
    (``fit_centres``) rather than their centroids."""
    out, counts = [], []
    params = BlobParams(threshold=STILL_THRESHOLD_DN)
    for path in paths:
        total, n = None, 0
        with Capture(path, gray=True, max_frames=max_frames) as cap:
            for frame in cap.frames():
                img = frame.image.astype(np.float64)
                total = img if total is None else total + img
                n += 1
        if total is None:
            raise UmaError(f"{path}: no frames")
        mean = total / n
        out.append(fit_centres(mean, find_blobs(np.rint(mean).astype(np.uint8), params).uv))
        counts.append(n)
    return out, min(counts)


def matched_blobs(paths: list[str], max_frames: int = 20_000) -> list[list[Array]]:
    """Blob pixels of every camera's recording, frame sets matched by time: each camera's
    frame nearest to the first camera's, within half a frame period, else none."""
    per_cam: list[tuple[Array, list[Array]]] = []
    for path in paths:
        times, blobs = [], []
        with Capture(path, gray=True, max_frames=max_frames) as cap:
            for frame in cap.frames():
                times.append(frame.t_ns)
                blobs.append(find_blobs(frame.image).uv)
        if not times:
            raise UmaError(f"{path}: no frames")
        t = np.array(times, float)
        per_cam.append((t - t[0], blobs))
    ref_t, _ = per_cam[0]
    period = float(np.median(np.diff(ref_t))) if len(ref_t) > 1 else 1.0
    out = []
    for t in ref_t:
        row = []
        for ts, blobs in per_cam:
            k = int(np.argmin(np.abs(ts - t)))
            row.append(blobs[k] if abs(ts[k] - t) <= period / 2 else np.zeros((0, 2)))
        out.append(row)
    return out


def rig_report(cal: RigCalibration, truth: list | None = None) -> dict[str, Any]:
    """Figures of a calibration, and its errors when the truth is known (simulation):
    in the world frame the L-frame defines, and of the rig's shape (the calibrated rig
    moved onto the true one by the best rigid motion, which takes the world frame's own
    error out)."""
    out: dict[str, Any] = {"rms_px": round(cal.rms_px, 4), "wand_frames": cal.wand_frames,
                           "lframe_frames": cal.lframe_frames,
                           "wand_observations": cal.observations, "cameras": {}}
    for c, cam in enumerate(cal.cameras):
        ps, rs = cal.std(c)
        out["cameras"][cam.name] = {"position": [round(float(x), 5) for x in cam.position],
                                    "quaternion": [round(float(x), 6) for x in cam.quaternion],
                                    "pos_std_mm": round(ps * 1e3, 3),
                                    "rot_std_deg": round(float(np.degrees(rs)), 4)}
    if truth is None:
        return out
    T = np.array([c.position for c in truth])
    E = np.array([c.position for c in cal.cameras])
    R, p = absolute_orientation(E, T)
    q_align = geo.matrix_to_quat(R)
    for c, (cam, tc) in enumerate(zip(cal.cameras, truth, strict=True)):
        entry = out["cameras"][cam.name]
        entry["world_pos_error_mm"] = round(float(np.linalg.norm(E[c] - T[c])) * 1e3, 3)
        entry["world_rot_error_deg"] = round(float(np.degrees(
            geo.quat_angle(cam.quaternion, tc.quaternion))), 4)
        entry["shape_pos_error_mm"] = round(float(np.linalg.norm(R @ E[c] + p - T[c])) * 1e3,
                                            3)
        entry["shape_rot_error_deg"] = round(float(np.degrees(geo.quat_angle(
            geo.quat_multiply(q_align, cam.quaternion), tc.quaternion))), 4)
    for key in ("world_pos_error_mm", "world_rot_error_deg", "shape_pos_error_mm",
                "shape_rot_error_deg"):
        out[f"max_{key}"] = max(v[key] for v in out["cameras"].values())
    return out


def _print(report: dict[str, Any], path: str) -> None:
    w = sys.stdout.write
    w(f"rig calibrated from {report['wand_frames']} wand frame sets "
      f"({report['wand_observations']} camera views) and {report['lframe_frames']} L-frame "
      f"frame sets; reprojection RMS {report['rms_px']:.3f} px"
      + (f" (the simulated centroid noise: {report['simulated_noise_px']:.3f} px)"
         if "simulated_noise_px" in report else "") + "\n")
    for name, c in report["cameras"].items():
        line = (f"  {name}: position {c['position']} m  std {c['pos_std_mm']:.2f} mm "
                f"{c['rot_std_deg']:.3f} deg")
        if "world_pos_error_mm" in c:
            line += (f"  error {c['world_pos_error_mm']:.2f} mm {c['world_rot_error_deg']:.3f}"
                     f" deg (rig shape {c['shape_pos_error_mm']:.2f} mm "
                     f"{c['shape_rot_error_deg']:.4f} deg)")
        w(line + "\n")
    w(f"wrote {path}\n")


def calibrate_body_command(args: argparse.Namespace) -> int:
    cams, _, _ = load_rig(args.rig)
    if args.sim is not None:
        if not 3 <= args.frames <= 10_000:
            raise UmaError(f"--frames must be 3 or more, got {args.frames}")
        sim = Simulation(seed=args.sim, config=SimConfig(n_cameras=len(cams)))
        names = [b.name for b in sim.bodies]
        if args.sim_body not in names:
            raise UmaError(f"--sim-body {args.sim_body!r}: the simulation has {names}")
        k = names.index(args.sim_body)
        frozen = sim.marker_positions(0.0)[k]
        scene = static_body_scene(sim, k, frozen)
        per_frame = [[find_blobs(sim.render(c, i, scene).image).uv for c in range(len(cams))]
                     for i in range(args.frames)]
    else:
        paths = dict(args.video)
        missing = [c.name for c in cams if c.name not in paths]
        if len(paths) < 2:
            raise UmaError("give two cameras' videos at least: --video NAME=FILE")
        used = [c for c in cams if c.name in paths]
        per_frame = matched_blobs([paths[c.name] for c in used])
        cams = used
        if missing:
            print(f"note: cameras {missing} have no video and are not used", file=sys.stderr)
    points = [np.array([q.X for q in match_and_triangulate(
        cams, [cam.normalize(uv) for cam, uv in zip(cams, frame, strict=True)])
        if len(q.views) >= 2]).reshape(-1, 3) for frame in per_frame]
    body, scatter = body_from_points(args.name, points)
    path = Path(args.bodies)
    others = [b for b in (load_bodies(path) if path.exists() else []) if b.name != body.name]
    clashes = [b.name for b in others if not distinguishable(body, b, max(scatter, 2e-4))]
    path.write_text(dump_bodies([*others, body]))
    report = {"body": body.name, "markers": len(body.markers),
              "scatter_mm": round(scatter * 1e3, 3),
              "distances_mm": [round(float(d) * 1e3, 1) for d in body.signature],
              "not_distinguishable_from": clashes, "file": str(path)}
    if args.json:
        print(json.dumps(report))
    else:
        print(f"body {body.name}: {len(body.markers)} markers, scatter "
              f"{report['scatter_mm']:.2f} mm, distances {report['distances_mm']} mm; "
              f"wrote {path}")
    for name in clashes:
        print(f"warning: {body.name} and {name} share three markers' distances within the "
              "noise: the tracker may take one for the other; move a marker of one",
              file=sys.stderr)
    return 0


def static_body_scene(sim: Simulation, k: int, world: Array):
    """What each camera sees of body ``k`` held still at ``world`` (its own hull hides
    markers behind it), the other bodies away."""
    centre = world.mean(axis=0)

    def see(camera: int, t: float) -> dict:
        cam = sim.cameras[camera]
        vis = cam.visible(world, margin_px=3)
        return {(k, m): world[m] for m in np.nonzero(vis)[0]
                if not blocked(cam.position, world[m], [centre])}
    return see
