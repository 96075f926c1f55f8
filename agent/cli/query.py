"""``uma query SOURCE TARGET``: the pose of TARGET in SOURCE's frame across the realm.

Opens a short-lived client (:class:`agent.sdk.client.Client`), plans a route over every agent's
supernode summary, asks the owning agents for their segments and prints the composed pose,
its covariance, the path and the path's attributes.  Unknown frames, unreachable pairs,
missing agents and edges without data at the requested time are errors (exit 1) that name
what was missing.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from agent.errors import InvalidInputError
from agent.result import PoseResult
from agent.runtime.session import sdk_mode
from agent.sdk.client import Client


def parse_at(text: str | None) -> int | None:
    """``--at``: None (latest common time), ``now``, or integer ns since the epoch."""
    if text is None:
        return None
    if text.strip().lower() == "now":
        return time.time_ns()
    try:
        value = int(text)
    except ValueError:
        raise InvalidInputError(f"--at {text!r}: expected integer nanoseconds since the epoch or "
                                "'now'") from None
    if value < 0:
        raise InvalidInputError(f"--at {value}: times are nanoseconds since the epoch, >= 0")
    return value


def format_result(source: str, target: str, r: PoseResult) -> str:
    """The answer for people: pose, time, path, attributes, standard deviations."""
    lines = [f"pose of {target} in {source}"
             + (f" at t={r.t_ns}" if r.t_ns is not None else " (static: valid at all times)"),
             "  position [m]:     " + " ".join(f"{x: .6f}" for x in r.position),
             "  quaternion xyzw:  " + " ".join(f"{x: .6f}" for x in r.quaternion),
             "  path:             " + " -> ".join(r.path)]
    if r.covariance is not None:
        std = np.sqrt(np.clip(np.diag(r.covariance), 0.0, None))
        lines.append("  std (xi) [m, rad]: " + " ".join(f"{x:.3g}" for x in std))
    if r.extrapolated_s:
        lines.append(f"  extrapolated:     {r.extrapolated_s:.6g} s")
    attrs = ", ".join(f"{k}={v:.6g}" if isinstance(v, float) and not math.isinf(v)
                      else f"{k}={v}" for k, v in r.attributes.items())
    lines.append(f"  attributes:       {attrs}")
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    at = parse_at(args.at)
    with Client(realm=args.realm, connect=args.connect, timeout=args.timeout) as client:
        if sdk_mode(None, args.connect) == "client":  # its agent's answer is the realm
            client.tracker.settle_s = 0.0
        r = client.pose(args.source, args.target, at=at, error=args.error)
    if args.json:
        print(json.dumps({"source": args.source, "target": args.target, **r.to_dict()}))
    else:
        print(format_result(args.source, args.target, r))
    return 0
