"""Rendering of 8-bit camera images: laser spots on the screens' background, and
checkerboards.

Behind the 650 nm notch filter (Hogue 2003, §5.2) a camera sees a dark frame (plus what
the filter lets through of the projected content, ``projection``) with a few bright laser
spots.  A spot is the beam's footprint on the translucent screen: the beam's
Gaussian cross-section stretched by ``1 / cos(incidence)`` along its in-plane direction,
blurred by the screen's diffusion, mapped into the image by the local affine map of the
camera at that point.  Its total energy is fixed, so grazing spots are larger and dimmer;
head-on spots saturate the sensor, as in the thesis.  Sensor effects: a dark level, read
and shot noise, rounding to 8 bits, clipping at 255, a few stuck pixels.  Spots are
rendered with 3x3 sub-pixel samples, so the intensity centroid of a noise-free spot is
the projection of its centre to a few hundredths of a pixel.

Calibration patterns (checkerboards held in front of a camera, or projected on a screen)
are rendered by intersecting every sub-pixel viewing ray with the pattern's plane.  The
lens' point spread is applied to the pattern itself, analytically, before it is sampled:
a hard edge point-sampled 2x2 per pixel and blurred afterwards sits at a position rounded
to half a pixel, which moved the corners ``cv2.cornerSubPix`` finds by up to 0.35 px
(0.15 px RMS, 1-2 mm on a screen) and biased every calibration made from the images.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent.errors import InvalidInputError
from services.installation.camera import Camera

_SUB = (np.arange(3) - 1) / 3.0  # 3x3 sub-pixel sample offsets


@dataclass(frozen=True)
class SensorModel:
    """8-bit sensor behind the notch filter."""

    dark_level_dn: float = 8.0
    read_noise_dn: float = 1.5
    gain_dn_per_e: float = 0.1  # shot noise variance = gain * signal
    stuck_pixels: int = 3  # per camera, always 255 (hot pixels)


@dataclass(frozen=True)
class Spot:
    """A Gaussian blob in the image: centre (px), 2x2 covariance (px^2), energy (DN px^2),
    and an optional screen clip (pixels whose screen point is off the active area are
    dark): ``(A, b, side)`` maps a pixel ``uv`` to screen ``A @ uv + b``."""

    uv: np.ndarray
    cov: np.ndarray
    energy: float
    clip: tuple[np.ndarray, np.ndarray, float] | None = None


def spot_window(spots: list[Spot], width: int, height: int) -> tuple[int, int, int, int]:
    """Pixel box (u0, u1, v0, v1), exclusive ends, covering all blobs to 4 sigma."""
    lo = np.array([np.inf, np.inf])
    hi = -lo
    for s in spots:
        r = 4.0 * np.sqrt(np.diag(s.cov)) + 1.0
        lo = np.minimum(lo, s.uv - r)
        hi = np.maximum(hi, s.uv + r)
    u0, v0 = max(0, int(np.floor(lo[0]))), max(0, int(np.floor(lo[1])))
    u1, v1 = min(width, int(np.ceil(hi[0])) + 1), min(height, int(np.ceil(hi[1])) + 1)
    return u0, u1, v0, v1


def render_spots(spots: list[Spot], box: tuple[int, int, int, int]) -> np.ndarray:
    """Signal (DN, float) of the blobs in a pixel box, averaged over 3x3 sub-samples."""
    u0, u1, v0, v1 = box
    us = (np.arange(u0, u1)[:, None] + _SUB).ravel()
    vs = (np.arange(v0, v1)[:, None] + _SUB).ravel()
    uu, vv = np.meshgrid(us, vs)
    out = np.zeros_like(uu)
    for s in spots:
        inv = np.linalg.inv(s.cov)
        du, dv = uu - s.uv[0], vv - s.uv[1]
        m = inv[0, 0] * du * du + 2 * inv[0, 1] * du * dv + inv[1, 1] * dv * dv
        g = s.energy / (2 * np.pi * np.sqrt(np.linalg.det(s.cov))) * np.exp(-0.5 * m)
        if s.clip is not None:
            A, b, side = s.clip
            xs = A[0, 0] * uu + A[0, 1] * vv + b[0]
            ys = A[1, 0] * uu + A[1, 1] * vv + b[1]
            g *= (xs >= 0) & (xs <= side) & (ys >= 0) & (ys <= side)
        out += g
    h, w = v1 - v0, u1 - u0
    return out.reshape(h, 3, w, 3).mean(axis=(1, 3))


class NoiseBank:
    """Dark frames with read noise, pre-rendered once per camera; each image takes a random
    crop of one.  Fresh Gaussian noise for every 640x480 frame would dominate the cost of
    rendering, and detection never looks at the noise of two frames together."""

    PAD = 32

    def __init__(self, cam: Camera, sensor: SensorModel, rng: np.random.Generator,
                 n_frames: int = 4):
        shape = (n_frames, cam.height + self.PAD, cam.width + self.PAD)
        noise = sensor.dark_level_dn + sensor.read_noise_dn * rng.standard_normal(shape)
        self.frames = np.clip(np.rint(noise), 0, 255).astype(np.uint8)
        flat = rng.choice(cam.width * cam.height, sensor.stuck_pixels, replace=False)
        self.stuck = np.unravel_index(flat, (cam.height, cam.width))
        self.size = (cam.height, cam.width)

    def dark_frame(self, rng: np.random.Generator) -> np.ndarray:
        k = rng.integers(len(self.frames))
        oy, ox = rng.integers(0, self.PAD + 1, 2)
        img = self.frames[k, oy:oy + self.size[0], ox:ox + self.size[1]].copy()
        img[self.stuck] = 255
        return img


def add_spots(img: np.ndarray, spots: list[Spot], sensor: SensorModel,
              rng: np.random.Generator) -> None:
    """Add blobs to an 8-bit image in place (on whatever it shows: the dark level with its
    read noise, projected content), with their shot noise, rounding and saturation."""
    if not spots:
        return
    h, w = img.shape
    box = spot_window(spots, w, h)
    u0, u1, v0, v1 = box
    if u1 <= u0 or v1 <= v0:
        return
    signal = render_spots(spots, box)
    win = img[v0:v1, u0:u1]
    val = win + signal + np.sqrt(sensor.gain_dn_per_e * signal) \
        * rng.standard_normal(signal.shape)
    # keep stuck pixels stuck: take the max with what is there
    np.maximum(np.clip(np.rint(val), 0, 255).astype(np.uint8),
               np.where(win == 255, win, 0).astype(np.uint8), out=win)


def render_plane_pattern(cam: Camera, origin: np.ndarray, axis_a: np.ndarray,
                         axis_b: np.ndarray, pattern, supersample: int = 2,
                         background: float = 20.0, blur_px: float = 0.7,
                         box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """8-bit image of a planar pattern seen through a lens whose point spread is a Gaussian
    of ``blur_px`` (std, pixels), integrated over each pixel's area.

    ``pattern(a, b, blur_a, blur_b)`` gives the brightness (0..255, NaN where the plane
    shows nothing) at plane coordinates ``(a, b)`` along the unit axes ``axis_a``,
    ``axis_b`` from ``origin``, already blurred by the point spread, whose std along the
    plane's ``a`` and ``b`` directions is ``blur_a``, ``blur_b`` (metres, per sample; it
    grows with distance and obliquity).  Blurring before sampling keeps the image band-
    limited, so the ``supersample`` x ``supersample`` samples per pixel integrate it without
    aliasing -- edges and corners land where they are, not on the sample grid.  (Borders of
    the NaN region stay sharp: keep them away from the features being measured.)
    ``box`` (u0, u1, v0, v1), if given, is the only part of the image the pattern can
    cover (saves the ray casting elsewhere)."""
    if supersample < 2:
        raise InvalidInputError(f"supersample must be >= 2 (the blur's scale on the plane is taken "
                                f"from neighbouring samples), got {supersample}")
    if not blur_px > 0:
        raise InvalidInputError(f"blur_px must be > 0 (a lens has a point spread), got {blur_px}")
    k = supersample
    u0, u1, v0, v1 = box or (0, cam.width, 0, cam.height)
    u0, v0 = max(0, u0), max(0, v0)
    u1, v1 = min(cam.width, u1), min(cam.height, v1)
    out = np.full((cam.height, cam.width), background)
    if u1 <= u0 or v1 <= v0:
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)
    rays = cam.pixel_rays(supersample)[v0 * k:v1 * k, u0 * k:u1 * k]
    n = np.cross(axis_a, axis_b)
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((origin - cam.center) @ n) / denom
        pts = cam.center + s[..., None] * rays - origin
        a, b = pts @ axis_a, pts @ axis_b
        # metres on the plane per pixel along the image's steepest direction of a (of b)
        blur_a = blur_px * k * np.hypot(*np.gradient(a))
        blur_b = blur_px * k * np.hypot(*np.gradient(b))
        val = pattern(a, b, blur_a, blur_b)
    val = np.where((s > 0) & np.isfinite(val), val, background)
    out[v0:v1, u0:u1] = val.reshape(v1 - v0, k, u1 - u0, k).mean(axis=(1, 3))
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def blurred_box(x: np.ndarray, lo: float, hi: float, blur: np.ndarray) -> np.ndarray:
    """The indicator of ``lo <= x <= hi`` blurred by a Gaussian of std ``blur`` (0..1)."""
    # imported here: scipy.special would cost every process that loads the simulator
    # (the sim and accel-rig services, which never render) about 0.15 s of CPU at start
    from scipy.special import ndtr

    return ndtr((x - lo) / blur) - ndtr((x - hi) / blur)


def blurred_square_wave(x: np.ndarray, period_half: float, blur: np.ndarray) -> np.ndarray:
    """``(-1) ** floor(x / period_half)`` blurred by a Gaussian of std ``blur`` much
    smaller than ``period_half`` (only the nearest edge matters)."""
    k = np.floor(x / period_half)
    to_edge = np.minimum(x - k * period_half, (k + 1) * period_half - x)
    sign = 1.0 - 2.0 * (k % 2)
    from scipy.special import ndtr  # here, as in blurred_box

    return sign * (2.0 * ndtr(to_edge / blur) - 1.0)


def checkerboard(square_m: float, n_squares: tuple[int, int], black: float = 30.0,
                 white: float = 220.0, border_m: float = 0.0, border: float = 220.0,
                 outside: float = 20.0):
    """A pattern function for ``render_plane_pattern``: ``n_squares`` (along a, along b)
    squares from (0, 0), square (0, 0) black, surrounded by a ``border_m`` margin of
    brightness ``border``, and ``outside`` beyond it; every edge blurred by the lens."""
    na, nb = n_squares
    wa, wb = na * square_m, nb * square_m

    def pattern(a: np.ndarray, b: np.ndarray, blur_a: np.ndarray,
                blur_b: np.ndarray) -> np.ndarray:
        # a corner's blurred image is point-symmetric about it, so corners stay unbiased
        checker = 0.5 * (black + white) - 0.5 * (white - black) \
            * blurred_square_wave(a, square_m, blur_a) * blurred_square_wave(b, square_m, blur_b)
        w_board = blurred_box(a, 0.0, wa, blur_a) * blurred_box(b, 0.0, wb, blur_b)
        w_ring = blurred_box(a, -border_m, wa + border_m, blur_a) \
            * blurred_box(b, -border_m, wb + border_m, blur_b)
        return w_board * checker + (w_ring - w_board) * border + (1.0 - w_ring) * outside

    return pattern
