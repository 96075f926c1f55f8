"""``uma service run vrpn-in``: a VRPN tracker's sensors as uma ``pose6d`` abilities.

Connects to a VRPN server as a client (``--tracker NAME@HOST[:PORT]``: the UDP "call me
back" handshake, VRPN's default; ``NAME@tcp://HOST[:PORT]``: TCP only) and publishes each
mapped sensor's Pos_Quat reports as the ability ``sensorN`` with the edge ``WORLD ->
FRAME`` and the attributes given.  A report keeps the VRPN message's own time, moved to
uma's clock by ``--clock-offset-s`` (0 when the server's host keeps the same time, e.g.
by NTP); VRPN's time has microseconds, so uma sees times ending in 000 ns.  Positions are
metres and quaternions x, y, z, w on both sides, so values pass unchanged.

When the server goes away, nothing is published (the agent measures the ability's rate
falling and re-matches needs) and the client tries again every 0.25 s.  A server that goes
silent with its connection open (hung or stopped, or the network path gone without a FIN or
RST) takes the same path: nothing arrives to publish, and once it has sent nothing for
``--ping-s`` and not answered VRPN's ping within ``--pong-timeout-s`` the client says so,
drops the connection and tries again as for a server that went away
(:mod:`services.vrpn.client`), so a server restarted elsewhere on the network or resumed is
found again.  A server that only has nothing to report still answers the ping and is kept.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import threading
import time
from typing import Any

from agent import Service
from agent.errors import InvalidInputError
from agent.runtime import RateLimitedLog
from services.vrpn import protocol as vp
from services.vrpn.client import TrackerClient
from services.vrpn.loop import run_until

log = logging.getLogger("uma.vrpn")
#: a report this far from our clock means the hosts' clocks differ (said once)
CLOCK_WARN_S = 1.0


def sensor_frames(args: argparse.Namespace) -> dict[int, str]:
    """Sensor number -> frame; ``ValueError`` for a sensor or frame named twice."""
    world, frame0 = args.edge
    out = {0: frame0}
    for n, frame in args.sensor:
        if n in out:
            raise InvalidInputError(f"--sensor {n}={frame}: sensor {n} is already "
                                    f"{out[n]} (sensor 0 is --edge's FRAME)")
        if frame in out.values() or frame == world:
            raise InvalidInputError(f"--sensor {n}={frame}: frame {frame} is already used")
        out[n] = frame
    return out


class Publisher:
    """VRPN reports -> ability samples, on the client's loop."""

    def __init__(self, handles: dict[int, Any], offset_ns: int, address: vp.DeviceAddress,
                 ) -> None:
        self.handles = handles
        self.offset_ns = offset_ns
        self.address = address
        self.published = 0
        self._said: set[Any] = set()
        self._log = RateLimitedLog(log)

    def __call__(self, sensor: int, t_ns: int, position: Any, quaternion: Any) -> None:
        handle = self.handles.get(sensor)
        if handle is None:
            self._once(sensor, "sensor %d of %s reports but has no --sensor mapping; "
                       "its reports are ignored", sensor, self.address)
            return
        t = t_ns + self.offset_ns
        skew = time.time_ns() - t
        if abs(skew) > CLOCK_WARN_S * 1e9:
            self._once("clock", "%s's reports are %.1f s %s our clock: set --clock-offset-s",
                       self.address, abs(skew) / 1e9, "behind" if skew > 0 else "ahead of")
        try:
            handle.publish(t, position, quaternion)
        except ValueError as exc:  # e.g. a zero quaternion for a body the tracker lost
            self._log.warning(f"sensor {sensor} of {self.address}", f"report dropped: {exc}")
            return
        self.published += 1

    def _once(self, key: Any, text: str, *args: Any) -> None:
        if key not in self._said:
            self._said.add(key)
            log.warning(text, *args)


def run(args: argparse.Namespace, stop: threading.Event) -> int:

    frames = sensor_frames(args)
    attributes = {"frequency_hz": args.frequency_hz, "latency_s": args.latency_s,
                  "pos_std_m": args.pos_std_m, "rot_std_rad": args.rot_std_rad,
                  "vrpn_device": str(args.tracker)}
    attributes = {k: v for k, v in attributes.items() if v is not None}
    with Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect,
                 listen=args.listen or None) as svc:
        handles = {n: svc.ability(f"sensor{n}", type="pose6d", edge=(args.edge[0], frame),
                                  **attributes) for n, frame in sorted(frames.items())}
        svc.start()
        publish = Publisher(handles, round(args.clock_offset_s * 1e9), args.tracker)
        client = TrackerClient(args.tracker, publish, ping_s=args.ping_s,
                               pong_timeout_s=args.pong_timeout_s)

        async def main(done: asyncio.Event) -> int:
            log.info("vrpn-in: %s -> %s", args.tracker,
                     ", ".join(f"sensor{n}: {args.edge[0]} -> {f}"
                               for n, f in sorted(frames.items())))
            await client.run(done)
            return 0

        return run_until(main, stop)
