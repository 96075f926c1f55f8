"""What ``uma calibrate camera`` and ``uma markers ...`` do (grammar in ``commands.py``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2

from agent.errors import UmaError
from services.camera import calibrate, markers
from services.camera.capture import Capture


def missing_subcommand(args: argparse.Namespace) -> int:
    raise UmaError(f"say what: 'uma {args.command} --help' lists the subcommands")


def board_of(args: argparse.Namespace) -> cv2.aruco.CharucoBoard:
    """The ChArUco board the arguments describe."""
    marker = args.marker if args.marker is not None else args.square / 2
    return markers.charuco_board(args.squares, args.square, marker, args.board_family)


def calibrate_camera(args: argparse.Namespace) -> int:
    """Read the source, keep distinct views, calibrate, judge, write the file."""
    if args.every < 1 or args.max_frames < 1:
        raise UmaError("--every and --max-frames must be at least 1")
    board = board_of(args)
    detector = cv2.aruco.CharucoDetector(board)
    views, size = [], None
    with Capture(args.source, max_frames=args.max_frames, gray=True) as cap:
        for frame in cap.frames():
            if frame.seq % args.every:
                continue
            h, w = frame.image.shape[:2]
            if size not in (None, (w, h)):
                raise UmaError(f"{args.source}: frame {frame.seq} is {w}x{h}, the first was "
                               f"{size[0]}x{size[1]}")
            size = (w, h)
            view = calibrate.detect_view(detector, frame.image, frame.seq)
            if view is not None:
                views.append(view)
    if size is None:
        raise UmaError(f"{args.source}: no frames")
    kept, duplicates = calibrate.select_views(views, size)
    flags = cv2.CALIB_RATIONAL_MODEL if args.model == "rational" else 0
    result = calibrate.calibrate(kept, board, size, len(views), duplicates, flags=flags)
    if result.model is not None:
        result.model.save(args.output, views=result.views_used, verdict=result.verdict)
    summary = {**result.summary(), "output": None if result.model is None else args.output}
    print(json.dumps(summary) if args.json else _describe(result, args.output))
    return 0 if result.verdict == "good" else 3


def _describe(r: calibrate.Result, output: str) -> str:
    lines = [f"views: {r.views_seen} with the board, {r.duplicates} near-duplicates dropped, "
             f"{r.views_used} used"]
    if r.model is not None:
        K, s = r.model.K, r.std
        lines += [f"fx {K[0, 0]:.2f} ± {s['fx']:.2f}  fy {K[1, 1]:.2f} ± {s['fy']:.2f}  "
                  f"cx {K[0, 2]:.2f} ± {s['cx']:.2f}  cy {K[1, 2]:.2f} ± {s['cy']:.2f} px",
                  "distortion " + " ".join(f"{d:.4g}" for d in r.model.dist),
                  f"RMS reprojection error {r.rms_px:.3f} px (corner noise {r.noise_px:.3f} px: "
                  f"{r.corners} corners, {r.parameters} parameters fitted)",
                  f"written to {output}"]
    lines.append("corners per image region (3x3): " +
                 " | ".join(" ".join(f"{n:4d}" for n in row) for row in r.coverage))
    lines.append(f"verdict: {r.verdict}")
    lines += [f"  - {why}" for why in r.reasons]
    return "\n".join(lines)


def markers_print(args: argparse.Namespace) -> int:
    """Write the sheet (PDF or PNG) of markers or the ChArUco board."""
    out = Path(args.output)
    if out.suffix.lower() not in (".pdf", ".png"):
        raise UmaError(f"--output {out}: write a .pdf or a .png")
    if args.charuco:
        board = board_of(args)
        px = args.dpi / markers.MM_PER_INCH * 1000.0
        cols, rows = args.squares
        image = board.generateImage((round(cols * args.square * px),
                                     round(rows * args.square * px)))
        what = (f"ChArUco board {cols}x{rows}, squares {args.square * 1000:g} mm, markers "
                f"{board.getMarkerLength() * 1000:g} mm ({args.board_family})")
    else:
        image = markers.sheet(args.family, args.ids, args.size, args.dpi, args.page)
        what = f"{len(args.ids)} {args.family} tags of {args.size * 1000:g} mm"
    writer = markers.write_pdf if out.suffix.lower() == ".pdf" else markers.write_png
    writer(out, image, args.dpi)
    print(f"{out}: {what}; print at 100 % and measure it", file=sys.stderr)
    return 0


def markers_families(args: argparse.Namespace) -> int:
    for name in sorted(markers.families()):
        print(name)
    return 0
