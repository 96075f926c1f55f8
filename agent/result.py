"""What a pose query returns."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from agent import geometry as geo


class PoseResult:
    """The pose of ``target`` in ``source``'s frame at ``t_ns``, and how it was obtained.

    ``position`` (3,), ``quaternion`` (4, xyzw), ``covariance`` (6x6 over the left SE(3)
    perturbation, or None when every edge is exact), ``path`` (frame ids source..target),
    ``edges`` (each edge used, with its direction), ``attributes`` (the path's aggregated
    attributes), ``extrapolated_s`` (the largest extrapolation of any edge; 0 when every
    edge was interpolated or static) and ``stamps`` (per measured edge the sample times
    used).  ``attributes`` is computed on first access: most hot-path callers never read it.
    """

    __slots__ = ("_attributes", "_make_attributes", "covariance", "edges", "extrapolated_s",
                 "path", "position", "quaternion", "stamps", "t_ns")

    def __init__(self, position: np.ndarray, quaternion: np.ndarray,
                 covariance: np.ndarray | None, path: list[str], edges: list[dict[str, Any]],
                 t_ns: int | None, extrapolated_s: float, stamps: list[tuple[int, int]],
                 attributes: dict[str, Any] | Callable[[], dict[str, Any]]) -> None:
        self.position = position
        self.quaternion = quaternion
        self.covariance = covariance
        self.path = path
        self.edges = edges
        self.t_ns = t_ns
        self.extrapolated_s = extrapolated_s
        self.stamps = stamps
        if callable(attributes):
            self._attributes = None
            self._make_attributes = attributes
        else:
            self._attributes = attributes
            self._make_attributes = None

    @property
    def attributes(self) -> dict[str, Any]:
        if self._attributes is None:
            self._attributes = self._make_attributes()
        return self._attributes

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous transform (maps target coordinates to source coordinates)."""
        return geo.to_matrix(self.position, self.quaternion)

    def to_dict(self) -> dict[str, Any]:
        """Plain lists and numbers (JSON- and msgpack-friendly; infinities become None)."""
        return {
            "t_ns": self.t_ns,
            "position": [float(x) for x in self.position],
            "quaternion": [float(x) for x in self.quaternion],
            "covariance": None if self.covariance is None else self.covariance.tolist(),
            "path": list(self.path),
            "edges": [dict(e) for e in self.edges],
            "attributes": finite_or_none(self.attributes),
            "extrapolated_s": self.extrapolated_s,
            "stamps": [list(s) for s in self.stamps],
        }

    def __repr__(self) -> str:
        p = ", ".join(f"{x:.4g}" for x in self.position)
        q = ", ".join(f"{x:.4g}" for x in self.quaternion)
        return (f"PoseResult({' -> '.join(self.path)} at t={self.t_ns}: p=[{p}] q=[{q}], "
                f"extrapolated {self.extrapolated_s:g} s)")


def finite_or_none(attrs: dict[str, Any]) -> dict[str, Any]:
    """Attributes with infinite numbers replaced by None (JSON has no infinity)."""
    return {k: (None if isinstance(v, float) and math.isinf(v) else v)
            for k, v in attrs.items()}
