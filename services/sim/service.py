"""``uma service run sim``: the simulated world's ground truth as abilities.

Publishes the true head pose ``ivy/world -> alice/head`` (``pose6d``, attribute
``ground_truth: true``) at ``--rate-hz``, and the true rig mountings ``alice/head ->
marvin/laser_rig`` and ``alice/head -> marvin/accel_rig`` as static abilities
(``static: true``, re-published every second so late subscribers get them).  Trajectory
time is wall-clock time since ``SIM_EPOCH_NS``, so every process simulating the same seed
(the laser-camera service's default source, for one) agrees on where the head is.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time

from agent import Service
from agent.errors import InvalidInputError
from services import frames
from services.sim.plugin import MOUNTINGS
from services.sim.trajectory import HeadTrajectory
from services.sim.world import sim_time_s

log = logging.getLogger("uma.sim")
STATIC_REPUBLISH_S = 1.0


def run(args: argparse.Namespace, stop: threading.Event) -> int:
    if not 0 < args.rate_hz <= 2000:
        raise InvalidInputError(f"--rate-hz must be in (0, 2000], got {args.rate_hz}")
    trajectory = HeadTrajectory(args.seed)
    period = 1.0 / args.rate_hz
    with Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect,
                 listen=args.listen or None) as svc:
        head = svc.ability("head", type="pose6d", edge=(frames.WORLD, args.head_frame),
                           ground_truth=True, frequency_hz=args.rate_hz, latency_s=0.0,
                           pos_std_m=0.0, rot_std_rad=0.0, seed=args.seed)
        statics = [
            (svc.ability(name, type="pose6d", edge=(args.head_frame, child), static=True,
                         ground_truth=True), pose)
            for name, child, pose in MOUNTINGS[args.mountings]]
        svc.start()
        log.info("sim: publishing ground truth of seed %d at %.0f Hz", args.seed, args.rate_hz)
        next_static = 0.0
        next_tick = time.monotonic()
        while not stop.is_set():
            t_ns = time.time_ns()
            p, q = trajectory.pose(sim_time_s(t_ns))
            head.publish(t_ns, p[0], q[0])
            if time.monotonic() >= next_static:
                for handle, (pm, qm) in statics:
                    handle.publish(t_ns, pm, qm)
                next_static = time.monotonic() + STATIC_REPUBLISH_S
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay < -1.0:  # fell far behind (suspended): do not burst to catch up
                next_tick = time.monotonic()
            stop.wait(max(0.0, delay))
    return 0
