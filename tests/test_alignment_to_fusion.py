"""A calibration published by tracker alignment reaches the fusion service through the SRG.

The simulator publishes only the laser rig's mounting; the accelerometer rig's comes from a
static `laser_rig -> accel_rig` ability as the alignment service publishes it.  The fusion
service's own mounting lookup (`poll_mountings`) must find `head -> accel_rig` by composing
the two in the agent's SRG.
"""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
from agent_helpers.harness import agent
from conftest import endpoint, free_port

from agent import Service
from agent import geometry as geo
from services import frames
from services.fusion.service import poll_mountings
from services.sim import mounts


class MountingsSeen:
    """Stands in for the fusion filter state: records what poll_mountings hands it."""

    def __init__(self) -> None:
        self.optical = self.accel = None
        self.both = threading.Event()

    def on_optical_mount(self, m) -> None:
        self.optical = (m.position, m.quaternion)
        self._check()

    def on_accel_mount(self, m) -> None:
        self.accel = (m.position, m.quaternion)
        self._check()

    def _check(self) -> None:
        if self.optical is not None and self.accel is not None:
            self.both.set()

    def _drop(self, reason: str) -> None:
        pass

    def status(self) -> str:
        return "test"


def test_fusion_takes_the_aligned_mounting_from_the_srg(processes, realm) -> None:
    ep = endpoint(free_port())
    agent(processes, realm, "host", ep)  # up before its services start
    processes.start("service", "run", "sim", "--realm", realm, "--agent", "host",
                    "--connect", ep, "--mountings", "laser")
    # the alignment result: pose of the accelerometer rig in the laser rig
    p, q = geo.compose(*geo.inverse(*mounts.HEAD_TO_LASER_RIG), *mounts.HEAD_TO_ACCEL_RIG)
    seen = MountingsSeen()
    stop = threading.Event()
    args = SimpleNamespace(realm=realm, connect=[ep], head=frames.HEAD,
                           optical_rig=frames.LASER_RIG, accel_rig=frames.ACCEL_RIG)
    with Service("alignment", realm=realm, agent="host", connect=[ep]) as svc:
        calib = svc.ability("calibration", type="pose6d",
                            edge=(frames.LASER_RIG, frames.ACCEL_RIG), static=True,
                            pos_std_m=0.002, rot_std_rad=0.002)
        svc.start()
        poller = threading.Thread(target=poll_mountings, args=(seen, args, stop), daemon=True)
        poller.start()
        try:
            deadline = time.monotonic() + 20.0
            while not seen.both.is_set() and time.monotonic() < deadline:
                calib.publish(time.time_ns(), p, q)  # re-published, as the service does
                seen.both.wait(0.5)
        finally:
            stop.set()
            poller.join(timeout=10)
    assert seen.both.is_set(), "fusion never found head -> accel_rig in the SRG"
    dp, dq = geo.pose_error(*seen.accel, *mounts.HEAD_TO_ACCEL_RIG)
    assert dp < 1e-9 and dq < 1e-9
    assert np.allclose(seen.optical[0], mounts.HEAD_TO_LASER_RIG[0])
