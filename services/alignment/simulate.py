"""Simulated pose streams of two rigidly joined trackers, for the evaluation and the tests.

Sensor a rides on the simulated head (``HeadTrajectory``) at a mounting ``head -> sensor_a``;
sensor b sits at ``X`` in sensor a.  Tracker a reports sensor a in ``world_a``; tracker b
reports sensor b in its own ``world_b``, related to world_a by an arbitrary ``Y``
(``B_k = Y A_k X``).  Each tracker samples at its own rate and phase, adds pose noise (a
parent-frame rotation error and an independent position error, geometry's "decoupled"
form), and b stamps its samples ``offset_s`` late.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent.srg import geometry as geo
from services.alignment.solvers import Pose
from services.alignment.timesync import PoseSeries
from services.sim.trajectory import HeadTrajectory


@dataclass(frozen=True)
class StreamConfig:
    """Rates, noise and clock offset of the two simulated trackers."""

    seconds: float = 60.0
    rate_a_hz: float = 60.0
    rate_b_hz: float = 100.0
    pos_std_m: float = 0.001
    rot_std_rad: float = float(np.radians(0.1))
    offset_s: float = 0.0


def random_pose(rng: np.random.Generator, max_translation_m: float) -> Pose:
    """A uniformly random rotation and a translation up to ``max_translation_m`` per axis."""
    q = rng.normal(size=4)
    return Pose(rng.uniform(-max_translation_m, max_translation_m, 3),
                geo.quat_canonical(q / np.linalg.norm(q)))


def add_pose_noise(p: np.ndarray, q: np.ndarray, pos_std_m: float, rot_std_rad: float,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian position noise and a parent-frame rotation error of the given std per axis."""
    dq = geo.rotvec_to_quat(rng.normal(0.0, rot_std_rad, np.shape(p)))
    return p + rng.normal(0.0, pos_std_m, np.shape(p)), geo.quat_multiply(dq, q)


def simulate_streams(seed: int, mount_a: Pose, x: Pose, world_b: Pose,
                     config: StreamConfig = StreamConfig()) -> tuple[PoseSeries, PoseSeries]:
    """Streams of tracker a (``world_a -> sensor_a``) and b (``world_b -> sensor_b``).

    ``world_b`` is the pose of world_a in world_b (``Y``).  The head moves along
    ``HeadTrajectory(seed)``; noise is drawn from ``seed`` too.
    """
    rng = np.random.default_rng([seed, 1])
    trajectory = HeadTrajectory(seed)
    streams = []
    for rate, name, shift in ((config.rate_a_hz, "stream a", 0.0),
                              (config.rate_b_hz, "stream b", config.offset_s)):
        t_true = rng.uniform(0.0, 1.0 / rate) + np.arange(0.0, config.seconds, 1.0 / rate)
        ph, qh = trajectory.pose(t_true)
        p, q = geo.compose(ph, qh, *mount_a)
        if name == "stream b":
            p, q = geo.compose(*geo.compose(world_b.position, world_b.quaternion, p, q), *x)
        p, q = add_pose_noise(p, q, config.pos_std_m, config.rot_std_rad, rng)
        streams.append(PoseSeries(t_true + shift, p, q, name))
    return streams[0], streams[1]


def corrupt(p: np.ndarray, q: np.ndarray, fraction: float, rng: np.random.Generator,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Replace ``fraction`` of the poses by gross errors (5-30 deg, 5-20 cm); returns the mask.

    Models a tracker's mislabelled or mis-detected frames, e.g. a wrong laser-dot labeling.
    """
    n = len(p)
    bad = np.zeros(n, dtype=bool)
    bad[rng.choice(n, size=round(fraction * n), replace=False)] = True
    k = int(bad.sum())
    axis = rng.normal(size=(k, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.radians(rng.uniform(5.0, 30.0, k))[:, None]
    step = rng.normal(size=(k, 3))
    step *= rng.uniform(0.05, 0.20, (k, 1)) / np.linalg.norm(step, axis=-1, keepdims=True)
    p, q = p.copy(), q.copy()
    q[bad] = geo.quat_multiply(geo.rotvec_to_quat(axis * angle), q[bad])
    p[bad] += step
    return p, q, bad
