"""The ``vrpn-in`` and ``vrpn-out`` services' declarations: their options (with the parsers
of their values) and where they run (:func:`services.vrpn.bridge_in.run`,
:func:`services.vrpn.bridge_out.run`); light to import, as ``uma service run vrpn-in
--help`` needs no Zenoh."""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

from agent.runtime import ServicePlugin
from services.vrpn import protocol as vp
from services.vrpn.client import DEFAULT_PING_S, DEFAULT_PONG_TIMEOUT_S


def _device(text: str) -> vp.DeviceAddress:
    try:
        return vp.parse_device(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _edge(text: str) -> tuple[str, str]:
    source, colon, target = text.partition(":")
    if not colon or not source or not target:
        raise argparse.ArgumentTypeError(f"--edge {text!r} must be WORLD:FRAME, e.g. "
                                         "lab/world:lab/wand")
    return source, target


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of seconds")
    return value


def _sensor(text: str) -> tuple[int, str]:
    number, eq, frame = text.partition("=")
    if not eq or not number.isdigit() or not frame:
        raise argparse.ArgumentTypeError(f"--sensor {text!r} must be N=FRAME, e.g. "
                                         "1=lab/left_hand")
    return int(number), frame


@dataclass(frozen=True)
class Served:
    """One ``--serve``: the VRPN tracker ``name`` streams TARGET in SOURCE."""

    name: str
    source: str
    target: str
    error: str


def _served(text: str) -> Served:
    name, eq, rest = text.partition("=")
    path, _, error = rest.partition("@")
    source, colon, target = path.partition(":")
    if not eq or not name or not colon or not source or not target:
        raise argparse.ArgumentTypeError(
            f"--serve {text!r} must be NAME=SOURCE:TARGET[@ERROR], e.g. "
            "Head=ivy/world:alice/head or Head=ivy/world:alice/head@accuracy")
    try:
        vp.check_name(name)
    except vp.ProtocolError as exc:
        raise argparse.ArgumentTypeError(f"--serve {text!r}: {exc}") from None
    return Served(name, source, target, error or "latency")


def add_vrpn_in_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", default="vrpn-in", help="service id (default: vrpn-in)")
    parser.add_argument("--tracker", type=_device, required=True, metavar="NAME@HOST[:PORT]",
                        help="the VRPN tracker, e.g. Tracker0@localhost (UDP handshake, port "
                             "3883) or DTrack@tcp://10.0.0.5:3883 (TCP only)")
    parser.add_argument("--edge", type=_edge, required=True, metavar="WORLD:FRAME",
                        help="the tracker's frame WORLD and the frame of sensor 0: sensor 0 "
                             "is published as the pose of FRAME in WORLD")
    parser.add_argument("--sensor", type=_sensor, action="append", default=[],
                        metavar="N=FRAME",
                        help="publish sensor N too, as the pose of FRAME in WORLD "
                             "(repeatable); other sensors' reports are ignored, said once")
    parser.add_argument("--frequency-hz", type=float, default=100.0,
                        help="the tracker's rate, advertised (default 100)")
    parser.add_argument("--latency-s", type=float, default=0.005,
                        help="advertised latency (default 0.005)")
    parser.add_argument("--pos-std-m", type=float, default=None,
                        help="advertised position standard deviation, metres")
    parser.add_argument("--rot-std-rad", type=float, default=None,
                        help="advertised rotation standard deviation, radians")
    parser.add_argument("--clock-offset-s", type=float, default=0.0,
                        help="added to the VRPN server's timestamps to get this host's "
                             "clock (default 0: same clock)")
    parser.add_argument("--ping-s", type=_seconds, default=DEFAULT_PING_S,
                        help="ping a server that has sent nothing for this long (default "
                             f"{DEFAULT_PING_S:g}: VRPN's clients ping once a second)")
    parser.add_argument("--pong-timeout-s", type=_seconds, default=DEFAULT_PONG_TIMEOUT_S,
                        help="a server that answers no ping within this is hung or out of "
                             "reach: dropped and reconnected (default "
                             f"{DEFAULT_PONG_TIMEOUT_S:g}: VRPN's clients warn then)")


VRPN_IN = ServicePlugin(
    name="vrpn-in",
    help="A VRPN tracker as uma abilities: connects to a VRPN server (OptiTrack Motive, "
         "Vicon Tracker, ART DTrack, any vrpn_Tracker) and publishes each sensor's poses as "
         "a pose6d ability sensorN with the VRPN timestamps; reconnects by itself.",
    add_arguments=add_vrpn_in_arguments,
    run="services.vrpn.bridge_in:run",
)


def add_vrpn_out_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--serve", type=_served, action="append", required=True,
                        metavar="NAME=SOURCE:TARGET[@ERROR]",
                        help="a VRPN tracker NAME streaming the pose of TARGET in SOURCE "
                             "(repeatable); ERROR is the error function of the route "
                             "(latency, hops, accuracy, ...; default latency)")
    parser.add_argument("--port", type=int, default=vp.DEFAULT_PORT,
                        help="VRPN port, TCP and UDP (default 3883, VRPN's)")
    parser.add_argument("--bind", default="0.0.0.0",
                        help="address to listen on (default 0.0.0.0: every interface)")
    parser.add_argument("--max-buffer-kb", type=float, default=64.0,
                        help="a client with more than this waiting unread is dropped "
                             "(default 64, VRPN's own TCP buffer)")


VRPN_OUT = ServicePlugin(
    name="vrpn-out",
    help="uma poses as VRPN trackers: a VRPN server whose tracker NAME streams the pose of "
         "TARGET in SOURCE (a uma subscription) to any number of VRPN clients (Unity, "
         "Unreal, MotionBuilder, vrpn_print_devices...) over TCP or UDP.",
    add_arguments=add_vrpn_out_arguments,
    run="services.vrpn.bridge_out:run",
)
