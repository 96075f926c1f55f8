"""Live fusion: the EKF fed by asynchronous streams whose samples arrive late and out of order.

SCAAT needs every measurement applied at its own time, but the streams arrive with their
own delays.  The accelerometer stream is the filter's clock:

* an optical pose older than the filter (it arrived late: exposure, transfer, dot
  detection) rewinds to the last snapshot before it, is applied at its time, and the
  accelerometer samples after it are replayed -- the fused output never waits for the
  optics;
* a (re)start of the filter (the first optical poses, or the optics overruling the gate)
  cuts the history: nothing is rewound across it, since the state before it is the one
  the filter gave up on, but the accelerometer samples after it (kept while the filter
  waited for its second pose) are replayed;
* an optical pose newer than the filter (the accelerometer samples of that instant are
  still on their way: a busy or distant inertial service lags) waits until the inertial
  stream reaches its time; only when no accelerometer sample has *arrived* for
  ``max_wait_s`` of wall-clock time (the inertial stream stalled) is it applied at once.
  Judging the stall by arrival, not by timestamps, keeps a lagging inertial stream the
  clock instead of locking it out;
* without any optical measurement for ``max_coast_s`` the filter stops: the accelerometers
  alone are good for about a second (Hogue 2003, §6), after that the pose is a guess, and a
  client is better told "no pose" than given one off by decimetres.  The next two optical
  poses start it again.

Pure computation (no I/O): the fusion service feeds it from its need callbacks.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import bisect
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agent.errors import InvalidInputError
from services.fusion.ekf import FilterState, FusionEKF

#: keep this much history (s): optical poses older than this are dropped as too late
HISTORY_S = 0.5
#: snapshot every this many accelerometer samples (replay cost vs memory)
SNAPSHOT_EVERY = 8
#: without an accelerometer sample for this long (wall clock), optical poses go in alone.
#: The output follows the accelerometers, so waiting costs no fused pose; giving up too
#: early costs many: on a busy host the inertial stream arrives in bursts, and once an
#: optical pose has moved the filter ahead every sample behind it is dropped (seen with
#: 0.1 s: two thirds of a lagging stream lost)
MAX_WAIT_S = 0.5
#: inertial-only output for at most this long after the last optical measurement (s):
#: beyond it the dead-reckoned pose is off by decimetres (docs/FUSION_TUNING.md)
MAX_COAST_S = 2.0
#: an optical pose further ahead of the filter than this (s) is refused: it would wait
#: for the inertial stream forever (a pose stamped a day ahead stayed pending for good);
#: generous, as an inertial stream may lag the optics by seconds on a busy host
MAX_AHEAD_S = 10.0


#: an optical measurement to apply at its time: ``apply(ekf, t) -> accepted``
Update = Callable[[FusionEKF, float], bool]


@dataclass
class TrackerStats:
    accel_samples: int = 0
    optical_poses: int = 0
    dot_frames: int = 0        # frame sets of labeled laser dots received
    dots_before_start: int = 0  # dot frames before (or of) the filter's start: dropped
    optical_late: int = 0      # applied by rewinding and replaying
    optical_too_old: int = 0   # older than the history: dropped
    optical_too_far_ahead: int = 0  # more than MAX_AHEAD_S ahead of the filter: refused
    optical_waited_out: int = 0  # applied without waiting longer for the inertial stream
    replayed_samples: int = 0
    coast_stops: int = 0        # the optics were gone for longer than max_coast_s


class FusionTracker:
    """``add_accel(t, readings)``, ``add_rig_pose(t, p, q, cov, mount)`` and
    ``add_dots(t, apply)`` in arrival order; ``pose(horizon)`` is the latest fused head
    pose."""

    def __init__(self, ekf: FusionEKF, history_s: float = HISTORY_S,
                 max_wait_s: float = MAX_WAIT_S, max_coast_s: float = MAX_COAST_S):
        if not (math.isfinite(max_coast_s) and max_coast_s > 0):
            raise InvalidInputError(f"max_coast_s must be positive seconds, got {max_coast_s!r}")
        self.ekf = ekf
        self.history_s = float(history_s)
        self.max_wait_s = float(max_wait_s)
        self.max_coast_s = float(max_coast_s)
        self.stats = TrackerStats()
        #: why the last ``add_accel`` gave no pose (for the service's log)
        self.refusal = ""
        self._coasted_out = False
        self._pending: list[tuple[float, Update]] = []   # optical data ahead of the filter
        self._last_accel_wall = -math.inf
        self._samples: deque[tuple[float, float, np.ndarray]] = deque()  # (motion t, t, a)
        self._snapshots: deque[FilterState] = deque()
        self._start_t: float | None = None   # the filter start the history belongs to

    def add_accel(self, t: float, readings: np.ndarray, now: float | None = None) -> bool:
        """One accelerometer sample (all axes) taken at ``t``; False, with the reason in
        ``refusal``, while the filter waits for optical poses or if the sample is older than
        the filter (a duplicate or a reordered packet)."""
        ekf = self.ekf
        readings = np.asarray(readings, float).reshape(-1)
        self._last_accel_wall = time.monotonic() if now is None else now
        motion_t = t - ekf.accel.latency_s
        if ekf.initialised and motion_t >= ekf.t:
            while self._pending and self._pending[0][0] <= motion_t:
                self._apply_now(*self._pending.pop(0))
        if ekf.initialised and ekf.last_optical_t is not None \
                and motion_t - ekf.last_optical_t > self.max_coast_s:
            self._coast_out()
        if not ekf.initialised:   # kept for the start, which may lie before them
            if not self._samples or motion_t > self._samples[-1][0]:
                self._samples.append((motion_t, t, readings))
                self._forget(motion_t - self.history_s)
            self.refusal = (f"no optical measurement for over {self.max_coast_s:g} s: the "
                            "filter stopped until two optical poses restart it"
                            if self._coasted_out else "waiting for two optical poses to start")
            return False
        if motion_t < ekf.t:
            self.refusal = "older than the filter (a duplicate or a reordered sample)"
            return False
        ekf.update_accel_sample(t, readings)
        self._samples.append((motion_t, t, readings))
        self.stats.accel_samples += 1
        if self.stats.accel_samples % SNAPSHOT_EVERY == 0:
            self._snapshot()
        self._forget(motion_t - self.history_s)
        return True

    def add_rig_pose(self, t: float, p: np.ndarray, q: np.ndarray, cov_se3: np.ndarray,
                     mount: tuple[np.ndarray, np.ndarray], now: float | None = None,
                     systematic_se3: np.ndarray | None = None) -> bool:
        """An optical rig pose for time ``t``, however late it arrives; False if gated,
        older than the history or more than ``MAX_AHEAD_S`` ahead of the filter.
        ``systematic_se3``: the part of ``cov_se3`` that persists from frame to frame
        (``FusionEKF.update_pose``)."""
        self.stats.optical_poses += 1
        pose = (p, q, cov_se3, mount, systematic_se3)
        return self.add_optical(t, lambda ekf, t_m: ekf.update_rig_pose(t_m, *pose), now)

    def add_dots(self, t: float, apply: Callable[[FusionEKF, float], int],
                 now: float | None = None) -> bool:
        """The labeled laser dots of the frame set at ``t``: ``apply(ekf, t)`` makes their
        single-dot updates and returns how many it used, late or early as
        ``add_rig_pose``; dropped (False) before the filter runs and for the frame set
        whose pose started it (that pose is already in the filter)."""
        self.stats.dot_frames += 1
        start = self.ekf.start_t
        if not self.ekf.initialised or start is None or t <= start:
            self.stats.dots_before_start += 1
            return False
        # a coast-out may stop the filter while the dots wait: then they are dropped
        return self.add_optical(t, lambda ekf, t_m: ekf.initialised and bool(apply(ekf, t_m)),
                                now)

    def add_optical(self, t: float, apply: Update, now: float | None = None) -> bool:
        """Apply an optical measurement (``apply(ekf, t)``) at its time ``t``: now, when the
        inertial stream reaches it, or by rewinding to the snapshot before it."""
        ekf = self.ekf
        if not ekf.initialised:
            return self._apply_now(t, apply)
        if t - ekf.t > MAX_AHEAD_S:
            self.stats.optical_too_far_ahead += 1
            return False
        if t >= ekf.t:
            bisect.insort(self._pending, (t, apply), key=lambda e: e[0])
            now = time.monotonic() if now is None else now
            if now - self._last_accel_wall > self.max_wait_s:   # inertial stream stalled
                while self._pending:
                    self.stats.optical_waited_out += 1
                    self._apply_now(*self._pending.pop(0))
            return True
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
        self.stats.replayed_samples += len(before)
        ok = apply(ekf, t)
        if not self._new_start():
            self._snapshot()
            self._replay(after)
        return ok

    def _apply_now(self, t: float, apply: Update) -> bool:
        ok = apply(self.ekf, t)
        if not self._new_start() and self.ekf.initialised:
            self._snapshot()
        return ok

    def _coast_out(self) -> None:
        """Stop the filter; optical poses that were waiting for the inertial stream become
        the candidates to start it again."""
        self.ekf.stop()
        self.stats.coast_stops += 1
        self._coasted_out = True
        self._new_start()
        pending, self._pending = self._pending, []
        for t, apply in pending:
            self._apply_now(t, apply)

    def _new_start(self) -> bool:
        """After a (re)start the history begins again there, and the samples after it are
        replayed; True if there was one."""
        if self.ekf.start_t == self._start_t:
            return False
        self._start_t = self.ekf.start_t
        self._snapshots.clear()
        if self.ekf.initialised:
            self._coasted_out = False
            after = [s for s in self._samples if s[0] > self.ekf.t]
            self._samples.clear()
            self._snapshot()
            self._samples.extend(after)
            self._replay(after)
        return True

    def _replay(self, samples: list[tuple[float, float, np.ndarray]]) -> None:
        for i, (_, t_s, a) in enumerate(samples):
            self.ekf.update_accel_sample(t_s, a)
            if (i + 1) % SNAPSHOT_EVERY == 0:
                self._snapshot()
        self.stats.replayed_samples += len(samples)

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
