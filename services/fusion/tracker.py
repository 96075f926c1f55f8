"""Live fusion: the EKF fed by asynchronous streams whose samples arrive late and out of order.

The accelerometer stream arrives within a millisecond of sampling; a laser-camera pose
arrives tens of milliseconds after the instant it describes (exposure, image transfer,
dot detection).  SCAAT needs every measurement applied at its own time, so the tracker
keeps snapshots of the filter and the recent accelerometer samples: a late optical pose
rewinds to the last snapshot before it, is applied at its time, and the accelerometer
samples after it are replayed.  The fused output therefore never waits for the optics.

Pure computation (no I/O): the fusion service feeds it from its need callbacks.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass

import numpy as np

from services.fusion.ekf import FilterState, FusionEKF

#: keep this much history (s): optical poses older than this are dropped as too late
HISTORY_S = 0.5
#: snapshot every this many accelerometer samples (replay cost vs memory)
SNAPSHOT_EVERY = 8


@dataclass
class TrackerStats:
    accel_samples: int = 0
    optical_poses: int = 0
    optical_late: int = 0      # applied by rewinding and replaying
    optical_too_old: int = 0   # older than the history: dropped
    replayed_samples: int = 0


class FusionTracker:
    """``add_accel(t, readings)`` and ``add_rig_pose(t, p, q, cov, mount)`` in arrival
    order; ``pose(horizon)`` is the latest fused head pose."""

    def __init__(self, ekf: FusionEKF, history_s: float = HISTORY_S):
        self.ekf = ekf
        self.history_s = float(history_s)
        self.stats = TrackerStats()
        self._samples: deque[tuple[float, float, np.ndarray]] = deque()  # (motion t, t, a)
        self._snapshots: deque[FilterState] = deque()

    def add_accel(self, t: float, readings: np.ndarray) -> bool:
        """One accelerometer sample (all axes) taken at ``t``; False before initialisation
        or if the sample is older than the filter (a duplicate or a reordered packet)."""
        ekf = self.ekf
        readings = np.asarray(readings, float).reshape(-1)
        if not ekf.initialised:
            return False
        motion_t = t - ekf.accel.latency_s
        if motion_t < ekf.t:
            return False
        ekf.update_accel_sample(t, readings)
        self._samples.append((motion_t, t, readings))
        self.stats.accel_samples += 1
        if self.stats.accel_samples % SNAPSHOT_EVERY == 0:
            self._snapshot()
        self._forget(motion_t - self.history_s)
        return True

    def add_rig_pose(self, t: float, p: np.ndarray, q: np.ndarray, cov_se3: np.ndarray,
                     mount: tuple[np.ndarray, np.ndarray]) -> bool:
        """An optical rig pose for time ``t``, however late it arrives; False if gated or
        older than the history."""
        ekf = self.ekf
        self.stats.optical_poses += 1
        if not ekf.initialised or t >= ekf.t:
            ok = ekf.update_rig_pose(t, p, q, cov_se3, mount)
            self._snapshot()
            return ok
        times = [s.t for s in self._snapshots]
        k = bisect.bisect_right(times, t) - 1
        if k < 0:
            self.stats.optical_too_old += 1
            return False
        self.stats.optical_late += 1
        snap = self._snapshots[k]
        self.ekf.restore(snap)
        while len(self._snapshots) > k + 1:
            self._snapshots.pop()
        replay = [s for s in self._samples if s[0] > snap.t]
        before = [s for s in replay if s[0] <= t]
        after = [s for s in replay if s[0] > t]
        for _, t_s, a in before:
            ekf.update_accel_sample(t_s, a)
        ok = ekf.update_rig_pose(t, p, q, cov_se3, mount)
        self._snapshot()
        for i, (_, t_s, a) in enumerate(after):
            ekf.update_accel_sample(t_s, a)
            if (i + 1) % SNAPSHOT_EVERY == 0:
                self._snapshot()
        self.stats.replayed_samples += len(replay)
        return ok

    def pose(self, horizon_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        return self.ekf.pose(horizon_s)

    # ------------------------------------------------------------------ internals

    def _snapshot(self) -> None:
        self._snapshots.append(self.ekf.snapshot())

    def _forget(self, t_min: float) -> None:
        while self._samples and self._samples[0][0] < t_min:
            self._samples.popleft()
        # keep one snapshot at or before the oldest sample so the history can be replayed
        while len(self._snapshots) > 1 and self._snapshots[1].t <= t_min:
            self._snapshots.popleft()
