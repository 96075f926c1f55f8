"""Marker centres by fitting a ball's image to the pixels, weighted by their noise.

A retro-reflective ball images as a disk of uniform brightness blurred by the lens,
``m(x) = b + a erfc((|x - c| - r) / (sqrt 2 s)) / 2``.  The intensity-weighted centroid
(``blobs``) weighs every pixel by its distance from the centre, so the faint rim pixels,
nearly all read noise, pull on it as hard as the bright core; the maximum-likelihood
centre weighs each pixel by how much the model changes with the centre there over that
pixel's noise (shot noise of its signal and read noise).  On the simulated rig's isolated
marker images this takes a third off the centroid's error (rms per axis, seeds 1-4:
blobs of 3-5 pixels 0.035 -> 0.022 px, 6-9 pixels 0.029 -> 0.019, 10-15 pixels 0.018 ->
0.013), where the unweighted fit of the same model takes a quarter off.

The fit is Levenberg-Marquardt on all blobs of an image at once (numpy; the compiled
twin in ``_blobs.c`` takes the same steps), over a square around each blob that leaves
out saturated pixels (their signal is unknown) and pixels nearer another blob (its
light), with the weights from the model of the pass before (weights from the pixels
themselves would favour those that came out dark).  Centre, amplitude, radius, blur and
background are all free: the blur and the ring light's brightness are not calibrated.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.special import erfc

from agent.runtime import compiled_twin
from services.linalg import solve_stack

Array = np.ndarray

#: passes of weights (from the model the pass before) and Levenberg-Marquardt steps in each;
#: the covariance and misfit then take the weights of the model reached (a second pass
#: moved no centre further: 0.0214 / 0.0131 / 0.0103 px rms for 3-9 / 10-15 / 16+ px blobs
#: with one pass or two, seeds 1-3, at a third more of the cost)
PASSES = 1
STEPS = 3
#: a fit's cost per degree of freedom this many of its stds over 1 is a misfit (``_misfit``)
MISFIT_SIGMAS = 3.0
#: a fitted centre further than this from the blob's centroid is not taken (px)
MAX_SHIFT_PX = 0.5
_LOWER = np.array([1.0, -np.inf, -np.inf, 0.05, 0.2, -np.inf])
_UPPER = np.array([np.inf, np.inf, np.inf, 8.0, 3.0, np.inf])
_SQRT2 = np.sqrt(2.0)
_SQRTPI = np.sqrt(np.pi)


#: the compiled fit in use (tests set it to None to run the numpy one)
NATIVE: Any = compiled_twin("services.outside_in._blobs", "UMA_BLOBS_PURE_PYTHON")


def half_size(area: Array) -> Array:
    """The fitted square's half side for each blob: its radius from its area and a pixel
    of tail, 2-6 px (a wider square fits no better, at the cost of its pixels)."""
    return np.clip(np.ceil(np.sqrt(np.asarray(area, float) / np.pi)) + 1, 2, 6).astype(int)


def fit_centres(image: Array, uv: Array, area: Array, fit: Array, dark: float, gain: float,
                read_noise: float) -> tuple[Array, Array, Array]:
    """The centres (n, 2) of the blobs at centroids ``uv`` (n, 2, every blob of the image:
    their light is left out of the others' fits) with areas ``area`` (n,): fitted where
    ``fit`` (n, bool), with their std (n,, px, from the fit's covariance), and whether
    each was fitted (n,).  A blob not fitted (not asked, too near the image's edge, its fit
    failed or moved further than ``MAX_SHIFT_PX``) keeps its centroid, std nan."""
    uv = np.ascontiguousarray(uv, float).reshape(-1, 2)
    area = np.ascontiguousarray(area, float).reshape(-1)
    fit = np.asarray(fit, bool).reshape(-1)
    if NATIVE is not None:
        rows = np.frombuffer(NATIVE.fit(np.ascontiguousarray(image), uv, area,
                                        np.ascontiguousarray(fit, np.uint8), dark, gain,
                                        read_noise), np.float64).reshape(-1, 4)
        return rows[:, :2].copy(), rows[:, 2].copy(), rows[:, 3] > 0
    out, std, ok = uv.copy(), np.full(len(uv), np.nan), np.zeros(len(uv), bool)
    half = half_size(area)
    img = np.asarray(image)
    h, w = img.shape
    centre = np.rint(uv).astype(int)
    inside = (fit & (centre[:, 0] >= half) & (centre[:, 0] < w - half)
              & (centre[:, 1] >= half) & (centre[:, 1] < h - half))
    for size in np.unique(half[inside]):
        sel = np.flatnonzero(inside & (half == size))
        got, s, fine = _fit_group(img, uv, area, sel, int(size), dark, gain, read_noise)
        out[sel[fine]], std[sel[fine]], ok[sel[fine]] = got[fine], s[fine], True
    return out, std, ok


def _fit_group(img: Array, uv: Array, area: Array, sel: Array, half: int, dark: float,
               gain: float, read_noise: float) -> tuple[Array, Array, Array]:
    """The fit of blobs ``sel`` of ``uv``, all on squares of half side ``half``, from the
    centroid, a radius from the area (the few steps taken do not reach a near marker's
    saturated disk, three pixels across, from a one-pixel start) and the blur of the
    simulated lens."""
    n = len(sel)
    k = np.arange(-half, half + 1)
    centre = np.rint(uv[sel]).astype(int)
    xx = centre[:, 0, None, None] + k[None, None, :]          # (n, 1, side)
    yy = centre[:, 1, None, None] + k[None, :, None]          # (n, side, 1)
    pix = img[yy, xx].astype(float).reshape(n, -1)
    xx = np.broadcast_to(xx, (n, len(k), len(k))).reshape(n, -1).astype(float)
    yy = np.broadcast_to(yy, (n, len(k), len(k))).reshape(n, -1).astype(float)
    use = (pix < 255) & _own_pixels(xx, yy, uv, sel)
    x = np.empty((n, 6))
    x[:, 0] = np.maximum(pix.max(axis=1) - dark, 10.0)
    x[:, 1:3] = uv[sel]
    x[:, 3] = np.maximum(np.sqrt(area[sel] / np.pi) - 0.5, 1.0)
    x[:, 4] = 0.7
    x[:, 5] = dark
    read2 = read_noise ** 2 + 1.0 / 12.0     # and the 8-bit rounding
    model, J = _model(x, xx, yy)
    for _ in range(PASSES):
        weight = _weights(model, use, dark, gain, read2)
        x, model, J, _ = _levenberg_marquardt(x, model, J, xx, yy, pix, weight)
    weight = _weights(model, use, dark, gain, read2)
    res = model - pix
    cost = np.sum(weight * res * res, axis=1)
    dof = np.count_nonzero(use, axis=1) - 6
    var = _centre_variance(np.einsum("npi,np,npj->nij", J, weight, J)) * _misfit(cost, dof)
    fine = (np.all(np.isfinite(x), axis=1) & (var > 0) & (dof > 0)
            & (np.hypot(x[:, 1] - uv[sel, 0], x[:, 2] - uv[sel, 1]) <= MAX_SHIFT_PX))
    return x[:, 1:3], np.sqrt(np.where(var > 0, var, np.nan)), fine


def _weights(model: Array, use: Array, dark: float, gain: float, read2: float) -> Array:
    """Each pixel's weight, one over its noise variance (the model's shot noise and the
    read noise); none for the pixels not used."""
    return use / (gain * np.maximum(model - dark, 0.0) + read2)


def _misfit(cost: Array, dof: Array) -> Array:
    """What a blob's centre variance is multiplied by for how badly the model fits it:
    a blob the model does not describe (two markers' images run together, a marker over
    a reflection's edge) leaves more than the pixels' noise, and its std grows by the
    square root of the cost per degree of freedom where that is beyond 3 of its own
    stds above 1 (``sqrt(2 / dof)``); below, what is left is the pixels' noise, and
    growing a ball's std by its chance excess (half of them, 5-7 % on average) brought
    the two-camera NEES under its band on 4 of 10 seeds."""
    per_dof = cost / np.maximum(dof, 1)
    return np.where(per_dof > 1.0 + MISFIT_SIGMAS * np.sqrt(2.0 / np.maximum(dof, 1)),
                    per_dof, 1.0)


def _centre_variance(info: Array) -> Array:
    """The centre's variance per axis (mean of u's and v's) from each blob's information
    matrix (n, 6, 6); nan where it is singular."""
    out = np.full(len(info), np.nan)
    try:
        cov = np.linalg.inv(info)
        return 0.5 * (cov[:, 1, 1] + cov[:, 2, 2])
    except np.linalg.LinAlgError:
        for i, m in enumerate(info):
            try:
                c = np.linalg.inv(m)
            except np.linalg.LinAlgError:
                continue
            out[i] = 0.5 * (c[1, 1] + c[2, 2])
    return out


def _own_pixels(xx: Array, yy: Array, uv: Array, sel: Array) -> Array:
    """Which pixels of each square are nearer its blob than any other blob of the image."""
    d_own = _distance(xx - uv[sel, 0, None], yy - uv[sel, 1, None])
    own = np.ones(xx.shape, bool)
    for j in range(len(uv)):
        d = _distance(xx - uv[j, 0], yy - uv[j, 1])
        own &= (d >= d_own) | (sel == j)[:, None]
    return own


def _distance(du: Array, dv: Array) -> Array:
    """``sqrt(du^2 + dv^2)`` (a few pixels: hypot's care for overflow costs for nothing)."""
    return np.sqrt(du * du + dv * dv)


def _model(x: Array, xx: Array, yy: Array) -> tuple[Array, Array]:
    """The model's pixels (n, p) at parameters ``x`` (n, 6: amplitude, centre u, v,
    radius, blur, background), and its Jacobian (n, p, 6)."""
    a, cu, cv_, r, s, b = (x[:, i, None] for i in range(6))
    with np.errstate(all="ignore"):   # a diverging trial step: its cost is not finite
        du, dv = xx - cu, yy - cv_
        d = _distance(du, dv)
        z = (d - r) / (_SQRT2 * s)
        model = b + 0.5 * a * erfc(z)
        g = -a * np.exp(-z * z) / (_SQRTPI * _SQRT2 * s)       # d model / d distance
        ux = np.where(d > 0, du / d, 0.0)
        uy = np.where(d > 0, dv / d, 0.0)
        J = np.stack([0.5 * erfc(z), -g * ux, -g * uy, -g, -g * (d - r) / s,
                      np.ones_like(z)], axis=2)
    return model, J


def _levenberg_marquardt(x: Array, model: Array, J: Array, xx: Array, yy: Array,
                         pix: Array, weight: Array) -> tuple[Array, Array, Array, Array]:
    """``STEPS`` damped Gauss-Newton steps of every blob at once from ``x`` (its model
    and Jacobian given), each kept only where it lowers the blob's weighted cost, within
    the parameters' bounds: the parameters, model, Jacobian and cost reached."""
    lam = np.full(len(x), 1e-3)
    res = model - pix
    cost = np.sum(weight * res * res, axis=1)
    for _ in range(STEPS):
        H = np.einsum("npi,np,npj->nij", J, weight, J)
        g = np.einsum("npi,np->ni", J, weight * res)
        damped = H + lam[:, None, None] * np.eye(6) * np.diagonal(H, axis1=1, axis2=2)[:, None, :]
        step = solve_stack(damped, -g)
        trial = np.clip(x + step, _LOWER, _UPPER)
        t_model, t_J = _model(trial, xx, yy)
        t_res = t_model - pix
        t_cost = np.sum(weight * t_res * t_res, axis=1)
        better = t_cost < cost
        x = np.where(better[:, None], trial, x)
        J = np.where(better[:, None, None], t_J, J)
        model = np.where(better[:, None], t_model, model)
        res = np.where(better[:, None], t_res, res)
        cost = np.where(better, t_cost, cost)
        lam = np.where(better, lam / 3.0, lam * 4.0)
    return x, model, J, cost
