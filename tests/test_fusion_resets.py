"""The fusion eval's reset figure: after each (re)start the error must stay within the
error of the optical pose the filter started from plus three of its own standard
deviations; a start that runs away is reported as unbounded."""

from __future__ import annotations

import math

import numpy as np

from agent import geometry as geo
from services.fusion import evaluate as fe
from services.fusion.ekf import FusionStats
from services.sim.trajectory import HeadTrajectory

RATE_HZ = 300.0


def recording(traj: HeadTrajectory, starts: list[float], drift_rad_s: float,
              std_rad: float = math.radians(0.2)) -> fe.Recording:
    """A run whose output follows the truth but turns away from it at ``drift_rad_s``
    after each start, claiming ``std_rad`` per axis; optical poses exact at 15 Hz."""
    t = np.arange(0.0, 6.0, 1 / RATE_HZ)
    p, q = traj.pose(t)
    since = t - np.array([max([s for s in starts if s <= x], default=0.0) for x in t])
    turn = np.zeros((t.size, 3))
    turn[:, 2] = drift_rad_s * since
    q_out = geo.quat_multiply(geo.rotvec_to_quat(turn), q)
    cov = np.tile(np.diag([1e-6] * 3 + [std_rad ** 2] * 3), (t.size, 1, 1))
    t_opt = np.arange(0.0, 6.0, 1 / fe.OPTICAL_HZ)
    p_opt, q_opt = traj.pose(t_opt)
    return fe.Recording(t, p, q_out, cov, p, q_out, t_opt, p_opt, q_opt, 0.0, FusionStats(),
                        {}, np.zeros(0), {}, np.array(starts))


def errors(rec: fe.Recording, traj: HeadTrajectory) -> tuple[np.ndarray, np.ndarray]:
    p, q = traj.pose(rec.t)
    return geo.pose_error(rec.p, rec.q, p, q)


def test_a_start_that_converges_is_bounded_and_one_that_runs_away_is_not() -> None:
    traj = HeadTrajectory(seed=1)
    calm = recording(traj, [0.1, 3.0], drift_rad_s=math.radians(0.05))
    f = fe.reset_figures(calm, *errors(calm, traj), traj)
    assert f["starts"] == 2 and f["bounded"], f
    assert f["worst_orientation_deg"] < 0.11 and f["worst_orientation_excess_deg"] < 0
    wild = recording(traj, [0.1, 3.0], drift_rad_s=math.radians(13))  # 26 deg in 2 s
    f = fe.reset_figures(wild, *errors(wild, traj), traj)
    assert not f["bounded"] and f["worst_orientation_deg"] > 20, f
    assert f["worst_orientation_excess_deg"] > 19


def test_a_run_that_never_started_reports_no_reset() -> None:
    traj = HeadTrajectory(seed=1)
    rec = recording(traj, [], drift_rad_s=0.0)
    f = fe.reset_figures(rec, *errors(rec, traj), traj)
    assert f == {"starts": 0, "window_s": fe.RESET_WINDOW_S}
