"""``uma service run vrpn-out``: uma poses as VRPN trackers for any VRPN client.

Each ``--serve NAME=SOURCE:TARGET[@ERROR]`` is a VRPN tracker ``NAME`` (sensor 0) whose
reports are the pose of TARGET in SOURCE, a uma subscription (composed across agents,
following route changes, optimal for the error function ERROR, ``latency`` by default):
one Pos_Quat per pose the subscription pushes, i.e. at the rate of the route's fastest
edge, stamped with the pose's own time (to the microsecond).  Clients connect as to any
VRPN server (``NAME@HOST:PORT`` by the UDP handshake, ``NAME@tcp://HOST:PORT``); a client
that stops reading is dropped once ``--max-buffer-kb`` wait for it, so it never holds up
the others.  A subscription with no route yet is tried again every second.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import threading
import time
from typing import Any

from agent import Client
from agent.errors import InvalidInputError, UmaError
from services.vrpn.loop import run_until, wait_for_event
from services.vrpn.plugin import Served
from services.vrpn.server import TrackerServer

log = logging.getLogger("uma.vrpn")
RESUBSCRIBE_S = 1.0


class Subscriptions:
    """The uma side: one subscription per served tracker, retried until it has a route."""

    def __init__(self, client: Any, served: list[Served], server: TrackerServer) -> None:
        self.client = client
        self.served = served
        self.server = server
        self.subs: dict[int, Any] = {}
        self._said: set[int] = set()

    def try_subscribe(self) -> None:
        """Subscribe every tracker that has no subscription yet (blocking: run it off the
        loop).  No route or frame yet is said once and tried again; a bad error function
        (``ValueError``) ends the service with its message."""
        for i, s in enumerate(self.served):
            if i in self.subs:
                continue
            try:
                self.subs[i] = self.client.subscribe(s.source, s.target, self._pusher(i),
                                                     error=s.error)
                log.info("vrpn-out: tracker %s streams %s -> %s", s.name, s.source, s.target)
            except UmaError as exc:  # no route (yet): retried
                if i not in self._said:
                    self._said.add(i)
                    log.warning("vrpn-out: tracker %s has no pose yet (%s); trying again "
                                "every %.0f s", s.name, exc, RESUBSCRIBE_S)

    def _pusher(self, i: int) -> Any:
        def on_pose(result: Any) -> None:
            t_ns = result.t_ns if result.t_ns is not None else time.time_ns()
            self.server.report_threadsafe(i, t_ns, result.position, result.quaternion)
        return on_pose

    def close(self) -> None:
        for sub in self.subs.values():
            sub.close()


def run(args: argparse.Namespace, stop: threading.Event) -> int:

    names = [s.name for s in args.serve]
    if len(set(names)) != len(names):
        raise InvalidInputError(f"--serve names a tracker twice: {names}")
    if not 0 <= args.port < 65536:
        raise InvalidInputError(f"--port {args.port} is not a port number")
    if not args.max_buffer_kb > 0:
        raise InvalidInputError(f"--max-buffer-kb must be > 0, got {args.max_buffer_kb}")
    server = TrackerServer(names, args.bind, args.port, int(args.max_buffer_kb * 1000))
    with Client(realm=args.realm, connect=args.connect, listen=args.listen or None) as client:
        subs = Subscriptions(client, args.serve, server)

        async def main(done: asyncio.Event) -> int:
            try:
                await server.start()
            except OSError as exc:
                raise OSError(f"cannot serve VRPN on {args.bind} port {args.port} (TCP and "
                              f"UDP): {exc.strerror or exc}") from None
            log.info("vrpn-out: VRPN server on %s port %d (TCP and UDP): %s", args.bind,
                     server.port, ", ".join(names))
            loop = asyncio.get_running_loop()
            try:
                while not done.is_set():
                    if len(subs.subs) < len(args.serve):
                        await loop.run_in_executor(None, subs.try_subscribe)
                    await wait_for_event(done, RESUBSCRIBE_S)
            finally:
                await loop.run_in_executor(None, subs.close)
                await server.close()
            return 0

        return run_until(main, stop)
