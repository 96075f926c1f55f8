"""Matching marker images between cameras and triangulating them, outliers rejected.

Observations are undistorted normalised coordinates (``RigCamera.normalize``); distances
are reported in pixels (normalised distance times the camera's focal length) so that one
tolerance fits every camera.  The matching follows Dorfmüller-Ulhaas §2 (epipolar
constraint between camera images, then triangulation) with the multi-camera step that
makes it robust: every pair of blobs on corresponding epipolar lines of two cameras is
triangulated, the point is looked for in every other camera, each candidate is refined
on all the views that support it (the worst view dropped while it is further than the
tolerance), and candidates are taken greedily, most views and smallest residual first, no
blob used twice.  Points seen by two cameras only are kept but marked: where epipolar
lines cross, two cameras alone can triangulate ghosts, which the body identification
(``bodies``) tells from markers by the body's distances.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from services.outside_in.rig import RigCamera

Array = np.ndarray


@dataclass(frozen=True)
class Point3:
    """A triangulated point and the blobs it came from."""

    X: Array                       # (3,) world
    views: tuple[tuple[int, int], ...]  # (camera index, blob index), by camera
    rms_px: float                  # reprojection error over its views

    @property
    def cameras(self) -> tuple[int, ...]:
        return tuple(c for c, _ in self.views)


def triangulate_dlt(P: Array, x: Array) -> Array:
    """Linear (DLT) triangulation of ``n`` points seen in ``v`` views each.

    ``P`` (n, v, 3, 4) projection matrices of normalised coordinates, ``x`` (n, v, 2)
    observations; returns (n, 3).  The smallest right singular vector of the stacked
    ``x P_3 - P_1``, ``y P_3 - P_2`` rows (Hartley & Zisserman §12.2)."""
    P = np.asarray(P, float)
    x = np.asarray(x, float)
    A = np.concatenate([x[..., 0:1] * P[..., 2, :] - P[..., 0, :],
                        x[..., 1:2] * P[..., 2, :] - P[..., 1, :]], axis=-2)
    _, _, vt = np.linalg.svd(A)
    h = vt[..., -1, :]
    return h[..., :3] / h[..., 3:4]


def refine_point(R: Array, t: Array, obs: Array, focal: Array, X0: Array,
                 iterations: int = 4) -> tuple[Array, Array, Array]:
    """Gauss-Newton on the reprojection error of one point in pixels.

    ``R`` (v, 3, 3), ``t`` (v, 3) world -> camera, ``obs`` (v, 2) normalised, ``focal``
    (v,) pixels per normalised unit.  Returns the point, each view's residual (px) and
    the (2 v, 3) Jacobian in pixels (``sigma^2 (J^T J)^-1`` is the point's covariance)."""
    X = np.asarray(X0, float).copy()
    J = np.zeros((2 * len(R), 3))
    res = np.full(len(R), np.inf)
    for _ in range(iterations):
        r, J = _point_residual(R, t, obs, focal, X)
        if r is None:
            break
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        X += step
        if np.max(np.abs(step)) < 1e-9:
            break
    r, J = _point_residual(R, t, obs, focal, X)
    if r is not None:
        res = np.hypot(r[0::2], r[1::2])
    return X, res, J


def _point_residual(R: Array, t: Array, obs: Array, focal: Array,
                    X: Array) -> tuple[Array | None, Array]:
    xc = R @ X + t
    z = xc[:, 2]
    if np.any(z <= 1e-6):
        return None, np.zeros((2 * len(R), 3))
    proj = xc[:, :2] / z[:, None]
    r = ((proj - obs) * focal[:, None]).reshape(-1)
    J = (R[:, :2, :] - proj[:, :, None] * R[:, 2:3, :]) * (focal / z)[:, None, None]
    return r, J.reshape(-1, 3)


@dataclass(frozen=True)
class MatchParams:
    """Tolerances of matching and triangulation (pixels)."""

    epipolar_px: float = 2.0      # blob distance to the other camera's epipolar line
    support_px: float = 2.0       # reprojection distance that counts a view in
    max_rms_px: float = 1.5       # a point's reprojection rms after refinement
    min_depth_m: float = 0.2


def match_and_triangulate(cameras: list[RigCamera], observations: list[Array],
                          params: MatchParams = MatchParams(),
                          keep_ambiguous: bool = False) -> list[Point3]:
    """3D points from normalised observations of each camera (a list of (n_i, 2)).

    With ``keep_ambiguous`` the two-view candidates are all kept, even those sharing a
    blob: two cameras alone cannot tell a marker from a ghost where epipolar lines cross,
    the body identification can (its points must not share a blob, ``identify``'s
    ``views``)."""
    R = np.array([c.R_cw for c in cameras])
    t = np.array([c.t_cw for c in cameras])
    f = np.array([c.focal_px for c in cameras])
    obs = [np.asarray(o, float).reshape(-1, 2) for o in observations]
    hypotheses: dict[tuple[tuple[int, int], ...], None] = {}
    for i, j in combinations(range(len(cameras)), 2):
        if len(obs[i]) == 0 or len(obs[j]) == 0:
            continue
        a, b = _epipolar_pairs(R, t, f, obs, i, j, params.epipolar_px)
        if len(a) == 0:
            continue
        P = np.stack([np.broadcast_to(cameras[i].projection, (len(a), 3, 4)),
                      np.broadcast_to(cameras[j].projection, (len(a), 3, 4))], axis=1)
        X = triangulate_dlt(P, np.stack([obs[i][a], obs[j][b]], axis=1))
        for views in _supports(R, t, f, obs, X, i, j, a, b, params):
            hypotheses.setdefault(views, None)
    points = [p for p in (_refined(R, t, f, obs, v, params) for v in hypotheses) if p]
    if not keep_ambiguous:
        return _greedy(points, R, t, f, obs, params)
    strong = _greedy([p for p in points if len(p.views) >= 3], R, t, f, obs, params)
    used = {v for p in strong for v in p.views}
    weak = [p for p in points if len(p.views) == 2 and not used & set(p.views)]
    return strong + weak


def _epipolar_pairs(R: Array, t: Array, f: Array, obs: list[Array], i: int, j: int,
                    tol_px: float) -> tuple[Array, Array]:
    """Index pairs (blob of i, blob of j) within ``tol_px`` of each other's epipolar line."""
    R_ij = R[j] @ R[i].T
    t_ij = t[j] - R_ij @ t[i]
    tx = np.array([[0, -t_ij[2], t_ij[1]], [t_ij[2], 0, -t_ij[0]], [-t_ij[1], t_ij[0], 0]])
    E = tx @ R_ij
    xi = np.hstack([obs[i], np.ones((len(obs[i]), 1))])
    xj = np.hstack([obs[j], np.ones((len(obs[j]), 1))])
    lj = xi @ E.T            # lines in j of each blob of i (ni, 3)
    li = xj @ E              # lines in i of each blob of j (nj, 3)
    alg = xj @ lj.T          # (nj, ni): x_j^T E x_i
    dj = np.abs(alg) / np.hypot(lj[:, 0], lj[:, 1])[None, :] * f[j]
    di = np.abs(alg) / np.hypot(li[:, 0], li[:, 1])[:, None] * f[i]
    b, a = np.nonzero(np.maximum(di, dj) < tol_px)
    return a, b


def _supports(R: Array, t: Array, f: Array, obs: list[Array], X: Array, i: int, j: int,
              a: Array, b: Array, p: MatchParams) -> list[tuple[tuple[int, int], ...]]:
    """Each candidate's views: its pair and the nearest blob within tolerance elsewhere."""
    views = [[(i, int(ai)), (j, int(bj))] for ai, bj in zip(a, b, strict=True)]
    xc_i = X @ R[i].T + t[i]
    xc_j = X @ R[j].T + t[j]
    ok = (xc_i[:, 2] > p.min_depth_m) & (xc_j[:, 2] > p.min_depth_m)
    for k in range(len(R)):
        if k in (i, j) or len(obs[k]) == 0:
            continue
        xc = X @ R[k].T + t[k]
        front = xc[:, 2] > p.min_depth_m
        proj = xc[:, :2] / np.where(front, xc[:, 2], 1.0)[:, None]
        d = np.linalg.norm(proj[:, None, :] - obs[k][None, :, :], axis=2) * f[k]
        best = np.argmin(d, axis=1)
        hit = front & (d[np.arange(len(X)), best] < p.support_px)
        for n in np.nonzero(hit)[0]:
            views[n].append((k, int(best[n])))
    return [tuple(sorted(v)) for v, good in zip(views, ok, strict=True) if good]


def _refined(R: Array, t: Array, f: Array, obs: list[Array],
             views: tuple[tuple[int, int], ...], p: MatchParams) -> Point3 | None:
    """The point of ``views`` refined, its worst view dropped while beyond tolerance."""
    views = tuple(views)
    while len(views) >= 2:
        cams = np.array([c for c, _ in views])
        o = np.array([obs[c][k] for c, k in views])
        P = np.concatenate([R[cams], t[cams][:, :, None]], axis=2)
        X0 = triangulate_dlt(P[None], o[None])[0]
        X, res, _ = refine_point(R[cams], t[cams], o, f[cams], X0)
        if not np.all(np.isfinite(res)):
            return None
        worst = int(np.argmax(res))
        if res[worst] <= p.support_px:
            rms = float(np.sqrt(np.mean(res ** 2)))
            return Point3(X, views, rms) if rms <= p.max_rms_px else None
        views = views[:worst] + views[worst + 1:]
    return None


def _greedy(points: list[Point3], R: Array, t: Array, f: Array, obs: list[Array],
            p: MatchParams) -> list[Point3]:
    """Most views first, then smallest residual; a candidate sharing a blob with a taken
    point keeps its other views if two or more remain."""
    queue = sorted(points, key=lambda q: (-len(q.views), q.rms_px))
    used: set[tuple[int, int]] = set()
    out: list[Point3] = []
    while queue:
        q = queue.pop(0)
        free = tuple(v for v in q.views if v not in used)
        if len(free) != len(q.views):
            if len(free) >= 2:
                again = _refined(R, t, f, obs, free, p)
                if again is not None:
                    queue.append(again)
                    queue.sort(key=lambda r: (-len(r.views), r.rms_px))
            continue
        used.update(q.views)
        out.append(q)
    return out
