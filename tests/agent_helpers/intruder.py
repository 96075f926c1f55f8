"""A process that tries to write where its certificate does not allow: it opens a client
session (the Zenoh configuration comes from ``UMA_ZENOH_CONFIG``), puts ``--count`` poses
stamped ``--t-ns`` on ``--key`` at 100 Hz, optionally declares a liveliness token, and
reports ``{"event": "sent", "n": N}`` (or ``{"event": "refused", "error": ...}`` when it
cannot even connect).  It then waits for SIGTERM, keeping its token declared.

    python -m tests.agent_helpers.intruder --connect EP --key uma/R/data/h1/cam/pose \\
        --count 200 --t-ns 123 [--token uma/R/agent/h1]
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

from agent.errors import UmaError
from agent.runtime.session import close_session, open_session
from schemas.codec import encode_pose


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--key", required=True)
    ap.add_argument("--count", type=int, default=100)
    ap.add_argument("--t-ns", type=int, required=True)
    ap.add_argument("--token", default=None)
    args = ap.parse_args()
    try:
        session = open_session("client", None, [args.connect])
    except UmaError as exc:
        print(json.dumps({"event": "refused", "error": str(exc)}), flush=True)
        return 3
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    token = session.liveliness().declare_token(args.token) if args.token else None
    for i in range(args.count):
        session.put(args.key, encode_pose(args.t_ns, [9.0, 9.0, 9.0], [0, 0, 0, 1], seq=i + 1))
        time.sleep(0.01)
    print(json.dumps({"event": "sent", "n": args.count}), flush=True)
    stop.wait(120)
    if token is not None:
        token.undeclare()
    close_session(session)
    return 0


if __name__ == "__main__":
    sys.exit(main())
