"""``uma service run accel-rig``: MARVIN's six-accelerometer tracker as a uma service.

Abilities (edge ``ivy/world -> marvin/accel_rig``):

* ``accel`` -- ``accel_raw``: each sample's N accelerations (m/s^2 along each calibrated
  axis).  Its attributes carry the rig geometry and calibration
  (``services.accel_rig.sensor.Calibration.to_dict``: positions, axes, biases, gains, their
  covariance, noise model, latency), so a fusion service can run its own model (SCAAT);
* ``pose`` -- ``pose6d``: the dead-reckoned pose (Hogue 2003, §4.3) relative to the absolute
  pose it was last reset to, with its covariance; ``ttl_s`` is short because inertial
  drift grows quickly (about a second of useful pose, Hogue 2003, ch. 6).  Nothing is
  published before the first reset: without one there is no pose.

Need ``reset`` -- ``pose6d`` of the head (``ivy/world -> */head``, composed with the
head-to-rig mounting; in ``uma demo`` the 300 Hz fused head pose) or of the rig itself: an
absolute pose to restart from, at most every ``--reset-every`` seconds (0: every pose).
Velocity and angular velocity at a reset come from a least-squares fit to the recent
absolute poses (``pose_rates``) when they are more certain than the integrator's own; the
first reset waits for them (a moving head is not at rest).  A pose without covariance gets
the scatter the fit sees.  A bad sample or absolute pose is refused with a rate-limited log
line naming it and the reason; the service keeps running.

Input: the simulator (default), ``csv:FILE`` (replayed) or ``serial:DEVICE`` (a line per
sample, ``t v_1 .. v_N``), converted with a calibration file.  ``--calibrate`` runs the
static calibration of Hogue 2003, §4.4.2 (simulated, or recorded poses) and writes the file.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import argparse
import logging
import math
import re
import threading
import time
from collections import Counter, deque
from typing import Any

import numpy as np

from agent import Service
from agent import geometry as geo
from agent.errors import InvalidInputError
from schemas.codec import Measurement
from services import frames
from services.accel_rig.calibration import (
    SIX_POSES,
    StaticRecording,
    calibrate,
    calibration_errors,
)
from services.accel_rig.integrator import HISTORY_S, DeadReckoner
from services.accel_rig.pose_rates import AbsolutePoses, Rates
from services.accel_rig.rig import DEFAULT_DELTA_M, layout_by_name
from services.accel_rig.sensor import Calibration
from services.accel_rig.simulator import (
    SensorTruth,
    axis_down_quaternion,
    default_device,
    simulate_static,
)
from services.accel_rig.sources import LineSource, SimSource, parse_line
from services.sim import mounts
from services.sim.trajectory import HeadTrajectory

log = logging.getLogger("uma.accel_rig")

#: A kind of refused input is logged at most once per this many seconds (with its count).
LOG_INTERVAL_S = 10.0
#: Distinct reasons remembered for that; beyond, each kind shares one line per interval.
MAX_LOGGED_REASONS = 256


def run(args: argparse.Namespace, stop: threading.Event) -> int:
    _check_args(args)
    parse_mount(args.mount)  # refuse a bad mounting before any work
    nominal = layout_by_name(args.layout, args.delta)
    if args.calibrate:
        return _calibrate(args, nominal)
    cal, source = _open(args, nominal)
    try:
        return _serve(args, cal, source, stop)
    finally:
        source.close()


def _check_args(args: argparse.Namespace) -> None:
    for name, low, high in (("rate_hz", 1.0, 10_000.0), ("reset_every", 0.0, 3600.0),
                            ("ttl_s", 1e-3, 3600.0), ("pose_seconds", 0.01, 3600.0),
                            ("speed", 0.0, 1000.0)):
        value = getattr(args, name)
        if not (math.isfinite(value) and low <= value <= high):
            raise InvalidInputError(
                f"--{name.replace('_', '-')} must be within [{low:g}, {high:g}], "
                f"got {value!r}")
    if args.pose and not args.calibrate:
        raise InvalidInputError("--pose is for --calibrate with recorded static poses")


def parse_mount(text: str | None) -> tuple[np.ndarray, np.ndarray]:
    """``X,Y,Z,QX,QY,QZ,QW`` to a pose; the simulated mounting when ``None``."""
    if text is None:
        return mounts.HEAD_TO_ACCEL_RIG
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise InvalidInputError(f"--mount {text!r}: expected 7 numbers X,Y,Z,QX,QY,QZ,QW") from None
    if len(v) != 7:
        raise InvalidInputError(
            f"--mount {text!r}: expected 7 numbers X,Y,Z,QX,QY,QZ,QW, got {len(v)}")
    return geo.check_vector(v[:3], "--mount position"), \
        geo.check_quaternion(v[3:], "--mount quaternion")


# ---------------------------------------------------------------------- calibration


def _calibrate(args: argparse.Namespace, nominal) -> int:
    path = args.calibration or "accel_calibration.json"
    if args.pose:
        recs, device = _recorded_poses(args.pose, nominal.count), None
    else:
        if args.source != "sim":
            raise InvalidInputError("--calibrate with a real source needs one --pose LABEL=CSV per "
                                    "static orientation (at least 4)")
        device = default_device()
        recs = []
        for i, label in enumerate(SIX_POSES, start=1):
            print(f"pose {i}/{len(SIX_POSES)}: rig axis {label} pointing down along gravity, "
                  f"held still for {args.pose_seconds:g} s (simulated)")
            q = axis_down_quaternion(label)
            recs.append(StaticRecording(q, simulate_static(q, args.pose_seconds, args.rate_hz,
                                                           seed=i, sensor=device)))
    noise = device.noise_model() if device is not None else None
    latency = device.latency_s(args.rate_hz) if device is not None else 0.0
    cal = calibrate(nominal, recs, args.rate_hz, noise=noise, latency_s=latency)
    _print_calibration(cal, device)
    cal.save(path)
    print(f"wrote {path}")
    return 0


def _recorded_poses(specs: list[str], channels: int) -> list[StaticRecording]:
    recs = []
    for spec in specs:
        label, _, file = spec.partition("=")
        if not file:
            raise InvalidInputError(f"--pose {spec!r}: expected LABEL=CSV, e.g. +x=px.csv")
        q = axis_down_quaternion(label)
        try:
            with open(file, encoding="ascii", errors="replace") as f:
                rows = [parse_line(line, channels, f"{file} line {n}")
                        for n, line in enumerate(f, start=1)]
        except OSError as exc:
            raise InvalidInputError(f"--pose {spec!r}: cannot read {file!r} ({exc.strerror})") \
                from None
        volts = [v for r in rows if r is not None for v in [r[1]]]
        if not volts:
            raise InvalidInputError(f"--pose {spec!r}: {file!r} holds no samples")
        print(f"pose {label}: {len(volts)} samples from {file}")
        recs.append(StaticRecording(q, np.array(volts)))
    return recs


def _print_calibration(cal: Calibration, device: SensorTruth | None) -> None:
    err = None if device is None else calibration_errors(
        cal, device.bias_v, device.gain_v_per_mps2, device.layout.axes)
    for j in range(cal.layout.count):
        n = cal.axes[j]
        line = (f"accelerometer {j + 1}: bias {cal.bias_v[j] * 1e3:+8.2f} mV, gain "
                f"{cal.gain_v_per_mps2[j] * 9.80665 * 1e3:6.1f} mV/g, axis "
                f"[{n[0]:+.5f} {n[1]:+.5f} {n[2]:+.5f}]")
        if err is not None:
            line += (f"   error: bias {err.bias_lsb[j]:+.3f} LSB, scale "
                     f"{err.scale_percent[j]:+.4f} %, axis {err.axis_deg[j]:.4f} deg")
        print(line)


# ---------------------------------------------------------------------- serving


def _open(args: argparse.Namespace, nominal) -> tuple[Calibration, Any]:
    if args.source == "sim":
        device = default_device() if args.layout == "marvin-six" and args.delta == \
            DEFAULT_DELTA_M else SensorTruth.draw(layout=nominal)
        if args.calibration:
            cal = Calibration.load(args.calibration)
        else:
            log.info("accel-rig: calibrating the simulated rig (no --calibration)")
            recs = [StaticRecording(axis_down_quaternion(lab),
                                    simulate_static(axis_down_quaternion(lab), 5.0,
                                                    args.rate_hz, seed=i, sensor=device))
                    for i, lab in enumerate(SIX_POSES)]
            cal = calibrate(nominal, recs, args.rate_hz, noise=device.noise_model(),
                            latency_s=device.latency_s(args.rate_hz))
        if cal.layout.count != device.layout.count:
            raise InvalidInputError(f"calibration has {cal.layout.count} accelerometers, the "
                                    f"simulated rig {device.layout.count}")
        return cal, SimSource(device, args.seed, args.rate_hz, HeadTrajectory(args.seed))
    if not args.calibration:
        raise InvalidInputError(f"--source {args.source}: real input needs --calibration FILE "
                                "(write one with --calibrate --pose LABEL=CSV ...)")
    cal = Calibration.load(args.calibration)
    return cal, LineSource.open(args.source, cal.layout.count, args.speed)


class LiveRig:
    """The service's state between samples: dead reckoner, absolute poses, refusals.

    ``on_reset`` runs on the SDK's dispatch thread and only validates and queues;
    ``process`` (the sample loop) applies resets, so the integrator is touched by one
    thread only.  Neither ever raises for a bad input: a sample or absolute pose that
    cannot be used is counted and logged (``EventLog``) and the service keeps running.
    """

    def __init__(self, cal: Calibration, rate_hz: float, mount: tuple[np.ndarray, np.ndarray] |
                 None, reset_every_s: float, reset_name: str = "reset pose"):
        self.cal = cal
        self.dr = DeadReckoner(cal, rate_hz)
        self.mount = mount
        self.reset_every_s = reset_every_s
        self.reset_name = reset_name
        self.origin_ns: int | None = None
        self.pending: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]] = deque(
            maxlen=64)
        self.poses = AbsolutePoses()
        self.last_reset: float | None = None
        self.events = EventLog()
        self.counts = self.events.counts
        self.raw_out: Any = None
        self.pose_out: Any = None

    # -- absolute poses (SDK thread)
    def on_reset(self, m: Measurement) -> None:
        try:
            self.pending.append(self._rig_pose(m))
        except (ValueError, TypeError, ArithmeticError) as exc:
            self.events.warn(f"{self.reset_name} refused", exc)

    def _rig_pose(self, m: Measurement) -> tuple[int, np.ndarray, np.ndarray, np.ndarray | None]:
        """The absolute pose of the rig from a reset sample, validated: ``ValueError``
        naming the sample and what is wrong with it."""
        t_ns = m.t_ns
        if isinstance(t_ns, bool) or not isinstance(t_ns, (int, np.integer)):
            raise InvalidInputError(f"time stamp {t_ns!r} is not an integer of nanoseconds")
        where = f"at t_ns={int(t_ns)}"
        if m.position is None or m.quaternion is None:
            raise InvalidInputError(f"sample {where} carries no pose")
        p = geo.check_vector(m.position, f"position {where}").reshape(3)
        q = geo.check_quaternion(m.quaternion, f"quaternion {where}").reshape(4)
        C = None if m.covariance is None else \
            geo.check_covariance(m.covariance, f"covariance {where}")
        if self.mount is not None:  # the mounting is exact: the covariance carries over
            C = geo.compose_covariance(p, q, C, None)
            p, q = geo.compose(p, q, *self.mount)
        return int(t_ns), p, q, C

    # -- samples (main thread)
    def process(self, t_ns: int, volts: np.ndarray) -> None:
        try:
            accel = self.cal.to_accel(volts)
        except ValueError as exc:
            self.events.warn("accelerometer sample refused", exc)
            return
        if self.origin_ns is None:
            self.origin_ns = t_ns
        self.raw_out.publish_measurement(Measurement(type="accel_raw", t_ns=t_ns,
                                                     values=accel))
        self._apply_resets((t_ns - self.origin_ns) * 1e-9)
        had_pose = self.dr.initialised
        try:
            est = self.dr.update((t_ns - self.origin_ns) * 1e-9, accel)
        except ValueError as exc:
            lost = had_pose and not self.dr.initialised
            self.events.warn("dead reckoning lost" if lost else "accelerometer sample refused",
                             exc)
            return
        if est is None:
            self.events.warn("no pose to publish: waiting for an absolute pose to reset from")
            return
        try:
            self.pose_out.publish(self.origin_ns + round(est.t * 1e9), est.position,
                                  est.quaternion, covariance=est.covariance)
        except ValueError as exc:
            self.events.warn("dead-reckoned pose not published", exc)
            return
        self.events.count("poses")

    def _apply_resets(self, t_sample: float) -> None:
        """Take the queued absolute poses; reset from the newest when it is time to."""
        latest = None
        while self.pending:
            t_ns, p, q, C = self.pending.popleft()
            t = (t_ns - self.origin_ns) * 1e-9  # set by the first sample, before this
            try:
                if t > t_sample + HISTORY_S:  # kept, it would block every later pose
                    raise InvalidInputError(f"absolute pose at t_ns={t_ns} is {t - t_sample:.3f} s "
                                            "ahead of the samples; the clocks disagree")
                self.poses.add(t, p, q, C)
            except ValueError as exc:
                self.events.warn(f"{self.reset_name} refused", exc)
                continue
            latest = (t, p, q, C)
        if latest is None:
            return
        t, p, q, C = latest
        if self.dr.initialised and self.last_reset is not None \
                and t - self.last_reset < self.reset_every_s:
            return  # without a pose (diverged), the next usable pose resets at once
        rates = self.poses.rates()
        velocity, omega = self._rates_to_use(rates)
        if not self.dr.initialised and not (velocity and omega):
            self.events.warn("without a pose, a reset waits for three absolute poses close "
                             "together (for the velocities)")
            return
        if not self.dr.initialised and not rates.settled:
            # a fast source's first three poses, ms apart, give rates (0.8 rad/s of angular
            # velocity from 1 mrad poses at 300 Hz) that turn the reckoning by a radian a
            # second; the full window (50 ms) gives them ten times better
            self.events.warn("without a pose, a reset waits for a full window of absolute "
                             "poses (rates from its first few would be too uncertain)")
            return
        if C is None and rates is not None:
            if not rates.settled:
                self.events.warn("a reset without covariance waits for a full window of "
                                 "absolute poses (to estimate their noise)")
                return
            # no covariance given: the scatter of the source's poses around the fit (none
            # for a slow source, whose three poses fit exactly: then exact, as it says)
            C = geo.covariance_from_std(p, math.sqrt(rates.position_var),
                                        math.sqrt(rates.rotation_var))
        try:
            self.dr.reset(t, p, q, covariance=C, **velocity, **omega)
        except ValueError as exc:
            self.events.warn(f"{self.reset_name} refused", exc)
            return
        self.last_reset = t
        self.events.count("resets")

    def _rates_to_use(self, rates: Rates | None) -> tuple[dict[str, Any], dict[str, Any]]:
        """Velocity and angular velocity from the absolute poses, each when it is more
        certain than the integrator's own (always at a first reset)."""
        if rates is None:
            return {}, {}
        own = self.dr.state_covariance() if self.dr.initialised else None
        velocity, omega = {}, {}
        if own is None or rates.velocity_var < float(np.trace(own[6:9, 6:9])) / 3.0:
            velocity = {"velocity": rates.velocity,
                        "velocity_cov": rates.velocity_var * np.eye(3)}
        if own is None or rates.omega_var < float(np.trace(own[9:12, 9:12])) / 3.0:
            omega = {"omega": rates.omega, "omega_cov": rates.omega_var * np.eye(3)}
        return velocity, omega


class EventLog:
    """Counts what happened by kind; ``warn`` also logs it, rate-limited: the first of each
    kind and reason at once, then at most one line per kind and reason every
    ``LOG_INTERVAL_S`` with the count, so a stream of bad input at 300 Hz neither floods
    the log nor goes unnoticed.  Thread-safe (the SDK thread refuses reset poses, the
    sample loop samples).
    """

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self._logged_at: dict[tuple[str, str], float] = {}
        self._lock = threading.Lock()

    def count(self, what: str) -> None:
        with self._lock:
            self.counts[what] += 1

    def warn(self, what: str, exc: Exception | None = None) -> None:
        # the reason without its numbers: one line for "NaN at t_ns=1", "NaN at t_ns=2", ...
        reason = _DIGITS.sub("#", str(exc)) if exc is not None else ""
        now = time.monotonic()
        with self._lock:
            self.counts[what] += 1
            n = self.counts[what]
            key = (what, reason if len(self._logged_at) < MAX_LOGGED_REASONS else "")
            last = self._logged_at.get(key)
            if last is not None and now - last < LOG_INTERVAL_S:
                return
            self._logged_at[key] = now
        log.warning("accel-rig: %s%s (%d so far)", what, f": {exc}" if exc else "", n)


_DIGITS = re.compile(r"\d+")


def _serve(args: argparse.Namespace, cal: Calibration, source, stop: threading.Event) -> int:

    is_rig = args.reset_frame == frames.ACCEL_RIG
    live = LiveRig(cal, args.rate_hz, None if is_rig else parse_mount(args.mount),
                   args.reset_every, reset_name=f"reset pose of {args.reset_frame}")
    attrs = {k: v for k, v in cal.to_dict().items() if k != "latency_s"}
    with Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect,
                 listen=args.listen or None) as svc:
        live.raw_out = svc.ability("accel", type="accel_raw",
                                   edge=(frames.WORLD, frames.ACCEL_RIG),
                                   frequency_hz=args.rate_hz, latency_s=cal.latency_s, **attrs)
        live.pose_out = svc.ability("pose", type="pose6d", edge=(frames.WORLD, frames.ACCEL_RIG),
                                    frequency_hz=args.rate_hz, latency_s=cal.latency_s,
                                    ttl_s=args.ttl_s, dead_reckoned=True)
        svc.need("reset", type="pose6d", edge=(frames.WORLD, args.reset_frame),
                 where="frequency_hz >= 1", prefer="latency_s", on_sample=live.on_reset)
        svc.start()
        log.info("accel-rig: %d accelerometers from %s at %g Hz", cal.layout.count,
                 source.name, args.rate_hz)
        for item in source.samples():
            if stop.is_set():
                break
            if isinstance(item, ValueError):
                live.events.warn("input line refused", item)
                continue
            try:
                live.process(*item)
            except Exception as exc:  # a bug must not stop the tracker: say it, go on
                live.events.warn("internal error on a sample (a bug; please report it)",
                                 RuntimeError(f"{type(exc).__name__}: {exc}"))
        else:
            log.info("accel-rig: input %s ended", source.name)
    log.info("accel-rig: %s", dict(live.counts))
    return 0
