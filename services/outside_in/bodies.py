"""Rigid bodies of markers and their identification in a cloud of 3D points.

A body is its markers' positions in its own frame.  Finding it among triangulated points
(markers of every body, ghosts, reflections) is the sub-structure search Dorfmüller-Ulhaas
§2 calls NP-complete; with 4-5 markers an interpretation tree pruned by the body's
pairwise distances (its *distance signature*) is fast: marker k is given a point only if
its distances to the points already given match the body's within the tolerance, or is
declared missing (occluded) while enough markers can still be found.  The best
interpretation has the most markers, then the smallest distance misfit; one whose runner-up
with as many markers fits nearly as well is ambiguous (a symmetric body) and refused.
When the filter predicts a pose the tracker does not search at all: it looks for each
marker near its predicted image (``tracker``).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path

import numpy as np

from agent.errors import UmaError

Array = np.ndarray


@dataclass(frozen=True)
class RigidBody:
    """A named body: marker positions (n, 3) in its own frame, metres."""

    name: str
    markers: Array
    distances: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        m = np.asarray(self.markers, float)
        if m.ndim != 2 or m.shape[1] != 3 or not 3 <= len(m) <= 12 or not np.all(
                np.isfinite(m)):
            raise UmaError(f"body {self.name!r}: markers must be 3 to 12 finite (x, y, z) "
                           f"positions, got shape {m.shape}")
        d = np.linalg.norm(m[:, None] - m[None], axis=2)
        close = np.min(d[np.triu_indices(len(m), 1)])
        if close < 0.01:
            raise UmaError(f"body {self.name!r}: two markers are {close * 1e3:.1f} mm apart "
                           f"(at least 10 mm are needed to tell their images apart)")
        object.__setattr__(self, "markers", m)
        object.__setattr__(self, "distances", d)

    @property
    def signature(self) -> Array:
        """The sorted pairwise distances."""
        return np.sort(self.distances[np.triu_indices(len(self.markers), 1)])


def load_bodies(path: str | Path) -> list[RigidBody]:
    """Bodies from a TOML file: ``[[body]] name = "wand"  markers = [[x, y, z], ...]``."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise UmaError(f"bodies file {path} does not exist") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UmaError(f"bodies file {path} is not valid TOML: {exc}") from None
    tables = data.get("body")
    if not isinstance(tables, list) or not tables:
        raise UmaError(f"bodies file {path}: no [[body]] tables")
    bodies = []
    for i, t in enumerate(tables):
        if not isinstance(t, dict) or not isinstance(t.get("name"), str):
            raise UmaError(f"bodies file {path}: body #{i + 1} needs a name")
        try:
            markers = np.array(t.get("markers"), float)
        except (TypeError, ValueError):
            raise UmaError(f"bodies file {path}: body {t['name']!r} markers must be a list of "
                           f"[x, y, z] numbers") from None
        bodies.append(RigidBody(t["name"], markers))
    names = [b.name for b in bodies]
    if len(set(names)) != len(names):
        raise UmaError(f"bodies file {path}: body names repeat: {names}")
    return bodies


def dump_bodies(bodies: list[RigidBody]) -> str:
    """The TOML text ``load_bodies`` reads."""
    out = []
    for b in bodies:
        rows = ", ".join("[" + ", ".join(f"{x:.6f}" for x in m) + "]" for m in b.markers)
        out.append(f'[[body]]\nname = "{b.name}"\nmarkers = [{rows}]\n')
    return "\n".join(out)


def distinguishable(a: RigidBody, b: RigidBody, noise_m: float) -> bool:
    """Whether no 3-marker part of one body matches a part of the other within noise:
    the identification needs at least three markers, so bodies must differ there."""
    tol = 4.0 * noise_m
    return not any(_triangle_matches(a, tri, b, tol)
                   for tri in combinations(range(len(a.markers)), 3))


def _triangle_matches(a: RigidBody, tri: tuple[int, int, int], b: RigidBody,
                      tol: float) -> bool:
    pts = a.markers[list(tri)]
    return identify(b, pts, tol, min_markers=3) is not None


@dataclass(frozen=True)
class Identification:
    """Which point each marker is (-1: not found), and the misfit of the distances."""

    points: tuple[int, ...]
    misfit_m: float
    #: the markers that every near-equal assignment gave the same point (``identify``'s
    #: ``agreed``), the rest of the best one's left out
    agreed_only: bool = False

    @property
    def found(self) -> int:
        return sum(k >= 0 for k in self.points)


def identify(body: RigidBody, points: Array, tolerance_m: float, min_markers: int = 3,
             exclude: set[int] | frozenset[int] = frozenset(),
             views: list[frozenset] | None = None,
             agreed: bool = False) -> Identification | None:
    """The body's markers among ``points`` (m, 3), or None when not found or ambiguous.
    ``views`` (per point, the blobs it came from): two markers never share a blob.  With
    ``agreed``, an ambiguous search gives the markers that every near-equal assignment
    gave the same point, when there are ``min_markers`` of them: two markers whose images
    run together in one camera triangulate to two points off by millimetres, each of which
    fits either marker about as well, while the body's other markers are found alike."""
    P = np.asarray(points, float).reshape(-1, 3)
    n = len(body.markers)
    D = np.linalg.norm(P[:, None] - P[None], axis=2)
    allowed = [i for i in range(len(P)) if i not in exclude]
    best: list[tuple[int, float, tuple[int, ...]]] = []
    chosen: list[int] = []

    def extend(k: int, misfit: float) -> None:
        found = sum(c >= 0 for c in chosen)
        if found + (n - k) < min_markers:
            return
        if k == n:
            best.append((found, misfit, tuple(chosen)))
            return
        for i in allowed:
            if i in chosen or (views is not None and any(
                    j >= 0 and views[i] & views[j] for j in chosen)):
                continue
            err = 0.0
            for l, j in enumerate(chosen):
                if j < 0:
                    continue
                e = abs(D[i, j] - body.distances[k, l])
                if e > tolerance_m:
                    break
                err += e * e
            else:
                chosen.append(i)
                extend(k + 1, misfit + err)
                chosen.pop()
        chosen.append(-1)
        extend(k + 1, misfit)
        chosen.pop()

    extend(0, 0.0)
    if not best:
        return None
    top = max(b[0] for b in best)
    cands = sorted((b for b in best if b[0] == top), key=lambda b: b[1])
    pairs = top * (top - 1) / 2
    rms = np.sqrt(cands[0][1] / pairs)
    rivals = [c for c in cands[1:] if np.sqrt(c[1] / pairs) < max(3.0 * rms, 0.3 * tolerance_m)]
    if not rivals:
        return Identification(cands[0][2], float(rms))
    if not agreed:
        return None
    common = tuple(i if all(c[2][m] == i for c in rivals) else -1
                   for m, i in enumerate(cands[0][2]))
    if sum(i >= 0 for i in common) < min_markers:
        return None
    return Identification(common, float(rms), agreed_only=True)



def body_from_points(name: str, frames: list[Array], tolerance_m: float = 0.003,
                     reach_m: float = 0.4) -> tuple[RigidBody, float]:
    """A body from a few seconds of its markers held still: each frame's triangulated
    points (k, 3); the points found in most frames, averaged.  The body's frame is the
    world's axes at the markers' centroid.  Returns the body and the markers' scatter
    (m, rms over frames), the noise its distances are known to."""
    frames = [np.asarray(f, float).reshape(-1, 3) for f in frames if len(f)]
    if not frames:
        raise UmaError(f"body {name!r}: no markers were seen")
    clusters: list[list[Array]] = []
    for pts in frames:
        for x in pts:
            for c in clusters:
                if np.linalg.norm(np.mean(c, axis=0) - x) < tolerance_m:
                    c.append(x)
                    break
            else:
                clusters.append([x])
    steady = [np.array(c) for c in clusters if len(c) > len(frames) / 2]
    if steady:
        # a reflection seen by two cameras triangulates to a steady point too, but not
        # next to the body: keep what lies within a body's reach of the points' median
        centre = np.median([c.mean(axis=0) for c in steady], axis=0)
        steady = [c for c in steady if np.linalg.norm(c.mean(axis=0) - centre) < reach_m]
    if len(steady) < 3:
        raise UmaError(f"body {name!r}: {len(steady)} markers were seen in most of the "
                       f"{len(frames)} frames; three at least must be, held still")
    markers = np.array([c.mean(axis=0) for c in steady])
    scatter = float(np.sqrt(np.mean([np.mean(np.sum((c - c.mean(axis=0)) ** 2, axis=1))
                                     for c in steady])))
    return RigidBody(name, markers - markers.mean(axis=0)), scatter
