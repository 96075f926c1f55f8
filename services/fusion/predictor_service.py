"""``uma service run predictor``: Dorfmüller-Ulhaas's predictor on any pose stream.

Need ``pose``: any ``pose6d`` ability on ``--source -> --target`` (by default the head of
any user in IVY).  Ability ``predicted``: the same motion predicted ``--horizon-ms`` ahead,
on the edge ``--source -> --output`` (default ``<target>_predicted``: a frame of its own,
so the predictor never matches its own output and a client chooses explicitly).  Each
sample is stamped with the time it predicts; ``predicted_s`` says how far ahead it looks.

Dorfmüller-Ulhaas: Dorfmüller-Ulhaas, *Robust Optical User Motion Tracking Using a Kalman
Filter*.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
from typing import Any

import numpy as np

from agent import Service
from agent.errors import InvalidInputError
from services.fusion.predictor import DorfmullerPredictor, PredictorConfig

log = logging.getLogger("uma.predictor")

#: process noise for human head motion (the figures of ``uma eval predictor``'s head run)
HEAD_MOTION = {"omega_walk": 20.0, "velocity_walk": 3.0, "accel_walk": 30.0,
               "initial_std": (5.0, 2.0, 10.0)}


class LivePredictor:
    """Need callback -> predictor -> publication; one thread (the SDK's dispatch)."""

    def __init__(self, horizon_s: float, point_std_m: float | None, publish: Any = None):
        self.horizon_s = horizon_s
        self.point_std_m = point_std_m
        self.publish = publish
        self.predictor: DorfmullerPredictor | None = None
        self.t0_ns: int | None = None
        self.refused = 0
        self.published = 0

    def on_pose(self, m: Any) -> None:
        if self.predictor is None:
            self.predictor = DorfmullerPredictor(PredictorConfig(
                point_std_m=self._noise(m.attributes), **HEAD_MOTION))
        if self.t0_ns is None:
            self.t0_ns = int(m.t_ns)
        try:
            self.predictor.update((int(m.t_ns) - self.t0_ns) * 1e-9, m.position, m.quaternion)
        except ValueError as exc:
            self.refused += 1
            if self.refused in (1, 10, 100, 1000):
                log.info("predictor: sample refused (%s); %d so far", exc, self.refused)
            return
        if self.predictor.ready and self.publish is not None:
            p, q = self.predictor.predict(self.horizon_s)
            self.publish(int(m.t_ns) + round(self.horizon_s * 1e9), p, q, None)
            self.published += 1

    def _noise(self, attributes: Any) -> float:
        if self.point_std_m is not None:
            return self.point_std_m
        pos = getattr(attributes, "pos_std_m", None) if attributes is not None else None
        if isinstance(attributes, dict):
            pos = attributes.get("pos_std_m")
        return float(pos) if pos else 1e-3


def run(args: argparse.Namespace, stop: threading.Event) -> int:

    if not (math.isfinite(args.horizon_ms) and 0 < args.horizon_ms <= 500):
        raise InvalidInputError(f"--horizon-ms must be within (0, 500], got {args.horizon_ms!r}")
    if args.point_std_m is not None and not (np.isfinite(args.point_std_m)
                                             and args.point_std_m > 0):
        raise InvalidInputError(f"--point-std-m must be positive, got {args.point_std_m!r}")
    output = args.output or f"{args.target}_predicted"
    if "*" in args.target:
        raise InvalidInputError("--target must be one frame (the output is a frame of its own), "
                                f"got the pattern {args.target!r}")
    live = LivePredictor(args.horizon_ms / 1e3, args.point_std_m)
    with Service(args.id, realm=args.realm, agent=args.agent, connect=args.connect,
                 listen=args.listen or None) as svc:
        out = svc.ability("predicted", type="pose6d", edge=(args.source, output),
                          predicted_s=args.horizon_ms / 1e3, latency_s=0.0)
        live.publish = out.publish
        svc.need("pose", type="pose6d", edge=(args.source, args.target), prefer="latency_s",
                 on_sample=live.on_pose)
        svc.start()
        log.info("predictor: %s -> %s predicted %.0f ms ahead as %s", args.source,
                 args.target, args.horizon_ms, output)
        while not stop.wait(1.0):
            pass
    return 0
