"""Benchmark of the laser-dot tracker: dot detection per 640x480 image and the whole
pipeline per six-camera frame set (goals: detection <= 1.0x the baseline,
pipeline <= 1.5 ms median).

Baseline measured in the same run: detection with ``cv2.findContours`` and intensity
``cv2.moments`` per contour, the usual OpenCV recipe.  Both detectors are also scored
against the true spot centres.  The pipeline runs as configured (windows around the
predicted dots while tracking, with the installation's online estimate) and, for reference,
on full frames only and without the estimate (the estimate's cost, same run), the three
trackers taking each frame set in turn.  By default OpenCV
runs on one thread, so the figures are per core (``--threads 0`` leaves OpenCV's default).

    python bench/bench_laser.py [--frames 120] [--calibration FILE] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np
from summary import contour_centroids, cpu_model, median_p99

from services.laser_camera.calibration import Calibration, calibrate_sim
from services.laser_camera.detection import DetectorParams, detect_dots
from services.laser_camera.tracker import LaserTracker, TrackerParams
from services.sim.world import IvyWorld


def contour_baseline(img: np.ndarray, p: DetectorParams) -> np.ndarray:
    """Dots by findContours + intensity moments (no fragment merging)."""
    return contour_centroids(img, p.threshold, p.dark_level, p.min_area)


def timed(fn, *args) -> tuple[float, float, object]:
    """(wall s, cpu s, result) of one call."""
    w, c = time.perf_counter(), time.process_time()
    r = fn(*args)
    return time.perf_counter() - w, time.process_time() - c, r


def centroid_errors(found: np.ndarray, truth: dict) -> list[float]:
    errs = []
    for uv in truth.values():
        if len(found):
            d = np.hypot(*(found[:, :2] - uv).T).min()
            if d < 3:
                errs.append(float(d))
    return errs


def time_pipelines(trackers: list[LaserTracker], frames: list,
                   ) -> list[tuple[list[float], list[float]]]:
    """Wall and CPU seconds of each tracker's ``process`` per frame set, the trackers taking
    each frame set in turn: a burst of load on a shared machine then falls on all of them
    alike, so their ratios hold where one pass after the other would not (each tracker
    keeps its own state, so the turns do not change what it computes)."""
    out: list[tuple[list[float], list[float]]] = [([], []) for _ in trackers]
    for f in frames:
        for tracker, (wall, cpu) in zip(trackers, out, strict=True):
            w, c, _ = timed(tracker.process, f.images, f.t)
            wall.append(w)
            cpu.append(c)
    return out


def stats_ms(x: list[float]) -> dict[str, float]:
    """Median and p99 of durations in seconds, in ms to 4 decimals."""
    return {k: round(v, 4) for k, v in median_p99(np.array(x) * 1e3, "ms").items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=120, help="frame sets to time (default 120)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--ideal", action="store_true",
                    help="black screens (the ideal installation) instead of the realistic "
                         "default with projected imagery (docs/SIMULATION.md)")
    ap.add_argument("--calibration", default=None, metavar="FILE",
                    help="calibration file (default: calibrate the simulated cameras first)")
    ap.add_argument("--threads", type=int, default=1,
                    help="OpenCV threads (default 1: figures per core; 0: OpenCV's default)")
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    args = ap.parse_args()
    if args.threads > 0:
        cv2.setNumThreads(args.threads)
    world = IvyWorld(seed=args.seed, ideal=args.ideal)
    cal = Calibration.load(args.calibration) if args.calibration else calibrate_sim(world)
    frames = [world.render(i / 30) for i in range(args.frames)]

    det_wall, det_cpu, base_wall, base_cpu, err_ours, err_base = [], [], [], [], [], []
    for f in frames:
        for name, img in f.images.items():
            params = cal.camera(name).detector
            w, c, ours = timed(detect_dots, img, params)
            det_wall.append(w)
            det_cpu.append(c)
            w, c, base = timed(contour_baseline, img, params)
            base_wall.append(w)
            base_cpu.append(c)
            err_ours += centroid_errors(ours, f.image_points[name])
            err_base += centroid_errors(base, f.image_points[name])

    tracker = LaserTracker(cal)
    full_frame = LaserTracker(cal, TrackerParams(roi_half_px=0))
    plain = LaserTracker(cal, TrackerParams(estimate_installation=False))
    (pipe_wall, pipe_cpu), (full_wall, _), (plain_wall, plain_cpu) = time_pipelines(
        [tracker, full_frame, plain], frames)

    det, base = stats_ms(det_wall), stats_ms(base_wall)
    pipe = stats_ms(pipe_wall)
    figures = {
        "cpu": cpu_model(),
        "installation": "ideal" if args.ideal else "realistic (projected imagery)",
        "images": len(det_wall),
        "frame_sets": len(frames),
        "opencv_threads": cv2.getNumThreads(),
        "detection_ms_per_image": det,
        "detection_cpu_ms_per_image_median": stats_ms(det_cpu)["median_ms"],
        "baseline_contours_ms_per_image": base,
        "baseline_cpu_ms_per_image_median": stats_ms(base_cpu)["median_ms"],
        "detection_over_baseline_ratio": round(det["median_ms"] / base["median_ms"], 3),
        "detection_centroid_error_px_mean": round(float(np.mean(err_ours)), 4),
        "baseline_centroid_error_px_mean": round(float(np.mean(err_base)), 4),
        "pipeline_ms_per_frame_set": pipe,
        "pipeline_cpu_ms_per_frame_set_median": stats_ms(pipe_cpu)["median_ms"],
        "pipeline_detection_passes": dict(tracker.passes),
        "pipeline_full_frames_only_ms_per_frame_set": stats_ms(full_wall),
        "pipeline_without_estimate_ms_per_frame_set": stats_ms(plain_wall),
        "pipeline_without_estimate_cpu_ms_per_frame_set_median":
            stats_ms(plain_cpu)["median_ms"],
        "pipeline_over_without_estimate_ratio": round(
            pipe["median_ms"] / stats_ms(plain_wall)["median_ms"], 3),
        "pipeline_over_without_estimate_cpu_ratio": round(
            stats_ms(pipe_cpu)["median_ms"] / stats_ms(plain_cpu)["median_ms"], 3),
        "poses": tracker.counts["pose"],
        "poses_full_frames_only": full_frame.counts["pose"],
    }
    if args.json:
        print(json.dumps(figures))
    else:
        for k, v in figures.items():
            print(f"{k}: {v}")


if __name__ == "__main__":
    main()
