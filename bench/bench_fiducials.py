"""Benchmark of the fiducial tracker's per-frame pipeline: 10 AprilTags (36h11, 8 cm) at
0.6-1.6 m in front of a simulated 640x480 webcam (goals: <= 1.3x the anchor, >= 60
frames/s; judged on both the median frame and the total CPU over all frames, which counts
the rare frames with a steep tag's image fit in full).

Anchor, measured in the same run on the same frames: bare ``ArucoDetector.detectMarkers``
(OpenCV's defaults) + ``cv2.solvePnP(SOLVEPNP_IPPE_SQUARE)`` per marker, what a user of
OpenCV writes.  uma's pipeline: :meth:`FiducialTracker.process` (detection, edge-fitted
corners, both IPPE solutions refined, covariance, noise pooling, ambiguity judgement).
Capture is excluded from both (the frames are rendered before timing).  OpenCV runs on
one thread (``--threads 0`` leaves its default), so the figures are per core; the times
are the calling thread's CPU time (``time.thread_time``), which a shared, loaded machine
inflates far less than wall-clock time (also reported).

    python bench/bench_fiducials.py [--frames 200] [--tags 10] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np
from summary import cpu_model, median_p99

from services.camera.markers import dictionary, marker_corners
from services.camera.simulator import FAITHFUL, SimCamera
from services.fiducials.simulate import tags, wandering, webcam
from services.fiducials.tracker import FiducialTracker

FAMILY = "apriltag36h11"
SIZE_M = 0.08


def frames(n: int, n_tags: int, seed: int) -> tuple[list[np.ndarray], object]:
    """``n`` frames of ``n_tags`` tags wandering at 0.6-1.6 m, and the camera."""
    rng = np.random.default_rng(seed)
    camera = webcam(rng)
    trajectories = [wandering(rng, camera, (0.6, 1.6), 8.0, max_tilt_rad=0.5, fill=0.8)
                    for _ in range(n_tags)]
    scene = tags(FAMILY, list(range(n_tags)), SIZE_M, trajectories)
    sim = SimCamera(camera, supersampling=FAITHFUL)
    return [sim.render(scene, k / 30.0, rng) for k in range(n)], camera


def bare(detector: cv2.aruco.ArucoDetector, camera, image: np.ndarray) -> int:
    corners, ids, _ = detector.detectMarkers(image)
    if ids is None:
        return 0
    obj = marker_corners(SIZE_M)
    for c in corners:
        cv2.solvePnP(obj, c.reshape(4, 2), camera.K, camera.dist,
                     flags=cv2.SOLVEPNP_IPPE_SQUARE)
    return len(ids)


def uma(tracker: FiducialTracker, image: np.ndarray, t_ns: int) -> int:
    return len(tracker.process(image, t_ns))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--tags", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1,
                    help="OpenCV threads (default 1: per-core figures; 0: OpenCV's default)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.threads:
        cv2.setNumThreads(args.threads)
    images, camera = frames(args.frames, args.tags, args.seed)
    detector = cv2.aruco.ArucoDetector(dictionary(FAMILY))
    tracker = FiducialTracker(camera, FAMILY, SIZE_M)
    cpu: dict[str, list[float]] = {"bare": [], "uma": []}
    wall: dict[str, list[float]] = {"bare": [], "uma": []}
    found = {"bare": 0, "uma": 0}
    for k, image in enumerate(images):  # interleaved: both see the same load
        t_ns = round(k / 30 * 1e9)
        for name, step, step_args in (("bare", bare, (detector, camera, image)),
                                      ("uma", uma, (tracker, image, t_ns))):
            w, c = time.perf_counter(), time.thread_time()
            found[name] += step(*step_args)
            cpu[name].append((time.thread_time() - c) * 1e3)
            wall[name].append((time.perf_counter() - w) * 1e3)
    a, o = median_p99(cpu["bare"], "ms"), median_p99(cpu["uma"], "ms")
    figures = {"cpu": cpu_model(), "frames": args.frames, "tags": args.tags,
               "markers_found_per_frame": {k: round(v / args.frames, 2) for k, v in found.items()},
               "bare_aruco_solvepnp": a, "uma_pipeline": o,
               "ratio_median": round(o["median_ms"] / a["median_ms"], 3),
               # the whole run's CPU: a frame whose steep tags take the image fit counts fully
               "ratio_total": round(sum(cpu["uma"]) / sum(cpu["bare"]), 3),
               "uma_frames_per_s": round(1e3 / o["median_ms"], 1),
               "uma_frames_per_s_mean": round(1e3 * args.frames / sum(cpu["uma"]), 1),
               "wall": {k: median_p99(v, "ms") for k, v in wall.items()}}
    if args.json:
        print(json.dumps(figures))
        return
    print(f"cpu: {figures['cpu']}; {args.frames} frames 640x480, {args.tags} tags; markers per "
          f"frame: bare {figures['markers_found_per_frame']['bare']}, uma "
          f"{figures['markers_found_per_frame']['uma']}")
    for name, f in (("bare detectMarkers+solvePnP", a), ("uma pipeline", o)):
        print(f"{name:28s} median {f['median_ms']:7.3f} ms  p99 {f['p99_ms']:7.3f} ms CPU")
    print(f"ratio (median) {figures['ratio_median']:.3f}  ->  {figures['uma_frames_per_s']:.0f} "
          "frames/s per core")
    print(f"ratio (total CPU over all frames) {figures['ratio_total']:.3f}  ->  "
          f"{figures['uma_frames_per_s_mean']:.0f} frames/s per core on average")
    print("wall clock (inflated by other processes): " + ", ".join(
        f"{k} median {v['median_ms']:.3f} ms p99 {v['p99_ms']:.3f} ms"
        for k, v in figures["wall"].items()))


if __name__ == "__main__":
    main()
