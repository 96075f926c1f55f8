"""Simulated pose streams of two rigidly joined trackers, for the evaluation and the tests.

Sensor a rides on the simulated head (``HeadTrajectory``) at a mounting ``head -> sensor_a``;
sensor b sits at ``X`` in sensor a.  Tracker a reports sensor a in ``world_a``; tracker b
reports sensor b in its own ``world_b``, related to world_a by an arbitrary ``Y``
(``B_k = Y A_k X``).  Each tracker samples at its own rate and phase, adds pose noise (a
parent-frame rotation error and an independent position error, geometry's "decoupled"
form), and b stamps its samples ``offset_s`` late.

``laser_stream`` replaces tracker a's Gaussian noise by the laser-dot tracker on the
simulated installation (``services.sim``, docs/SIMULATION.md): the rig's beams meet the
walls where the installation's housing and screens put them, the cameras (turned since
their calibration) see the spots, and ``LaserTracker`` turns those pixels into poses, so a's
errors are the installation's: persistent, pose-dependent and correlated between samples.
Only the images are skipped: each spot's centroid gets the detector's noise as measured on
rendered images of the realistic installation instead.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from agent import geometry as geo
from services.alignment.solvers import Pose
from services.alignment.timesync import PoseSeries
from services.laser_camera.detection import AREA, FLUX, STD, U, V
from services.laser_camera.tracker import (
    LaserTracker,
    installation_draw_sensitivity,
    installation_sensitivity,
)
from services.sim.trajectory import HeadTrajectory
from services.sim.world import IvyWorld

#: Centroid error (px, std per axis) of the detector on rendered frames of the realistic
#: installation, and the std it reports for them: measured over 800 spots (200 frames of
#: seed 3 at 30 Hz, detections against the spots' true pixels; the reported std is their
#: median).
CENTROID_NOISE_PX = 0.025
CENTROID_REPORTED_STD_PX = 0.0235


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
    t_a = _sample_times(config.rate_a_hz, config.seconds, rng)
    p, q = add_pose_noise(*geo.compose(*trajectory.pose(t_a), *mount_a), config.pos_std_m,
                          config.rot_std_rad, rng)
    return (_noisy_series(t_a, p, q, config, "stream a"),
            stream_b(trajectory, mount_a, x, world_b, config, rng))


def stream_b(trajectory: HeadTrajectory, mount_a: Pose, x: Pose, world_b: Pose,
             config: StreamConfig, rng: np.random.Generator) -> PoseSeries:
    """Tracker b's stream: sensor b (at ``x`` in sensor a) in ``world_b``, with Gaussian pose
    noise, at ``config.rate_b_hz``, stamped ``config.offset_s`` late."""
    t = _sample_times(config.rate_b_hz, config.seconds, rng)
    p, q = geo.compose(*trajectory.pose(t), *mount_a)
    p, q = geo.compose(*geo.compose(world_b.position, world_b.quaternion, p, q), *x)
    p, q = add_pose_noise(p, q, config.pos_std_m, config.rot_std_rad, rng)
    return _noisy_series(t + config.offset_s, p, q, config, "stream b")


def _noisy_series(t: np.ndarray, p: np.ndarray, q: np.ndarray, config: StreamConfig,
                  name: str) -> PoseSeries:
    """A stream of poses noisy as ``add_pose_noise`` makes them, with that noise as each
    sample's published covariance (geometry's convention: ``rho = dp - phi x p``), none of
    it systematic: the simulated tracker's honest account of its noise."""
    decoupled = np.diag([config.pos_std_m ** 2] * 3 + [config.rot_std_rad ** 2] * 3)
    J = np.tile(np.eye(6), (len(p), 1, 1))
    J[:, :3, 3:] = geo.skew(p)
    covariance = J @ decoupled @ np.swapaxes(J, 1, 2)
    return PoseSeries(t, p, q, name, covariance, systematic=np.zeros_like(covariance))


def _sample_times(rate_hz: float, seconds: float, rng: np.random.Generator) -> np.ndarray:
    """A free-running tracker's sample times: ``rate_hz`` from a random phase."""
    return rng.uniform(0.0, 1.0 / rate_hz) + np.arange(0.0, seconds, 1.0 / rate_hz)


def laser_stream(world: IvyWorld, tracker: LaserTracker, seconds: float, rate_hz: float,
                 rng: np.random.Generator) -> tuple[PoseSeries, PoseSeries]:
    """The laser-dot tracker's poses of ``marvin/laser_rig`` in ``ivy/world`` with their
    published covariances and their systematic parts over the world's head trajectory, at
    ``rate_hz`` from a random phase; frames without a pose are left out (a gap in the
    stream, as on the wire).  With them each pose's sensitivity to the installation's
    errors that the whole recording shares (``installation_sensitivity``); and the same
    stream with each pose's sensitivity to the installation's draw instead, which every
    recording in the same installation shares (``installation_draw_sensitivity``: with
    the tracker's online estimate, what of the draw the estimate has not taken out)."""
    t_all = _sample_times(rate_hz, seconds, rng)
    rig_p, rig_q = world.rig_pose(t_all)  # one batched call: the trajectory is vectorised
    t, p, q, c, held, s, draw = [], [], [], [], [], [], []
    for tk, pk, qk in zip(t_all, rig_p, rig_q, strict=True):
        dots = tracker.locate(_detections(world, pk, qk, rng))
        res = tracker.solve(dots, float(tk))
        if res.ok:
            t.append(tk)
            p.append(res.position)
            q.append(res.quaternion)
            c.append(res.covariance)
            held.append(res.systematic)
            s.append(installation_sensitivity(dots, res, tracker.params))
            draw.append(installation_draw_sensitivity(dots, res, tracker.params))
    series = PoseSeries(np.array(t), np.array(p), np.array(q), "laser stream", np.array(c),
                        *_columns(s), np.array(held))
    draw_columns, draw_names = _columns(draw)
    return series, replace(series, sensitivity=draw_columns, parameters=draw_names)


def _columns(per_pose: list[dict[str, np.ndarray]]) -> tuple[np.ndarray, tuple[str, ...]]:
    """Named sensitivities of each pose as one array (n, 6, m) over every name any pose
    has (a pose without one: zeros), and the names."""
    names = tuple(sorted({name for one in per_pose for name in one}))
    columns = np.array([[one.get(name, np.zeros(6)) for name in names] for one in per_pose])
    return np.swapaxes(columns.reshape(len(per_pose), len(names), 6), 1, 2), names


def _detections(world: IvyWorld, p: np.ndarray, q: np.ndarray, rng: np.random.Generator,
                ) -> dict[str, np.ndarray]:
    """Per camera, the detector's rows for the spots of the beams of a rig at ``(p, q)``."""
    hits = world.laser_hits(p, q)
    out = {}
    for name, spots in world.dot_pixels(hits).items():
        rows = np.zeros((len(spots), 5))
        if len(spots):
            uv = np.array(list(spots.values()))
            rows[:, [U, V]] = uv + rng.normal(0.0, CENTROID_NOISE_PX, uv.shape)
            rows[:, [FLUX, AREA]] = 1.0  # unused past detection
            rows[:, STD] = CENTROID_REPORTED_STD_PX
        out[name] = rows
    return out


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
