"""``uma record``, ``uma play`` and ``uma info`` as command plug-ins (``uma.commands``).

Only their grammar lives here, so that ``uma --help`` stays fast and needs neither ``mcap``
nor ``rosbags``; their work is imported when they run.
"""

from __future__ import annotations

import argparse

from agent.runtime import CommandPlugin, add_network_arguments

_KEYS_HELP = ("record only data keys matching AGENT/SERVICE/ABILITY (Zenoh wildcards * and **; "
              "repeatable; default: every stream of the realm)")


def _record_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", metavar="FILE.mcap", help="the recording to write (overwritten)")
    add_network_arguments(p, listen=False)
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds (default: at Ctrl-C / SIGTERM)")
    p.add_argument("--keys", action="append", default=[], metavar="PATTERN", help=_KEYS_HELP)
    p.add_argument("--no-ros", action="store_true",
                   help="leave out the ROS 2 /tf and /tf_static channels")
    p.add_argument("--json", action="store_true", help="print one JSON object at the end")


def _play_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", metavar="FILE.mcap", help="the recording to play")
    add_network_arguments(p, listen=False)
    p.add_argument("--agent", default=None, metavar="ID",
                   help="the agent the played services register with (default: host name)")
    p.add_argument("--rate", type=float, default=1.0, metavar="X",
                   help="speed factor: 2 plays twice as fast (default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    p.add_argument("--start", type=float, default=0.0, metavar="S",
                   help="skip the first S seconds of the recording")
    p.add_argument("--end", type=float, default=None, metavar="S",
                   help="stop S seconds after the recording's start")
    p.add_argument("--keys", action="append", default=[], metavar="PATTERN",
                   help="play only data keys matching AGENT/SERVICE/ABILITY (Zenoh "
                        "wildcards; repeatable; default: all)")
    p.add_argument("--now", action="store_true",
                   help="shift every timestamp by one offset so the recording happens now "
                        "(default: the recorded timestamps)")
    p.add_argument("--json", action="store_true", help="print one JSON object at the end")


def _info_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", metavar="FILE.mcap", help="the recording")
    p.add_argument("--json", action="store_true", help="print one JSON object")


RECORD = CommandPlugin(
    name="record",
    help="record a realm's data streams into an MCAP file",
    description="Record every data stream of the realm (or those --keys names) losslessly into "
                "FILE.mcap, one channel per ability with the exact bytes on the wire, plus the "
                "agents' services, matches and SRG summaries, and the poses as ROS 2 /tf for "
                "ros2 bag, Foxglove and rosbags. Stops at Ctrl-C or after --duration.",
    add_arguments=_record_arguments,
    run="agent.record.recorder:main")

PLAY = CommandPlugin(
    name="play",
    help="bring a recording's services back to life in a realm",
    description="Register every recorded service again (same abilities and attributes) with "
                "the agent --agent of --realm, and publish its recorded samples with the "
                "recorded timing scaled by --rate.",
    add_arguments=_play_arguments,
    run="agent.record.player:main")

INFO = CommandPlugin(
    name="info",
    help="what an MCAP recording holds",
    description="Print a recording's duration, its channels with message counts and rates, and "
                "the services and matches recorded. A truncated file is read up to the damage, "
                "which is named.",
    add_arguments=_info_arguments,
    run="agent.record.info:main")
