"""The ``uma`` commands that uma's own services add: ``uma demo`` and ``uma service
recalibrate``, as plug-ins (``uma.commands`` / ``uma.service_commands`` entry points), so
the agent's command line never names a service.

Only their grammar lives here, so that ``uma --help`` stays fast; their work is imported
when they run (``run`` names it).
"""

from __future__ import annotations

import argparse

from agent.runtime import CommandPlugin, add_network_arguments


def _demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=10.0, help="how long to run (default 10)")
    p.add_argument("--seed", type=int, default=1, help="simulation seed (default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--logs", default=None, metavar="DIR",
                   help="keep each service's log as DIR/<service>.log (default: discarded)")
    p.add_argument("--record", default=None, metavar="FILE.mcap",
                   help="record the demo (every stream, and the simulator's ground truth as "
                        "ivy/world -> alice/head_truth) for 'uma play' and 'uma eval fusion "
                        "--from'")
    p.add_argument("--view", action="store_true",
                   help="also serve the live view of the demo's realm (uma view; needs the "
                        "'view' extra) on http://127.0.0.1:PORT/")
    p.add_argument("--view-port", type=int, default=8080, metavar="PORT",
                   help="port of the view's page (default 8080)")
    p.add_argument("--cameras", action="store_true",
                   help="the camera demo instead: two simulated webcams on two agents track a "
                        "printed tag; a need preferring accuracy follows the camera that sees "
                        "it best, a client queries it in the world frame across the agents")
    p.add_argument("--outside-in", action="store_true",
                   help="the outside-in marker tracker instead: simulated IR cameras on two "
                        "agents, the reconstruction on a third, body poses queried across "
                        "them")
    p.add_argument("--skew-ms", type=float, default=20.0, metavar="MS",
                   help="with --outside-in: the first camera host's clock runs MS ahead of "
                        "the reconstruction's, the second's MS behind (default 20)")
    p.add_argument("--single-host", action="store_true",
                   help="with --outside-in: every camera and the reconstruction on one agent "
                        "with one clock (the reference for the distributed figures)")
    p.add_argument("--compare", action="store_true",
                   help="with --outside-in: the single-host and the three-host layouts at "
                        "once, each in a realm of its own, on the same simulated frames; "
                        "prints both and their errors on the frame sets both posed, three "
                        "hosts over one")
    p.add_argument("--optical", choices=("dots", "pose"), default="dots",
                   help="the fusion's optical update: one SCAAT update per labeled laser dot "
                        "(default; more accurate, docs/FUSION_TUNING.md) or the tracker's "
                        "poses")


def _recalibrate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("service_id", metavar="SERVICE", nargs="?", default="alignment",
                   help="the service's id (default alignment)")
    p.add_argument("--agent", required=True, metavar="ID",
                   help="the agent the service is registered with")
    add_network_arguments(p, listen=False)
    p.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="seconds to wait for the service's answer (default 5)")
    p.add_argument("--json", action="store_true", help="print the answer as one JSON object")


DEMO = CommandPlugin(
    name="demo",
    help="run everything in one command (agent, simulated trackers, fusion, a query)",
    description="The embedded default: an agent, the simulated IVY world, the laser-dot "
                "camera and accelerometer trackers, their fusion and pose queries, all on "
                "loopback; prints a summary.",
    add_arguments=_demo_arguments,
    run="services.demo:main")

RECALIBRATE = CommandPlugin(
    name="recalibrate",
    help="ask a running alignment service to calibrate again",
    description="Ask a running alignment service to drop the motions it collected and "
                "calibrate again from fresh ones (after a tracker's mounting changed). Prints "
                "its acknowledgement and the calibration it had; the new one follows when the "
                "motions allow (see its log or 'uma services').",
    add_arguments=_recalibrate_arguments,
    run="services.alignment.service:recalibrate_command")
