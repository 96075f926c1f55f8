"""The ``fiducials`` service's and evaluation's declarations: their options (with the
parsers of their values) and where they run (:func:`services.fiducials.service.run`,
:func:`services.fiducials.evaluate.run`); light to import, as ``uma service run fiducials
--help`` needs no Zenoh and ``uma eval fiducials --help`` not the evaluation."""

from __future__ import annotations

import argparse

from agent.runtime import EvalPlugin, ServicePlugin


def _id_size(text: str) -> tuple[int, float]:
    marker_id, eq, size = text.partition("=")
    try:
        value = float(size)
    except ValueError:
        value = -1.0
    if not eq or not marker_id.isdigit() or not 0 < value < 10:
        raise argparse.ArgumentTypeError(f"{text!r}: expected ID=METRES, e.g. 3=0.05")
    return int(marker_id), value


def _id_frame(text: str) -> tuple[int, str]:
    marker_id, eq, frame = text.partition("=")
    if not eq or not marker_id.isdigit() or not frame:
        raise argparse.ArgumentTypeError(f"{text!r}: expected ID=FRAME, e.g. 3=lab/wand")
    return int(marker_id), frame


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", default="fiducials", help="service id (default fiducials)")
    parser.add_argument("--source", required=True,
                        help="camera index (0), video file, image folder or stream URL")
    parser.add_argument("--calibration", required=True, metavar="FILE",
                        help="the camera's calibration: 'uma calibrate camera' output, any "
                             "OpenCV calibration YAML/JSON/XML or a ROS camera_info YAML")
    parser.add_argument("--family", default="apriltag36h11",
                        help="marker family (default apriltag36h11; 'uma markers families')")
    parser.add_argument("--size", type=float, default=None, metavar="M",
                        help="side of the markers' black square, metres, as printed; markers "
                             "of no known size are ignored (said once)")
    parser.add_argument("--marker-size", type=_id_size, action="append", default=[],
                        metavar="ID=M", help="a marker of another size (repeatable)")
    parser.add_argument("--bundles", metavar="FILE", default=None,
                        help="TOML file of marker bundles tracked as one body each "
                             "(see services/fiducials/bodies.py)")
    parser.add_argument("--frame", required=True,
                        help="the camera's frame in the SRG, e.g. lab/cam1")
    parser.add_argument("--prefix", default="markers",
                        help="frames of the bodies: PREFIX/NAME (default markers)")
    parser.add_argument("--name", type=_id_frame, action="append", default=[],
                        metavar="ID=FRAME", help="publish marker ID as FRAME instead "
                                                 "(repeatable)")
    parser.add_argument("--fps", type=float, default=None,
                        help="frame rate of an image folder (default 30)")
    parser.add_argument("--max-frames", type=int, default=None, metavar="N",
                        help="stop after N frames (default: the source's end, or never)")


FIDUCIALS = ServicePlugin(
    name="fiducials",
    help="Printed fiducial markers (AprilTag, ArUco) seen by a calibrated camera: one pose6d "
         "ability per marker or bundle seen, camera frame -> markers/<family>-<id>, with a "
         "covariance from the corners' measured noise, the planar ambiguity flagged, and "
         "rate, latency and accuracy advertised as measured.",
    add_arguments=add_arguments,
    run="services.fiducials.service:run",
)


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--fps", type=float, default=10.0,
                        help="frames per simulated second (default 10)")


EVAL = EvalPlugin(
    name="fiducials",
    help="8 cm AprilTag poses at 0.5-3 m from a simulated 640x480 webcam: uma's fiducial "
         "tracker beside bare OpenCV and AprilTag 3 (pupil-apriltags), NEES, silent flips, "
         "a 4-tag bundle vs its single tags (try --seconds 20 --seeds 1-10)",
    add_arguments=add_eval_arguments,
    run="services.fiducials.evaluate:run",
    higher_is_better=frozenset({"detected", "bundle_samples", "single_samples",
                                "share_inside_single_95", "effective_samples",
                                "gain_measured", "gain_claimed", "best_tag_samples",
                                "best_gain_measured", "best_gain_claimed",
                                "prior_gain_measured", "prior_gain_claimed",
                                "least_gain_share"}),
)
