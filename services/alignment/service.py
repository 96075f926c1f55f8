"""``uma service run alignment``: two pose streams in, a calibrated static SRG edge out.

Online (``--a PARENT:CHILD --b PARENT:CHILD``): needs two ``pose6d`` streams of sensors
that move rigidly together, ``A: world_a -> sensor_a`` and ``B: world_b -> sensor_b``
(edge patterns may use ``*``).  It buffers the last ``--window-s`` seconds of both and,
once the motions are well conditioned (``--min-seconds`` of data, at least ``--min-pairs``
motion pairs rotating by ``--min-angle-deg`` or more, rotation axes spread by
``--min-spread-deg``), estimates the
time offset and X (``services.alignment.pipeline``); it publishes once the bootstrap
standard deviations are within ``--max-pos-std-mm`` / ``--max-rot-std-deg`` (else it keeps
collecting and tries again).  The result is published as the
static ``pose6d`` ability ``calibration`` on the edge ``sensor_a -> sensor_b`` (attributes
``static: true``, ``pos_std_m``, ``rot_std_rad``, the 21-float ``covariance``, residuals,
time offset, pair counts; re-published every second for late subscribers) and written to
``--output``, a TOML ``[[static]]`` fragment agents load at start.

Re-calibration: on request (a Zenoh query to ``uma/<realm>/svc/<agent>/<service>/
recalibrate``, see ``request_recalibration``), the buffers are emptied and the service
collects fresh motions (the mounting may have changed) before solving again; with
``--recalibrate-every S`` it also re-solves on its sliding window every S seconds.  A
request counts only on the service's exact key (a wildcard query would empty every
alignment service of the realm) and at most once per ``RECALIBRATE_MIN_S`` seconds (each
request throws the collected motions away); others are refused with the reason, counted
and logged rate-limited.

Offline (``--from-file CSV``): aligns recorded pose pairs (``services.alignment.records``
documents the columns), prints the result and writes ``--output``; no network.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from agent import Service
from agent import geometry as geo
from agent.errors import InvalidInputError, UmaError, UmaTimeoutError
from agent.protocol import keys
from agent.runtime import RateLimitedLog, guarded, open_session
from schemas.codec import pack_covariance, systematic_covariance
from services.alignment import records
from services.alignment.covariance import MIN_RESAMPLES
from services.alignment.pipeline import (
    AlignmentOptions,
    AlignmentResult,
    align_stations,
    align_streams,
)
from services.alignment.selection import DEFAULT_MIN_ANGLE_RAD, select_pairs
from services.alignment.solvers import AlignmentError, all_pairs, relative_motions
from services.alignment.timesync import PoseSeries

log = logging.getLogger("uma.alignment")
_log = RateLimitedLog(log)

STATIC_REPUBLISH_S = 1.0
#: re-calibration requests accepted at most once per this many seconds
RECALIBRATE_MIN_S = 5.0
_TICK_S = 0.2
#: seconds between attempts while the motions are not yet good enough
_RETRY_S = 2.0
#: stations examined by the readiness check (A's motions only: b moves rigidly with a)
_READINESS_STATIONS = 30
_FRAME = r"[A-Za-z0-9_.\-*]+(/[A-Za-z0-9_.\-*]+)*"


def parse_edge(text: str, option: str) -> tuple[str, str]:
    """``PARENT:CHILD`` (frame ids or patterns with ``*``) -> (parent, child)."""
    parts = text.split(":")
    if len(parts) != 2 or not all(re.fullmatch(_FRAME, p) for p in parts):
        raise UmaError(f"{option} {text!r}: expected PARENT:CHILD, e.g. "
                       "ivy/world:marvin/laser_rig (patterns may use *)")
    return parts[0], parts[1]


def recalibrate_key(realm: str, agent_id: str, service_id: str) -> str:
    """Where the service answers re-calibration requests."""
    return keys.service_token(realm, agent_id, service_id) + "/recalibrate"


def options_from(args: argparse.Namespace) -> AlignmentOptions:
    """The pipeline options of the command line (``ValueError`` names a bad one)."""
    for name in ("min_angle_deg", "min_spread_deg", "max_offset_ms", "window_s", "min_seconds",
                 "recalibrate_every", "max_pos_std_mm", "max_rot_std_deg"):
        value = getattr(args, name)
        if not math.isfinite(value) or value < 0:
            raise InvalidInputError(f"--{name.replace('_', '-')} must be a finite number >= 0, "
                                    f"got {value}")
    if not 0 < args.min_angle_deg < 90:
        raise InvalidInputError(f"--min-angle-deg must lie in (0, 90), got {args.min_angle_deg}")
    if args.min_pairs < 2:
        raise InvalidInputError(f"--min-pairs must be >= 2, got {args.min_pairs}")
    if args.bootstrap < MIN_RESAMPLES:
        raise InvalidInputError(f"--bootstrap must be >= {MIN_RESAMPLES} (a 6-dof covariance from "
                                f"fewer resamples has no unbiased inverse), got {args.bootstrap}")
    if args.offset_ms is not None and not math.isfinite(args.offset_ms):
        raise InvalidInputError(f"--offset-ms must be finite, got {args.offset_ms}")
    return AlignmentOptions(
        method=args.method,
        max_stations=args.max_stations, bootstrap=args.bootstrap,
        estimate_offset=args.offset_ms is None,
        offset_s=(args.offset_ms or 0.0) / 1e3, max_offset_s=args.max_offset_ms / 1e3,
        seed=args.seed)


def static_attributes(result: AlignmentResult) -> dict[str, Any]:
    """The ability attributes that carry the calibration's quality."""
    return {
        "static": True,
        "pos_std_m": result.pos_std_m,
        "rot_std_rad": result.rot_std_rad,
        "covariance": pack_covariance(result.covariance),
        "residual_rot_rad": result.residual_rot_rad,
        "residual_pos_m": result.residual_pos_m,
        "time_offset_s": float(result.time_offset_s),
        "pairs_inlier": result.n_inliers,
        "pairs_selected": result.n_selected,
        "method": result.method,
    }


# --------------------------------------------------------------------------- offline


def run_from_file(args: argparse.Namespace) -> int:
    """``--from-file``: align recorded pose pairs, print, write the calibration file."""
    (_, sensor_a), (_, sensor_b) = parse_edge(args.a, "--a"), parse_edge(args.b, "--b")
    _concrete(sensor_a, "--a")
    _concrete(sensor_b, "--b")
    options = options_from(args)
    a, b = records.read_pose_pairs(args.from_file)
    if args.stations:
        result = align_stations(a.position, a.quaternion, b.position, b.quaternion, options,
                                time_offset_s=options.offset_s)
    else:
        result = align_streams(a, b, options)
    records.write_calibration(args.output, result, sensor_a, sensor_b)
    summary = {"parent": sensor_a, "child": sensor_b, **result.summary(),
               "output": args.output}
    if args.json:
        print(json.dumps(summary))
    else:
        for key, value in summary.items():
            print(f"{key}: {value}")
    return 0


def _concrete(frame: str, option: str) -> None:
    if "*" in frame:
        raise UmaError(f"{option}: the sensor frame {frame!r} must be a concrete frame id "
                       "to name the calibrated edge")


# --------------------------------------------------------------------------- online


class StreamBuffer:
    """The last ``window_s`` seconds of one pose stream; thread-safe appends.

    Samples that are out of order, repeated, non-finite or not unit quaternions are
    dropped (counted, logged at most once per reason); a change of the stream's edge
    (the agent re-matched the need to another sensor) restarts the buffer.
    """

    def __init__(self, name: str, window_s: float) -> None:
        self.name = name
        self.window_ns = int(window_s * 1e9)
        #: (t_ns, position, quaternion, published covariance or None, its systematic part
        #: or None)
        self.samples: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray | None,
                                  np.ndarray | None]] = deque()
        self.edge: tuple[str, str] | None = None
        self.dropped: dict[str, int] = {}
        self._lock = threading.Lock()

    def add(self, m: Any) -> None:
        try:
            p = geo.check_vector(m.position, f"{self.name} position")
            q = geo.check_quaternion(m.quaternion, f"{self.name} quaternion")
            t = int(m.t_ns)
            held = systematic_covariance(m)
        except (TypeError, ValueError) as exc:
            self._drop(str(exc).split(":")[0], str(exc))
            return
        with self._lock:
            edge = tuple(m.edge) if m.edge is not None else None
            if edge != self.edge:
                if self.edge is not None:
                    log.info("%s: stream now %s -> %s; restarting its buffer", self.name,
                             *edge or ("?", "?"))
                self.samples.clear()
                self.edge = edge
            if self.samples and t <= self.samples[-1][0]:
                self._drop("out of order", f"{self.name}: sample at {t} ns not after "
                                           f"{self.samples[-1][0]} ns")
                return
            self.samples.append((t, p, q, getattr(m, "covariance", None), held))
            while self.samples and self.samples[0][0] < t - self.window_ns:
                self.samples.popleft()

    def _drop(self, reason: str, message: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1
        if self.dropped[reason] == 1:
            log.warning("%s (dropping such samples; counted in 'dropped')", message)

    def clear(self) -> None:
        with self._lock:
            self.samples.clear()

    def first_ns(self) -> int | None:
        """Time of the oldest buffered sample."""
        with self._lock:
            return self.samples[0][0] if self.samples else None

    def series(self, t0_ns: int) -> PoseSeries | None:
        """The buffer as seconds since ``t0_ns``, or None with fewer than 3 samples; with
        the published covariances when every sample had one (they go into X's, as the
        tracker's held error: ``pipeline.held_error_covariance``), and their systematic
        parts when every sample had one too (then only those are held)."""
        with self._lock:
            if len(self.samples) < 3:
                return None
            t = np.array([s[0] for s in self.samples], dtype=np.int64)
            p = np.array([s[1] for s in self.samples])
            q = np.array([s[2] for s in self.samples])
            c = [s[3] for s in self.samples]
            held = [s[4] for s in self.samples]
        cov = None if any(x is None for x in c) else np.array(c)
        held_part = None if cov is None or any(x is None for x in held) else np.array(held)
        return PoseSeries((t - t0_ns) / 1e9, p, q, self.name, cov, systematic=held_part)


def readiness(a: PoseSeries | None, b: PoseSeries | None, options: AlignmentOptions,
              min_pairs: int, min_spread_rad: float, min_seconds: float = 0.0,
              min_angle_rad: float = DEFAULT_MIN_ANGLE_RAD) -> tuple[bool, str]:
    """Whether the buffered motions condition X well enough to solve, and why not: enough
    of a's motions rotate by ``min_angle_rad`` (a fixed criterion of enough movement; the
    solver's selection then follows the noise)."""
    if a is None or b is None:
        return False, "waiting for both streams"
    overlap = min(a.t[-1], b.t[-1]) - max(a.t[0], b.t[0])
    # the offset search needs 10x its range (timesync.coarse_offset), plus a margin for the
    # stream ends
    needed = max((10 * options.max_offset_s if options.estimate_offset else 0.0) + 1.0,
                 min_seconds)
    if overlap < needed:
        return False, f"streams overlap {max(overlap, 0):.1f} s of the {needed:.1f} s needed"
    pick = np.unique(np.linspace(0, len(a) - 1, _READINESS_STATIONS).astype(int))
    motions = relative_motions(a.position[pick], a.quaternion[pick], a.position[pick],
                               a.quaternion[pick], all_pairs(len(pick)))
    sel = select_pairs(motions, min_angle_rad)
    if len(sel.index) < min_pairs:
        return False, (f"{len(sel.index)} of {min_pairs} motion pairs rotate by "
                       f"{math.degrees(min_angle_rad):.0f} deg or more: keep moving")
    if sel.axis_spread_rad < min_spread_rad:
        return False, (f"rotation axes spread {math.degrees(sel.axis_spread_rad):.0f} of "
                       f"{math.degrees(min_spread_rad):.0f} deg: rotate about other axes")
    return True, "ready"


class LiveAlignment:
    """The online service's state: buffers, readiness, solving, publishing, persisting."""

    def __init__(self, args: argparse.Namespace, options: AlignmentOptions) -> None:
        self.args = args
        self.options = options
        self.a = StreamBuffer("stream a", args.window_s)
        self.b = StreamBuffer("stream b", args.window_s)
        self.result: AlignmentResult | None = None
        self.edge: tuple[str, str] | None = None
        self.status = "waiting for both streams"
        self.requested = threading.Event()
        self.last_request = -math.inf
        self.refused = 0  # re-calibration requests refused (wrong key, too soon)
        self.last_solve = 0.0
        self.last_attempt = -math.inf

    def request(self) -> None:
        """Start over: forget the buffered motions, collect new ones, solve again."""
        self.last_request = time.monotonic()
        self.a.clear()
        self.b.clear()
        self.requested.set()

    def refusal(self, asked: str, key: str) -> str | None:
        """Why a re-calibration request on ``asked`` is refused (this service's key is
        ``key``), or None."""
        if asked != key:
            return f"{asked!r} is not this service's key {key!r} (wildcards are refused)"
        since = time.monotonic() - self.last_request
        if since < RECALIBRATE_MIN_S:
            return (f"a re-calibration was requested {since:.1f} s ago; at most one per "
                    f"{RECALIBRATE_MIN_S:g} s")
        return None

    def due(self) -> bool:
        """Whether to try solving now (first result, request, or periodic)."""
        now = time.monotonic()
        if self.result is None or self.requested.is_set():
            return now - self.last_attempt >= _RETRY_S
        every = self.args.recalibrate_every
        return every > 0 and now - self.last_solve >= every

    def try_solve(self) -> AlignmentResult | None:
        """Solve if the buffers are ready; the new result, or None (``status`` says why)."""
        if self.a.edge is None or self.b.edge is None:
            self.status = "waiting for both streams"
            return None
        firsts = [f for f in (self.a.first_ns(), self.b.first_ns()) if f is not None]
        t0 = min(firsts) if firsts else 0
        sa, sb = self.a.series(t0), self.b.series(t0)
        ready, self.status = readiness(sa, sb, self.options, self.args.min_pairs,
                                       math.radians(self.args.min_spread_deg),
                                       self.args.min_seconds,
                                       math.radians(self.args.min_angle_deg))
        if not ready:
            return None
        self.last_attempt = time.monotonic()
        try:
            result = align_streams(sa, sb, self.options)
        except (AlignmentError, ValueError) as exc:
            self.status = f"solve failed: {exc}"
            log.warning("alignment: %s", self.status)
            return None
        if (result.pos_std_m > self.args.max_pos_std_mm / 1e3
                or result.rot_std_rad > math.radians(self.args.max_rot_std_deg)):
            self.status = (f"std {result.pos_std_m * 1e3:.2f} mm / "
                           f"{math.degrees(result.rot_std_rad):.3f} deg not yet within "
                           f"{self.args.max_pos_std_mm} mm / {self.args.max_rot_std_deg} deg: "
                           "keep moving")
            log.info("alignment: %s", self.status)
            return None
        self.requested.clear()
        self.last_solve = time.monotonic()
        self.result, self.edge = result, (self.a.edge[1], self.b.edge[1])
        self.status = "calibrated"
        log.info("alignment: %s -> %s calibrated: %s", *self.edge, result.summary())
        return result


def run(args: argparse.Namespace, stop: threading.Event) -> int:
    if args.from_file:
        return run_from_file(args)

    a_edge, b_edge = parse_edge(args.a, "--a"), parse_edge(args.b, "--b")
    live = LiveAlignment(args, options_from(args))
    with Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect,
                 listen=args.listen or None) as svc:
        svc.need("a", type="pose6d", edge=a_edge, on_sample=live.a.add)
        svc.need("b", type="pose6d", edge=b_edge, on_sample=live.b.add)
        svc.start()
        key = recalibrate_key(svc.realm, svc.agent_id, svc.service_id)
        queryable = svc.session.declare_queryable(key, guarded(
            lambda q: _answer_request(q, live, key), f"alignment {key}", _log))
        try:
            _serve(svc, live, stop)
        finally:
            queryable.undeclare()
    return 0


def _serve(svc: Any, live: LiveAlignment, stop: threading.Event) -> None:
    """Solve when due and ready, publish the static edge, persist it.

    One ability per calibrated edge (``calibration``, then ``calibration_2``... if a need
    was re-matched to other sensors); a re-calibration updates its attributes.
    """
    outs: dict[tuple[str, str], Any] = {}
    out = None
    next_static = 0.0
    while not stop.is_set():
        if live.due():
            result = live.try_solve()
            if result is not None:
                attrs = static_attributes(result)
                out = outs.get(live.edge)
                if out is None:
                    name = "calibration" + (f"_{len(outs) + 1}" if outs else "")
                    out = outs[live.edge] = svc.ability(name, type="pose6d", edge=live.edge,
                                                        **attrs)
                else:
                    out.update(**attrs)
                _persist(live)
                next_static = 0.0
        if out is not None and live.result is not None and time.monotonic() >= next_static:
            out.publish(time.time_ns(), live.result.position, live.result.quaternion,
                        live.result.covariance)
            next_static = time.monotonic() + STATIC_REPUBLISH_S
        stop.wait(_TICK_S)


def _persist(live: LiveAlignment) -> None:
    try:
        records.write_calibration(live.args.output, live.result, *live.edge)
    except AlignmentError as exc:  # keep serving the edge; say why the file is missing
        log.error("alignment: %s", exc)


def _answer_request(query: Any, live: LiveAlignment, key: str) -> None:
    """Reply at once: the request is taken (the new result follows when motions allow) or
    refused (``LiveAlignment.refusal``: the reason, as an error reply)."""
    refused = live.refusal(str(query.key_expr), key)
    if refused is None:
        live.request()
    else:
        live.refused += 1
        _log.warning(f"alignment {key}", f"re-calibration refused: {refused} "
                     f"({live.refused} refused so far)")
    reply = {"ok": refused is None,
             "status": refused or "collecting new motions",
             "previous": None if live.result is None else live.result.summary()}
    try:
        query.reply(key, json.dumps(reply).encode())
    except Exception as exc:  # never raise into Zenoh's thread
        log.warning("alignment: cannot answer re-calibration request: %s", exc)


def request_recalibration(realm: str, agent_id: str, service_id: str = "alignment",
                          connect: list[str] | None = None, timeout: float = 2.0,
                          ) -> dict[str, Any]:
    """Ask a running alignment service to re-calibrate; its acknowledgement.

    A new session learns the service's queryable only after connecting, and a ``get`` that
    reaches no queryable returns at once: retry until ``timeout``.
    """

    session = open_session("peer", None, connect or [], realm,
                           require_connection=bool(connect))
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            left = max(deadline - time.monotonic(), 0.05)
            for reply in session.get(recalibrate_key(realm, agent_id, service_id),
                                     timeout=left):
                if reply.ok is not None:
                    return json.loads(reply.ok.payload.to_bytes())
            time.sleep(0.1)
    finally:
        session.close()
    raise UmaTimeoutError(f"alignment service {service_id!r} of agent {agent_id!r} did not "
                          f"answer within {timeout} s")


def recalibrate_command(args: argparse.Namespace) -> int:
    """``uma service recalibrate [SERVICE] --agent ID``: ``request_recalibration`` for people."""
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise InvalidInputError(f"--timeout must be positive seconds, got {args.timeout!r}")
    ack = request_recalibration(args.realm, args.agent, args.service_id, args.connect,
                                args.timeout)
    if ack.get("ok") is False:
        raise UmaError(f"{args.service_id} (agent {args.agent}) refused the request: "
                       f"{ack.get('status')}")
    if args.json:
        print(json.dumps(ack))
        return 0
    print(f"{args.service_id} (agent {args.agent}): {ack.get('status', ack)}")
    previous = ack.get("previous")
    print("  previous calibration: " + (", ".join(f"{k}={v}" for k, v in previous.items())
                                        if previous else "none yet"))
    return 0
