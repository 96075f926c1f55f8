"""Edge attributes (Klinker, Bauer 2005, §1.3.2) and how they aggregate along a path.

An edge carries ``latency_s``, ``frequency_hz``, ``confidence`` [0, 1], ``pos_std_m``,
``rot_std_rad`` (or a full 6x6 ``covariance``), ``ttl_s``, ``cost`` and ``static``.
A path's attributes are what an error function ranks: latencies and costs add up, the
update rate is the slowest edge's, confidences multiply (independent detections), the time
to live is the shortest, and the covariance is propagated through the chain (first order,
see :mod:`agent.geometry`); ``accuracy`` is the trace of that propagated covariance.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError

#: attributes an edge may carry
EDGE_ATTRIBUTES = ("latency_s", "frequency_hz", "confidence", "pos_std_m", "rot_std_rad",
                   "covariance", "ttl_s", "cost", "static")
#: attributes of a path, the names an error expression may use
PATH_ATTRIBUTES = ("hops", "latency_s", "frequency_hz", "confidence", "pos_std_m",
                   "rot_std_rad", "accuracy", "ttl_s", "cost", "static")
#: the error functions whose best local paths a supernode summary describes (the built-in
#: ones of :mod:`agent.srg.errorfn`)
SUMMARY_ERRORS = ("hops", "latency", "accuracy", "confidence", "cost")

_NONNEGATIVE = ("latency_s", "pos_std_m", "rot_std_rad", "cost")
_POSITIVE = ("frequency_hz", "ttl_s")


def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise InvalidInputError(f"attribute {name}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise InvalidInputError(f"attribute {name}: must be finite, got {v!r}")
    return v


def check_attributes(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """Validated, normalised copies of the given edge attributes (``None`` values dropped).

    Unknown names are refused so that a typo (``latency=``) never silently ranks a path.
    """
    unknown = sorted(set(attrs) - set(EDGE_ATTRIBUTES))
    if unknown:
        raise InvalidInputError(f"unknown edge attribute(s) {', '.join(unknown)}; known: "
                                f"{', '.join(EDGE_ATTRIBUTES)}")
    out: dict[str, Any] = {}
    for name, value in attrs.items():
        if value is None:
            continue
        if name == "static":
            if not isinstance(value, (bool, np.bool_)):
                raise InvalidInputError(f"attribute static: expected true/false, got {value!r}")
            out[name] = bool(value)
        elif name == "covariance":
            out[name] = geo.check_covariance(value, "attribute covariance")
        else:
            v = _number(name, value)
            if name in _NONNEGATIVE and v < 0:
                raise InvalidInputError(f"attribute {name}: must be >= 0, got {v:g}")
            if name in _POSITIVE and v <= 0:
                raise InvalidInputError(f"attribute {name}: must be > 0, got {v:g}")
            if name == "confidence" and not 0.0 <= v <= 1.0:
                raise InvalidInputError(f"attribute confidence: must be in [0, 1], got {v:g}")
            out[name] = v
    return out


def same_attributes(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Equality that compares covariance matrices by value."""
    if a.keys() != b.keys():
        return False
    for k, v in a.items():
        w = b[k]
        if isinstance(v, np.ndarray) or isinstance(w, np.ndarray):
            if not np.array_equal(v, w):
                return False
        elif v != w:
            return False
    return True


def nominal_covariance(attrs: Mapping[str, Any], position: Any) -> np.ndarray | None:
    """The 6x6 covariance an edge's attributes describe at a pose with this translation."""
    cov = attrs.get("covariance")
    if cov is not None:
        return cov
    return geo.covariance_from_std(position, attrs.get("pos_std_m"), attrs.get("rot_std_rad"))


def aggregate(edge_attrs: Sequence[Mapping[str, Any]], position: Any,
              covariance: np.ndarray | None) -> dict[str, Any]:
    """Attributes of a path from its edges' attributes and its propagated covariance.

    ``position`` is the translation of the composed pose; it turns the SE(3) covariance
    into per-axis position and rotation standard deviations.
    """
    return {**path_constants(edge_attrs), **uncertainty(position, covariance)}


def path_constants(edge_attrs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The attributes of a path that its edges' attributes alone decide (a query plan
    computes them once, not at every answer)."""
    freq = [a["frequency_hz"] for a in edge_attrs
            if not a.get("static") and "frequency_hz" in a]
    ttl = [a["ttl_s"] for a in edge_attrs if "ttl_s" in a]
    confidence = 1.0
    for a in edge_attrs:
        confidence *= a.get("confidence", 1.0)
    return {
        "hops": len(edge_attrs),
        "latency_s": sum(a.get("latency_s", 0.0) for a in edge_attrs),
        "frequency_hz": min(freq) if freq else math.inf,
        "confidence": confidence,
        "ttl_s": min(ttl) if ttl else math.inf,
        "cost": sum(a.get("cost", 0.0) for a in edge_attrs),
        "static": all(a.get("static", False) for a in edge_attrs),
    }


def uncertainty(position: Any, covariance: np.ndarray | None) -> dict[str, float]:
    """``pos_std_m``, ``rot_std_rad`` and ``accuracy`` (the trace) of a path's covariance."""
    if covariance is None:
        return {"pos_std_m": 0.0, "rot_std_rad": 0.0, "accuracy": 0.0}
    pos_trace, rot_trace, trace = geo.decoupled_traces(position, covariance)
    return {"pos_std_m": math.sqrt(max(pos_trace, 0.0) / 3.0),
            "rot_std_rad": math.sqrt(max(rot_trace, 0.0) / 3.0),
            "accuracy": trace}


def combine(segments: Sequence[Mapping[str, Any]], position: Any,
            covariance: np.ndarray | None) -> dict[str, Any]:
    """Attributes of a route made of segments (paths) whose attributes are already aggregated.

    The same rules as :func:`aggregate`, with ``hops`` summed; used by the planner that
    joins the segments of several agents.
    """
    edges = [dict(s) for s in segments]
    out = aggregate(edges, position, covariance)
    out["hops"] = sum(int(s.get("hops", 1)) for s in segments)
    freq = [s["frequency_hz"] for s in segments if not s.get("static")]
    out["frequency_hz"] = min(freq) if freq else math.inf
    return out
