"""Marker corners from the marker's four edges, not from its corners.

A corner detector (``cornerSubPix``, or the contour OpenCV thresholds) puts an L-shaped
corner inside the true one under blur: on simulated 640x480 frames the corners of an
8 cm tag at 1 m came out 0.5 px inside (the tag 2.5 % too small, its depth 2.5 % too
far).  A straight edge's mid-level crossing does not move under a symmetric blur, so,
as ARToolKit and AprilTag do, each side is located along its whole length and the corners
are the intersections of the four fitted lines:

1. along each side, ``SAMPLES`` points away from the corners (placed from the corners
   of a first pass of the same kind, started from the detected quad); at each, the
   image profile across the side (``cv2.remap``, bilinear), from most of a module
   inside (the black border) to as far outside (the white quiet zone);
2. where the profile crosses the middle between black and white: one sub-pixel edge
   point (which middle: :func:`_levels`); across a decoded tag's thinnest sides, where
   no crossing is free of the cells around the border, the edge point of the tag's
   modelled image fitted to the profiles (:mod:`services.fiducials.border`);
3. the edge points undistorted (the lens bends straight sides), one least-squares line per
   side (the points' principal axis, as ``cv2.fitLine`` with ``DIST_L2``, vectorised over
   all markers), adjacent lines intersected: the corners in *ideal* pixels of the camera
   matrix, i.e. with the lens distortion already removed.

A side with fewer than ``MIN_POINTS`` edge points (too little contrast, no crossing) is
the line through its detected corners; a marker whose fitted corners land far from the
detected ones keeps the detected ones (undistorted likewise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from agent.runtime import compiled_twin
from services.camera.model import CameraModel
from services.fiducials import border

#: edge points per side over its middle ``SPAN`` (the rest is the corners' blur), placed
#: from the corners of a first, cheaper pass (``FIRST_SAMPLES`` over ``FIRST_SPAN``, lines
#: fitted in distorted pixels): placed from the detector's own corners, which jitter by
#: up to a pixel, points that near a corner follow the jitter.  On simulated 640x480
#: frames (seeds 1-10 of ``uma eval fiducials``) the corners came out 0.089 / 0.093 /
#: 0.143 / 0.270 px (RMS) from the truth at 0.5 / 1 / 1.5 / 2 m, where one pass of 18 over
#: 0.7 put them 0.111 / 0.117 / 0.173 / 0.335 px and 12 over 0.6 0.118 / 0.134 / 0.215 /
#: 0.401 px (AprilTag 3's: 0.117 / 0.107 / 0.197 / 0.279 px)
SAMPLES = 20
SPAN = 0.86
FIRST_SAMPLES = 8
FIRST_SPAN = 0.6
#: the profile's samples across a side, over twice the reach: a profile's crossing is the
#: chord between the two samples either side of its middle, which misses a blurred edge
#: by more the farther apart they lie; the miss is the same at every point of a side and
#: so moves its whole line.  A near tag's reach is wide (0.8 of cells 8-10 px across): at
#: 13 samples they lay 1.1-1.3 px apart and its corners erred by 0.030 px RMS; at 25,
#: 0.019 px.  On seeds
#: 1-10 of ``uma eval fiducials`` (10 s, the 577 tags the image fit leaves to the edge
#: fits, by the cells' width across the tag's narrowest side, 0-2.5 / 2.5-3.5 / 3.5-5 /
#: 5-8 / 8+ px): the corners 0.041 / 0.027 / 0.021 / 0.019 / 0.019 px RMS from the truth
#: (13 samples: 0.039 / 0.029 / 0.024 / 0.024 / 0.030)
STEPS = 25
MIN_CONTRAST = 20.0
MIN_POINTS = 3
#: how far across a side the profile reaches each way, in cells: past the one-cell black
#: border's middle inside and into the one-cell white quiet zone outside; but at least
#: ``REACH_MIN_PX``, where a small tag's cells are narrower than the blur
REACH_MODULES = 0.8
REACH_MIN_PX = 2.5
#: an edge point is an outlier beyond this many standard deviations of its marker's
#: scatter (and beyond half a cell: ``_inliers``)
OUTLIER_SIGMAS = 4.0
MAD_TO_STD = 1.4826
#: per-axis standard deviation (px) of a corner not located from its edges: the
#: detector's own corner, what the edge fit falls back to
FALLBACK_STD = 1.0
#: a side's outside is the print's white plateau when its profiles' outermost samples fall
#: short of their brightest by less than this share of their contrast (mean over the
#: side); a one-cell margin on a darker ground falls off by more at a steep view
PLATEAU_FALL = 0.05
#: ... and across a side whose cells are narrower than this (px) a one-cell border is
#: thin enough for the blur to lift its darkest sample (by 2 Phi(-w / 2 sigma) of the
#: contrast for a width w: 5 % at 3 px for the 0.75 px of a webcam's optics and pixels);
#: wider, each profile's own middle is as good and its own noise is what the edge fits'
#: scatter shows (the corners' covariance is built from it)
THIN_CELL_PX = 3.5
#: ... and across a side whose cells are narrower than this (px) the edge points are
#: the fit of the tag's modelled image (:mod:`services.fiducials.border`), its code's
#: cells known once decoded.  It costs about a millisecond a tag, so it is kept to the
#: thinnest borders, where the crossings err most: on the eval's frames the crossings'
#: worst misses are sides 1-1.5 px across (tags tilted 73-79 degrees at 0.6-1.3 m, 51-62
#: degrees at 2.2-2.4 m), and a limit of 1.7 px does as well there as 2.0 or 2.5; none of
#: the bench's ten tags at 0.6-1.6 m is under 1.6 px
MODEL_CELL_PX = 1.7
#: ... and across a side whose cells are narrower than this (px), and not modelled, the
#: crossings are corrected for the code's cells behind the border (:func:`_code_corrected`).
#: Wider, the code moves them little (on the eval's frames, seeds 1-10, the sides' offsets
#: at 2.8-3.5 px 0.017 px RMS, 0.012 corrected) and the correction costs the most: the
#: bench's frames have 16 sides a frame under 3.5 px, 7 under 3 (the correction's numpy
#: costs about 0.15 ms a call and 0.02 ms a side); under 2.5 px it left the poses'
#: median error at 1.5-2 m 1.50 mm where under 3 px gives 1.06 and under 3.5 px 1.01
CODE_CELL_PX = 3.0
#: how far (px) a profile's inner end may reach beyond a neighbouring side (an acute
#: corner's): on the eval's frames (seeds 1-10 and 101-110, worst seed's position p95 per
#: bin) 1 px left out too many of the short sides' points of tags tilted 73-76 degrees
#: and 2 px did best; without the rule corners at 77-79 degrees were 0.3 px off
CORNER_OVERSHOOT_PX = 2.0
#: pixel locking: a profile sampled bilinearly between pixel centres crosses its middle
#: off the true edge towards the nearer pixel border, by about ``A sin(2π x)`` along the
#: image axis nearer the side's normal (x: the edge's coordinate on that axis, pixel
#: centres at whole numbers).  Its sign follows from the sampling for any symmetric blur
#: (a blurred step is concave on either side of its middle, so the chord between two
#: pixel centres crosses the middle nearer the border between them); its size ``A``
#: follows from the edge's profile at the pixel scale, which one profile cannot show
#: (rendered tags along the axes, each pixel integrated over its area: 0.07-0.09 /
#: 0.055-0.077 / 0.028-0.05 / 0.011-0.025 px at a blur of 0.3 / 0.6 / 1.0 / 1.3 px, of
#: one sign at profile sample spacings of 0.42-1.18 px; sampled at the pixels' centres
#: alone the rendered edges lock to the grid themselves and the sign changes with the
#: tag's size).  So :class:`Locking` learns ``A`` from the camera's own frames, from the
#: sides within ``LOCK_ANGLE_DEG`` of an axis (beyond, the locking turns two-dimensional
#: and fades: 0.06 px at 3-10 degrees, 0.046 at 20, 0.01 at 30 on rendered tags), and
#: those of them whose points sweep ``LOCK_TEACH_PX`` or more across the axis, at every
#: phase, teach it, and those whose points sweep less than ``LOCK_SWEEP_PX``, all at
#: nearly one phase so that the locking moves their whole line, are corrected by it
#: (:func:`_unlocked`); along the others it averages out in the line and stays in the
#: scatter the corners' covariance is built from.  The figures below were measured on
#: seeds 1-10 of ``uma eval fiducials`` (cached frames; "alike": the edge-fitted corners
#: 0.0289 px RMS from the truth, their 8-dof NEES 7.94, the poses' NEES and errors per
#: bin within 0.01 of those at the value kept)
LOCK_ANGLE_DEG = 10.0
#: the sides corrected sweep less than this (px) across their axis: one period of the
#: locking, where its mean over the side's points, ``sinc(sweep)`` of its amplitude, has
#: its first zero; below it the locking moves the whole line (up to ``A / sqrt(2)``),
#: beyond it at most 0.22 of that and the rest is scatter.  At 0.5 px the corners were
#: 0.0292 px RMS from the truth and the poses at 2-2.5 / 2.5-3 m 3.13 / 3.53 mm RMS
#: against 3.00 / 3.32; at 1.5 px the corners 0.0283 px and the poses 2.99 / 3.35 mm.
#: Correcting every side within ``LOCK_ANGLE_DEG`` puts the corners at 0.0274 px (fresh
#: seeds 101-110: 0.0259 against 0.0273) and the poses 1-5 % nearer at 0.5-2.5 m, and
#: takes the locking's sine out of those sides' scatter, which the edge fits' covariance
#: otherwise counts as noise (at 3-10 degrees from an axis the edge fits' variance of a
#: side's offset falls from 1.37e-4 to 0.85e-4 px², its measured variance stays at
#: 1.59e-4); but the covariance's other terms, refitted to it, leave the poses' NEES at
#: 0.5-1 m over its band on seeds 1-10 (6.88 against 6.79): the period kept
LOCK_SWEEP_PX = 1.0
#: the sides that teach sweep at least this (px): over two periods the sine less its
#: straight-line fit along the side keeps 0.94 of its variance (averaged over the phase;
#: 0.75 over one period, 0.12 over half), so each teaching point counts nearly in full
#: and no side's own line fit takes up what it shows.  1.5 and 3 px taught alike
LOCK_TEACH_PX = 2.0
#: the amplitude's prior spread, what the covariance carries before any evidence: the
#: amplitude of the locking left uncorrected, fitted by maximum likelihood on the corner
#: errors of seeds 1-10 (the tracker's ``LOCK_PX``)
LOCK_PRIOR_PX = 0.046
#: a teaching point's scatter (px) about its side's line and the locking's curve: what
#: the regression weighs the evidence by, and the estimate's spread follows from.  The
#: teaching sides' 8,507 points scatter by 0.042 px about them, each side's own line and
#: amplitude fitted (0.057 before the curve's part is taken out; fresh seeds 101-110:
#: 6,876 points, 0.042).  0.015 and 0.06 taught alike: after a few frames the spread
#: (0.002-0.003 px on the eval's frames) lies far below the locking the tracker's covariance
#: keeps (``LOCK_LEFT_PX``)
LOCK_NOISE_PX = 0.042
#: the share of its evidence a camera keeps from one frame that teaches to the next.  A
#: camera's locking changes only with its optics' blur (focus, exposure), so the memory
#: is long: half the evidence after 34 teaching frames, a tenth after 114 (some 4 s at
#: 30 frames/s where every frame teaches).  On the eval's frames (14-32 teaching frames a
#: seed) 0.95 and 0.99 taught alike: the amplitude moves by 0.001 px RMS from frame to
#: frame after the fifth, within 0.0035-0.0041 px of its mean over a seed, with either
LOCK_MEMORY = 0.98
#: the sides whose points sweep ``LOCK_SWEEP_PX`` or more across the axis nearer their
#: normal, at least this many of them, have the locking's sine and cosine fitted out of
#: their scatter before it is pooled into the corners' noise
#: (:func:`_locking_scatter`): two of their dof, so that a side left with fewer than six
#: keeps its scatter whole
LOCK_FIT_POINTS = 8
#: the locking's amplitude against the learnt one (sides within ``LOCK_ANGLE_DEG`` of an
#: axis) by a side's angle to its nearer axis, degrees: the rendered tags' 0.06 px at 3-10
#: degrees, 0.046 at 20, 0.01 at 30 (beyond, the locking turns two-dimensional and fades)
LOCK_FADE_DEG = (LOCK_ANGLE_DEG, 20.0, 30.0, 45.0)
LOCK_FADE = (1.0, 0.77, 0.17, 0.0)


#: the profile's steps across a side
_OFFS = np.linspace(-1.0, 1.0, STEPS)
_CENTRE = STEPS // 2
#: side k runs from corner k to corner k + 1; corner k lies on sides k - 1 and k
_NEXT, _PREV = [1, 2, 3, 0], [3, 0, 1, 2]


def _fractions(span: float, samples: int) -> np.ndarray:
    return np.linspace((1 - span) / 2, (1 + span) / 2, samples)[:, None]


_FIRST, _SECOND = _fractions(FIRST_SPAN, FIRST_SAMPLES), _fractions(SPAN, SAMPLES)


@dataclass
class Locking:
    """A camera's pixel-locking amplitude (px), learnt from the edge points of its frames.

    The points of a side within ``LOCK_ANGLE_DEG`` of a pixel axis that sweeps
    ``LOCK_TEACH_PX`` or more across it lie at every phase of the pixel grid, so their
    scatter about the side's line shows ``A sin(2π x)`` (what the line itself cannot take
    up: the sine less its straight-line fit along the side); a side that lies along the
    axis has all its points at one phase, its whole line moved by the same error and
    nothing of it in its scatter.
    The first teach the amplitude, the second are corrected by it.  The estimate is the
    regression of those scatters on the sine, over the frames seen (older ones fading by
    ``LOCK_MEMORY`` with each frame that teaches: a camera that sees no side across an
    axis keeps what it knows), shrunk towards zero by a prior of spread ``LOCK_PRIOR_PX``."""

    evidence: float = 0.0  # sum of residual x sine (px)
    weight: float = 0.0  # sum of sine squared

    def add(self, evidence: float, weight: float) -> None:
        """A frame's regression sums."""
        self.evidence = LOCK_MEMORY * self.evidence + evidence
        self.weight = LOCK_MEMORY * self.weight + weight

    @property
    def amplitude(self) -> float:
        """The estimate (px); zero before any evidence."""
        return self.evidence / (self.weight + (LOCK_NOISE_PX / LOCK_PRIOR_PX) ** 2)

    @property
    def spread(self) -> float:
        """The estimate's standard deviation (px); ``LOCK_PRIOR_PX`` before any evidence."""
        return LOCK_NOISE_PX / math.sqrt(self.weight + (LOCK_NOISE_PX / LOCK_PRIOR_PX) ** 2)


def place(gray: np.ndarray, quads: np.ndarray, modules: int) -> np.ndarray:
    """Where (n, 4, 2, distorted pixels) the second pass of :func:`refine` places its
    edge points: the corners of a first, cheaper pass of the same kind (lines fitted in
    distorted pixels) started from the detected ``quads`` (n, 4, 2) of markers
    ``modules`` cells wide; a marker's detected corners where the pass fails.  Its
    sides' cell widths (:func:`cell_widths`) are what every stage that follows is gated
    on."""
    quads = np.asarray(quads, np.float64).reshape(-1, 4, 2)
    if len(quads) == 0:
        return quads
    edge, good, reach, _ = _edge_points(gray, quads, modules, _FIRST, _sides(quads, modules))
    w = good.astype(np.float64)
    mean, _, direction = _lines(edge, w)
    placed, ok = _intersections(np.where((w.sum(-1) < MIN_POINTS)[..., None], quads, mean),
                                direction, quads, reach)
    return np.where(ok[:, None, None], placed, quads)


def refine(gray: np.ndarray, quads: np.ndarray, modules: int, camera: CameraModel,
           cells: np.ndarray | None = None, placed: np.ndarray | None = None,
           modelled: np.ndarray | None = None, locking: Locking | None = None,
           learn: bool = True, gains: np.ndarray | None = None,
           ) -> tuple[np.ndarray, np.ndarray]:
    """Corners (n, 4, 2) in ideal pixels (``camera.K``, no distortion) of the detected
    ``quads`` (n, 4, 2, distorted pixels) of markers ``modules`` cells wide, and each
    marker's corners' joint covariance (n, 8, 8) from the edge fits' scatter.  With the
    markers' ``cells`` (n, modules, modules, 1 white: their decoded codes) the thinnest
    sides' edge points come from a model of their blurred image (:func:`_modelled`) and
    the thin ones' crossings are corrected for the code behind the border
    (:func:`_code_corrected`), on the markers ``modelled`` (n,; all by default): the
    others' corners are only where a whole-image fit starts from, which replaces them.
    ``placed``: :func:`place` of ``quads``, if already known.  With the camera's
    ``locking`` the points of the sides along a pixel axis are corrected for it, after it
    has learnt what this frame shows of it (:func:`_unlocked`) unless ``learn`` is False
    (the frame's tags have taught it already: a frame teaches once)."""
    quads = np.asarray(quads, np.float64).reshape(-1, 4, 2)
    if len(quads) == 0:
        return quads, np.zeros((0, 4, 2, 2))
    if placed is None:
        placed = place(gray, quads, modules)
    sides = _sides(placed, modules)
    edge, good, reach, own = _edge_points(gray, placed, modules, _SECOND, sides,
                                          marker_levels=True)
    clear = _clear_of_corners(sides, reach)
    if cells is not None:
        which = np.ones(len(quads), bool) if modelled is None else np.asarray(modelled, bool)
        crossed = _code_corrected(edge, placed, sides, cells, reach, own, which)
        edge, good, model = _modelled(gray, placed, sides, cells, edge, good, which)
        edge = np.where(model[..., None], edge, crossed)
        clear |= model
    good = good & clear
    # the detected corners and the edge points undistorted in one call
    both = camera.ideal_pixels(np.concatenate([quads.reshape(-1, 2), edge.reshape(-1, 2)]))
    fallback = both[:quads.size // 2].reshape(quads.shape)
    ideal = both[quads.size // 2:].reshape(edge.shape)
    # one line per side through its edge points (least squares: the points' principal
    # axis) without the points that crossed a neighbouring cell's edge, or through the
    # side's detected corners when too few edge points were found
    w = good.astype(np.float64)
    mean, dev, direction = _lines(ideal, w)
    inliers = _inliers(dev, direction, w, reach / REACH_MODULES)
    if inliers is not w:
        w = inliers
        mean, dev, direction = _lines(ideal, w)
    if locking is not None and _unlocked(ideal, edge, dev, direction, w, locking, learn):
        mean, dev, direction = _lines(ideal, w)
    chord = fallback[:, _NEXT] - fallback
    chord /= np.maximum(np.sqrt(_dot2(chord, chord)), 1e-9)[..., None]
    few = (w.sum(-1) < MIN_POINTS)[..., None]
    point = np.where(few, fallback, mean)
    direction = np.where(few, chord, direction)
    corners, ok = _intersections(point, direction, fallback, reach)
    taken, locked = _locking_terms(edge, dev, direction, w, corners)
    cov = _corner_covariance(corners, point, direction, dev, w, few, taken)
    cov = np.where(ok[:, None, None], cov, FALLBACK_STD ** 2 * np.eye(8))
    if gains is not None:
        gains[...] = np.where(ok[:, None, None], locked, 0.0)
    return np.where(ok[:, None, None], corners, fallback), cov


def _locking_axes(edge: np.ndarray, direction: np.ndarray,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per side (n, 4) of the lines' ``direction``: whether it lies within
    ``LOCK_ANGLE_DEG`` of a pixel axis; the coordinates (n, 4, k) of its points ``edge``
    (distorted pixels, where the pixel grid is) on the axis nearer its normal; and that
    axis as a unit vector (n, 4, 2)."""
    axis = np.argmax(np.abs(direction), axis=-1) ^ 1  # the normal's larger component
    along = np.take_along_axis(np.abs(direction), (axis ^ 1)[..., None], -1)[..., 0]
    near = along >= math.cos(math.radians(LOCK_ANGLE_DEG))
    x = np.take_along_axis(edge, axis[..., None, None], -1)[..., 0]
    return near, x, np.eye(2)[axis]


def _locking_evidence(dev: np.ndarray, direction: np.ndarray, w: np.ndarray,
                      near: np.ndarray, x: np.ndarray, unit: np.ndarray) -> tuple[float, float]:
    """The regression sums (:meth:`Locking.add`) of the ``near`` sides' points' scatter
    across their lines (``dev``: from their means; ``w``: weights), as moves along their
    axis (``unit``), on ``sin(2π x)`` less its own straight-line fit along the side: the
    part of the locking a line fit leaves in its scatter."""
    normal = direction[..., ::-1] * [-1.0, 1.0]
    cos = np.abs(_dot2(normal, unit))
    across = _dot2(dev, normal[:, :, None]) * np.sign(_dot2(normal, unit))[..., None]
    u = _dot2(dev, direction[:, :, None])
    sine = np.sin(2 * np.pi * x)
    count = np.maximum(w.sum(-1, keepdims=True), 1.0)
    centred = sine - (w * sine).sum(-1, keepdims=True) / count
    spread = np.maximum((w * u * u).sum(-1, keepdims=True), 1e-12)
    slope = (w * u * centred).sum(-1, keepdims=True) / spread
    left = centred - slope * u
    keep = (w * near[..., None]) > 0
    moves = across / np.maximum(cos, 1e-6)[..., None]
    return float(np.sum(np.where(keep, moves * left, 0.0))), \
        float(np.sum(np.where(keep, left * left, 0.0)))


def _unlocked(ideal: np.ndarray, edge: np.ndarray, dev: np.ndarray, direction: np.ndarray,
              w: np.ndarray, locking: Locking, learn: bool) -> bool:
    """Adds what the sides' edge points show of the pixel locking to ``locking`` (if
    ``learn``) and moves the points ``ideal`` (n, 4, k, 2, in place) of the sides that
    sweep less than ``LOCK_SWEEP_PX`` across their axis back by it, ``locking.amplitude *
    sin(2π x)`` along that axis (``x``: their coordinates on it in the image, ``edge``);
    whether any moved.  ``dev``, ``direction``: the lines' fits of ``ideal`` with weights
    ``w``.  The undistortion between the image and the ideal pixels is smooth and near
    unit scale over a pixel, so the move is the same there."""
    near, x, unit = _locking_axes(edge, direction)
    if not near.any():
        return False
    sweep = _sweeps(dev, direction, w, unit)
    teach = near & (sweep >= LOCK_TEACH_PX)
    if learn and teach.any():
        locking.add(*_locking_evidence(dev, direction, w, teach, x, unit))
    locked = near & (sweep < LOCK_SWEEP_PX)
    if not locked.any():
        return False
    move = np.where(locked[..., None], locking.amplitude * np.sin(2 * np.pi * x), 0.0)
    ideal -= move[..., None] * unit[:, :, None, :]
    return True


def _sweeps(dev: np.ndarray, direction: np.ndarray, w: np.ndarray, unit: np.ndarray,
            ) -> np.ndarray:
    """How far (n, 4, px) each side's points (``dev``: from their mean; ``w``: weights)
    sweep across its locking axis ``unit`` (:func:`_locking_axes`)."""
    along = _dot2(dev, direction[:, :, None])
    extent = np.where(w > 0, along, -np.inf).max(-1) + np.where(w > 0, -along, -np.inf).max(-1)
    return np.maximum(extent, 0.0) * np.abs(_dot2(direction, unit))


def _locking_terms(edge: np.ndarray, dev: np.ndarray, direction: np.ndarray, w: np.ndarray,
                   corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_locking_scatter` and :func:`_locking_gains` of the same sides, in one call
    of the compiled twin where it is built (in numpy some hundred calls a frame on a few
    hundred numbers: the interpreter's cost)."""
    if NATIVE is None or not len(edge):
        return (_locking_scatter(edge, dev, direction, w),
                _locking_gains(edge, dev, direction, w, corners))
    c = np.ascontiguousarray
    taken, gains = np.empty((*w.shape[:2], 2)), np.empty((*w.shape[:2], 2))
    NATIVE.locking_terms(c(edge, np.float64), c(dev, np.float64), c(direction, np.float64),
                         c(w, np.float64), c(corners, np.float64), _FADE_DEG, _FADE,
                         float(LOCK_FIT_POINTS), LOCK_SWEEP_PX, taken, gains)
    return taken, gains


_FADE_DEG, _FADE = np.array(LOCK_FADE_DEG), np.array(LOCK_FADE)


def _locking_scatter(edge: np.ndarray, dev: np.ndarray, direction: np.ndarray,
                     w: np.ndarray) -> np.ndarray:
    """Per side (n, 4, 2): the share of its points' squared scatter across its line
    (``dev``: from their mean; ``w``: weights; ``edge``: where they lie in the image) that
    a sine and a cosine of their phase on the pixel grid explain (the axis nearer the
    side's normal, :func:`_locking_axes`) beyond the line's own offset and turn, and the
    2 dof that fit takes, on the sides whose points sweep ``LOCK_SWEEP_PX`` or more across
    that axis and number ``LOCK_FIT_POINTS`` or more; zero on the others.  Why: the
    locking, ``A sin(2π x)``, scatters a side's points by up to ``A / sqrt(2)`` (0.035-0.047
    px on the eval's frames, against 0.04 of noise; its phases explain 41-75 % of the
    sides' squared scatter at every angle to the axis, where noise alone would explain 22
    %) but moves its line by only what :func:`_locking_gains` says: counted as noise it
    would claim the line errs by as much again, where the covariance's locking terms carry
    what it moves the line by (``tracker.side_offset_covariance``)."""
    _, x, unit = _locking_axes(edge, direction)
    normal = direction[..., ::-1] * [-1.0, 1.0]
    across = _dot2(dev, normal[:, :, None])
    u = _dot2(dev, direction[:, :, None])
    count = w.sum(-1, keepdims=True)
    spread = np.maximum((w * u * u).sum(-1, keepdims=True), 1e-12)

    def off_line(f: np.ndarray) -> np.ndarray:
        """``f`` less its weighted straight-line fit along the side."""
        centred = f - (w * f).sum(-1, keepdims=True) / np.maximum(count, 1.0)
        return centred - (w * u * centred).sum(-1, keepdims=True) / spread * u

    phase = 2 * np.pi * x
    s, c = off_line(np.sin(phase)), off_line(np.cos(phase))
    ss, sc, cc = (w * s * s).sum(-1), (w * s * c).sum(-1), (w * c * c).sum(-1)
    sr, cr = (w * s * across).sum(-1), (w * c * across).sum(-1)
    det = ss * cc - sc * sc
    use = ((count[..., 0] >= LOCK_FIT_POINTS)
           & (_sweeps(dev, direction, w, unit) >= LOCK_SWEEP_PX)
           & (det > 1e-6 * np.maximum(count[..., 0], 1.0) ** 2))
    explained = (cc * sr * sr - 2 * sc * sr * cr + ss * cr * cr) / np.where(use, det, 1.0)
    return np.stack([np.where(use, explained, 0.0), np.where(use, 2.0, 0.0)], axis=-1)


def _locking_gains(edge: np.ndarray, dev: np.ndarray, direction: np.ndarray, w: np.ndarray,
                   corners: np.ndarray) -> np.ndarray:
    """Per side (n, 4, 2): how far a pixel locking of unit amplitude, ``sin(2π(x + φ))``
    at its points' phases ``x`` on the pixel grid (the axis nearer the side's normal, in
    the image: ``edge``) and a random ``φ``, moves its fitted line (one standard deviation
    over ``φ`` is ``1 / sqrt(2)`` of these): the offset at the points' mean, ``|mean
    exp(2πix)|``, and the turn, the points' straight-line fit of it along the side
    (``dev``: from their mean; ``w``: weights) at the side's ends (half the side between
    ``corners``).  Why the points' own phases: they sample the sine at discrete steps, and
    where a step is near a whole pixel the sine does not average out along the side
    however far the side sweeps across the axis (a near tag's 20 points lie 3-4 px
    apart along a side)."""
    _, x, _ = _locking_axes(edge, direction)
    z = np.exp(2j * np.pi * x)
    count = np.maximum(w.sum(-1), 1.0)
    mean = (w * z).sum(-1) / count
    u = _dot2(dev, direction[:, :, None])
    spread = np.maximum((w * u * u).sum(-1), 1e-12)
    side = corners[:, _NEXT] - corners
    half = np.sqrt(_dot2(side, side)) / 2
    turn = np.abs((w * u * (z - mean[..., None])).sum(-1)) / spread * half
    angle = np.degrees(np.arccos(np.clip(np.abs(direction).max(-1), 0.0, 1.0)))
    fade = np.interp(angle, LOCK_FADE_DEG, LOCK_FADE)
    return np.stack([np.abs(mean), turn], axis=-1) * fade[..., None]


def cell_widths(quads: np.ndarray, modules: int) -> np.ndarray:
    """The width (n, 4, px) of the cells of markers ``modules`` cells wide across each
    side of their ``quads`` (n, 4, 2)."""
    return _sides(quads, modules)[-1]


def _sides(quads: np.ndarray, modules: int,
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The sides of ``quads`` (n, 4, 2) of markers ``modules`` cells wide: each side's
    vector (n, 4, 2), its length (n, 4, 1), unit direction and outward normal (n, 4, 2),
    and its cells' width across it (n, 4, px)."""
    side = quads[:, _NEXT] - quads
    length = np.sqrt(_dot2(side, side))[..., None]
    along = side / np.maximum(length, 1e-9)
    # OpenCV's corners run clockwise in the image: the outward normal is along's left turn
    normal = along[..., ::-1] * [1.0, -1.0]
    # the cells' width across a side: along the neighbouring sides, times the sine of the
    # angle they make with it (a tilted tag is narrower one way than the other)
    sine = np.abs(along[..., 0] * along[:, _PREV, 1] - along[..., 1] * along[:, _PREV, 0])
    across = (length[:, _PREV, 0] + length[:, _NEXT, 0]) / (2 * modules) \
        * (sine + sine[:, _NEXT]) / 2
    return side, length, along, normal, across


def _edge_points(gray: np.ndarray, quads: np.ndarray, modules: int, fractions: np.ndarray,
                 sides: tuple[np.ndarray, ...], marker_levels: bool = False,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel edge points (n, 4, len(fractions), 2) along the sides of ``quads`` at
    ``fractions`` of each side, whether each was found, the reach (n, 4, 1) px and
    whether each side's profiles were crossed at their own middles (n, 4).  Each
    profile is crossed at its own middle, or with ``marker_levels`` at :func:`_levels`'
    (the first pass, which only places the second's points, spares the cost).  ``sides``:
    :func:`_sides` of ``quads``."""
    side, length, _, normal, across = sides
    reach = np.maximum(REACH_MODULES / 2 / modules * (length[:, _PREV] + length[:, _NEXT]),
                       REACH_MIN_PX)
    base = quads[:, :, None, :] + fractions * side[:, :, None, :]
    step = reach[..., None] * normal[:, :, None, :]  # (n, 4, 1, 2)
    # each coordinate's samples built contiguous (the map cv2.remap takes) and the
    # extremes taken on the 8-bit profile: no strided copies, no float pass
    x = (base[..., 0, None] + _OFFS * step[..., 0, None]).astype(np.float32)
    y = (base[..., 1, None] + _OFFS * step[..., 1, None]).astype(np.float32)
    raw = cv2.remap(gray, x.reshape(1, -1), y.reshape(1, -1), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE).reshape(x.shape)
    profile = raw.astype(np.float64)
    dark = raw[..., :_CENTRE + 1].min(axis=-1).astype(np.float64)
    bright = raw[..., _CENTRE:].max(axis=-1).astype(np.float64)
    level = (dark + bright) / 2
    own = np.ones(across.shape, bool)
    if marker_levels:
        level = _levels(profile, dark, bright, across < THIN_CELL_PX)
        own = np.all(level == (dark + bright) / 2, axis=-1)
    s = _crossings(profile, level)
    good = (bright - dark > MIN_CONTRAST) & np.isfinite(s)
    return base + np.where(good, s, 0.0)[..., None] * step, good, reach, own


def _crossings(profile: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Where each profile (..., ``STEPS``) first rises through its ``level`` (...) nearest
    its centre, in units of the reach (linearly between samples); inf where it does not."""
    if NATIVE is not None:
        out = np.empty(level.shape)
        NATIVE.crossings(np.ascontiguousarray(profile), np.ascontiguousarray(level, np.float64),
                         _OFFS, out)
        return out
    d = profile - level[..., None]
    lo, hi = d[..., :-1], d[..., 1:]
    rising = (lo < 0) & (hi >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        where = np.where(rising, _OFFS[:-1] + lo / (lo - hi) * (_OFFS[1] - _OFFS[0]), np.inf)
    pick = np.argmin(np.abs(where), axis=-1)
    return np.take_along_axis(where, pick[..., None], -1)[..., 0]


#: the compiled twin of :func:`_crossings` (to the bit), :func:`_lines`,
#: :func:`_locking_terms` and :func:`_corner_covariance` (to rounding) (``_kernels.c``;
#: tests set it to None to run the numpy code)
NATIVE: Any = compiled_twin("services.fiducials._kernels", "UMA_FIDUCIALS_PURE_PYTHON")


def _clear_of_corners(sides: tuple[np.ndarray, ...], reach: np.ndarray) -> np.ndarray:
    """Whether each second-pass profile (n, 4, ``SAMPLES``) stays inside the tag: at an
    acute corner of the tag's image (a steeply tilted tag's are 20-40 degrees) a profile
    near the corner, reaching ``reach`` px inwards, leaves the tag through the
    neighbouring side, and the blurred white beyond it moves its crossing outwards
    (0.2-0.4 px on the eval's frames tilted 77-79 degrees, the corners 0.3 px off).  A
    profile at ``a`` px from a corner of angle ``theta`` ends ``a sin(theta) - reach
    cos(theta)`` px inside the neighbouring side; one that ends more than
    ``CORNER_OVERSHOOT_PX`` outside it is left out.  ``sides``: :func:`_sides` of the
    quads the profiles were placed on."""
    _, length, along, _, _ = sides
    cosine = -_dot2(along, along[:, _PREV])  # at corner k
    sine = np.sqrt(np.maximum(1 - cosine ** 2, 0.0))
    reach = reach[..., 0][..., None]
    start = _SECOND[:, 0] * length * sine[..., None] - reach * cosine[..., None]
    end = (1 - _SECOND[:, 0]) * length * sine[:, _NEXT, None] - reach * cosine[:, _NEXT, None]
    return np.minimum(start, end) >= -CORNER_OVERSHOOT_PX


def _code_corrected(edge: np.ndarray, quads: np.ndarray, sides: tuple[np.ndarray, ...],
                    cells: np.ndarray, reach: np.ndarray, own: np.ndarray,
                    which: np.ndarray) -> np.ndarray:
    """The edge points ``edge`` (n, 4, k, 2) of the sides whose cells are narrower across
    than :data:`CODE_CELL_PX` (and not modelled, :data:`MODEL_CELL_PX`) moved back by
    what the code's cells behind the border move their crossings
    (:func:`border.crossing_bias`, the tags' ``cells`` known from their codes; ``own``:
    the sides crossed at their profiles' own middles).  Why: where the cells are 1.7-2.5 px
    across (seeds 1-10 of ``uma eval fiducials``) a side's crossing follows the white share
    of the code cells behind it (correlation 0.9, 0.2 px from all black to all white at
    1.7-2 px) and its turn their slope along it, so each tag's code sets its own error:
    the sides' offsets are 0.047 / 0.030 px RMS at 1.7-2.2 / 2.2-2.8 px without this,
    0.018 / 0.014 with it.  ``quads``: those the profiles were placed on; ``sides``:
    :func:`_sides` of them; ``reach`` (n, 4, 1) px, the profiles'; ``which`` (n,): the
    tags corrected."""
    _, _, _, normal, across = sides
    thin = (across < CODE_CELL_PX) & (across >= MODEL_CELL_PX) & which[:, None]
    if not thin.any():
        return edge
    tag, side = np.nonzero(thin)
    # at every other point (and the last), the rest halfway between their neighbours: the
    # line fit follows the mean and the trend along the side
    bias = np.empty((len(tag), len(_SECOND)))
    bias[:, _COARSE] = border.crossing_bias(quads[tag], cells[tag], side, _SECOND[_COARSE],
                                            across[tag, side], reach[tag, side] * _OFFS,
                                            own[tag, side])
    bias[:, 1:-1:2] = (bias[:, :-2:2] + bias[:, 2::2]) / 2
    edge = edge.copy()
    edge[tag, side] -= bias[..., None] * normal[tag, side, None, :]
    return edge


_COARSE = np.r_[0:SAMPLES:2, SAMPLES - 1]


def _modelled(gray: np.ndarray, quads: np.ndarray, sides: tuple[np.ndarray, ...],
              cells: np.ndarray, edge: np.ndarray, good: np.ndarray, which: np.ndarray,
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The edge points ``edge`` (n, 4, k, 2) and whether found ``good`` (n, 4, k), those
    of the sides whose cells are narrower across than :data:`MODEL_CELL_PX` replaced by
    the fit of the tag's modelled image (:func:`border.fit_offsets`, the tags ``cells``
    known from their codes) where it is trusted, and which were (n, 4, k).  The fit starts
    from the crossings.  ``sides``: :func:`_sides` of ``quads``; ``which`` (n,): the tags
    modelled."""
    side, _, _, normal, across = sides
    thin = (across < MODEL_CELL_PX) & which[:, None]
    modelled = np.zeros(good.shape, bool)
    if not thin.any():
        return edge, good, modelled
    pick = np.flatnonzero(thin.any(axis=1))
    base = quads[pick, :, None, :] + _SECOND * side[pick, :, None, :]
    start = np.einsum("nksc,nkc->nks", edge[pick] - base, normal[pick])
    offset, ok = border.fit_offsets(gray, quads[pick], cells[pick], _SECOND, across[pick],
                                    np.where(good[pick], start, 0.0))
    use = ok & thin[pick][..., None]
    edge, good = edge.copy(), good.copy()
    edge[pick] = np.where(use[..., None], base + offset[..., None] * normal[pick, :, None, :],
                          edge[pick])
    good[pick] |= use
    modelled[pick] = use
    return edge, good, modelled


def _levels(profile: np.ndarray, dark: np.ndarray, bright: np.ndarray, thin: np.ndarray,
            ) -> np.ndarray:
    """The level (n, 4, k) whose crossing is each profile's edge point.  Under a symmetric
    blur a step's edge is where it crosses the middle of the levels on its two sides; a
    profile's own extremes are those levels only where its black and white are wider than
    the blur.  A steeply tilted tag's one-cell border is not: where a white cell follows
    it, the blur lifts the profile's darkest sample, its middle rises and the edge point
    moves outwards, and an acute corner of the tag's image moves several times as far as
    its sides.  So where a side's cells are ``thin`` (n, 4: narrower across it than
    :data:`THIN_CELL_PX`) and its outside is a white plateau (the print's margin wider
    than the profile reaches, as on a sheet of paper) the level is the middle of the
    marker's own black and white (the darker half of its profiles' darkest samples, the
    brighter half of their brightest).  Where the outside falls off again (a one-cell
    margin on a darker ground seen steeply, as the tags of ``uma eval fiducials``) each
    profile keeps its own middle: the thin margin's shift there offsets the border's, and
    the marker's middle came out worse.  Fifteen of that eval's steepest frames (tilted
    52-79 degrees from the line of sight) rendered with a four-cell margin: corners 0.30
    px RMS from the truth (median; max 0.89) with each profile's own middle, 0.10 (max
    0.22) with the marker's; with the one-cell margin unchanged."""
    local = (dark + bright) / 2
    if not thin.any():
        return local
    contrast = (bright - dark > MIN_CONTRAST).astype(np.float64)
    fall = (bright - profile[..., -1]) / np.maximum(bright - dark, 1.0)
    plateau = thin & ((contrast * fall).sum(-1) < PLATEAU_FALL * contrast.sum(-1))
    if not plateau.any():
        return local
    # the darker half of the darkest samples, the brighter half of the brightest: those off
    # their level by a thin stripe's blur are the other half
    both = np.stack([-dark, bright])  # (2, n, 4, k)
    total = np.maximum(contrast.sum((1, 2)), 1.0)
    mean = (contrast * both).sum((2, 3)) / total
    half = contrast * (both >= mean[..., None, None])
    minus_black, white = (half * both).sum((2, 3)) / np.maximum(half.sum((2, 3)), 1.0)
    return np.where(plateau[..., None], ((white - minus_black) / 2)[:, None, None], local)


def _inliers(dev: np.ndarray, direction: np.ndarray, w: np.ndarray, cell: np.ndarray,
             ) -> np.ndarray:
    """The weights ``w`` (n, 4, k) (``w`` itself when none is dropped) without the edge
    points that lie further from their side's line (``dev``: from its mean, along
    ``direction``) than half a cell (``cell``, (n, 4, 1) px across the side) and
    ``OUTLIER_SIGMAS`` of the marker's scatter (the median absolute distance, as a
    standard deviation): a profile that crossed the edge of a cell next to the border (a
    tilted tag's cells are narrower than the reach) instead of the side itself.  Least
    squares follows such a point: two or three of twenty, 2 px off, put a corner of a
    grazing tag 1-2 px away."""
    normal = direction[..., ::-1] * [-1.0, 1.0]
    across = np.abs(_dot2(dev, normal[:, :, None]))
    if not np.any(across > cell / 2):
        return w  # the usual frame: no point is a candidate
    found = (w > 0).reshape(len(w), -1)
    ranked = np.sort(np.where(found, across.reshape(len(w), -1), np.inf), axis=1)
    count = found.sum(1)
    middle = np.take_along_axis(ranked, np.maximum(count - 1, 0)[:, None] // 2, 1)[:, 0]
    scatter = np.where(count > 0, middle, 0.0) * MAD_TO_STD  # a median: the lower one
    limit = np.maximum(cell / 2, OUTLIER_SIGMAS * scatter[:, None, None])
    out = np.where(across <= limit, w, 0.0)
    return w if np.array_equal(out, w) else out


def _intersections(point: np.ndarray, direction: np.ndarray, fallback: np.ndarray,
                   reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corner k where side k-1's line meets side k's, and per marker whether all four
    are well defined and within three reaches of ``fallback``."""
    p1, d1 = point[:, _PREV], direction[:, _PREV]
    det = d1[..., 1] * direction[..., 0] - d1[..., 0] * direction[..., 1]
    diff = point - p1
    with np.errstate(divide="ignore", invalid="ignore"):
        s1 = (direction[..., 0] * diff[..., 1] - diff[..., 0] * direction[..., 1]) / det
    corners = p1 + s1[..., None] * d1
    moved = corners - fallback
    ok = np.all((np.abs(det) > 1e-6) & np.isfinite(s1)
                & (_dot2(moved, moved) < 9 * reach[..., 0] ** 2), axis=1)
    return corners, ok


def _lines(points: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each side's least-squares line through its weighted points (n, 4, k, 2): the
    points' mean, their deviations from it, the principal axis."""
    if NATIVE is not None:
        points = np.ascontiguousarray(points, np.float64)
        mean, dev, direction = np.empty((*w.shape[:-1], 2)), np.empty_like(points), \
            np.empty((*w.shape[:-1], 2))
        if w.size:
            NATIVE.lines(points, np.ascontiguousarray(w, np.float64), mean, dev, direction)
        return mean, dev, direction
    mean = (w[..., None, :] @ points)[..., 0, :] / np.maximum(w.sum(-1), 1)[..., None]
    dev = points - mean[:, :, None, :]
    wdev = w[..., None] * dev
    sums = (wdev * dev).sum(2)
    cxx, cyy = sums[..., 0], sums[..., 1]
    cxy = (wdev[..., 0] * dev[..., 1]).sum(-1)
    theta = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
    return mean, dev, np.stack([np.cos(theta), np.sin(theta)], axis=-1)


def _corner_covariance(corners: np.ndarray, point: np.ndarray, direction: np.ndarray,
                       dev: np.ndarray, w: np.ndarray, few: np.ndarray,
                       taken: np.ndarray) -> np.ndarray:
    """The corners' joint covariance (n, 8, 8) (x and y of corner 0, of corner 1, ...) from
    the fits of the four lines they are the intersections of.  A line fitted to N edge
    points scattered by s across it is off by ``a`` (s/sqrt(N)) at the points' mean and
    turned by ``b`` (s/sqrt(sum u^2), u: the points' distances along it from their mean),
    independently; at u along it, it is off by ``a + u b`` across itself.  s^2 is pooled
    over the marker's four sides (their residuals across the fitted lines, less what the
    pixel locking explains of them and the dof its fit takes: ``taken`` (n, 4, 2),
    :func:`_locking_scatter`).  Corner k moves
    by the offsets of sides k-1 and k through the inverse of the 2x2 matrix of their
    normals, so the two corners of a side move together with its line: their covariance is
    not block-diagonal (across the side, a turn moves them oppositely, correlation about
    -0.6; taken as independent, the poses of 60 rendered frames at 0.6-1.4 m claimed too
    much spread, mean NEES 4.1, under its band, where the joint covariance gives 6.6).  A
    side with too few edge points (the line through its detected corners) is off by
    ``FALLBACK_STD`` at each end, independently."""
    if NATIVE is not None:
        c = np.ascontiguousarray
        out = np.empty((len(corners), 8, 8))
        if len(corners):
            NATIVE.corner_covariance(c(corners, np.float64), c(point, np.float64),
                                     c(direction, np.float64), c(dev, np.float64),
                                     c(w, np.float64), c(few[..., 0], np.uint8),
                                     c(taken, np.float64), FALLBACK_STD, out)
        return out
    normal = direction[..., ::-1] * [-1.0, 1.0]  # (n, 4, 2)
    across = _dot2(dev, normal[:, :, None])
    along = _dot2(dev, direction[:, :, None])
    count = w.sum(-1)
    fitted = ~few[..., 0]
    rss = np.where(fitted, (w * (across * across)).sum(-1) - taken[..., 0], 0.0).sum(-1)
    dof = np.where(fitted, np.maximum(count - 2, 0) - taken[..., 1], 0).sum(-1)
    s2 = np.where(dof > 0, rss / np.maximum(dof, 1), FALLBACK_STD ** 2)[:, None]  # (n, 1)
    s_uu = np.maximum((w * (along * along)).sum(-1), 1e-12)
    # where corner k lies along side k (its near end) and along side k - 1 (its far end)
    u_near = _dot2(corners - point, direction)
    u_far = _dot2(corners - point[:, _PREV], direction[:, _PREV])
    # a fallback side's a and b are taken at its middle: each end then off by FALLBACK_STD
    # alone
    length = np.abs(u_far[:, _NEXT] - u_near)
    middle = np.where(fitted, 0.0, (u_far[:, _NEXT] + u_near) / 2)
    var_a = np.where(fitted, s2 / np.maximum(count, 1), FALLBACK_STD ** 2 / 2)
    var_b = np.where(fitted, s2 / s_uu, 2 * FALLBACK_STD ** 2 / np.maximum(length, 1e-6) ** 2)
    Ninv = inverse_2x2(np.stack([normal[:, _PREV], normal], axis=-2))  # (n, 4, 2, 2)
    n = len(corners)
    # corner k (x, y) <- (a, b) of side k - 1 and of side k: G[:, k, :, side, a or b]
    G = np.zeros((n, 4, 2, 4, 2))
    k = np.arange(4)
    by_prev = np.moveaxis(Ninv[..., 0], 1, 0)  # (4, n, 2): the advanced index goes first
    by_side = np.moveaxis(Ninv[..., 1], 1, 0)
    G[:, k, :, _PREV, 0] = by_prev
    G[:, k, :, _PREV, 1] = by_prev * (u_far - middle[:, _PREV]).T[..., None]
    G[:, k, :, k, 0] = by_side
    G[:, k, :, k, 1] = by_side * (u_near - middle).T[..., None]
    G = G.reshape(n, 8, 8)
    lam = np.stack([var_a, var_b], axis=-1).reshape(n, 1, 8)
    return (G * lam) @ np.swapaxes(G, -1, -2)


def _dot2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The dot products of (broadcast) 2-vectors along the last axis: ``einsum``'s sum,
    without its dispatch, which costs more than the arithmetic on these small arrays."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def inverse_2x2(m: np.ndarray) -> np.ndarray:
    """The inverses of a stack (..., 2, 2) of 2x2 matrices in closed form (``np.linalg.inv``
    costs a LAPACK call per matrix)."""
    det = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    out = np.empty_like(m)
    out[..., 0, 0], out[..., 1, 1] = m[..., 1, 1], m[..., 0, 0]
    out[..., 0, 1], out[..., 1, 0] = -m[..., 0, 1], -m[..., 1, 0]
    return out / det[..., None, None]
