"""``uma eval fusion --from FILE.mcap``: the fusion service's filter on a recording's inputs.

Offline tuning: the recorded optical poses (``pose6d`` of ``ivy/world -> marvin/laser_rig``)
and raw accelerometer samples (``accel_raw`` of ``*/* -> marvin/accel_rig``, whose ability
attributes carry the rig's calibration) go, in the order the recorder received them, into
the same :class:`services.fusion.service.LiveFusion` the service runs, as fast as the CPU
allows.  The rig mountings come from the recorded static edges (``uma/R/agent/A/static``)
or, failing those, from static ground-truth abilities.  Nothing depends on the wall clock,
so two runs give identical figures.

The live fusion's own output, when recorded, is evaluated the same way (``recorded_live``),
and the replay at the live output's instants (``replayed_at_live_times``): the two agree
where the live filter kept up with its inputs.  When the recording holds the simulator's
ground truth (a non-static ``pose6d`` ability of
``ivy/world -> X`` with ``ground_truth: true``; ``uma demo --record`` publishes it as
``alice/head_truth``), every fused pose after ``warmup_s`` is compared with the truth
interpolated at its time (an SRG measured edge: slerp and linear).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from agent.errors import UmaError
from agent.record import layout
from agent.record.reader import Message, Recording, read
from agent.record.statics import decode_statics
from agent.srg import Graph
from agent.srg import geometry as geo
from schemas.codec import decode_measurement
from schemas.models import Ability
from services import frames
from services.figures import error_stats
from services.fusion.service import LiveFusion
from services.fusion.state import MODEL_FLOOR

WARMUP_S = 3.0
_TRUTH = "truth"


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


def replay(path: str, horizon_s: float | None = None,
           warmup_s: float = WARMUP_S) -> dict[str, Any]:
    """Run the fusion on the recording at ``path``; the figures (module docstring).
    ``horizon_s`` None: the recorded fusion's own (its ability's ``predicted_s``, else 0)."""
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
    out: list[tuple[int, np.ndarray, np.ndarray]] = []
    fusion = LiveFusion(horizon_s, MODEL_FLOOR,
                        publish=lambda t, p, q, cov: out.append((t, np.array(p), np.array(q))))
    for rig, setter in ((frames.LASER_RIG, fusion.on_optical_mount),
                        (frames.ACCEL_RIG, fusion.on_accel_mount)):
        p, q = mounts[rig]
        setter(_Pose(p, q))
    inputs = sorted([(m.log_ns, 0, i, m) for i, m in enumerate(optical_msgs)]
                    + [(m.log_ns, 1, i, m) for i, m in enumerate(accel_msgs)],
                    key=lambda x: x[:3])
    for _, kind, _, msg in inputs:
        m = decode_measurement(msg.data)
        m.attributes = (optical if kind == 0 else accel).attributes
        (fusion.on_optical if kind == 0 else fusion.on_accel)(m)
    figures: dict[str, Any] = {
        "from": path, "inputs": {"optical": len(optical_msgs), "accel": len(accel_msgs)},
        "fused_poses": len(out), "dropped": dict(fusion.dropped), "damage": rec.damage}
    live = _recorded_output(rec)
    figures["replayed"] = _against_truth(rec, out, out[0][0] if out else 0, warmup_s)
    figures["recorded_live"] = _against_truth(rec, live, out[0][0] if out else 0, warmup_s)
    # the same instants as the live output: equal figures where the live filter kept up
    live_times = {t for t, _, _ in live}
    figures["replayed_at_live_times"] = _against_truth(
        rec, [o for o in out if o[0] in live_times], out[0][0] if out else 0, warmup_s)
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
    ``first_ns`` (the replay's first pose, so live and replayed cover the same span)."""
    truth, msgs = _data(rec, _is_truth)
    if truth is None or not msgs or not out:
        return {"ground_truth": None}
    samples = [decode_measurement(m.data) for m in msgs]
    span_s = (samples[-1].t_ns - samples[0].t_ns) / 1e9
    g = Graph(buffer_s=span_s + 10.0, max_extrapolation_s=0.0)
    for s in samples:
        g.add_measurement(frames.WORLD, _TRUTH, s.t_ns, s.position, s.quaternion)
    start = first_ns + int(warmup_s * 1e9)
    ep, er = [], []
    for t, p, q in out:
        if t < start or not samples[0].t_ns <= t <= samples[-1].t_ns:
            continue
        r = g.pose(frames.WORLD, _TRUTH, at=t)
        e_p, e_r = geo.pose_error(p, q, r.position, r.quaternion)
        ep.append(float(e_p))
        er.append(float(e_r))
    return {"ground_truth": f"{truth.edge[0]} -> {truth.edge[1]}", "evaluated": len(ep),
            "position_error_mm": error_stats(ep, 1e3),
            "orientation_error_deg": error_stats(er, 180.0 / math.pi)}
