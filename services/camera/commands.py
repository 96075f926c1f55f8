"""The commands the camera layer adds to ``uma``: ``uma calibrate`` and ``uma markers``.

Both are command plug-ins (``uma.commands`` entry points) with subcommands.  ``uma
calibrate``'s subcommands are themselves plug-ins of the ``uma.calibrate`` entry-point
group (each a :class:`~agent.runtime.plugins.CommandPlugin`), so other packages add theirs
(``uma calibrate rig``) next to ``uma calibrate camera`` without touching this module.

Only the grammar lives here, so that ``uma --help`` stays fast; the work is imported when
a command runs.
"""

from __future__ import annotations

import argparse

from agent.runtime import CommandPlugin, load_all

CALIBRATE_GROUP = "uma.calibrate"


def _squares(text: str) -> tuple[int, int]:
    cols, x, rows = text.lower().partition("x")
    if not x or not cols.isdigit() or not rows.isdigit() or int(cols) < 3 or int(rows) < 3:
        raise argparse.ArgumentTypeError(f"{text!r}: squares are COLSxROWS, at least 3x3, "
                                         "e.g. 9x6")
    return int(cols), int(rows)


def _length(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = 0.0
    if not 0 < value < 10:
        raise argparse.ArgumentTypeError(f"{text!r} is not a length in metres (0 < m < 10)")
    return value


def _ids(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, dash, hi = part.partition("-")
        if not lo.isdigit() or (dash and not hi.isdigit()):
            raise argparse.ArgumentTypeError(f"{text!r}: ids are like 0-3,7")
        out.extend(range(int(lo), int(hi) + 1) if dash else [int(lo)])
    return out


def add_board_arguments(p: argparse.ArgumentParser) -> None:
    """The ChArUco board's geometry (printing it and calibrating with it)."""
    p.add_argument("--squares", type=_squares, default=(7, 5), metavar="COLSxROWS",
                   help="chessboard squares of the ChArUco board (default 7x5: 245 x 175 mm "
                        "with the default squares, on A4 or Letter)")
    p.add_argument("--square", type=_length, default=0.035, metavar="M",
                   help="side of one square as printed, metres (default 0.035: measure it)")
    p.add_argument("--marker", type=_length, default=None, metavar="M",
                   help="side of the markers in the white squares, metres (default: half the "
                        "square; larger markers bias the corners OpenCV finds)")
    p.add_argument("--board-family", default="aruco4x4_50", metavar="FAMILY",
                   help="marker family of the board (default aruco4x4_50)")


def _camera_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--source", required=True,
                   help="a camera index (0), a video file, a folder of images or a stream "
                        "URL, showing the printed board from many angles")
    add_board_arguments(p)
    p.add_argument("--output", "-o", default="camera.yaml", metavar="FILE",
                   help="calibration file to write: .yaml, .json or .xml (OpenCV's format; "
                        "default camera.yaml)")
    p.add_argument("--max-frames", type=int, default=600, metavar="N",
                   help="read at most N frames (default 600; a camera is read until then)")
    p.add_argument("--every", type=int, default=1, metavar="K",
                   help="look at every K-th frame only (default 1)")
    p.add_argument("--model", choices=("plumb_bob", "rational"), default="plumb_bob",
                   help="distortion model: 5 coefficients (default) or OpenCV's 8-coefficient "
                        "rational model for wide-angle lenses")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")


def _print_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--output", "-o", required=True, metavar="FILE",
                   help="the sheet to write: .pdf (printed at its physical size) or .png "
                        "(its DPI recorded in the file)")
    p.add_argument("--family", default="apriltag36h11",
                   help="marker family (default apriltag36h11; 'uma markers families' lists "
                        "them)")
    p.add_argument("--ids", type=_ids, default=[0], metavar="LIST",
                   help="marker ids, e.g. 0-3,7 (default 0)")
    p.add_argument("--size", type=_length, default=0.08, metavar="M",
                   help="side of each marker's black square, metres (default 0.08)")
    p.add_argument("--charuco", action="store_true",
                   help="print a ChArUco calibration board instead (--squares, --square, "
                        "--marker, --board-family)")
    add_board_arguments(p)
    p.add_argument("--dpi", type=float, default=300.0, help="resolution (default 300)")
    p.add_argument("--page", choices=("a4", "letter"), default="a4",
                   help="paper size (default a4)")


CAMERA = CommandPlugin(
    name="camera",
    help="intrinsic calibration of a camera from a ChArUco board",
    description="Calibrate a camera's intrinsics (focal length, principal point, lens "
                "distortion) from a video, an image folder or a live camera showing a "
                "printed ChArUco board ('uma markers print --charuco'). Keeps distinct "
                "views, reports the RMS error, each parameter's standard deviation and the "
                "image regions no corner was seen in, says 'good' or 'needs more views' and "
                "why, and writes the calibration file the camera trackers read.",
    add_arguments=_camera_arguments,
    run="services.camera.cli:calibrate_camera")

MARKERS_PRINT = CommandPlugin(
    name="print",
    help="write a printable sheet of markers (or a ChArUco board) at an exact size",
    description="Write a PDF or PNG of fiducial markers of a given printed size (or a ChArUco "
                "board for 'uma calibrate camera'). Print at 100 % ('actual size') and "
                "measure the result: the size you measure is the one to give the trackers.",
    add_arguments=_print_arguments,
    run="services.camera.cli:markers_print")

MARKERS_FAMILIES = CommandPlugin(
    name="families",
    help="list the marker families",
    description="List the marker families the fiducial tracker and 'uma markers print' know.",
    add_arguments=lambda p: None,
    run="services.camera.cli:markers_families")


def _subcommands(p: argparse.ArgumentParser, dest: str, commands: list[CommandPlugin]) -> None:
    sub = p.add_subparsers(dest=dest, metavar="WHAT")
    for c in commands:
        sp = sub.add_parser(c.name, help=c.help, description=c.description)
        c.add_arguments(sp)
        sp.set_defaults(plugin_run=c.run)


CALIBRATE = CommandPlugin(
    name="calibrate",
    help="calibrate a camera (and what other packages add: 'uma calibrate --help')",
    description="Calibration commands; each is a plug-in of the 'uma.calibrate' entry-point "
                "group.",
    add_arguments=lambda p: _subcommands(p, "calibrate_what",
                                         load_all(CALIBRATE_GROUP)),
    run="services.camera.cli:missing_subcommand")

MARKERS = CommandPlugin(
    name="markers",
    help="fiducial markers: print sheets and boards, list families",
    description="Fiducial markers for the camera trackers.",
    add_arguments=lambda p: _subcommands(p, "markers_what", [MARKERS_PRINT, MARKERS_FAMILIES]),
    run="services.camera.cli:missing_subcommand")
