"""A process that tries to write where its certificate does not allow: it opens a client
session (the Zenoh configuration comes from ``UMA_ZENOH_CONFIG``), puts ``--count`` poses
stamped ``--t-ns`` on ``--key`` at 100 Hz, optionally declares a liveliness token, and
reports ``{"event": "sent", "n": N}`` (or ``{"event": "refused", "error": ...}`` when it
cannot even connect).  It then waits for SIGTERM, keeping its token declared.

With ``--ask SELECTOR`` (repeatable) it instead sends, on each selector, a registration of
service ``--service`` with instance ``--instance`` and no key, as a hijacker would, and
reports how many answers (replies or refusals) came back per selector:
``{"event": "asked", "answers": {SELECTOR: N}}``.

    python -m tests.agent_helpers.intruder --connect EP --key uma/R/data/h1/cam/pose \\
        --count 200 --t-ns 123 [--token uma/R/agent/h1]
    python -m tests.agent_helpers.intruder --connect EP --ask uma/R/agent/h1/register \\
        --agent h1 --service cam --instance 0123456789abcdef
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

from agent.errors import UmaError
from agent.protocol.registration import register_request
from agent.runtime.session import close_session, open_session, query
from schemas.codec import encode_descriptor, encode_pose
from schemas.models import ServiceDescriptor


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--key")
    ap.add_argument("--count", type=int, default=100)
    ap.add_argument("--t-ns", type=int, default=1)
    ap.add_argument("--token", default=None)
    ap.add_argument("--ask", action="append", default=[])
    ap.add_argument("--agent", default="h1")
    ap.add_argument("--service", default="cam")
    ap.add_argument("--instance", default="0" * 16)
    args = ap.parse_args()
    try:
        session = open_session("client", None, [args.connect])
    except UmaError as exc:
        print(json.dumps({"event": "refused", "error": str(exc)}), flush=True)
        return 3
    if args.ask:
        print(json.dumps({"event": "asked", "answers": hijack(session, args)}), flush=True)
        close_session(session)
        return 0
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


def hijack(session, args: argparse.Namespace) -> dict[str, int]:
    """A keyless registration of ``--service`` (an ability on a forged edge) on each
    ``--ask`` selector: how many answers each got."""
    desc = ServiceDescriptor(service_id=args.service, agent_id=args.agent, abilities=[
        {"name": "pose", "type": "pose6d", "edge": ["evil/world", "evil/head"]}])
    payload = register_request(encode_descriptor(desc), args.instance, 10**6, {})
    return {sel: len(list(query(session, sel, 2.0, payload=payload))) for sel in args.ask}


if __name__ == "__main__":
    sys.exit(main())
