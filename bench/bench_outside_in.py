"""Benchmark of the outside-in tracker: marker blobs per 640x480 IR image and the whole
tracker per frame set (six cameras by default, three bodies, 5 false blobs per camera).

Anchors measured in the same run on the same images: blob detection with
``cv2.findContours`` and intensity ``cv2.moments`` per contour (the usual OpenCV recipe),
and per frame set the OpenCV-only baseline of ``uma eval outside-in`` (per body the best
camera pair, ``cv2.triangulatePoints``, ``cv2.estimateAffine3D``).  The frames are
rendered first, outside the timing.  ``frame_sets_per_s`` is what one core sustains
(detection in every image plus the tracker), to hold against the cameras' 120 Hz.

With ``--live SECONDS`` it runs the services instead, as processes on loopback
(``outside_in_live``): exposure-to-pose latency next to the bare transport's, the
published rate against the camera rate and every service's CPU.

    python bench/bench_outside_in.py [--frames 120] [--cameras 6] [--json]
    python bench/bench_outside_in.py --live 10 [--cameras 8] [--rate-hz 120] [--json]
"""

from __future__ import annotations

import argparse
import os
import time

import cv2
import numpy as np
from summary import contour_centroids, cpu_model, median_p99, report

from services.outside_in.blobs import BlobParams, find_blobs
from services.outside_in.evaluate import opencv_baseline
from services.outside_in.simulator import SimConfig, Simulation
from services.outside_in.tracker import CameraFrame, OutsideInTracker


def contour_blobs(img: np.ndarray, p: BlobParams) -> np.ndarray:
    """Blobs by findContours + intensity moments."""
    return contour_centroids(img, p.threshold, p.dark_level)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120, help="frame sets (default 120)")
    ap.add_argument("--cameras", type=int, default=6, help="cameras, 2-16 (default 6)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="also print one JSON object")
    ap.add_argument("--live", type=float, default=None, metavar="SECONDS",
                    help="run the services as processes and measure for SECONDS")
    ap.add_argument("--rate-hz", type=float, default=120.0,
                    help="with --live: the cameras' frame rate (default 120)")
    ap.add_argument("--per-process", type=int, default=2, metavar="N",
                    help="with --live: cameras per marker-camera process (default 2)")
    ap.add_argument("--stall", type=float, nargs="+", default=None,
                    metavar="AT SECONDS [SHARE]",
                    help="with --live: hold the reconstruction's process back AT seconds into "
                         "the measurement for SECONDS: stopped (SIGSTOP), or with SHARE let "
                         "run that share of every 20 ms (a busy machine's leftovers), then "
                         "continued; reports whether and how soon its poses come at the "
                         "camera rate again")
    ap.add_argument("--logs", default=None, metavar="DIR",
                    help="with --live: keep every process's log in DIR")
    args = ap.parse_args()
    if args.frames < 2 or not 2 <= args.cameras <= 16:
        ap.error("--frames must be 2 or more and --cameras 2-16")
    if args.live is not None:
        if not (args.live > 0 and args.rate_hz > 0 and args.per_process >= 1):
            ap.error("--live, --rate-hz and --per-process must be positive")
        from outside_in_live import Stall, run
        stall = Stall(*args.stall) if args.stall is not None and len(args.stall) in (2, 3) \
            else None
        if args.stall is not None and not (stall and stall.at_s >= 0 and stall.seconds > 0
                                           and stall.at_s + stall.seconds < args.live
                                           and 0 <= stall.share < 1):
            ap.error("--stall AT SECONDS [SHARE]: AT >= 0, SECONDS > 0, ending inside the "
                     "measurement (--live), SHARE in [0, 1)")
        figures = {"cpu": cpu_model(), "load": os.getloadavg()[0],
                   **run(args.cameras, args.rate_hz, args.live, args.per_process, args.seed,
                          args.logs, stall)}
        report(figures, args.json)
        return
    cv2.setNumThreads(1)
    sim = Simulation(seed=args.seed, config=SimConfig(n_cameras=args.cameras))
    sets = [[sim.render(c, i) for c in range(args.cameras)] for i in range(args.frames)]
    tracker = OutsideInTracker(list(sim.cameras), sim.bodies)
    detect, anchor_detect, track, anchor_track = [], [], [], []
    for frames in sets:
        blobs = []
        for f in frames:
            t = time.perf_counter()
            blobs.append(find_blobs(f.image))
            detect.append(time.perf_counter() - t)
            t = time.perf_counter()
            contour_blobs(f.image, BlobParams())
            anchor_detect.append(time.perf_counter() - t)
        t = time.perf_counter()
        tracker.process([CameraFrame(c, f.t, b) for c, (f, b) in enumerate(zip(frames, blobs,
                                                                             strict=True))])
        track.append(time.perf_counter() - t)
        t = time.perf_counter()
        for k, body in enumerate(sim.bodies):
            opencv_baseline(sim.cameras, frames, blobs, k, body)
        anchor_track.append(time.perf_counter() - t)
    ms = np.array
    d, ad = ms(detect) * 1e3, ms(anchor_detect) * 1e3
    tr, at = ms(track) * 1e3, ms(anchor_track) * 1e3
    per_set = tr + d.reshape(len(sets), -1).sum(axis=1)
    figures = {"cpu": cpu_model(), "frames": args.frames, "cameras": args.cameras,
               "detection": median_p99(d, "ms"), "anchor_contours": median_p99(ad, "ms"),
               "detection_ratio_to_anchor": float(np.median(d) / np.median(ad)),
               "tracker": median_p99(tr, "ms"), "anchor_opencv_baseline": median_p99(at, "ms"),
               "tracker_ratio_to_anchor": float(np.median(tr) / np.median(at)),
               "frame_sets_per_s": float(1e3 / np.median(per_set))}
    report(figures, args.json)


if __name__ == "__main__":
    main()
