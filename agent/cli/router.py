"""``uma router``: a Zenoh router in this Python process.

Larger sites run agents and clients in *client* mode attached to a router (see
``deploy/router.json5`` and ``deploy/start_site.sh``); on one LAN, peers with explicit
endpoints need none.  A Zenoh JSON5 configuration given by ``--config`` (else by
``ZENOH_CONFIG``, Zenoh's own convention) is the base that uma's settings are applied on
top of, and its listen endpoints are used unless ``--listen`` is given.  Safe by default:
it refuses to listen without TLS where other hosts reach it unless ``--insecure``.  Stops
cleanly on Ctrl-C / SIGTERM.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from agent.runtime.processes import stop_on_signals
from agent.runtime.ready import notify
from agent.runtime.session import (
    DEFAULT_ROUTER_LISTEN,
    close_session,
    listening_endpoints,
    open_session,
)

log = logging.getLogger("uma.router")


def main(args: argparse.Namespace) -> int:
    """Handler of ``uma router``."""
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    stop = stop_on_signals()
    base = args.config or os.environ.get("ZENOH_CONFIG") or None
    session = open_session("router", args.listen or (None if base else [DEFAULT_ROUTER_LISTEN]),
                           base_file=base, exposed_as="uma router", insecure=args.insecure)
    try:
        endpoints = listening_endpoints(session)
        status = f"uma router {session.zid()} listening on {' '.join(endpoints)}"
        print(status, flush=True)
        notify(READY="1", STATUS=status)
        while not stop.wait(0.5):
            pass
    finally:
        notify(STOPPING="1")
        close_session(session)
    return 0
