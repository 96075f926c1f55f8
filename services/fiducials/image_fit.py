"""A steeply seen tag's corners from a model of its whole image fitted to the pixels.

Seen at 70-80 degrees from its line of sight, a tag's short sides are a few pixels long and
its cells 1-1.5 px across them: every edge profile there crosses the blurred sum of the
border, the code cells behind it and the margin, and an acute corner of the image blurs
into both of its sides.  Edge crossings (:mod:`services.fiducials.edges`, even across a
modelled border, :mod:`services.fiducials.border`) leave such corners 0.1-0.7 px off, and
a pose from them 8-17 mm off at 1.0-1.3 m.  Once the tag is decoded its whole print is
known, so its whole image can be modelled and fitted instead:

* the print: the tag's cells (its code inside the black border), a one-cell white margin,
  and beyond it, per side, whatever lies there (one level each);
* the geometry: the homography from the tag's cell coordinates to ideal pixels fixed by the
  four corners (the parameters), the lens distortion through each pixel's ideal position
  (:meth:`CameraModel.ideal_pixels`), each pixel the mean of ``SUBSAMPLES`` x
  ``SUBSAMPLES`` points over its area (the light it integrates), then a Gaussian blur
  whose width is fitted (optics, focus, motion: no kernel is assumed);
* fitted by Levenberg-Marquardt to the pixels on the tag and its margin: the eight corner
  coordinates, the blur and the levels (black, white, beyond each side).

On the frames of ``uma eval fiducials`` the model's misfit at the true corners is the
sensor's noise (3.1-3.3 gray levels RMS); over the 322 tags under ``CELL_PX`` of seeds
1-10 and 101-110 the worst corner of each lies 0.026-0.033 px from the truth (median; at
most 0.075 px) where the edge fits left 0.13-0.20 px (at most 0.74 px).  The fit's own
covariance of the corners (:data:`COVARIANCE_SCALE`) is what the pose is weighed by.  It
costs 4-7 ms a tag (thread CPU, on a loaded machine), so it is kept to the tags whose cells
are thinner across a side than ``CELL_PX``: steep ones (70-80 degrees from the line of
sight at 0.5-1.5 m) and far ones.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from services.camera.model import CameraModel
from services.fiducials.border import normal_cdf

#: a tag is fitted when its cells are narrower than this (px) across one of its sides: on
#: the eval's frames 1.9 px is as accurate as 2.2 in the bins where the edge fits alone
#: fall behind AprilTag 3, and fits 5 of the 1,674 tags of ``bench/bench_fiducials.py``
#: where 2.2 fits about 30; at 1.7 two seeds' NEES leave their band.  The widths are
#: those of the edges' first pass (:func:`edges.place`), undistorted: the tags fitted
#: skip the border model, whose corners the fit replaces
CELL_PX = 1.9
#: the fit's own covariance of the corners times this: what the pixels' noise gives, and
#: what the model misses.  Fitted by maximum likelihood (a pure scale: the fitted corners'
#: mean 8-dof NEES against the truth brought to 8) over the 151 tags the fit takes on
#: seeds 1-10 of ``uma eval fiducials`` (unscaled: 9.4); on the fresh seeds 101-110 (171
#: tags) their mean NEES is then 7.0 (unscaled: 8.2)
COVARIANCE_SCALE = 1.18
#: each pixel the mean of this many points each way over its area
SUBSAMPLES = 2
#: the points' own smoothing (px): their spacing's half, so that the mean of a pixel's
#: points moves smoothly with the edges
SMOOTH_PX = 0.5 / SUBSAMPLES
#: the pixels fitted: those whose centres lie within the tag and this much (cells) of its
#: margin; the model covers ``SUPPORT_PX`` more around them for the blur
MASK_CELLS = 0.7
SUPPORT_PX = 3
#: Levenberg-Marquardt's steps at most
ITERATIONS = 10
#: the fit has converged when no corner moved by more than this (px) in a step
CONVERGED_PX = 5e-3
#: the blur's width (px) the fit starts from, and the range it is kept in
SIGMA_START_PX = 0.8
SIGMA_BOUNDS_PX = (0.25, 1.5)
#: Levenberg-Marquardt's starting damping, a share of the normal matrix's diagonal
DAMPING = 1e-3
#: the fit is kept where its corners moved less than this (px: about half a cell of the
#: tags it fits) from the edges', its residuals' RMS is under this share of the tag's
#: contrast, and that contrast (white less black, gray levels) is over ``MIN_CONTRAST``
MAX_MOVE_PX = 1.0
MAX_RMS_SHARE = 0.15
MIN_CONTRAST = 20.0

_OFFSETS = (np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES - 0.5
#: class of a cell of the extended print: black, white, beyond side 0 (top), 1, 2, 3
_BLACK, _WHITE, _LEVELS = 0, 1, 6


def refine(gray: np.ndarray, corners: np.ndarray, covariance: np.ndarray, across: np.ndarray,
           cells: np.ndarray, camera: CameraModel,
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The corners (n, 4, 2, ideal pixels) and their joint covariances (n, 8, 8) of ``n``
    decoded tags, those whose cells are thinner across a side (``across``, (n, 4) px) than
    ``CELL_PX`` replaced by the fit of the tag's modelled image (``cells``: (n, m, m),
    1 white) to ``gray`` where it succeeds; and which were (n,)."""
    fitted = np.zeros(len(corners), bool)
    steep = np.flatnonzero(gate(across))
    if not len(steep):
        return corners, covariance, fitted
    corners, covariance = corners.copy(), covariance.copy()
    for i in steep:
        try:
            got = fit(gray, corners[i], cells[i], camera)
        except np.linalg.LinAlgError:  # a degenerate quad: its edge fits' corners stay
            got = None
        if got is not None:
            corners[i], covariance[i] = got
            fitted[i] = True
    return corners, covariance, fitted


def gate(across: np.ndarray) -> np.ndarray:
    """Which of ``n`` tags (n,) are fitted: those whose cells are thinner than ``CELL_PX``
    across a side (``across``, (n, 4) px)."""
    return np.asarray(across).min(axis=1) < CELL_PX


def fit(gray: np.ndarray, corners: np.ndarray, cells: np.ndarray, camera: CameraModel,
        ) -> tuple[np.ndarray, np.ndarray] | None:
    """One tag's corners (4, 2, ideal pixels) and their covariance (8, 8) from its image
    in ``gray``, its cells ``cells`` (m, m, 1 white) known, started from ``corners``;
    None where the fit fails (too little contrast, a poor fit, corners moved too far).

    The parameters are the eight entries of the homography from ideal pixels (relative to
    the tag's centre) to the tag's cells: every point's cell coordinates, and so the
    model's derivatives, are closed forms in them; the corners and their covariance
    follow at the end."""
    corners = np.asarray(corners, np.float64)
    scene = _Scene.around(gray, corners, cells, camera)
    if scene is None:
        return None
    g, sigma = scene.start, SIGMA_START_PX
    r, J, levels = scene.residual(g, sigma)
    cost, lam, now = r @ r, DAMPING, scene.corners(g)
    for _ in range(ITERATIONS):
        A = J.T @ J
        step = -np.linalg.solve(A + lam * np.diag(np.diag(A)) + 1e-12 * np.eye(len(A)),
                                J.T @ r)
        g_try = g + step[:8]
        sigma_try = float(np.clip(sigma + step[8], *SIGMA_BOUNDS_PX))
        r_try, J_try, levels_try = scene.residual(g_try, sigma_try, levels + step[9:])
        if r_try @ r_try < cost:
            g, sigma, levels, r, J = g_try, sigma_try, levels_try, r_try, J_try
            cost, lam = r @ r, lam / 3
            before, now = now, scene.corners(g)
            if np.abs(now - before).max() < CONVERGED_PX:
                break
        else:
            lam *= 8
    dof = len(r) - J.shape[1]
    rms = np.sqrt(cost / max(dof, 1))
    contrast = levels[_WHITE] - levels[_BLACK]
    if dof < 1 or not contrast > MIN_CONTRAST or rms > MAX_RMS_SHARE * contrast \
            or not np.abs(now - corners).max() < MAX_MOVE_PX:
        return None
    A = J.T @ J
    try:
        inverse = np.linalg.inv(A + 1e-12 * np.eye(len(A)))
    except np.linalg.LinAlgError:
        return None
    by_g = scene.corner_jacobian(g)
    return now, COVARIANCE_SCALE * rms ** 2 * by_g @ inverse[:8, :8] @ by_g.T


class _Scene:
    """What the fit of one tag's image keeps fixed: the pixels it models (a window around
    the tag: where each of their points lies in ideal pixels, relative to ``centre``),
    the observed values of those it fits, and the print's cells."""

    def __init__(self, obs: np.ndarray, fitted: np.ndarray, support: np.ndarray,
                 points: np.ndarray, centre: np.ndarray, classes: np.ndarray,
                 start: np.ndarray) -> None:
        self.obs, self.fitted = obs, fitted
        self._supported = np.flatnonzero(support)
        self._mean = np.full(SUBSAMPLES * SUBSAMPLES, 1.0 / SUBSAMPLES ** 2)
        self.x, self.y = points[:, 0], points[:, 1]
        self.centre, self.classes, self.start = centre, classes, start
        self.m = classes.shape[0] - 8
        self.n = len(points)
        self._square = _square(self.m)

    @staticmethod
    def around(gray: np.ndarray, corners: np.ndarray, cells: np.ndarray,
               camera: CameraModel) -> _Scene | None:
        """The scene of the tag at ``corners`` (4, 2, ideal pixels) with ``cells`` (m, m)
        in ``gray``: the pixels within its margin fitted, those a blur's reach around them
        modelled; None where the window, cut to the image, is too small or holds too few
        pixels to fit."""
        m = cells.shape[0]
        centre = corners.mean(0)
        to_cells = _homography(corners - centre, _square(m))
        # the window: the tag with its margin and a blur's reach, in the image's pixels (the
        # lens moves them by the ideal corners' offset, nearly constant over a tag)
        reach = _square(m + 3.0) - 1.5
        outline = _apply(np.linalg.inv(to_cells), reach) + centre
        outline += (_distorted(camera, corners) - corners).mean(0)
        lo = np.maximum(np.floor(outline.min(0)).astype(int) - SUPPORT_PX, 0)
        hi = np.minimum(np.ceil(outline.max(0)).astype(int) + SUPPORT_PX + 1,
                        [gray.shape[1], gray.shape[0]])
        if np.any(hi - lo < 2 * SUPPORT_PX + 2):
            return None
        xs, ys = np.meshgrid(np.arange(lo[0], hi[0], dtype=np.float64),
                             np.arange(lo[1], hi[1], dtype=np.float64))
        shape = xs.shape
        ideal = camera.ideal_pixels(np.column_stack([xs.ravel(), ys.ravel()]))
        ideal = ideal.reshape(*shape, 2) - centre
        uv = _apply(to_cells, ideal.reshape(-1, 2)).reshape(*shape, 2)
        inside = ((uv > -MASK_CELLS) & (uv < m + MASK_CELLS)).all(-1)
        fitted = np.zeros(shape, bool)
        core = (slice(SUPPORT_PX, -SUPPORT_PX),) * 2
        fitted[core] = inside[core]
        if fitted.sum() < 20:
            return None
        kernel = np.ones((2 * SUPPORT_PX + 1, 2 * SUPPORT_PX + 1), np.uint8)
        support = cv2.dilate(fitted.astype(np.uint8), kernel).astype(bool)
        # each supported pixel's points, placed by the lens' local Jacobian
        dy, dx = np.gradient(ideal, axis=(0, 1))
        ox, oy = (o.reshape(1, -1, 1) for o in np.meshgrid(_OFFSETS, _OFFSETS))
        points = ideal[support][:, None, :] + ox * dx[support][:, None, :] \
            + oy * dy[support][:, None, :]
        obs = gray[lo[1]:hi[1], lo[0]:hi[0]].astype(np.float64)[fitted]
        return _Scene(obs, fitted, support, points.reshape(-1, 2), centre, _classes(cells),
                      (to_cells / to_cells[2, 2]).ravel()[:8])

    def _memberships(self, g: np.ndarray) -> tuple[np.ndarray, ...]:
        """Each point's cell coordinates (u, v), ``1 / w`` of the homography ``g``, and
        the nine cells around it: their classes, shares and the shares' derivatives by
        u and by v (9, N)."""
        x, y = self.x, self.y
        iw = 1.0 / (g[6] * x + g[7] * y + 1.0)
        u = (g[0] * x + g[1] * y + g[2]) * iw
        v = (g[3] * x + g[4] * y + g[5]) * iw
        # the points' smoothing in cells: |d(u, v)/d(x, y)| times SMOOTH_PX
        su = np.hypot(g[0] - u * g[6], g[1] - u * g[7]) * (iw * SMOOTH_PX)
        sv = np.hypot(g[3] - v * g[6], g[4] - v * g[7]) * (iw * SMOOTH_PX)
        au, dau, k0 = _axis_shares(u, np.abs(su), self.m)
        av, dav, l0 = _axis_shares(v, np.abs(sv), self.m)
        width = self.classes.shape[1]
        cls = self.classes.ravel().take((l0 * width + k0)[None] + (_J * width + _I)[:, None])
        return u, v, iw, cls, au[_I] * av[_J], dau[_I] * av[_J], au[_I] * dav[_J]

    def _class_shares(self, cls: np.ndarray, wts: np.ndarray) -> np.ndarray:
        """Each point's share (``_LEVELS``, N) of each class, summed over the nine cells
        around it (classes ``cls``, shares ``wts``, (9, N))."""
        index = (cls * self.n + np.arange(self.n)).ravel()
        return np.bincount(index, wts.ravel(), _LEVELS * self.n).reshape(_LEVELS, self.n)

    def residual(self, g: np.ndarray, sigma: float, levels: np.ndarray | None = None,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model's misfit (k,) to the fitted pixels, its Jacobian (k, 9 + levels) by
        the homography's entries, the blur and the levels, and the levels: those given,
        or (None) those that fit best for ``g`` and ``sigma`` (linear least squares on
        the same blurred shares of the print's classes, not computed twice)."""
        u, v, iw, cls, wts, wts_u, wts_v = self._memberships(g)
        kernel, d_kernel = _kernels(sigma)
        sharp = self._window(self._class_shares(cls, wts))
        shares = self._fitted(_blur(sharp, kernel, kernel))
        if levels is None:
            levels = np.linalg.lstsq(shares.T, self.obs, rcond=None)[0]
        value = levels[cls]
        g_u = np.einsum("kn,kn->n", wts_u, value) * iw
        g_v = np.einsum("kn,kn->n", wts_v, value) * iw
        x, y = self.x, self.y
        g_w = -(g_u * u + g_v * v)
        d = np.stack([g_u * x, g_u * y, g_u, g_v * x, g_v * y, g_v, g_w * x, g_w * y])
        by_g = self._fitted(_blur(self._window(d), kernel, kernel))
        # the blur's derivative: the (sharp) model image through the kernel's derivative
        # along x and along y
        model = sharp @ levels
        d_sigma = self._fitted(_blur(model, d_kernel, kernel) + _blur(model, kernel, d_kernel))
        J = np.concatenate([by_g, d_sigma.reshape(1, -1), shares]).T
        return levels @ shares - self.obs, J, levels

    def corners(self, g: np.ndarray) -> np.ndarray:
        """The tag's corners (4, 2, ideal pixels) for the homography entries ``g``."""
        return _apply(np.linalg.inv(np.append(g, 1.0).reshape(3, 3)), self._square) \
            + self.centre

    def corner_jacobian(self, g: np.ndarray) -> np.ndarray:
        """d(corners)/d(g) (8, 8): a corner is ``G⁻¹ s`` (homogeneous) for its square
        corner ``s``, and d(G⁻¹) = -G⁻¹ dG G⁻¹."""
        inverse = np.linalg.inv(np.append(g, 1.0).reshape(3, 3))
        q = np.column_stack([self._square, np.ones(4)]) @ inverse.T  # (4, 3): G⁻¹ s
        out = np.empty((4, 2, 8))
        for i in range(8):
            row, col = divmod(i, 3)
            dq = -np.outer(q[:, col], inverse[:, row])  # -G⁻¹ E_(row, col) q
            out[:, :, i] = (dq[:, :2] - q[:, :2] / q[:, 2:] * dq[:, 2:]) / q[:, 2:]
        return out.reshape(8, 8)

    def _window(self, samples: np.ndarray) -> np.ndarray:
        """Per-point quantities (c, N) as the window's image (h, w, c): each supported
        pixel the mean of its points, the others 0."""
        per_pixel = samples.reshape(len(samples), -1, len(self._mean)) @ self._mean
        image = np.zeros((self.fitted.size, len(samples)))
        image[self._supported] = per_pixel.T
        return image.reshape(*self.fitted.shape, -1)

    def _fitted(self, image: np.ndarray) -> np.ndarray:
        """The fitted pixels' values (c, k) of a window's image (h, w, c) or (h, w)."""
        return image.reshape(*self.fitted.shape, -1)[self.fitted].T


def _kernels(sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The sampled, normalised Gaussian kernel of ``sigma`` px (out to 4 sigma) and its
    derivative by ``sigma``."""
    offsets = np.arange(-math.ceil(4 * sigma), math.ceil(4 * sigma) + 1, dtype=np.float64)
    weights = np.exp(-0.5 * (offsets / sigma) ** 2)
    kernel = weights / weights.sum()
    square = offsets ** 2 / sigma ** 3
    return kernel, kernel * (square - kernel @ square)


def _blur(image: np.ndarray, along_x: np.ndarray, along_y: np.ndarray) -> np.ndarray:
    """``image`` filtered by the separable kernels ``along_x`` and ``along_y``, its edge
    pixels repeated beyond the window."""
    return cv2.sepFilter2D(image, cv2.CV_64F, along_x, along_y,
                           borderType=cv2.BORDER_REPLICATE)


_I, _J = np.repeat(np.arange(3), 3), np.tile(np.arange(3), 3)


def _square(side: float) -> np.ndarray:
    """The corners (4, 2) of the square ``side`` cells wide, in OpenCV's corner order."""
    return np.float64([[0, 0], [side, 0], [side, side], [0, side]])


def _distorted(camera: CameraModel, ideal: np.ndarray) -> np.ndarray:
    """Where ideal pixels (n, 2) lie in the image (the lens' distortion applied)."""
    K = camera.K
    rays = np.column_stack([(ideal - K[:2, 2]) / np.diag(K)[:2], np.ones(len(ideal))])
    return camera.project(rays)


def _classes(cells: np.ndarray) -> np.ndarray:
    """The extended print's cells (m + 8, m + 8): the tag's, a white margin, beyond it
    each side's own class, out to where the memberships' neighbours reach."""
    m = len(cells)
    out = np.empty((m + 8, m + 8), np.intp)
    idx = np.arange(m + 8) - 4  # index k holds the cells u in [k - 4, k - 3)
    uu, vv = np.meshgrid(idx, idx)
    out[:] = np.where(vv < -1, 2, np.where(vv > m, 4, np.where(uu < -1, 5, 3)))
    margin = (uu >= -1) & (uu <= m) & (vv >= -1) & (vv <= m)
    out[margin] = _WHITE
    out[4:m + 4, 4:m + 4] = np.where(cells > 0.5, _WHITE, _BLACK)
    return out


def _axis_shares(u: np.ndarray, smooth: np.ndarray, m: int,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's shares (3, N) of the cell columns left of, at and right of the one it
    lies in (smoothed by ``smooth`` cells), their derivatives by ``u``, and the index of
    the left one in :func:`_classes`' table."""
    ue = np.clip(u, -2.5, m + 2.5)
    k = np.floor(ue)
    f = ue - k
    z0, z1 = -f / smooth, (f - 1) / smooth
    left, right = normal_cdf(z0), normal_cdf(z1)
    p0, p1 = _pdf(z0) / smooth, _pdf(z1) / smooth
    shares = np.stack([left, 1 - left - right, right])
    d = np.stack([-p0, p0 - p1, p1])
    return shares, d, (k + 3).astype(np.intp)


def _pdf(z: np.ndarray) -> np.ndarray:
    """The standard normal density: the derivative the fit takes for :func:`normal_cdf`'s."""
    return np.exp(-0.5 * z * z) * _INV_SQRT_2PI


_INV_SQRT_2PI = 1 / np.sqrt(2 * np.pi)


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The homography (3, 3) taking the four points ``src`` to ``dst`` (float64 throughout:
    ``cv2.getPerspectiveTransform`` reads float32)."""
    A = np.zeros((8, 8))
    b = dst.reshape(-1)
    for i, ((x, y), (X, Y)) in enumerate(zip(src, dst, strict=True)):
        A[2 * i] = [x, y, 1, 0, 0, 0, -x * X, -y * X]
        A[2 * i + 1] = [0, 0, 0, x, y, 1, -x * Y, -y * Y]
    return np.append(np.linalg.solve(A, b), 1.0).reshape(3, 3)


def _apply(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """The points (n, 2) mapped by the homography ``h`` (3, 3)."""
    q = pts @ h[:, :2].T + h[:, 2]
    return q[:, :2] / q[:, 2:]


