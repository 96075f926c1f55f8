"""Edge points across a decoded tag's thin border, from a model of its blurred image.

Seen steeply or from afar, a tag's one-cell black border is 1-2.5 px wide across a side,
no wider than the optics' blur: the image across that side is not a step between two
levels but the blurred sum of the border, the code cells behind it (black or white, as
the tag's code says) and the print's white margin with whatever lies beyond it.  Where a
white cell follows the border its darkest sample is lifted and a level-crossing edge
point moves outwards; where the margin ends a cell or two outside, the other way.  Once
the tag is decoded its cell layout is known, so that image can be modelled instead:

* the tag's cells from the current quad (a homography from the tag's cell coordinates to
  the image, the side turned to the top), each sample's depth inside the side (px) and
  where it lies along it; the code cells of the first ``ROWS`` rows behind the border
  blended along the side by the blur (a Gaussian blur of a cell is a product of two
  edge functions);
* across the side, ``black + (white - black) * (margin + code cells) + (beyond - black) *
  beyond the margin``, each term a difference of normal CDFs of the sample's depth
  against the lines between the cells, over the blur ``sigma``;
* fitted to the profiles across all four sides by Gauss-Newton (Levenberg's damping, a
  step kept only where it lowers the misfit): per profile its edge's offset along the
  side's normal; per tag the print's black and white, the blur (estimated from the
  tag's own profiles: whatever the lens, focus, pixels and motion give: no kernel is
  assumed) and the margin's width in cells (a printed tag's is whatever the sheet
  gives); per side the level beyond the margin.  The offsets are eliminated profile by
  profile (a Schur complement): a step solves one 8x8 system per tag.  The tag's wider
  sides, whose crossings are sound, lend the fit their clean levels and blur.

The fitted offsets are the side's edge points; the line fits, the corners and their
covariance follow as for any side (:func:`services.fiducials.edges.refine`).
"""

from __future__ import annotations

import functools
from typing import Any

import cv2
import numpy as np

from agent.runtime import compiled_twin

#: code rows behind the border that the model includes (deeper ones lie beyond the
#: profiles' reach and the blur)
ROWS = 2
#: samples per profile, over ``SPREAD`` cells each way of the side
STEPS = 15
SPREAD = 2.1
ITERATIONS = 4
#: the blur (px) and margin width (cells) the fit starts from, and their bounds
SIGMA_START_PX = 0.8
SIGMA_BOUNDS_PX = (0.25, 3.0)
MARGIN_START = 1.0
MARGIN_BOUNDS = (0.3, 20.0)
#: Levenberg's damping at the start, relative to the normal matrix's diagonal
DAMPING = 1e-3
#: samples closer than this (px) to the tag's neighbouring sides are not modelled: inside
#: an acute corner of the tag's image a profile leaves the tag through its neighbour
CORNER_CLEARANCE_PX = 2.0
#: a fitted offset is trusted where its profile's residuals' RMS is under this share of
#: the side's contrast and it moved less than a cell
MAX_RMS_SHARE = 0.25

_T = np.linspace(-SPREAD, SPREAD, STEPS)
_SQRT_2PI = np.sqrt(2 * np.pi)


def code_cells(dictionary: cv2.aruco.Dictionary) -> np.ndarray:
    """Every tag's cells (ids, modules, modules) in ``dictionary``, 1 for white: its
    code's bits (OpenCV's rows and columns, as the detected corners turn them) inside
    the one-cell black border."""
    size = dictionary.markerSize
    bits = [cv2.aruco.Dictionary.getBitsFromByteList(dictionary.bytesList[i:i + 1], size)
            for i in range(len(dictionary.bytesList))]
    return np.pad(np.asarray(bits, np.float64), ((0, 0), (1, 1), (1, 1)))


def fit_offsets(gray: np.ndarray, quads: np.ndarray, cells: np.ndarray,
                fractions: np.ndarray, across: np.ndarray, start: np.ndarray,
                ) -> tuple[np.ndarray, np.ndarray]:
    """For ``n`` tags ``quads`` (n, 4, 2, distorted pixels, OpenCV's corner order) whose
    cells are ``cells`` (n, m, m, 1 white), their cells ``across`` (n, 4) px wide across
    each side: the offsets (n, 4, k) px, outwards along each side's normal, of its edge
    from the points at ``fractions`` (k, 1) of the side, fitted to ``gray`` from the
    crossings ``start`` (n, 4, k); and whether each is trusted."""
    n = len(quads)
    reach = across.reshape(-1, 1)
    obs, s0, step, cw, mask = _profiles(gray, quads, cells, fractions, reach)
    flat = obs.reshape(n, -1)
    g = np.concatenate([flat.min(1)[:, None], flat.max(1)[:, None],
                        np.tile([SIGMA_START_PX, MARGIN_START], (n, 1)),
                        obs[..., -1].mean(-1).reshape(n, 4)], axis=1)
    e = np.clip(start.reshape(4 * n, -1), -reach, reach)
    lam = np.full(n, DAMPING)
    r, d_e, d_g = _residuals(obs, s0 + e[..., None], step, cw, _per_side(g), mask)
    cost = np.einsum("uki,uki->u", r, r).reshape(n, 4).sum(1)
    for _ in range(ITERATIONS):
        e_try, g_try = _step(e, g, r, d_e, d_g, lam)
        tried = _residuals(obs, s0 + e_try[..., None], step, cw, _per_side(g_try), mask)
        cost_try = np.einsum("uki,uki->u", tried[0], tried[0]).reshape(n, 4).sum(1)
        better = cost_try < cost
        lam = np.where(better, lam / 3, lam * 8)
        g, cost = np.where(better[:, None], g_try, g), np.where(better, cost_try, cost)
        side_better = np.repeat(better, 4)
        e = np.where(side_better[:, None], e_try, e)
        r, d_e, d_g = (np.where(side_better.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)
                       for new, old in zip(tried, (r, d_e, d_g), strict=True))
    rms = np.sqrt(np.einsum("uki,uki->uk", r, r) / np.maximum(mask.sum(-1), 1))
    ok = np.isfinite(e) & (np.abs(e) < reach) \
        & (rms < MAX_RMS_SHARE * np.repeat(np.abs(g[:, 1:2] - g[:, :1]), 4, axis=0)) \
        & mask[..., STEPS // 2 - 3:STEPS // 2 + 4].all(-1)
    return np.where(ok, e, 0.0).reshape(n, 4, -1), ok.reshape(n, 4, -1)


def crossing_bias(quads: np.ndarray, cells: np.ndarray, sides: np.ndarray,
                  fractions: np.ndarray, across: np.ndarray, offsets: np.ndarray,
                  own: np.ndarray) -> np.ndarray:
    """How far (u, k) px, outwards, the code's cells behind ``u`` sides move the
    mid-level crossings of the profiles at ``fractions`` (k, 1) of each side, against
    those of an average code (half its cells white): side ``sides`` (u, 0-3) of the tag
    ``quads`` (u, 4, 2, OpenCV's corner order) whose cells are ``cells`` (u, m, m, 1
    white), about ``across`` (u,) px wide across the side; each profile sampled at
    ``offsets`` (u, I) px along the side's outward normal and crossed at its own middle
    (where ``own``, (u,)) or at the middle of the print's black and white.

    Across a thin border a white cell behind it lifts the profile's darkest sample and
    the blur carries some of its white across the border: the crossing moves.  Both
    follow from the blurred print: black 0, the white margin 1, and ``ROWS`` code rows
    behind the border at their white shares in the same sum of normal CDFs as
    :func:`_residuals`, at the blur the fit starts from (``SIGMA_START_PX``: a webcam's
    optics, its pixels' area and the profiles' bilinear sampling), the profile crossed
    as the edge points are.  Where each row lies behind a point of the side, and how
    wide the cells are there, comes from the quad's homography (a steep tag's cells are
    slanted parallelograms: the cell behind a point is not the one beside it, and near
    an acute corner the row reaches the white margin beyond the neighbouring side); each
    row's cells are blended along the side by the blur.  The margin outside the side
    itself is left out: it moves every code's crossings alike (the tag looks smaller or
    larger as a whole), what is subtracted is the code's own part."""
    m = cells.shape[-1]
    each = np.arange(len(sides))[:, None]
    rolled = quads[each, _ROLL[sides]]  # the side on top
    at_row, at_col = _behind(m)
    rows = cells[each[..., None], at_row[sides], at_col[sides]]  # (u, ROWS, m)
    side = rolled[:, 1] - rolled[:, 0]
    normal = side[:, ::-1] * [1.0, -1.0] / np.hypot(side[:, :1], side[:, 1:])
    depth = (np.arange(ROWS + 1) + 0.5) * across[:, None]  # (u, ROWS + 1)
    pts = (rolled[:, None, 0] + fractions * side[:, None])[:, :, None, :] \
        - depth[:, None, :, None] * normal[:, None, None, :]  # (u, k, ROWS + 1, 2)
    _, step, a, along_step = _tag_coordinates(rolled, pts, m)
    if NATIVE is not None:
        c = np.ascontiguousarray
        crossed = np.empty((2, *step.shape[:2]))
        NATIVE.code_crossings(c(rows, np.float64), c(a[..., 1:]), c(along_step[..., 1:]),
                              c(step[..., 0]), c(offsets, np.float64), c(own, np.uint8),
                              SIGMA_START_PX, _PAGE_A, _PAGE_B, crossed)
        return crossed[0] - crossed[1]
    edge_cdf = normal_cdf((np.arange(m + 1.0) - a[..., 1:, None])
                    * (along_step[..., 1:] / SIGMA_START_PX)[..., None])  # (u, k, ROWS, m + 1)
    # beyond the tag's neighbouring sides (a slanted row reaches them near an acute
    # corner) lies the white margin; an average code has half its cells white between
    # the border's black ones
    average = np.zeros_like(rows)
    average[..., 1:-1] = 0.5
    white = np.einsum("vurc,ukrc->vukr", np.stack([rows, average]),
                      edge_cdf[..., 1:] - edge_cdf[..., :-1]) \
        + (edge_cdf[..., 0] + 1 - edge_cdf[..., -1])[None]  # (2, u, k, ROWS)
    width = step[..., 0, None, None]  # the border's cells across, px (u, k, 1, 1)
    s = offsets[:, None, None, :]  # (u, 1, 1, I)
    cdf = normal_cdf((s + np.arange(1.0, ROWS + 2)[:, None] * width) / SIGMA_START_PX)
    profile = normal_cdf(s[..., 0, :] / SIGMA_START_PX) \
        + (white[..., None] * (cdf[..., 1:, :] - cdf[..., :-1, :])).sum(-2)  # (2, u, k, I)
    centre = profile.shape[-1] // 2
    local = (profile[..., :centre + 1].min(-1) + profile[..., centre:].max(-1)) / 2
    level = np.where(own[:, None], local, 0.5)[..., None]
    crossed = _crossing(profile - level, s[..., 0, :])
    return crossed[0] - crossed[1]


#: the compiled twin of :func:`crossing_bias` once its points are placed (``_kernels.c``;
#: tests set it to None to run the numpy code)
NATIVE: Any = compiled_twin("services.fiducials._kernels", "UMA_FIDUCIALS_PURE_PYTHON")


@functools.cache
def _behind(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Where (row, column; (4, ROWS, m) each) in a tag's cells (m, m) the ``ROWS`` rows
    behind side s lie, along the side: the rows of the cells turned by s quarter turns
    (``np.rot90``), as :func:`_profiles` turns them."""
    r, j = np.arange(1, ROWS + 1)[:, None], np.arange(m)[None, :]
    last = m - 1
    rows = np.broadcast_arrays(r, j + 0 * r, last - r, last - j + 0 * r)
    cols = np.broadcast_arrays(j + 0 * r, last - r, last - j + 0 * r, r)
    return np.stack(rows), np.stack(cols)


def _crossing(d: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Where the profiles ``d`` (..., I, less their levels) sampled at ``s`` (..., I)
    rise through zero, nearest the middle (linear between samples; 0 where none does)."""
    lo, hi = d[..., :-1], d[..., 1:]
    rising = (lo < 0) & (hi >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        at = np.where(rising, s[..., :-1] + lo / (lo - hi) * (s[..., 1:] - s[..., :-1]), np.inf)
    near = np.take_along_axis(at, np.argmin(np.abs(at), axis=-1)[..., None], -1)[..., 0]
    return np.where(np.isfinite(near), near, 0.0)


def _profiles(gray: np.ndarray, quads: np.ndarray, cells: np.ndarray, fractions: np.ndarray,
              reach: np.ndarray) -> tuple[np.ndarray, ...]:
    """The profiles (4 n, k, I) across the tags' sides, ``STEPS`` samples over ``SPREAD``
    cells (``reach``, (4 n, 1) px each) either way, and per sample its depth inside the
    side (px), px per cell across it, the code rows' white shares (ROWS, 4 n, k, I) and
    whether it is modelled (not near the neighbouring sides)."""
    n, m = len(quads), cells.shape[-1]
    # side s of a tag is the top side (corners 0 -> 1) of its quad rolled by s, whose cells
    # are the tag's turned by s quarter turns
    rolled = quads[:, _ROLL].reshape(-1, 4, 2)  # (4 n, 4, 2)
    views = np.stack([np.rot90(cells, s, axes=(1, 2)) for s in range(4)], axis=1)
    side = rolled[:, 1] - rolled[:, 0]
    normal = side[:, ::-1] * [1.0, -1.0] / np.hypot(side[:, :1], side[:, 1:])
    pts = (rolled[:, None, 0] + fractions * side[:, None])[:, :, None, :] \
        + (reach * _T)[:, None, :, None] * normal[:, None, None, :]  # (4 n, k, I, 2)
    obs = cv2.remap(gray, pts[..., 0].astype(np.float32).reshape(1, -1),
                    pts[..., 1].astype(np.float32).reshape(1, -1), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE).reshape(pts.shape[:-1]).astype(np.float64)
    depth, step, along, along_step = _tag_coordinates(rolled, pts, m)
    # the code rows' cells blended along the side by the blur (at the starting blur: the
    # fit hardly moves it)
    edge_cdf = normal_cdf((np.arange(m + 1.0) - along[..., None])
                    * (along_step / SIGMA_START_PX)[..., None])
    cw = np.einsum("urc,ukic->ruki", views.reshape(4 * n, m, m)[:, 1:ROWS + 1],
                   edge_cdf[..., 1:] - edge_cdf[..., :-1])
    clear = np.minimum(along, m - along) * along_step
    return obs, depth * step, step, cw, (clear >= CORNER_CLEARANCE_PX).astype(np.float64)


def _per_side(g: np.ndarray) -> np.ndarray:
    """The tags' parameters (n, 8: black, white, blur, margin, beyond each side) as each
    side's (4 n, 5)."""
    shared = np.repeat(g[:, :4], 4, axis=0)
    return np.concatenate([shared, g[:, 4:].reshape(-1, 1)], axis=1)


_ROLL = (np.arange(4)[:, None] + np.arange(4)) % 4  # side s: corners s, s + 1, ...


def normal_cdf(z: np.ndarray) -> np.ndarray:
    """The standard normal CDF to within 2e-4 (the tanh form of Page 1977), five times
    faster than ``scipy.special.ndtr``: the fit evaluates some thousands per side and
    step, and 2e-4 of a tag's contrast is far below the sensor's noise."""
    return 0.5 + 0.5 * np.tanh(z * (_PAGE_A + _PAGE_B * z * z))


_PAGE_A = np.sqrt(2 / np.pi)
_PAGE_B = 0.044715 * _PAGE_A


def _tag_coordinates(quads: np.ndarray, pts: np.ndarray, m: int,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per sample (u, k, I): its depth inside the quad's top side in cells, px per cell
    across that side, its position along it in cells, px per cell along it; from the
    homography that takes the tag's cell coordinates to ``quads`` (u, 4, 2)."""
    square = np.float32([[0, 0], [m, 0], [m, m], [0, m]])
    h = np.stack([cv2.getPerspectiveTransform(q.astype(np.float32), square)
                  for q in quads])[:, None, None]  # image -> cells, (u, 1, 1, 3, 3)
    x, y = pts[..., 0], pts[..., 1]
    w = h[..., 2, 0] * x + h[..., 2, 1] * y + h[..., 2, 2]
    a = (h[..., 0, 0] * x + h[..., 0, 1] * y + h[..., 0, 2]) / w
    d = (h[..., 1, 0] * x + h[..., 1, 1] * y + h[..., 1, 2]) / w
    # the lengths of their gradients (cells per px)
    ga = np.hypot(h[..., 0, 0] - a * h[..., 2, 0], h[..., 0, 1] - a * h[..., 2, 1]) / np.abs(w)
    gd = np.hypot(h[..., 1, 0] - d * h[..., 2, 0], h[..., 1, 1] - d * h[..., 2, 1]) / np.abs(w)
    return d, 1 / gd, a, 1 / ga


def _residuals(obs: np.ndarray, s: np.ndarray, step: np.ndarray, cw: np.ndarray,
               g: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model's misfit (u, k, I) to the profiles ``obs`` at depths ``s`` px (``step``
    px per cell, ``cw`` (ROWS, u, k, I) the code rows' white shares) for the sides'
    parameters ``g`` (u, 5: black, white, blur, margin, beyond), masked, and its
    derivatives by the depth (the edge offset) and by the parameters (u, k, I, 5)."""
    black, white, sigma, margin, back = (g[:, i, None, None] for i in range(5))
    rows = np.arange(1.0, ROWS + 2)[:, None, None, None]
    z = np.concatenate([np.stack([-s, -(s + margin * step)]), s - rows * step]) / sigma
    cdf = normal_cdf(z)
    pdf = np.exp(-0.5 * z * z) / _SQRT_2PI
    code = cw * (cdf[2:-1] - cdf[3:])
    shares = cdf[0] - cdf[1] + code.sum(0)
    beyond = cdf[1]
    contrast, rise = white - black, back - black
    r = (black + contrast * shares + rise * beyond - obs) * mask
    # d/ds of normal_cdf(+-s / sigma) is +-pdf / sigma (the first two terms fall with s);
    # d/dsigma of normal_cdf(z) is -z pdf / sigma
    code_pdf = (cw * (pdf[2:-1] - pdf[3:])).sum(0)
    d_s = (contrast * (code_pdf - pdf[0] + pdf[1]) - rise * pdf[1]) * (mask / sigma)
    zpdf = z * pdf
    code_zpdf = (cw * (zpdf[2:-1] - zpdf[3:])).sum(0)
    d_sigma = -(contrast * (zpdf[0] - zpdf[1] + code_zpdf) + rise * zpdf[1]) / sigma
    d_margin = (white - back) * pdf[1] * step / sigma
    d_g = np.stack([1 - shares - beyond, shares, d_sigma, d_margin, beyond], axis=-1)
    return r, d_s, d_g * mask[..., None]


def _step(e: np.ndarray, g: np.ndarray, r: np.ndarray, d_e: np.ndarray, d_g: np.ndarray,
          lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One damped Gauss-Newton step for the offsets ``e`` (4 n, k) and the tags'
    parameters ``g`` (n, 8) from the residuals ``r`` (4 n, k, I) and their derivatives
    (``d_g`` by each side's five), the offsets eliminated profile by profile."""
    u, k, steps = r.shape
    n = u // 4
    side_lam = np.repeat(lam, 4)
    h_ee = np.einsum("uki,uki->uk", d_e, d_e) * (1 + side_lam[:, None]) + 1e-12
    h_eg = (d_e[..., None, :] @ d_g)[..., 0, :]  # (u, k, 5)
    b_e = np.einsum("uki,uki->uk", d_e, r)
    flat = d_g.reshape(u, k * steps, 5)
    x = h_eg / np.sqrt(h_ee)[..., None]
    # each side's Schur complement of its offsets, then assembled over its tag's
    # parameters: four shared, one of its own
    schur = (np.swapaxes(flat, 1, 2) @ flat - np.swapaxes(x, 1, 2) @ x).reshape(n, 4, 5, 5)
    rhs = ((r.reshape(u, 1, -1) @ flat)[:, 0]
           - np.einsum("ukp,uk->up", h_eg, b_e / h_ee)).reshape(n, 4, 5)
    A = np.zeros((n, 8, 8))
    A[:, :4, :4] = schur[:, :, :4, :4].sum(1)
    A[:, :4, 4:] = np.swapaxes(schur[:, :, :4, 4], 1, 2)
    A[:, 4:, :4] = schur[:, :, 4, :4]
    A[:, _OWN, _OWN] = schur[:, :, 4, 4]
    b = np.concatenate([rhs[:, :, :4].sum(1), rhs[:, :, 4]], axis=1)
    A[:, _DIAG, _DIAG] *= 1 + lam[:, None]
    A[:, _DIAG, _DIAG] += 1e-9
    dg = -np.linalg.solve(A, b[..., None])[..., 0]
    de = -(b_e + np.einsum("ukp,up->uk", h_eg, _per_side(dg))) / h_ee
    g = g + dg
    g[:, 2] = np.clip(g[:, 2], *SIGMA_BOUNDS_PX)
    g[:, 3] = np.clip(g[:, 3], *MARGIN_BOUNDS)
    return e + de, g


_OWN = np.arange(4, 8)
_DIAG = np.arange(8)
