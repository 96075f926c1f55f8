"""Error functions: what "best path" means for a query (Klinker, Bauer 2005, "Optimal paths").

Built-ins: ``hops``, ``latency`` (sum of latencies), ``cost`` (sum of costs), ``confidence``
(-log of the product of confidences) are additive over edges, so Dijkstra/Yen rank paths
exactly by them; ``accuracy`` (trace of the propagated covariance) and any expression over
path attributes (``latency_s + 10 * pos_std_m``, parsed by :mod:`schemas.expr`, never
``eval``) are path-level, evaluated on the aggregated attributes of candidate paths.
Every error function can score an already aggregated path (``path_value``), which is what
the cross-agent planner uses on the segments of supernode summaries.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from agent.attributes import PATH_ATTRIBUTES
from agent.srg.errors import BadErrorFunctionError
from schemas.expr import Expr, ExprError, parse

#: weight added per edge so that, among equally good paths, the shortest wins
TIE_BREAK = 1e-9


@dataclass(frozen=True)
class ErrorFunction:
    """A named error function; ``key`` identifies it in plan caches."""

    key: str
    additive: bool
    expr: Expr | None = None

    def edge_weight(self, attrs: Mapping[str, Any]) -> float:
        """Weight of one edge (additive functions only); ``inf`` excludes the edge."""
        if self.key == "hops":
            return 1.0
        if self.key == "latency":
            return attrs.get("latency_s", 0.0) + TIE_BREAK
        if self.key == "cost":
            return attrs.get("cost", 0.0) + TIE_BREAK
        if self.key == "confidence":
            c = attrs.get("confidence", 1.0)
            return -math.log(c) + TIE_BREAK if c > 0 else math.inf
        raise TypeError(f"error function {self.key!r} is path-level, not additive")

    def path_value(self, attrs: Mapping[str, Any]) -> float:
        """The error of a whole path from its aggregated attributes (lower is better)."""
        if self.key == "hops":
            return float(attrs["hops"])
        if self.key == "latency":
            return attrs["latency_s"] + TIE_BREAK * attrs["hops"]
        if self.key == "cost":
            return attrs["cost"] + TIE_BREAK * attrs["hops"]
        if self.key == "confidence":
            c = attrs["confidence"]
            return -math.log(c) + TIE_BREAK * attrs["hops"] if c > 0 else math.inf
        if self.key == "accuracy":
            return float(attrs["accuracy"])
        assert self.expr is not None
        try:
            value = self.expr.evaluate(attrs)
        except ExprError:
            return math.inf  # e.g. a division by zero on this path: rank it last
        return float(value)


BUILTIN = {
    "hops": ErrorFunction("hops", True),
    "latency": ErrorFunction("latency", True),
    "cost": ErrorFunction("cost", True),
    "confidence": ErrorFunction("confidence", True),
    "accuracy": ErrorFunction("accuracy", False),
}


def error_function(spec: str | ErrorFunction) -> ErrorFunction:
    """A built-in by name, or an expression over path attributes; ``BadErrorFunctionError`` else."""
    if isinstance(spec, ErrorFunction):
        return spec
    builtin = BUILTIN.get(spec) if type(spec) is str else None
    if builtin is not None:  # the common case, before the checks
        return builtin
    if not isinstance(spec, str) or not spec.strip():
        raise BadErrorFunctionError(f"error function must be a non-empty string, got {spec!r}")
    text = spec.strip()
    if text in BUILTIN:
        return BUILTIN[text]
    try:
        expr = parse(text, names=PATH_ATTRIBUTES)
    except ExprError as exc:
        raise BadErrorFunctionError(
            f"error function {text!r} is not one of {', '.join(BUILTIN)} nor a valid "
            f"expression over {', '.join(PATH_ATTRIBUTES)}: {exc}") from None
    if expr.is_predicate:
        raise BadErrorFunctionError(f"error function {text!r} is a condition (true/false); it must "
                               "be a number to minimise, e.g. 'latency_s + 10 * pos_std_m'")
    return ErrorFunction(f"expr:{text}", False, expr)
