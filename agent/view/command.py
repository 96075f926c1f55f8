"""The grammar of ``uma view``, a command plug-in (``uma.commands`` entry point); light to
import, since ``uma --help`` builds every command's parser.  Its work: :mod:`agent.view.app`
(which needs the ``view`` extra)."""

from __future__ import annotations

import argparse

from agent.runtime import CommandPlugin, add_network_arguments


def _arguments(p: argparse.ArgumentParser) -> None:
    add_network_arguments(p, listen=False)
    p.add_argument("--host", default="127.0.0.1",
                   help="address the page is served on (default 127.0.0.1: this host only)")
    p.add_argument("--port", type=int, default=8080,
                   help="port of the page (default 8080; 0: any free port, printed)")
    p.add_argument("--root", default="ivy/world", metavar="FRAME",
                   help="frame the 3D scene is drawn in (default ivy/world; changeable on "
                        "the page)")
    p.add_argument("--hz", type=float, default=30.0,
                   help="redraws per second at most (default and limit 30)")
    p.add_argument("--trail", type=float, default=3.0, metavar="S",
                   help="seconds of trail drawn behind moving frames (default 3; 0: none)")
    p.add_argument("--seconds", type=float, default=None, metavar="S",
                   help="stop after S seconds (default: run until Ctrl-C)")


VIEW = CommandPlugin(
    name="view",
    help="a live view of a realm in the browser",
    description="Serve a page that shows a realm live: its agents, services, needs, "
                "abilities and matches with each stream's measured rate, latency and state, an "
                "event log, every frame of the spatial relationship graph in 3D, and a query "
                "box. Open the printed address in a browser. Needs the 'view' extra: "
                "pip install 'uma-tracking[view]'.",
    add_arguments=_arguments,
    run="agent.view.app:main")
