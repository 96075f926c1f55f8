"""The evaluation kernel of a compiled chain: interpolate its measured edges at ``t`` and
compose them with its constants, on plain floats.

A query over a few edges is dominated by per-call overhead, not arithmetic: numpy spends
about a microsecond per call on a 3- or 4-vector, where the float arithmetic of a whole
edge (lerp, slerp as ``q0 Exp(a Log(q0^-1 q1))`` with the log cached per sample pair, one
composition) is a few dozen operations.  So the kernel works on tuples of floats, and a
compiled twin (``agent/srg/_kernel.c``, built when a C compiler is there) does the same
operations in the same order; :data:`NATIVE` is the compiled one unless it was not built
or ``UMA_SRG_PURE_PYTHON=1`` is set.  Both are tested to agree.  The quaternion products
are ``agent.geometry.quat_product``, the one definition on floats: writing them out
would spare this fallback a call per product, which the compiled kernel, the one that
runs where it was built, does not make (docs/MEASUREMENTS.md).

``items`` is the chain in path order; each entry is either ``(pose,)``, a constant (a
folded run of static edges, already oriented), or ``(buffer, times, values, deltas,
buffer_ns, limit_s, forward)``, a measured edge with its buffer's lists (the compiled kernel
reads them directly) and how far it may be extrapolated.  A pose is ``(px, py, pz, qx, qy,
qz, qw)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from agent import geometry as geo
from agent.geometry import _SMALL_ANGLE, quat_product
from schemas.native import compiled_twin

Pose = tuple[float, float, float, float, float, float, float]
#: per measured edge, when asked for: (i0, i1, factor, interpolated pose as sampled)
EdgeValue = tuple[int, int, float, Pose]
#: largest extrapolation (s), sample times per measured edge, and, only when asked for
#: (else None), the per-edge values and the composed pose after each item (covariance
#: propagation maps each item's covariance with them)
Result = tuple[float, list[tuple[int, int]], list[EdgeValue] | None, list[Pose] | None]


def _log_between(v0: Sequence[float], v1: Sequence[float]) -> tuple[float, float, float]:
    """The rotation vector of ``q0^-1 q1`` (slerp's log), as ``geometry.quat_to_rotvec``."""
    x, y, z, w = quat_product((-v0[3], -v0[4], -v0[5], v0[6]), v1[3:])
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    s = math.sqrt(x * x + y * y + z * z)
    k = 2.0 / w if s < _SMALL_ANGLE else 2.0 * math.atan2(s, w) / s
    return x * k, y * k, z * k


def _interpolated(v0: Pose, v1: Pose, delta: tuple[float, float, float], a: float) -> Pose:
    """Lerp of the position, ``q0 Exp(a delta)`` of the rotation."""
    rx, ry, rz = delta[0] * a, delta[1] * a, delta[2] * a
    th = math.sqrt(rx * rx + ry * ry + rz * rz)
    k = 0.5 - th * th / 48.0 if th < _SMALL_ANGLE else math.sin(0.5 * th) / th
    return (v0[0] + (v1[0] - v0[0]) * a, v0[1] + (v1[1] - v0[1]) * a,
            v0[2] + (v1[2] - v0[2]) * a,
            *quat_product(v0[3:], (rx * k, ry * k, rz * k, math.cos(0.5 * th))))


def _inverse(v: Pose) -> Pose:
    """``T^-1``: the conjugate rotation and ``-R^T p``."""
    x, y, z, w = -v[3], -v[4], -v[5], v[6]
    px, py, pz = _rotate(x, y, z, w, v[0], v[1], v[2])
    return -px, -py, -pz, x, y, z, w


def _rotate(x: float, y: float, z: float, w: float, vx: float, vy: float, vz: float,
            ) -> tuple[float, float, float]:
    """``v + w t + u x t`` with ``t = 2 u x v`` (``geometry.quat_rotate``)."""
    tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
    return (vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz),
            vz + w * tz + (x * ty - y * tx))


def compose(a: Pose, b: Pose) -> Pose:
    """``A B``: ``p_a + R_a p_b`` and ``q_a q_b``."""
    rx, ry, rz = _rotate(a[3], a[4], a[5], a[6], b[0], b[1], b[2])
    return (a[0] + rx, a[1] + ry, a[2] + rz, *quat_product(a[3:], b[3:]))


def evaluate(t_ns: int, items: Sequence[tuple], want_edges: bool, p_out: np.ndarray,
             q_out: np.ndarray) -> Result:
    """The chain's pose at ``t_ns`` written into ``p_out`` (3) and ``q_out`` (4): the
    result's own arrays, so that no tuple is converted afterwards (the compiled kernel
    fills them through the buffer protocol).  Raises the buffer's error for an edge
    undefined at ``t_ns``."""
    acc: Pose | None = None
    extrapolated = 0.0
    stamps: list[tuple[int, int]] = []
    edges: list[EdgeValue] | None = [] if want_edges else None
    prefixes: list[Pose] | None = [] if want_edges else None
    for entry in items:
        if len(entry) == 1:
            value = entry[0]
        else:
            buf, times, values, deltas, _, limit, forward = entry
            i0, i1, a, ex = buf.bracket(t_ns, limit)
            value = values[i0]
            if i0 != i1:
                delta = deltas[i0]
                if delta is None:
                    delta = deltas[i0] = _log_between(value, values[i1])
                value = _interpolated(value, values[i1], delta, a)
            if ex > extrapolated:
                extrapolated = ex
            stamps.append((times[i0], times[i1]))
            if edges is not None:
                edges.append((i0, i1, a, value))
            if not forward:
                value = _inverse(value)
        acc = value if acc is None else compose(acc, value)
        if prefixes is not None:
            prefixes.append(acc)
    p_out[:] = acc[:3]
    q_out[:] = acc[3:]
    return extrapolated, stamps, edges, prefixes


def propagate(poses: list[Pose], covariances: list[np.ndarray]) -> np.ndarray:
    """``sum(Ad(M_i) C_i Ad(M_i)^T)``: each 6x6 covariance mapped by the adjoint of its pose
    and summed (a path's covariance).  Compiled with :data:`NATIVE` (a batched numpy form
    costs tens of numpy calls for the two or three terms of a route); numpy otherwise, or
    for covariances that are not 6x6 float64 arrays."""
    if NATIVE is not None and _PROPAGATE is not None:
        out = np.empty((6, 6))
        if _PROPAGATE(poses, covariances, out):
            return out
    M = np.array(poses)
    Ad = geo.adjoint(M[:, :3], M[:, 3:])
    return (Ad @ np.array(covariances, dtype=float) @ Ad.transpose(0, 2, 1)).sum(axis=0)


def _native() -> Callable[..., Result | None] | None:
    """The compiled kernel, or None (not built, built from older source, or
    ``UMA_SRG_PURE_PYTHON=1``).  It returns None where :func:`evaluate` would raise, so
    that the error comes from one place."""
    kernel = compiled_twin("agent.srg._kernel", "UMA_SRG_PURE_PYTHON")
    return None if kernel is None else kernel.evaluate


#: the compiled kernel in use (tests set it to None to run the pure-Python one)
NATIVE: Any = _native()
#: the compiled evaluation with the chain's covariance, used while :data:`NATIVE` is
#: (``plan.Chain`` takes it for uncertain chains)
NATIVE_COVARIANCE: Any = None if NATIVE is None else getattr(
    __import__("agent.srg._kernel", fromlist=["evaluate_covariance"]), "evaluate_covariance",
    None)
#: the compiled :func:`propagate`, used while :data:`NATIVE` is
_PROPAGATE: Any = None if NATIVE is None else getattr(
    __import__("agent.srg._kernel", fromlist=["propagate"]), "propagate", None)
