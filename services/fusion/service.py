"""``uma service run fusion``: MARVIN's EKF/SCAAT fusion as a uma service (Hogue 2003, ch. 6).

Needs (matched by the agent, data straight from the publishing services):

* ``optical``: the absolute pose of the optical rig, ``ivy/world -> */laser_rig``
  (``pose6d``, 10 Hz or more: the laser-dot camera at 15-60 Hz), with the systematic part
  of its covariance if the tracker publishes one (``schemas.codec.SYSTEMATIC_COVARIANCE``:
  the filter weighs the pose by the rest and carries that part into its output);
* ``accel``: the raw accelerometer stream of the inertial rig (``accel_raw``, 100 Hz or
  more), whose ability attributes carry the rig's calibration (positions, axes, noise,
  latency: ``services.accel_rig.sensor.Calibration.to_dict``);
* ``dots`` (``--optical dots`` only): the labeled laser dots on the optical rig's edge
  (``points3d``, ids = diode labels 1..4, each dot's noise and installation std in
  ``schemas.codec.DOT_STD`` / ``DOT_SYSTEMATIC_STD``), also of frame sets without a pose;
  one SCAAT update per dot (``services.fusion.dots``) against the walls of the display's
  calibration file (``--display-calibration``, the laser tracker's).  The poses then only
  start the filter and bring their systematic covariance.

The mountings ``alice/head -> <rig>`` are the SRG's static edges (an agent's
``[[static]]`` configuration, an alignment result or the simulator's true mountings):
the service asks the agent's SRG with ``Client.pose`` until it has them and every few
seconds after (a re-calibrated rig rebuilds the filter).  Nothing about the rigs is a
constant here.

Ability ``head``: the fused ``ivy/world -> alice/head`` pose at the inertial rate with its
6x6 covariance, optionally predicted ``--horizon-ms`` ahead (attribute ``predicted_s``).
Late optical poses are applied at their own time by rewinding (``FusionTracker``).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from types import SimpleNamespace
from typing import Any

import numpy as np

from agent import Client, Service
from agent import geometry as geo
from agent.errors import InvalidInputError, UmaError
from schemas.codec import DOT_STD, DOT_SYSTEMATIC_STD, systematic_covariance
from services.fusion.dots import load_walls, update_dots
from services.fusion.ekf import FusionEKF
from services.fusion.state import AccelModel, FusionConfig
from services.fusion.tracker import MAX_AHEAD_S, MAX_COAST_S, FusionTracker
from services.installation.ivy import Wall
from services.installation.laser_housing import BEAM_DIRECTIONS
from services.laser_camera.tracker import LabeledDots

log = logging.getLogger("uma.fusion")

MOUNT_RETRY_S = 0.5
MOUNT_REFRESH_S = 5.0
STATUS_EVERY_S = 2.0
#: a laser pose without covariance is taken with these standard deviations
DEFAULT_OPTICAL_STD = (0.005, math.radians(0.5))


class LiveFusion:
    """The service's state: builds the filter once calibration and mountings are known,
    then turns need callbacks into filter updates and publications.  The need callbacks
    run on the SDK's single dispatch thread; the lock is for the mountings, which the SRG
    polling thread sets."""

    def __init__(self, horizon_s: float, model_floor: float,
                 publish: Any = None, config: FusionConfig | None = None,
                 max_coast_s: float = MAX_COAST_S, walls: list[Wall] | None = None):
        """``walls``: the display's walls; given, the fusion runs in dot mode."""
        self.horizon_s = horizon_s
        self.walls = walls
        self.max_coast_s = max_coast_s
        self.model_floor = model_floor
        self.publish = publish
        self.config = config or FusionConfig()
        self.optical_mount: tuple[np.ndarray, np.ndarray] | None = None
        self.accel_mount: tuple[np.ndarray, np.ndarray] | None = None
        self.calibration: dict[str, Any] | None = None
        self.tracker: FusionTracker | None = None
        self.t0_ns: int | None = None
        self.dropped: dict[str, int] = {}
        self.published = 0
        self._lock = threading.Lock()   # mountings arrive from the SRG polling thread

    # -- inputs
    def on_optical_mount(self, m: Any) -> None:
        with self._lock:
            self.optical_mount = (np.asarray(m.position, float),
                                  np.asarray(m.quaternion, float))

    def on_accel_mount(self, m: Any) -> None:
        new = (np.asarray(m.position, float), np.asarray(m.quaternion, float))
        with self._lock:
            if self.accel_mount is not None and not _same_pose(self.accel_mount, new):
                self.tracker = None  # the rig moved on the head: rebuild the model
            self.accel_mount = new

    def on_accel(self, m: Any) -> None:
        with self._lock:
            self._on_accel(m)

    def on_optical(self, m: Any) -> None:
        with self._lock:
            self._on_optical(m)

    def on_dots(self, m: Any) -> None:
        with self._lock:
            self._on_dots(m)

    def _on_accel(self, m: Any) -> None:
        if self.tracker is None and not self._build(m):
            return
        assert self.tracker is not None
        t = self._seconds(m.t_ns)
        if not self.tracker.add_accel(t, np.asarray(m.values, float)):
            self._drop(self.tracker.refusal)
            return
        if self.publish is not None:
            p, q = self.tracker.pose(self.horizon_s)
            shift_s = self.horizon_s - self.tracker.ekf.accel.latency_s
            t_out = int(m.t_ns) + round(shift_s * 1e9)
            self.publish(t_out, p, q, self.tracker.ekf.pose_covariance())
            self.published += 1

    def _on_optical(self, m: Any) -> None:
        ahead_s = (int(m.t_ns) - time.time_ns()) * 1e-9
        if ahead_s > MAX_AHEAD_S:
            self._drop(f"optical pose stamped more than {MAX_AHEAD_S:g} s ahead of this "
                       "host's clock")
            return
        if self.tracker is None or self.optical_mount is None:
            self._drop("optical pose before calibration and mountings are known")
            return
        cov = m.covariance
        if cov is None:
            cov = geo.covariance_from_std(m.position, *DEFAULT_OPTICAL_STD)
        try:
            systematic = systematic_covariance(m)
        except ValueError as exc:  # DecodeError: names the malformed extra
            self._drop(f"optical pose refused: {exc}")
            return
        ahead, mount = self.tracker.stats.optical_too_far_ahead, self.optical_mount
        t = self._seconds(m.t_ns)
        if self.walls is None or not self.tracker.ekf.initialised:
            self.tracker.add_rig_pose(t, m.position, m.quaternion, cov, mount,
                                      systematic_se3=systematic)
        elif systematic is not None:  # dot mode: its dots update, the pose's error stays
            p, q = m.position, m.quaternion

            def carry(ekf: Any, _t: float) -> bool:
                ekf.carry_rig_systematic(p, q, systematic, mount)
                return True  # nothing measured, nothing to gate
            self.tracker.add_optical(t, carry)
        if self.tracker.stats.optical_too_far_ahead > ahead:
            self._drop(f"optical pose more than {MAX_AHEAD_S:g} s ahead of the filter")

    def _on_dots(self, m: Any) -> None:
        """One SCAAT update per labeled dot (dot mode); a bad message or dot is dropped
        and counted with its reason."""
        if self.walls is None:
            self._drop("laser dots while not in dot mode")
            return
        if self.tracker is None or self.optical_mount is None:
            self._drop("laser dots before calibration and mountings are known")
            return
        try:
            dots = labeled_dots(m, self._seconds(m.t_ns), self._drop)
        except ValueError as exc:
            self._drop(f"laser dots refused: {exc}")
            return
        if not dots.labels:
            return
        walls, mount, stats = self.walls, self.optical_mount, self.tracker.stats
        before = (stats.dots_before_start, stats.optical_too_old, stats.optical_too_far_ahead)
        self.tracker.add_dots(dots.t, lambda ekf, _: update_dots(ekf, dots, walls, mount))
        for was, now, why in zip(before, (stats.dots_before_start, stats.optical_too_old,
                                          stats.optical_too_far_ahead), (
                "laser dots before the filter runs (or of the frame set that started it)",
                "laser dots older than the history",
                f"laser dots more than {MAX_AHEAD_S:g} s ahead of the filter"), strict=True):
            if now > was:
                self._drop(why)

    def status(self) -> dict[str, Any]:
        """Counters for the log: what came in, what went out, what was dropped and why."""
        with self._lock:
            out: dict[str, Any] = {"published": self.published, "dropped": dict(self.dropped)}
            if self.tracker is not None:
                out["tracker"] = vars(self.tracker.stats).copy()
                out["filter"] = vars(self.tracker.ekf.stats).copy()
            return out

    # -- internals
    def _build(self, m: Any) -> bool:
        """Create the filter from the accel ability's calibration and the SRG mounting."""
        if self.accel_mount is None:
            self._drop("accelerometer mounting (head -> accel rig) not known yet")
            return False
        attrs = _attributes(m.attributes)
        try:
            model = accel_model_from_attributes(attrs, self.accel_mount, self.model_floor)
        except ValueError as exc:
            self._drop(f"accel ability has no usable calibration ({exc})")
            return False
        if model.count != len(m.values):
            self._drop(f"accel sample has {len(m.values)} readings, calibration {model.count}")
            return False
        self.tracker = FusionTracker(FusionEKF(model, self.config),
                                     max_coast_s=self.max_coast_s)
        log.info("fusion: %d accelerometers, latency %.1f ms; waiting for the optics",
                 model.count, 1e3 * model.latency_s)
        return True

    def _seconds(self, t_ns: int) -> float:
        """Filter time: seconds since the first sample (keeps float precision)."""
        if self.t0_ns is None:
            self.t0_ns = int(t_ns)
        return (int(t_ns) - self.t0_ns) * 1e-9

    def _drop(self, why: str) -> None:
        n = self.dropped.get(why, 0)
        self.dropped[why] = n + 1
        if n == 0 or n in (10, 100, 1000, 10000):
            log.info("fusion: %s (%d so far)", why, n + 1)


def accel_model_from_attributes(attrs: dict[str, Any], mount: tuple[np.ndarray, np.ndarray],
                                model_floor: float) -> AccelModel:
    """The accelerometer model from an ``accel_raw`` ability's calibration attributes."""
    from services.accel_rig.sensor import Calibration

    # attributes cannot carry null: optional calibration fields may be absent
    cal = Calibration.from_dict({"bandwidth_hz": None, "param_cov": None, **attrs})
    rate = float(attrs.get("frequency_hz") or 300.0)
    return AccelModel.from_layout(cal.layout.positions, cal.layout.axes, mount,
                                  cal.accel_var(rate), cal.latency_s, model_floor)


def labeled_dots(m: Any, t: float, drop: Any) -> LabeledDots:
    """The labeled dots of a ``points3d`` laser-dot message at filter time ``t``.

    A message whose parts do not fit together (labels, points and stds of different
    counts, stds missing) is a ``ValueError``; a dot that cannot be used (an unknown
    label, a label twice, a non-finite point or std) is left out and ``drop(reason)``
    counts it."""
    points = np.asarray(m.points if m.points is not None else np.zeros((0, 3)), float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(f"points of shape {points.shape}, expected (n, 3)")
    n = len(points)
    ids = m.ids
    if ids is None or len(ids) != n:
        raise InvalidInputError(f"{'no' if ids is None else len(ids)} labels for {n} points")
    extra = getattr(m, "extra", None) or {}
    stds = []
    for key in (DOT_STD, DOT_SYSTEMATIC_STD):
        try:
            v = np.asarray(extra[key], float).reshape(-1)
        except (KeyError, TypeError, ValueError):
            raise InvalidInputError(f"extra {key!r}: expected {n} numbers") from None
        if v.shape != (n,):
            raise InvalidInputError(f"extra {key!r}: {v.size} numbers for {n} points")
        stds.append(v)
    std, sys_std = stds
    keep, seen = [], set()
    for i, label in enumerate(ids):
        if label not in BEAM_DIRECTIONS:
            drop(f"laser dot with unknown label {label!r}")
        elif label in seen:
            drop(f"laser dot label {label} twice in one message")
        elif not (np.all(np.isfinite(points[i])) and std[i] > 0 and math.isfinite(std[i])
                  and sys_std[i] >= 0 and math.isfinite(sys_std[i])):
            drop("laser dot with a non-finite point or a non-positive std")
        else:
            keep.append(i)
            seen.add(label)
    return LabeledDots(t, [int(ids[i]) for i in keep], points[keep], std[keep],
                       sys_std[keep], predicted=False)


def _attributes(a: Any) -> dict[str, Any]:
    if a is None:
        return {}
    if isinstance(a, dict):
        return dict(a)
    return a.model_dump()


def _same_pose(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> bool:
    dp, dr = geo.pose_error(a[0], a[1], b[0], b[1])
    return float(dp) < 1e-6 and float(dr) < 1e-6


def run(args: argparse.Namespace, stop: threading.Event) -> int:

    if not (math.isfinite(args.horizon_ms) and 0 <= args.horizon_ms <= 500):
        raise InvalidInputError(f"--horizon-ms must be within 0..500, got {args.horizon_ms!r}")
    if not (math.isfinite(args.model_floor) and args.model_floor >= 0):
        raise InvalidInputError(f"--model-floor must be >= 0, got {args.model_floor!r}")
    if not (math.isfinite(args.optical_bias_mm) and args.optical_bias_mm >= 0):
        raise InvalidInputError(f"--optical-bias-mm must be >= 0, got {args.optical_bias_mm!r}")
    if not (math.isfinite(args.optical_bias_tau_s) and args.optical_bias_tau_s > 0):
        raise InvalidInputError(
            f"--optical-bias-tau-s must be positive, got {args.optical_bias_tau_s!r}")
    if not (math.isfinite(args.max_coast_s) and args.max_coast_s > 0):
        raise InvalidInputError(f"--max-coast-s must be positive seconds, got {args.max_coast_s!r}")
    config = FusionConfig(optical_bias_std=args.optical_bias_mm / 1e3,
                          optical_bias_tau_s=args.optical_bias_tau_s)
    live = LiveFusion(args.horizon_ms / 1e3, args.model_floor, config=config,
                      max_coast_s=args.max_coast_s, walls=_walls(args))
    with Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect,
                 listen=args.listen or None) as svc:
        out = svc.ability("head", type="pose6d", edge=(args.world, args.head),
                          frequency_hz=300.0, latency_s=0.002, fused=True,
                          predicted_s=args.horizon_ms / 1e3)
        live.publish = out.publish
        # Mild predicates: the agent re-matches on *measured* rates, and on a busy host a
        # strict one (e.g. >= 100 Hz for 300 Hz accelerometers) would disconnect the only
        # source during a hiccup.  The filter copes with slow or irregular streams itself.
        svc.need("optical", type="pose6d", edge=(args.world, args.optical_rig),
                 where="frequency_hz >= 2", prefer="latency_s", on_sample=live.on_optical)
        svc.need("accel", type="accel_raw", edge=("*/*", args.accel_rig),
                 where="frequency_hz >= 20", prefer="latency_s", on_sample=live.on_accel)
        if live.walls is not None:
            svc.need("dots", type="points3d", edge=(args.world, args.optical_rig),
                     where="frequency_hz >= 2", prefer="latency_s", on_sample=live.on_dots)
        svc.start()
        log.info("fusion: publishing %s -> %s", args.world, args.head)
        poll_mountings(live, args, stop)
    return 0


def _walls(args: argparse.Namespace) -> list[Wall] | None:
    """The display's walls for dot mode (from the laser tracker's calibration file)."""
    if args.optical == "pose":
        if args.display_calibration:
            raise InvalidInputError("--display-calibration is for --optical dots")
        return None
    if not args.display_calibration:
        raise InvalidInputError("--optical dots needs --display-calibration FILE (the laser "
                                "tracker's calibration, whose walls the dots lie on)")
    return load_walls(args.display_calibration)


def poll_mountings(live: LiveFusion, args: argparse.Namespace, stop: threading.Event) -> None:
    """Ask the agent's SRG for head -> rig until known, then refresh every few seconds."""

    wanted = ((args.optical_rig, live.on_optical_mount), (args.accel_rig, live.on_accel_mount))
    next_status = time.monotonic() + STATUS_EVERY_S
    with Client(realm=args.realm, connect=args.connect, timeout=1.0) as client:
        while not stop.is_set():
            missing = 0
            for rig, setter in wanted:
                try:
                    r = client.pose(args.head, rig, error="hops")
                except UmaError as exc:
                    missing += 1
                    live._drop(f"mounting {args.head} -> {rig} not in the SRG yet ({exc})")
                    continue
                setter(SimpleNamespace(position=r.position, quaternion=r.quaternion))
            deadline = time.monotonic() + (MOUNT_RETRY_S if missing else MOUNT_REFRESH_S)
            while not stop.is_set() and time.monotonic() < deadline:
                if time.monotonic() >= next_status:
                    log.info("fusion: %s", live.status())
                    next_status = time.monotonic() + STATUS_EVERY_S
                stop.wait(min(0.5, max(0.0, deadline - time.monotonic())))
