"""``uma service run accel-rig``: MARVIN's six-accelerometer tracker as a uma service.

Abilities (edge ``ivy/world -> marvin/accel_rig``):

* ``accel`` -- ``accel_raw``: each sample's N accelerations (m/s^2 along each calibrated
  axis).  Its attributes carry the rig geometry and calibration
  (``services.accel_rig.sensor.Calibration.to_dict``: positions, axes, biases, gains, their
  covariance, noise model, latency), so a fusion service can run its own model (SCAAT);
* ``pose`` -- ``pose6d``: the dead-reckoned pose (seed 003 §4.3) relative to the absolute
  pose it was last reset to, with its covariance; ``ttl_s`` is short because inertial
  drift grows quickly (about a second of useful pose, seed 003 ch. 6).  Nothing is
  published before the first reset: without one there is no pose.

Need ``reset`` -- ``pose6d`` of the head (``ivy/world -> */head``, composed with the
head-to-rig mounting) or of the rig itself: an absolute pose to restart from, at most every
``--reset-every`` seconds.  Velocity and angular velocity at a reset come from the last
three absolute poses when they are more certain than the integrator's own; the first reset
waits for them (a moving head is not at rest).

Input: the simulator (default), ``csv:FILE`` (replayed) or ``serial:DEVICE`` (a line per
sample, ``t v_1 .. v_N``), converted with a calibration file.  ``--calibrate`` runs the
static calibration of seed 003 §4.4.2 (simulated, or recorded poses) and writes the file.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
from collections import Counter, deque
from typing import Any

import numpy as np

from agent.plugins import ServicePlugin
from agent.srg import geometry as geo
from schemas.codec import Measurement
from services.accel_rig.calibration import (
    SIX_POSES,
    StaticRecording,
    calibrate,
    calibration_errors,
)
from services.accel_rig.integrator import DeadReckoner
from services.accel_rig.rig import DEFAULT_DELTA_M, LAYOUTS, layout_by_name
from services.accel_rig.sensor import Calibration
from services.accel_rig.simulator import (
    DEFAULT_RATE_HZ,
    SensorTruth,
    axis_down_quaternion,
    default_device,
    simulate_static,
)
from services.accel_rig.sources import LineSource, SimSource, parse_line
from services.sim import mounts
from services.sim.trajectory import HeadTrajectory

log = logging.getLogger("uma.accel_rig")

#: Finite-difference velocities from absolute poses get at least this standard deviation
#: (truncation error of a three-point derivative on head motion at >= 30 Hz).
FD_VELOCITY_FLOOR = 0.01  # m/s
FD_OMEGA_FLOOR = 0.01  # rad/s
#: Absolute poses further apart than this are not differentiated.
FD_MAX_SPAN_S = 0.25


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", default="accel-rig", help="service id (default: accel-rig)")
    parser.add_argument("--source", default="sim", metavar="SRC",
                        help="'sim' (default: the simulated rig on the head trajectory), "
                             "'csv:FILE' (replay lines 't v1 .. vN') or 'serial:DEVICE' (the "
                             "same lines read live from a configured tty or a pipe)")
    parser.add_argument("--calibration", metavar="FILE", default=None,
                        help="calibration file (JSON) to load; required for csv/serial; "
                             "with the simulator, missing means: calibrate at start; with "
                             "--calibrate: where to write it (default accel_calibration.json)")
    parser.add_argument("--calibrate", action="store_true",
                        help="run the static calibration (seed 003 §4.4.2): the simulated "
                             "rig, or the recordings given by --pose; write --calibration "
                             "and exit")
    parser.add_argument("--pose", action="append", default=[], metavar="LABEL=CSV",
                        help="with --calibrate: a recording of the rig held still with axis "
                             "LABEL (+x -x +y -y +z -z) pointing down, lines 't v1 .. vN'; at "
                             "least 4 (repeatable; write --pose=-x=FILE for a minus sign)")
    parser.add_argument("--pose-seconds", type=float, default=20.0,
                        help="seconds per simulated calibration pose (default 20)")
    parser.add_argument("--layout", default="marvin-six", choices=sorted(LAYOUTS),
                        help="nominal accelerometer layout: positions (default marvin-six)")
    parser.add_argument("--delta", type=float, default=DEFAULT_DELTA_M,
                        help=f"accelerometer distance from the rig centre, m (default "
                             f"{DEFAULT_DELTA_M})")
    parser.add_argument("--rate-hz", type=float, default=DEFAULT_RATE_HZ,
                        help="sample rate (default 300, appendix C.1)")
    parser.add_argument("--seed", type=int, default=1,
                        help="simulated trajectory seed (default 1; as the sim service)")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="csv replay speed (1 = as recorded, 0 = as fast as possible)")
    parser.add_argument("--reset-frame", default="*/head", metavar="FRAME",
                        help="frame whose absolute pose in ivy/world resets the integrator: "
                             "a head (pattern, composed with --mount; default */head) or "
                             f"{mounts.ACCEL_RIG} itself")
    parser.add_argument("--reset-every", type=float, default=1.0,
                        help="seconds between resets from the absolute pose (default 1)")
    parser.add_argument("--mount", default=None, metavar="X,Y,Z,QX,QY,QZ,QW",
                        help="pose of the rig in the head frame (default: the simulated "
                             "head mounting)")
    parser.add_argument("--ttl-s", type=float, default=1.0,
                        help="advertised validity of a dead-reckoned pose (default 1 s)")


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
            raise ValueError(f"--{name.replace('_', '-')} must be within [{low:g}, {high:g}], "
                             f"got {value!r}")
    if args.pose and not args.calibrate:
        raise ValueError("--pose is for --calibrate with recorded static poses")


def parse_mount(text: str | None) -> tuple[np.ndarray, np.ndarray]:
    """``X,Y,Z,QX,QY,QZ,QW`` to a pose; the simulated mounting when ``None``."""
    if text is None:
        return mounts.HEAD_TO_ACCEL_RIG
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise ValueError(f"--mount {text!r}: expected 7 numbers X,Y,Z,QX,QY,QZ,QW") from None
    if len(v) != 7:
        raise ValueError(f"--mount {text!r}: expected 7 numbers X,Y,Z,QX,QY,QZ,QW, got {len(v)}")
    return geo.check_vector(v[:3], "--mount position"), \
        geo.check_quaternion(v[3:], "--mount quaternion")


# ---------------------------------------------------------------------- calibration


def _calibrate(args: argparse.Namespace, nominal) -> int:
    path = args.calibration or "accel_calibration.json"
    if args.pose:
        recs, device = _recorded_poses(args.pose, nominal.count), None
    else:
        if args.source != "sim":
            raise ValueError("--calibrate with a real source needs one --pose LABEL=CSV per "
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
            raise ValueError(f"--pose {spec!r}: expected LABEL=CSV, e.g. +x=px.csv")
        q = axis_down_quaternion(label)
        try:
            with open(file, encoding="ascii", errors="replace") as f:
                rows = [parse_line(line, channels, f"{file} line {n}")
                        for n, line in enumerate(f, start=1)]
        except OSError as exc:
            raise ValueError(f"--pose {spec!r}: cannot read {file!r} ({exc.strerror})") \
                from None
        volts = [v for r in rows if r is not None for v in [r[1]]]
        if not volts:
            raise ValueError(f"--pose {spec!r}: {file!r} holds no samples")
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
            raise ValueError(f"calibration has {cal.layout.count} accelerometers, the "
                             f"simulated rig {device.layout.count}")
        return cal, SimSource(device, args.seed, args.rate_hz, HeadTrajectory(args.seed))
    if not args.calibration:
        raise ValueError(f"--source {args.source}: real input needs --calibration FILE "
                         "(write one with --calibrate --pose LABEL=CSV ...)")
    cal = Calibration.load(args.calibration)
    return cal, LineSource.open(args.source, cal.layout.count, args.speed)


class LiveRig:
    """The service's state between samples: dead reckoner, pending resets, counters.

    ``on_reset`` runs on the SDK's dispatch thread and only queues; ``process`` (the
    sample loop) applies resets, so the integrator is touched by one thread only.
    """

    def __init__(self, cal: Calibration, rate_hz: float, mount: tuple[np.ndarray, np.ndarray] |
                 None, reset_every_s: float):
        self.cal = cal
        self.dr = DeadReckoner(cal, rate_hz)
        self.mount = mount
        self.reset_every_s = reset_every_s
        self.origin_ns: int | None = None
        self.pending: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]] = deque(
            maxlen=64)
        self.recent: deque[tuple[float, np.ndarray, np.ndarray, np.ndarray | None]] = deque(
            maxlen=3)
        self.last_reset: float | None = None
        self.counts: Counter[str] = Counter()
        self.raw_out: Any = None
        self.pose_out: Any = None

    # -- absolute poses (SDK thread)
    def on_reset(self, m: Measurement) -> None:
        if m.position is None or m.quaternion is None:
            self._count("reset sample without a pose")
            return
        p, q, C = m.position, m.quaternion, m.covariance
        if self.mount is not None:
            C = geo.compose_covariance(p, q, C, None)
            p, q = geo.compose(p, q, *self.mount)
        self.pending.append((int(m.t_ns), np.asarray(p, float), np.asarray(q, float), C))

    # -- samples (main thread)
    def process(self, t_ns: int, volts: np.ndarray) -> None:
        try:
            accel = self.cal.to_accel(volts)
        except ValueError as exc:
            self._count("sample refused", exc)
            return
        if self.origin_ns is None:
            self.origin_ns = t_ns
        self.raw_out.publish_measurement(Measurement(type="accel_raw", t_ns=t_ns,
                                                     values=accel))
        self._apply_resets()
        try:
            est = self.dr.update((t_ns - self.origin_ns) * 1e-9, accel)
        except ValueError as exc:
            self._count("sample refused", exc)
            return
        if est is None:
            self._count("no absolute pose yet to reset from")
            return
        self.pose_out.publish(self.origin_ns + round(est.t * 1e9), est.position,
                              est.quaternion, covariance=est.covariance)
        self.counts["poses"] += 1

    def _apply_resets(self) -> None:
        latest = None
        while self.pending:
            t_ns, p, q, C = self.pending.popleft()
            if self.origin_ns is None:
                continue
            t = (t_ns - self.origin_ns) * 1e-9
            if self.recent and t <= self.recent[-1][0]:
                continue  # out of order: not newer than what we have
            self.recent.append((t, p, q, C))
            latest = self.recent[-1]
        if latest is None:
            return
        if self.last_reset is not None and latest[0] - self.last_reset < self.reset_every_s:
            return
        t, p, q, C = latest
        velocity, omega = self._rates()
        if not self.dr.initialised and not (velocity and omega):
            self._count("first reset waits for three absolute poses (for the velocities)")
            return
        try:
            self.dr.reset(t, p, q, covariance=C, **velocity, **omega)
        except ValueError as exc:
            self._count("reset refused", exc)
            return
        self.last_reset = t
        self.counts["resets"] += 1

    def _rates(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """Velocity and body angular velocity at the newest absolute pose by the derivative
        of the parabola through the last three, when that beats the integrator's own."""
        if len(self.recent) < 3 or self.recent[-1][0] - self.recent[0][0] > FD_MAX_SPAN_S:
            return {}, {}
        (t0, p0, q0, C0), (t1, p1, q1, C1), (t2, p2, q2, C2) = self.recent
        w = np.array([(t2 - t1) / ((t0 - t1) * (t0 - t2)), (t2 - t0) / ((t1 - t0) * (t1 - t2)),
                      (2 * t2 - t0 - t1) / ((t2 - t0) * (t2 - t1))])
        v = w[0] * p0 + w[1] * p1 + w[2] * p2
        # rotation vectors of each pose relative to the newest, in the rig frame
        qi = geo.quat_conjugate(q2)
        r0 = geo.quat_to_rotvec(geo.quat_multiply(qi, q0))
        r1 = geo.quat_to_rotvec(geo.quat_multiply(qi, q1))
        omega = w[0] * r0 + w[1] * r1
        var_p = var_r = 0.0
        for C, p in ((C0, p0), (C1, p1), (C2, p2)):
            if C is not None:
                dec = geo.se3_to_decoupled(p, C)
                var_p = max(var_p, float(np.trace(dec[:3, :3]) / 3))
                var_r = max(var_r, float(np.trace(dec[3:, 3:]) / 3))
        k = float(w @ w)
        v_var = k * var_p + FD_VELOCITY_FLOOR**2
        w_var = k * var_r + FD_OMEGA_FLOOR**2
        velocity, rate = {}, {}
        if not self.dr.initialised or v_var < float(np.trace(self.dr.state_covariance()[6:9, 6:9])
                                                    / 3):
            velocity = {"velocity": v, "velocity_cov": v_var * np.eye(3)}
        if not self.dr.initialised or w_var < float(np.trace(
                self.dr.state_covariance()[9:12, 9:12]) / 3):
            rate = {"omega": omega, "omega_cov": w_var * np.eye(3)}
        return velocity, rate

    def _count(self, what: str, exc: Exception | None = None) -> None:
        n = self.counts[what]
        self.counts[what] = n + 1
        if n in (0, 10, 100, 1000) or n % 10000 == 0:
            log.warning("accel-rig: %s%s (%d so far)", what, f": {exc}" if exc else "", n + 1)


def _serve(args: argparse.Namespace, cal: Calibration, source, stop: threading.Event) -> int:
    from agent import Service  # imported here: '--help' and '--calibrate' need no Zenoh

    is_rig = args.reset_frame == mounts.ACCEL_RIG
    live = LiveRig(cal, args.rate_hz, None if is_rig else parse_mount(args.mount),
                   args.reset_every)
    attrs = {k: v for k, v in cal.to_dict().items() if k != "latency_s"}
    with Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect,
                 listen=args.listen or None) as svc:
        live.raw_out = svc.ability("accel", type="accel_raw",
                                   edge=(mounts.WORLD, mounts.ACCEL_RIG),
                                   frequency_hz=args.rate_hz, latency_s=cal.latency_s, **attrs)
        live.pose_out = svc.ability("pose", type="pose6d", edge=(mounts.WORLD, mounts.ACCEL_RIG),
                                    frequency_hz=args.rate_hz, latency_s=cal.latency_s,
                                    ttl_s=args.ttl_s, dead_reckoned=True)
        svc.need("reset", type="pose6d", edge=(mounts.WORLD, args.reset_frame),
                 where="frequency_hz >= 1", prefer="latency_s", on_sample=live.on_reset)
        svc.start()
        log.info("accel-rig: %d accelerometers from %s at %g Hz", cal.layout.count,
                 source.name, args.rate_hz)
        for item in source.samples():
            if stop.is_set():
                break
            if isinstance(item, ValueError):
                live._count("bad input line", item)
                continue
            live.process(*item)
        else:
            log.info("accel-rig: input %s ended", source.name)
    log.info("accel-rig: %s", dict(live.counts))
    return 0


PLUGIN = ServicePlugin(
    name="accel-rig",
    help="MARVIN's six-accelerometer inertial tracker (seed 003 ch. 4): publishes each "
         "sample's accelerations (accel_raw, with the rig geometry and calibration as "
         "attributes) and the dead-reckoned pose of marvin/accel_rig in ivy/world since the "
         "last absolute pose (need 'reset'). Input: the simulated rig (default), a CSV replay "
         "or a serial line, with a calibration file; '--calibrate' writes one.",
    add_arguments=add_arguments,
    run=run,
)
