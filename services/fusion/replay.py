"""``uma eval fusion --from FILE.mcap``: the fusion service's filter on a recording's inputs.

Offline tuning: the recorded optical poses (``pose6d`` of ``ivy/world -> marvin/laser_rig``)
and raw accelerometer samples (``accel_raw`` of ``*/* -> marvin/accel_rig``, whose ability
attributes carry the rig's calibration) go, in the order of their own sample times, into
the same :class:`services.fusion.service.LiveFusion` the service runs, as fast as the CPU
allows.  The rig mountings come from the recorded static edges (``uma/R/agent/A/static``)
or, failing those, from static ground-truth abilities.  Nothing depends on the wall clock,
so two runs give identical figures.  Sample-time order, not the recorder's receive order:
on a loaded host the recorder receives the laser's poses late by its own delays, not by
the fusion's, and the filter would drop what it sees as older than its history.

With ``display_calibration`` (the laser tracker's calibration file, whose walls are not in
the recording) the replay runs in dot mode, as ``uma demo`` does by default, and also feeds
the recorded laser dots (``points3d`` on the optical edge).

The live fusion's own output, when recorded, is evaluated the same way (``recorded_live``),
and the replay at the live output's instants (``replayed_at_live_times``), both from the
warm-up after the later of the two filters' starts: the two agree where the live filter
kept up with its inputs.  When the recording holds the simulator's
ground truth (a non-static ``pose6d`` ability of
``ivy/world -> X`` with ``ground_truth: true``; ``uma demo --record`` publishes it as
``alice/head_truth``), every fused pose after ``warmup_s`` is compared with the truth
interpolated at its time (linear and slerp, as the SRG interpolates a measured edge).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.errors import UmaError
from agent.record import Message, Recording, decode_statics, layout, read
from schemas.codec import decode_measurement
from schemas.models import Ability
from services import frames
from services.figures import error_stats
from services.fusion.dots import load_walls
from services.fusion.service import LiveFusion
from services.fusion.state import MODEL_FLOOR

WARMUP_S = 3.0


def _data(rec: Recording, want: Any) -> tuple[Ability | None, list[Message]]:
    """The first data channel whose ability satisfies ``want``, and its messages."""
    for ch in sorted(rec.channels.values(), key=lambda c: c.topic):
        ability = layout.ability_of(ch.metadata)
        if ability is not None and want(ability):
            return ability, [m for m in rec.messages if m.channel.id == ch.id]
    return None, []


def _is_optical(a: Ability) -> bool:
    return a.type == "pose6d" and a.edge == (frames.WORLD, frames.LASER_RIG) \
        and not a.attributes.model_extra.get("ground_truth")


def _is_dots(a: Ability) -> bool:
    return a.type == "points3d" and a.edge == (frames.WORLD, frames.LASER_RIG)


def _is_accel(a: Ability) -> bool:
    return a.type == "accel_raw" and a.edge is not None and a.edge[1] == frames.ACCEL_RIG


def _is_truth(a: Ability) -> bool:
    return (a.type == "pose6d" and a.edge is not None and a.edge[0] == frames.WORLD
            and not a.attributes.static and bool(a.attributes.model_extra.get("ground_truth")))


def mountings(rec: Recording) -> dict[str, tuple[list[float], list[float]]]:
    """``child rig -> (p, q)`` of the edges ``alice/head -> rig`` the recording holds."""
    found: dict[str, tuple[list[float], list[float]]] = {}
    for m in rec.messages:
        if m.channel.metadata.get("uma.kind") == layout.STATIC:
            for e in decode_statics(m.data)["edges"]:
                if e["parent"] == frames.HEAD:
                    found.setdefault(e["child"], (e["p"], e["q"]))
    for rig in (frames.LASER_RIG, frames.ACCEL_RIG):
        if rig not in found:
            _, msgs = _data(rec, lambda a, rig=rig: a.type == "pose6d" and a.attributes.static
                            and a.edge == (frames.HEAD, rig))
            if msgs:
                m = decode_measurement(msgs[0].data)
                found[rig] = (m.position.tolist(), m.quaternion.tolist())
    return found


def replay(path: str, horizon_s: float | None = None, warmup_s: float = WARMUP_S,
           display_calibration: str | None = None) -> dict[str, Any]:
    """Run the fusion on the recording at ``path``; the figures (module docstring).
    ``horizon_s`` None: the recorded fusion's own (its ability's ``predicted_s``, else 0);
    ``display_calibration``: dot mode with that file's walls."""
    rec = read(path)
    if horizon_s is None:
        horizon_s = _recorded_horizon(rec)
    optical, optical_msgs = _data(rec, _is_optical)
    accel, accel_msgs = _data(rec, _is_accel)
    if optical is None or accel is None:
        raise UmaError(f"{path}: the fusion's inputs are not recorded (need pose6d "
                       f"{frames.WORLD} -> {frames.LASER_RIG} and accel_raw -> "
                       f"{frames.ACCEL_RIG})")
    mounts = mountings(rec)
    missing = [r for r in (frames.LASER_RIG, frames.ACCEL_RIG) if r not in mounts]
    if missing:
        raise UmaError(f"{path}: no recorded mounting {frames.HEAD} -> {', '.join(missing)} "
                       "(static edges or ground-truth static abilities)")
    dots, dots_msgs = _data(rec, _is_dots) if display_calibration else (None, [])
    if display_calibration and dots is None:
        raise UmaError(f"{path}: dot mode, but no laser dots are recorded (points3d "
                       f"{frames.WORLD} -> {frames.LASER_RIG})")
    out: list[tuple[int, np.ndarray, np.ndarray]] = []
    fusion = LiveFusion(horizon_s, MODEL_FLOOR,
                        publish=lambda t, p, q, cov: out.append((t, np.array(p), np.array(q))),
                        walls=None if display_calibration is None
                        else load_walls(display_calibration))
    for rig, setter in ((frames.LASER_RIG, fusion.on_optical_mount),
                        (frames.ACCEL_RIG, fusion.on_accel_mount)):
        p, q = mounts[rig]
        setter(_Pose(p, q))
    streams = ((optical, optical_msgs, fusion.on_optical), (accel, accel_msgs, fusion.on_accel),
               (dots, dots_msgs, fusion.on_dots))
    inputs = sorted(((m.publish_ns, kind, i, m) for kind, (_, msgs, _) in enumerate(streams)
                     for i, m in enumerate(msgs)), key=lambda x: x[:3])
    for _, kind, _, msg in inputs:
        ability, _, on_sample = streams[kind]
        m = decode_measurement(msg.data)
        m.attributes = ability.attributes
        on_sample(m)
    figures: dict[str, Any] = {
        "from": path, "optical_update": "dots" if display_calibration else "pose",
        "inputs": {"optical": len(optical_msgs), "accel": len(accel_msgs),
                   "dots": len(dots_msgs)},
        "fused_poses": len(out), "dropped": dict(fusion.dropped), "damage": rec.damage}
    live = _recorded_output(rec)
    first = out[0][0] if out else 0
    figures["replayed"] = _against_truth(rec, out, first, warmup_s)
    # the live filter starts later than the replay (it waits for its mountings from the
    # SRG), from other optical poses: both are compared from the warm-up after the later
    # start, where both have forgotten where they started and agree but for what the live
    # filter got late and dropped
    both = max(first, live[0][0]) if live else first
    figures["recorded_live"] = _against_truth(rec, live, both, warmup_s)
    live_times = {t for t, _, _ in live}
    figures["replayed_at_live_times"] = _against_truth(
        rec, [o for o in out if o[0] in live_times], both, warmup_s)
    return figures


def _is_fused(a: Ability) -> bool:
    return a.type == "pose6d" and a.edge == (frames.WORLD, frames.HEAD) \
        and bool(a.attributes.model_extra.get("fused"))


def _recorded_horizon(rec: Recording) -> float:
    fused, _ = _data(rec, _is_fused)
    value = fused.attributes.model_extra.get("predicted_s") if fused is not None else None
    return float(value) if isinstance(value, int | float) else 0.0


def _recorded_output(rec: Recording) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The live fusion's own poses as recorded (``fused: true`` on the fused edge)."""
    _, msgs = _data(rec, _is_fused)
    poses = [decode_measurement(m.data) for m in msgs]
    return [(m.t_ns, m.position, m.quaternion) for m in poses]


class _Pose:
    def __init__(self, p: list[float], q: list[float]) -> None:
        self.position, self.quaternion = p, q


def _against_truth(rec: Recording, out: list[tuple[int, np.ndarray, np.ndarray]],
                   first_ns: int, warmup_s: float) -> dict[str, Any]:
    """Errors of ``out`` against the recorded ground truth from ``warmup_s`` after
    ``first_ns``."""
    truth, msgs = _data(rec, _is_truth)
    if truth is None or not msgs or not out:
        return {"ground_truth": None}
    samples = sorted((decode_measurement(m.data) for m in msgs), key=lambda m: m.t_ns)
    T = np.array([m.t_ns for m in samples], dtype=np.int64)
    P = np.array([m.position for m in samples])
    Q = np.array([m.quaternion for m in samples])
    start = first_ns + int(warmup_s * 1e9)
    kept = [o for o in out if o[0] >= start and T[0] <= o[0] < T[-1]]
    ep: list[float] = []
    er: list[float] = []
    if kept:
        ts = np.array([o[0] for o in kept], dtype=np.int64)
        i = np.searchsorted(T, ts, side="right") - 1
        alpha = (ts - T[i]) / (T[i + 1] - T[i])
        p_true, q_true = geo.interpolate(P[i], Q[i], P[i + 1], Q[i + 1], alpha)
        e_p, e_r = geo.pose_error(np.array([o[1] for o in kept]),
                                  np.array([o[2] for o in kept]), p_true, q_true)
        ep, er = e_p.tolist(), e_r.tolist()
    return {"ground_truth": f"{truth.edge[0]} -> {truth.edge[1]}", "evaluated": len(ep),
            "position_error_mm": error_stats(ep, 1e3),
            "orientation_error_deg": error_stats(er, 180.0 / math.pi)}
