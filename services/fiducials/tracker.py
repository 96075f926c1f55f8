"""The fiducial tracker's per-frame pipeline: detect, solve each body, judge, estimate noise.

``FiducialTracker.process(image, t_ns)`` returns one :class:`Estimate` per body seen:

* **detection**: ``cv2.aruco.ArucoDetector`` finds and decodes the markers; their corners
  are then located from their four sides (:mod:`services.fiducials.edges`; across the
  thinnest borders from a model of the decoded tag's blurred image,
  :mod:`services.fiducials.border`), in ideal pixels (lens distortion removed), where
  the poses are solved; a tag whose cells are thinnest has its whole image fitted
  instead (:mod:`services.fiducials.image_fit`, started from its plain edge crossings;
  the border model only where that fit is rejected);
* **pose**: :mod:`services.fiducials.pose` (IPPE candidates refined by Gauss-Newton
  steps, LM for bundles, then a step weighted by the corners' covariances; a frame's
  lone markers all at once);
* **covariance**: ``(Jᵀ Σ⁻¹ J)⁻¹`` with ``Σ`` the corners' joint covariance from the four
  edge lines they are the intersections of (:func:`edges.refine`: their fits' scatter,
  length and angle; two corners of a side move with its line), plus what each side's
  fit cannot show: its line's offset across it, larger where the cells across that side
  are narrow, the four sides' together, its pixel locking's offset and turn, and the
  turn the code's cells give it where its crossings are not corrected for them
  (:func:`side_offset_covariance`).  So it grows when
  the marker is far, blurred, tilted or badly lit, corner by corner and side by side;
* **corner noise for the ambiguity judgement**: a separate, cautious figure: per body,
  the residuals of its last ``POOL_FRAMES`` fits pooled (``σ² = Σ RSS / Σ dof``; the
  camera's calibrated pixel noise fills in for the dof missing up to ``FULL_DOF``, then
  weighs ``PRIOR_DOF``), never below :func:`corner_floor_px` of the marker's cell size
  (it is also the covariance's noise when corners come without their covariances, as
  in :meth:`FiducialTracker.estimate` called with bare corners);
* **planar ambiguity**: the two IPPE solutions are two branches of a two-state hidden
  Markov model (which one is the true pose), their evidence carried from frame to frame:
  each frame adds its own log-likelihood ratio (half the χ² distance between the two
  fits, in units of σ², at least the calibration's pixel noise), the branch a solution
  continues is the previous favourite's if it lies clearly on its side (within
  ``HISTORY_SIDE`` of the angle between the two), and between frames (at most
  ``HISTORY_S`` apart) the branches may swap with a probability that depends on how far
  apart the two solutions are against how far the pose moves in a frame interval
  (:func:`branch_switch`): the true pose moves continuously, and can only pass to the
  other solution's branch where the two meet (a view near fronto-parallel).  A frame
  whose own gap exceeds ``AMBIGUITY_GAP`` decides (``ambiguity = "none"``); otherwise
  the branch the evidence favours is reported, as ``"history"`` when the carried
  evidence agrees and the total reaches ``HISTORY_LLR`` (its covariance the chosen
  solution's own, the evidence's chance of the other beside it: ``flip_probability``),
  else as ``"covered"``, its covariance the second moment of the two solutions' mixture
  at the other's chance (at least ``COVERED_CHANCE_FLOOR``): its offset and spread
  weighed by how likely it is, a flip to it inside the covariance's 99.9 % region.
  Never a silent flip: the sample says which, and how likely the other.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.camera.markers import dictionary
from services.camera.model import CameraModel
from services.fiducials import border, edges, image_fit, pose
from services.fiducials.bodies import Body, marker_body, marker_in_body

#: the fits whose residuals are pooled into a body's corner noise (the ambiguity
#: judgement's, and the covariance's where corners come without their own): a second at
#: 30 frames/s, 60 dof for a lone tag (2 a frame), so its variance is within 18 % (one
#: standard deviation) and follows a change of light or focus within that second.  On
#: the eval's frames (seeds 1-10 and 101-110) 10 and 100 change no figure: the pooled
#: noise (0.03 px median) lies under the tag's cell-size floor (:func:`corner_floor_px`)
#: in 533 of 610 frames (seeds 1-5, 101-103) and never above the calibration's 0.3 px
POOL_FRAMES = 30
#: the calibration's pixel noise counts as this many degrees of freedom: enough to start
#: from, too few to matter after a frame (4 dof at 0.3 px held sub-0.1 px corners of near
#: tags at 0.1 px and made their covariance 3x too large: mean NEES 1-3.6 at 0.5-1 m)
PRIOR_DOF = 0.1
#: ... but until the body's own fits add up to this many dof, the prior fills the rest: a
#: noise estimate from a frame or two can be small by chance (and a covariance from it a
#: silent flip)
FULL_DOF = 20
#: the pixel noise (px, per axis) of a calibration that states none (``pixel_std``): the
#: prior of the pooled corner noise above and the least noise the ambiguity is judged at
#: (a larger one shrinks the gap between the two solutions: more poses ``history`` or
#: ``covered``).  The simulated webcam states the same figure
#: (:func:`services.fiducials.simulate.webcam`); its edge-fitted corners err by 0.029 px
#: RMS per axis (seeds 1-10), so on its frames the judgement is cautious by a factor of ten
DEFAULT_PIXEL_STD = 0.3
FLOOR_A = 1.2
FLOOR_B = 1.58
#: what a side's edge fit cannot show: the line's offset across the side errs by about
#: ``SIDE_A * exp(-across / SIDE_SCALE_PX)`` px beyond its fit's scatter, ``across`` the
#: width (px) of the cells across that side (:func:`edges.cell_widths`: the black border
#: inside it, the white quiet zone outside it, a cell each).  Where they are narrow
#: against the blur, the profile's dark and bright ends are not the print's black and
#: white and its mid-level crossing moves; the offsets of a tag's four sides err together
#: (``SIDE_CORRELATION``: the tag looks smaller or larger as a whole).  Per side, not per
#: tag: a tilted tag's long sides have narrow cells across them and err, its short sides
#: have wide ones and do not.  What the code's cells behind the border add is corrected
#: (:func:`edges.refine`): this is what remains
SIDE_A = 0.025
SIDE_SCALE_PX = 1.70
SIDE_CORRELATION = 1.0
#: ... and an edge's crossing errs with its sub-pixel phase against the pixel grid (pixel
#: locking), by ``LOCK_PX * sin(2π phase)`` (on the eval's frames 0.04-0.06 px where a
#: side lies within a third of a pixel of an axis, its sign following the phase, on seeds
#: 1-10 and 101-110 alike): where a side's points lie at phases spread over a period the
#: error shows in the fit's scatter (and is taken out of it, :func:`edges.refine`), but
#: where they share one phase (a side nearly along an axis, or points a whole pixel apart
#: across it) it moves the whole line and turns it, by ``LOCK_PX / sqrt(2)`` times the
#: gains read off the points' own phases (:func:`edges.refine`'s ``gains``; without them
#: the continuum's ``sinc(sweep)`` and :func:`_locked_slope`, ``sweep`` the pixels the
#: side's fitted span sweeps across that axis), independent from side to side, offset
#: and turn uncorrelated over the phase.  Beyond these the sides' offsets err by
#: ``EDGE_SHARE`` of the cells' width across them, independently: what grows with the
#: tag's size in the image; and the edge fits' own covariance is ``EDGE_FIT_SCALE`` times
#: what their scatter says: sensor noise alone it states (a tag rendered 60 times with
#: fresh noise, at 0.6-1.4 m: the corners' scatter 0.88-1.12 of the claim), so the rest
#: is the frames' other errors, shared by neighbouring points.  The five figures
#: (``SIDE_A``, ``SIDE_SCALE_PX``, ``EDGE_SHARE``, ``EDGE_FIT_SCALE``, ``CODE_TURN_A``;
#: the locking's kept) were fitted by maximum likelihood on seeds 1-10 of ``uma eval
#: fiducials`` at 10 s and 60 s together, the errors of the four corners against the
#: truth of the 4,129 tags the image fit leaves to the edge fits (a side's offset 0.008
#: px where its cells are 2 px across): the corners' mean 8-dof NEES 8.8 at 10 s, 7.7 at
#: 60 s; the bundle scenes' tags at 10 s, not fitted, 7.3
LOCK_PX = edges.LOCK_PRIOR_PX
EDGE_FIT_SCALE = 1.17
EDGE_SHARE = 0.00070
#: ... and once the camera has learnt its locking (:class:`edges.Locking`) and takes it out
#: of the sides along an axis, the covariance's locking term is what is left: the larger of
#: ``LOCK_LEFT_PX`` and the learnt amplitude's own spread.  Refitted by maximum likelihood
#: on seeds 1-10, as above, with the correction on (the other figures came out within 1 %
#: of theirs and are kept): the corners' 8-dof NEES by cell width 7.3-7.8 (over 7 px:
#: 10.6), fresh seeds 7.2-8.5
LOCK_LEFT_PX = 0.029
#: ... and a side whose cells are ``CODE_CELL_PX`` or wider across it, whose crossings
#: are not corrected for the code's cells behind its border (:func:`edges.refine`), is
#: turned by them: the white share of the cells behind it changes along it, and the
#: blur carries more white across the border where it is larger.  Its ends move by
#: ``CODE_TURN_A * exp(-across / CODE_TURN_SCALE_PX)`` px, the one outwards, the other
#: inwards (0.015 px at 3 px, 0.0075 at 3.5, 0.0009 at 5), independently from side to
#: side.  On seeds 1-10 of ``uma eval fiducials`` (the 577 edge-fitted tags' corners)
#: how far the sides' ends move oppositely against the truth jumps at the gate: 0.020 /
#: 0.017 px RMS at 2.6-2.8 / 2.8-3.0 px, 0.024 / 0.027 at 3.0-3.2 / 3.2-3.4 (fresh seeds
#: 101-110: 0.019 / 0.018, 0.025 / 0.028), where the other terms claim 0.021-0.024.
#: ``CODE_TURN_A`` is fitted with the figures above, ``CODE_TURN_SCALE_PX`` on those
#: corners alone.  The sides'
#: offsets do not jump alike on the fresh seeds, and an offset beside the turn puts the
#: poses' NEES at 1.5-2 m under its band: none is carried
CODE_TURN_A = 1.38
CODE_TURN_SCALE_PX = 0.70
#: the tag-wide part of that offset (``SIDE_CORRELATION``) is shared by the tags of a
#: bundle: seen alike (the same blur, view and cell widths), they look smaller or larger
#: together, and averaging them does not average it away.  On the eval's bundle scenes
#: (four tags on a plate, seeds 1-10) the tags' offsets, the mean over their four sides,
#: correlated at 0.64-0.70 from tag to tag (uncentred) where the cells are under 3.5 px
#: (0.19 wider, where the offset is small), their mean over the four tags 0.0105 px RMS
#: against 0.0125 px for one
TAG_CORRELATION = 0.65
#: a χ² gap between the two IPPE solutions' fits beyond which a frame decides alone
#: (``ambiguity`` "none"): a likelihood ratio of exp(8), the other solution's chance
#: 3e-4, beyond the 20 : 1 history needs (``HISTORY_LLR``).  Candidates within 1.5 times
#: it are refined as rivals (the cost of LM on them).  On the eval's frames 12 and 25
#: move samples only between "none" and "history" (seeds 1-10: 149 and 214 history
#: against 176; no pose, covariance, NEES or flip changes)
AMBIGUITY_GAP = 16.0
#: how long (s) a track's branch evidence is carried to the next frame it is seen in: a
#: gap longer than this starts the evidence afresh.  On the eval's frames (10 frames/s)
#: 0.25 s drops it across missed detections (covered samples 193 -> 200 on seeds 1-10,
#: 173 -> 182 fresh; fresh 2-2.5 m's pooled NEES 3.98 -> 3.85, under its band), 1 s
#: changes next to nothing (191 covered)
HISTORY_S = 0.5
#: a solution continues the previous favourite branch when it is within this share of
#: the two solutions' angle of it (clearly on its side)
HISTORY_SIDE = 0.4
#: the angular speed (rad/s) a track is assumed to turn at before it has shown its own
#: (a hand-held or hand-moved tag; the eval's tags turn at up to about 1 rad/s)
TURN_PRIOR_RAD_S = 1.0
#: the weight of a frame's turn in the track's running mean square angular speed
TURN_WEIGHT = 0.3
#: the least rotation (rad) between frames the branch switch allows for: what the
#: solutions' own noise and an unseen jerk can move them
TURN_FLOOR_RAD = math.radians(1.0)
#: the least chance per frame interval that the branches swapped: what the motion model
#: cannot promise (a detection from another tag's corners, a jump between frames)
SWITCH_FLOOR = 1e-6
#: the log-likelihood ratio (about 20 : 1) at which history reports its branch as such
HISTORY_LLR = 3.0
#: the least chance a ``covered`` pose's covariance gives the other solution: its offset
#: then lies within sqrt(8) standard deviations, a flip to it inside chi2(3)'s 99.9 %
#: region (16.3) with room for its own spread (at the chance itself, from 4.7 %, it could
#: lie 4.6 standard deviations out)
COVERED_CHANCE_FLOOR = 0.125
#: the log-likelihood ratio a frame with a single solution stores (any finite figure
#: beyond what ``SWITCH_FLOOR`` lets history carry, log(1e6) = 13.8)
_DECISIVE = 50.0


@dataclass(frozen=True)
class Estimate:
    """One body's pose in the camera frame at the frame's capture time."""

    name: str
    t_ns: int
    R: np.ndarray  # (3, 3) body -> camera
    t: np.ndarray  # (3,) body origin in the camera frame, m
    covariance: np.ndarray  # (6, 6) decoupled [position, camera-frame rotation]
    sigma_px: float  # corner noise used (per axis)
    rms_px: float  # this frame's reprojection RMS (per axis)
    ambiguity: str  # "none", "history" or "covered"
    markers: tuple[int, ...]
    alternative_gap: float  # χ² gap to the other solution (inf if there is none)
    flip_probability: float = 0.0  # the evidence's chance that the other solution is true


def corner_floor_px(module_px: float) -> float:
    """The least corner noise (px, per axis) the ambiguity judgement assumes for a marker
    of ``module_px``-pixel cells: what its residuals cannot show (the corners of a small,
    blurred tag move together, so the pose absorbs the error).  On simulated 640x480
    frames (seeds 1-10) the edge-fitted corners' error against the truth went from
    0.06 px at 8 px cells to 0.43 px at 2.3 px, ``1.65 / module_px ** 1.58``; the floor
    is 0.73 of that (``FLOOR_A`` 1.2): 0.8 let one sample of ten seeds through as a
    silent flip, 1.2 none of thirteen."""
    return FLOOR_A / max(module_px, 0.5) ** FLOOR_B


def apparent_tilt(sigma_px: float, side_px: float) -> float:
    """The tilt (rad) a fronto-parallel marker of ``side_px`` seems to have under corner
    noise ``sigma_px``: foreshortening is second order in the tilt (its corners move by
    about ``side_px * tilt² / 4``), so noise alone puts IPPE's two solutions about twice
    this apart where they really coincide (on simulated crossings at 1.2 m, 0.25 px:
    9.6 degrees here, the solutions 8-24 degrees apart at the crossing)."""
    return 2 * math.sqrt(sigma_px / max(side_px, 1.0))


def branch_switch(near_rad: float, far_rad: float, separation_rad: float, turn_rad: float,
                  meet_rad: float) -> float:
    """The chance that the true pose passed to the other IPPE branch between two frames.
    The pose turns continuously, ``turn_rad`` per axis in the interval (Gaussian), and
    the solution nearer the previous branch (``near_rad`` from it) continues it unless

    * the pose turned ``far_rad``, to the other solution, instead: odds
      ``exp(-(far² - near²) / (2 turn²))``, next to nothing where the solutions lie far
      apart against the motion (a tilted tag's mirror pose is twice its tilt away); or
    * it crossed the view where the two branches meet (fronto-parallel): its tilt, half
      the ``separation_rad`` seen, is known to ``meet_rad`` (:func:`apparent_tilt`) there,
      and it crosses if it lies within the turn of it and turns towards it:
      ``0.4 turn / meet * exp(-separation² / (8 meet²))`` (at most an even chance).

    Never below ``SWITCH_FLOOR``."""
    x = (far_rad ** 2 - near_rad ** 2) / (2 * turn_rad ** 2)
    moved = 1 / (1 + math.exp(min(x, 700.0)))
    crossed = 0.4 * turn_rad / meet_rad * math.exp(-separation_rad ** 2 / (8 * meet_rad ** 2))
    return max(moved, min(crossed, 0.5), SWITCH_FLOOR)


def _covered(own: np.ndarray, chosen: pose.Solution, solutions: list[pose.Solution],
             cov_of: Callable[[pose.Solution], np.ndarray], chance: float) -> np.ndarray:
    """A ``covered`` pose's covariance: the corners barely tell the two solutions apart
    and the track has not decided, so the error about the chosen pose is a mixture, its
    ``own`` covariance with the chance the chosen is true, the other solution's offset
    and spread with the ``chance`` that it is (``flip_probability``, at least
    ``COVERED_CHANCE_FLOOR``): the mixture's second moment about the chosen pose.

    Not the other solution within one standard deviation on top of the chosen one's own
    (``own`` + its offset and spread): that claims the other's whole spread in every
    covered frame, where the chosen one is the true pose in 2,505 of the 2,533 covered
    tag samples of the eval's bundle scenes (seeds 1-10 and 101-110; their mean
    ``flip_probability`` 0.26); a tag's claimed position error would be 1.2-2.2x its
    measured one there (seeds 5, 9, 106, 108, covered in 60-85 % of their frames), and a
    bundle more accurate than that tag by less than the covariances say.  The 28 flipped
    ones, at ``flip_probability`` 0.49-0.5, lie within the mixture's 99.9 % region
    (rotation Mahalanobis distance² at most 14.0).

    A ``history`` pose gains nothing: the chance of its other solution is at most
    ``1 / (1 + exp(HISTORY_LLR))`` (4.7 %), and a two-solution mixture's second moment
    of weight ``p`` puts the other solution at a Mahalanobis distance² of about ``1 / p``,
    beyond chi2(3)'s 99.9 % point (16.3) for any ``p`` under 6 %: it would not make a
    flip to it any less silent, only widen the covariance along the flip, the weakly
    seen tilt, for the likely case (on the eval's frames, seeds 7 and 10 at 2-2.5 m:
    mean NEES 2.9 and 1.6 with the mixture, 8.1 and 3.6 without).  The chance itself is
    published (``flip_probability``)."""
    other = max(solutions[:2], key=lambda s: pose.rotation_angle(s.rotation, chosen.rotation))
    d = pose.difference(chosen, other)
    weight = max(chance, COVERED_CHANCE_FLOOR)
    return (1 - weight) * own + weight * (np.outer(d, d) + cov_of(other))


def _tilt(solution: pose.Solution) -> float:
    """The angle (rad) between a solution's marker plane normal and its line of sight."""
    sight = solution.tvec / np.linalg.norm(solution.tvec)
    return math.acos(min(abs(float(solution.rotation[:, 2] @ sight)), 1.0))


def _met(own: np.ndarray, chosen: pose.Solution, meet_rad: float) -> np.ndarray:
    """The covariance of a pose whose two planar solutions refined to one minimum: the
    marker faces the camera within ``meet_rad`` (:func:`apparent_tilt`), where its
    corners tell its tilt only to second order, so the fit's curvature there claims far
    less than the tilt's spread (a tag 2.8 degrees from facing the camera at 3 m, its
    neighbours' frames covered by 4-15 degrees, was claimed to 1.9 degrees and erred 5.1).
    The tilt lies anywhere within ``meet_rad`` about the line of sight: ``meet_rad² / 4``
    on each of the two axes across it, added to the fit's own."""
    sight = chosen.tvec / np.linalg.norm(chosen.tvec)
    out = own.copy()
    out[3:, 3:] += meet_rad ** 2 / 4 * (np.eye(3) - np.outer(sight, sight))
    return out


def corner_covariance(edge_fit: np.ndarray, corners: np.ndarray, in_image: np.ndarray,
                      modules: int, lock_px: float | np.ndarray = LOCK_PX,
                      gains: np.ndarray | None = None) -> np.ndarray:
    """The joint covariances (m, 8, 8) of the corners (m, 4, 2, ideal pixels) of ``m``
    markers ``modules`` cells wide, at ``in_image`` in the image's pixels (m, 4, 2: where
    the sides' pixel locking is), from their edge fits' (:func:`edges.refine`, times
    ``EDGE_FIT_SCALE``), plus the four sides' offsets and turns that the fits cannot show
    (:func:`side_offset_covariance`, pixel locking of amplitude ``lock_px``, per side
    (m, 4) or one for all, and ``gains``, :func:`edges.refine`'s)."""
    return EDGE_FIT_SCALE * edge_fit + side_offset_covariance(corners, in_image, modules,
                                                              lock_px, gains)


def side_offset_covariance(corners: np.ndarray, in_image: np.ndarray,
                           modules: int, lock_px: float | np.ndarray = LOCK_PX,
                           gains: np.ndarray | None = None) -> np.ndarray:
    """The corners' covariance (m, 8, 8) from their four sides' lines moving across
    themselves: by ``SIDE_A * exp(-across / SIDE_SCALE_PX)`` px, the four sides together
    at ``SIDE_CORRELATION``; each by ``EDGE_SHARE`` of its cells' width and by its pixel
    locking, ``lock_px / sqrt(2)`` times the offset gain of ``gains`` (m, 4, 2), which
    also turns it by the turn gain, as the code's cells behind an uncorrected side do
    (:func:`_code_turn_px`).  Without ``gains``, those of a continuum of phases,
    ``sinc(sweep)`` and :func:`_locked_slope` (``sweep``: how many pixels across its
    nearer image axis the side's fitted span covers in the image, ``in_image``: the
    refined corners there, not the detector's whole pixels, since a pixel's difference in
    ``sweep`` is the whole term).  Corner k is where side k - 1
    ends and side k starts: when side k moves across itself by ``o``, corner k slides
    along side k - 1 by ``o / sin`` of the angle between them, and when side k - 1
    moves, back along side k (the sides' outward directions all flip with the quad's
    orientation, which the covariance does not see)."""
    shift, turn, across = _side_moves(corners, modules)
    sweep = side_sweeps(in_image)
    tau = _side_offset_px(across)
    if gains is None:
        gains = np.stack([np.sinc(sweep), _locked_slope(sweep)], axis=-1)
    own = ((1 - SIDE_CORRELATION) * tau ** 2 + lock_px ** 2 / 2 * gains[..., 0] ** 2
           + (EDGE_SHARE * across) ** 2)
    tilt = lock_px ** 2 / 2 * gains[..., 1] ** 2 + _code_turn_px(across) ** 2
    common = (shift * tau[:, None, :]).sum(axis=-1)
    return (SIDE_CORRELATION * common[:, :, None] * common[:, None, :]
            + (shift * own[:, None, :]) @ np.swapaxes(shift, -1, -2)
            + (turn * tilt[:, None, :]) @ np.swapaxes(turn, -1, -2))


def side_sweeps(in_image: np.ndarray) -> np.ndarray:
    """How many pixels (m, 4) across its nearer image axis each side's fitted span
    covers, its quad's corners ``in_image`` (m, 4, 2) in the image's pixels."""
    in_image = np.asarray(in_image, np.float64)
    return np.abs(in_image[:, _NEXT] - in_image).min(axis=-1) * edges.SPAN


def _locked_slope(sweep: np.ndarray) -> np.ndarray:
    """How far (per unit of locking amplitude) pixel locking turns a side whose fitted span
    sweeps ``sweep`` px across its nearer axis: the crossing's phase runs linearly along
    the span, so its error ``sin(2π(φ + sweep·u))`` (u from -1/2 to 1/2) has a slope the
    line fit takes up, ``12 ∫ u sin(2π sweep u) du``, moving the span's ends by half that
    and the corners, ``1 / SPAN`` times farther out, by ``1 / (2 SPAN)`` of it (zero for a
    side exactly along an axis, largest at about half a pixel, gone once the phases
    average out over several)."""
    x = np.pi * np.maximum(sweep, 1e-6)
    return 12 * (np.sin(x) - x * np.cos(x)) / (2 * x ** 2) / (2 * edges.SPAN)


def tag_scale(corners: np.ndarray, modules: int) -> np.ndarray:
    """How the corners (m, 8) of ``m`` markers move with the tag-wide part of their
    sides' offsets, one standard deviation (:func:`side_offset_covariance`'s first term
    is its outer product)."""
    shift, _, across = _side_moves(corners, modules)
    return np.sqrt(SIDE_CORRELATION) * (shift * _side_offset_px(across)[:, None, :]).sum(axis=-1)


def _side_offset_px(across: np.ndarray) -> np.ndarray:
    """How far (px, one standard deviation) a side's line errs across itself where its
    cells are ``across`` px wide: ``SIDE_A * exp(-across / SIDE_SCALE_PX)``."""
    return SIDE_A * np.exp(across / -SIDE_SCALE_PX)


def _code_turn_px(across: np.ndarray) -> np.ndarray:
    """How far (px, one standard deviation) the code's cells behind a side turn it, its
    ends moving oppositely, where its cells are ``across`` px wide: ``CODE_TURN_A *
    exp(-across / CODE_TURN_SCALE_PX)`` where its crossings are not corrected for them
    (``edges.CODE_CELL_PX`` or wider), none where they are."""
    return np.where(across >= edges.CODE_CELL_PX,
                    CODE_TURN_A * np.exp(across / -CODE_TURN_SCALE_PX), 0.0)


def _side_moves(corners: np.ndarray, modules: int,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per marker of ``corners`` (m, 4, 2): how its corners (8) move when each side (4)
    moves outwards by 1 px (m, 8, 4), and when each side turns about its middle, its end
    moving outwards by 1 px and its start inwards (m, 8, 4); and the cells' width
    across each side (m, 4, px: :func:`edges.cell_widths`)."""
    corners = np.asarray(corners, np.float64)
    side = corners[:, _NEXT] - corners
    along = side / np.sqrt(side[..., 0] ** 2 + side[..., 1] ** 2)[..., None]
    before = along[:, _PREV]
    sine = (before[..., 0] * along[..., 1] - before[..., 1] * along[..., 0])[..., None, None]
    by_ending = -along[..., None] / sine * _ENDING  # (m, 4 corners, 2, 4 sides)
    by_starting = before[..., None] / sine * _STARTING
    return ((by_ending + by_starting).reshape(-1, 8, 4),
            (by_ending - by_starting).reshape(-1, 8, 4), edges.cell_widths(corners, modules))


_NEXT, _PREV = [1, 2, 3, 0], [3, 0, 1, 2]
#: corner k is where side k - 1 ends and side k starts
_ENDING = np.eye(4)[_PREV][:, None, :]
_STARTING = np.eye(4)[:, None, :]


def bundle_covariance(blocks: list[np.ndarray], corners: list[np.ndarray],
                      modules: int) -> np.ndarray:
    """The joint covariance of a bundle's markers' corners: each marker's own (8, 8)
    ``blocks`` along the diagonal, and between two markers their tag-wide side offsets
    (:func:`tag_scale` of their ``corners``, (4, 2) each) at ``TAG_CORRELATION``.  A
    marker whose corners come from the image fit (its cells under
    ``image_fit.CELL_PX`` across a side) has errors of its own: it shares none; nor
    does any marker more of that offset than its own block carries."""
    stacked = np.stack(corners)
    scale = tag_scale(stacked, modules)
    scale[edges.cell_widths(stacked, modules).min(axis=1) < image_fit.CELL_PX] = 0.0
    for k, b in enumerate(blocks):
        scale[k] /= math.sqrt(max(1.0, scale[k] @ np.linalg.solve(b, scale[k])))
    out = np.zeros((8 * len(blocks), 8 * len(blocks)))
    for k, b in enumerate(blocks):
        out[8 * k:8 * k + 8, 8 * k:8 * k + 8] = b - TAG_CORRELATION * np.outer(scale[k], scale[k])
    flat = scale.reshape(-1)
    return out + TAG_CORRELATION * np.outer(flat, flat)


def _weighted_gap(solutions: list[pose.Solution], information: np.ndarray,
                  ) -> tuple[list[pose.Solution], float]:
    """A bundle's two best ``solutions`` ordered by their corners' residual χ² weighted by
    the corners' joint inverse covariance ``information`` (each at its weighted minimum,
    :func:`pose.reweigh`), and the χ² between them: the gap the ambiguity is judged by.
    A lone marker's gap is judged at a floor of its corner noise
    (:func:`corner_floor_px`: its four corners move together and its fit absorbs it); a
    bundle's markers spread that over a plate, and its joint covariance carries what
    they share (:func:`bundle_covariance`).  On the eval's bundle scenes (seeds 1-10 and
    101-110) the bundle's two solutions lie 9-15 mm and 5-15 degrees apart where the
    floor's gap is 1-11 (61 of 1,717 frames ``covered`` or decided by history, the
    chosen one right in all); weighted, the gaps are 12-1,700 and decide."""
    two = pose.reweigh(pose.Fits.of(solutions[:2]), np.stack([information] * 2))
    chi2 = np.einsum("mi,ij,mj->m", two.residual, information, two.residual)
    order = [0, 1] if chi2[0] <= chi2[1] else [1, 0]
    return [solutions[i] for i in order] + solutions[2:], float(abs(chi2[1] - chi2[0]))


def _moved(R: np.ndarray, t: np.ndarray, T_marker_body: np.ndarray,
           ) -> tuple[np.ndarray, np.ndarray]:
    """A marker's pose (R, t) in the camera frame -> its body's."""
    return R @ T_marker_body[:3, :3], R @ T_marker_body[:3, 3] + t


def _quad_areas(quads: np.ndarray) -> np.ndarray:
    """The areas (m,) of quadrilaterals (m, 4, 2) (the shoelace formula)."""
    x, y = quads[..., 0], quads[..., 1]
    nxt = [1, 2, 3, 0]
    return 0.5 * np.abs((x * y[:, nxt] - x[:, nxt] * y).sum(axis=1))


def detector_parameters() -> cv2.aruco.DetectorParameters:
    """OpenCV's defaults but for two things.  One adaptive-threshold pass with a 5 px
    window instead of three (3, 13 and 23 px): a 3 px window alone lost sharp, close
    tags (21-27 of 30 frames), 5 px none.  And 8 pixels per cell, not 4, in the
    canonical image the bits are read from (a far tag's cells are read from less of their
    blurred edges).  Tags found on the frames of ``uma eval fiducials`` seeds 1-10 at
    0.5-1 / 1-1.5 / 1.5-2 / 2-2.5 / 2.5-3 m: 290 / 137 / 117 / 46 / 10, where OpenCV's
    defaults found 290 / 136 / 112 / 45 / 5 and AprilTag 3 286 / 132 / 123 / 52 / 11;
    198 of 200 at 0.2-0.6 m (the defaults 190) and as many as the defaults with ten tags
    at 0.6-1.6 m (436), no wrong id, in 0.3-0.4 of the defaults' time.  Corners are not
    refined by OpenCV (:mod:`services.fiducials.edges` does it)."""
    p = cv2.aruco.DetectorParameters()
    p.adaptiveThreshWinSizeMin = p.adaptiveThreshWinSizeMax = 5
    p.perspectiveRemovePixelPerCell = 8
    return p


@dataclass
class _BodyState:
    pool: deque = field(default_factory=deque)  # (rss, dof) of the last POOL_FRAMES fits
    rss: float = 0.0
    dof: int = 0
    branch: np.ndarray | None = None  # rotation of the branch the evidence favours
    llr: float = 0.0  # its log-likelihood ratio against the other (>= 0)
    branch_ns: int = 0
    turn2: float = TURN_PRIOR_RAD_S ** 2  # running mean square angular speed, rad²/s²

    def add(self, rss: float, dof: int) -> None:
        self.pool.append((rss, dof))
        self.rss += rss
        self.dof += dof
        if len(self.pool) > POOL_FRAMES:
            old_rss, old_dof = self.pool.popleft()
            self.rss -= old_rss
            self.dof -= old_dof


@dataclass
class _Pick:
    """One body's solutions in a frame and what was chosen from them."""

    body: Body
    ids: list[int]
    solutions: list[pose.Solution]
    module_px: float
    sigma2: float
    chosen: pose.Solution
    ambiguity: str
    gap: float
    flip_probability: float


class FiducialTracker:
    """Tracks the markers of one family seen by one calibrated camera."""

    def __init__(self, camera: CameraModel, family: str, size_m: float | None,
                 sizes: dict[int, float] | None = None, bundles: list[Body] | None = None,
                 name_of: dict[int, str] | None = None) -> None:
        self.camera = camera
        self.family = family
        self.size_m = size_m
        self.sizes = dict(sizes or {})
        d = dictionary(family)
        self.detector = cv2.aruco.ArucoDetector(d, detector_parameters())
        self._modules = d.markerSize + 2
        self._cells = border.code_cells(d)
        self._K = camera.K
        camera.ideal_offsets()  # the edge points' undistortion table, before the first frame
        self._locking = edges.Locking()
        self.bundles = list(bundles or [])
        self._bundle_of = {i: b for b in self.bundles for i in b.corners}
        self._name_of = dict(name_of or {})
        self._singles: dict[int, Body] = {}
        self._state: dict[str, _BodyState] = {}
        self._frames: dict[tuple[str, int], tuple[np.ndarray, float]] = {}
        prior = camera.pixel_std if camera.pixel_std else DEFAULT_PIXEL_STD
        self._prior_sigma2 = prior ** 2
        #: ids seen that are neither in a bundle nor of a known size (no --size)
        self.unsized: set[int] = set()

    def detect(self, image: np.ndarray) -> dict[int, np.ndarray]:
        """Marker id -> its four corners (4, 2) in ideal pixels (distortion removed)."""
        return self.observe(image)[0]

    def observe(self, image: np.ndarray,
                ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """Marker id -> its four corners (4, 2) in ideal pixels (distortion removed), and
        marker id -> their joint covariance (8, 8) (:func:`corner_covariance`)."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _ = self.detector.detectMarkers(gray)
        if ids is None:
            return {}, {}
        detected = np.asarray(corners, np.float64).reshape(-1, 4, 2)
        cells = self._cells[ids.ravel()]
        placed = edges.place(gray, detected, self._modules)
        # the detector's corners and the first pass's undistorted in one call: the lens'
        # offset at each corner, and the cells' widths the image fit is gated on
        both = self.camera.ideal_pixels(np.concatenate([detected, placed])).reshape(-1, 4, 2)
        lens = detected - both[:len(detected)]
        across = edges.cell_widths(both[len(detected):], self._modules)
        # the tags the image fit is for: their edge fits only start it, the border model
        # and the code's correction of their crossings are left out unless it fails
        whole = image_fit.gate(across)
        ideal, cov = self._edge_fits(gray, detected, lens, placed, cells, ~whole, True)
        ideal, cov, fitted = image_fit.refine(gray, ideal, cov, across, cells, self.camera)
        failed = np.flatnonzero(whole & ~fitted)
        if len(failed):
            ideal[failed], cov[failed] = self._edge_fits(gray, detected[failed], lens[failed],
                                                         placed[failed], cells[failed], None,
                                                         False)
        keys = [int(i) for i in ids.ravel()]
        return dict(zip(keys, ideal, strict=True)), dict(zip(keys, cov, strict=True))

    def _edge_fits(self, gray: np.ndarray, detected: np.ndarray, lens: np.ndarray,
                   placed: np.ndarray, cells: np.ndarray, modelled: np.ndarray | None,
                   learn: bool) -> tuple[np.ndarray, np.ndarray]:
        """The corners (n, 4, 2, ideal pixels) of the ``detected`` markers (n, 4, 2) from
        their edges (:func:`edges.refine`, from ``placed``: :func:`edges.place`; the thin
        sides of those ``modelled`` (all where None) from their ``cells``), and their
        joint covariances (n, 8, 8, :func:`corner_covariance`); ``lens`` (n, 4, 2): the
        distortion's offset at the detected corners; ``learn``: whether their sides teach
        the camera's pixel locking (once a frame: not when the tags the image fit rejected
        are fitted again)."""
        gains = np.empty((len(detected), 4, 2))
        ideal, cov = edges.refine(gray, detected, self._modules, self.camera, cells, placed,
                                  modelled, self._locking, learn, gains)
        # the refined corners in the image's pixels: the distortion's offset is smooth, the
        # detector's corner a pixel away has the same
        in_image = ideal + lens
        return ideal, corner_covariance(cov, ideal, in_image, self._modules,
                                        self._lock_px(side_sweeps(in_image)), gains)

    def _lock_px(self, sweep: np.ndarray) -> np.ndarray:
        """The pixel locking (px) the covariance carries on each side sweeping ``sweep``
        (m, 4) px across its axis: what is left of it (``LOCK_LEFT_PX``, or the learnt
        amplitude's spread) on the sides :func:`edges.refine` takes it out of, and the
        whole of it on the others (the learnt amplitude, its spread added): near an axis
        their fits' scatter has it taken out (:func:`edges._locking_scatter`), so nothing
        else carries what it moves their lines by; farther from one it fades, and so does
        this term (``sinc`` of a sweep of several pixels)."""
        locking = self._locking
        return np.where(sweep < edges.LOCK_SWEEP_PX, max(LOCK_LEFT_PX, locking.spread),
                        math.hypot(locking.amplitude, locking.spread))

    def process(self, image: np.ndarray, t_ns: int) -> list[Estimate]:
        """Every body seen in ``image`` (captured at ``t_ns``)."""
        seen, noise = self.observe(image)
        return self.estimate(seen, t_ns, noise)

    def estimate(self, seen: dict[int, np.ndarray], t_ns: int,
                 noise: dict[int, np.ndarray] | None = None) -> list[Estimate]:
        """Every body among the detected markers ``seen`` (ideal-pixel corners).  With
        ``noise`` (the corners' covariances, :meth:`observe`) the pose is weighted by it
        and its covariance follows from it; without, from the pooled residuals.  The
        lone markers are solved together (:func:`pose.solve_squares`), each bundle on
        its own."""
        groups: dict[str, tuple[Body, list[int]]] = {}
        for marker_id in sorted(seen):
            body = self._body(marker_id)
            if body is not None:
                groups.setdefault(body.name, (body, []))[1].append(marker_id)
        singles = [(body, ids) for body, ids in groups.values() if not body.is_bundle]
        out = self._finish(singles, self._solve_singles(singles, seen), t_ns, seen, noise)
        for body, ids in groups.values():
            if body.is_bundle:
                out += self._finish([(body, ids)], [self._solve_bundle(body, ids, seen)], t_ns,
                                    seen, noise)
        return out

    def _body(self, marker_id: int) -> Body | None:
        if marker_id in self._bundle_of:
            return self._bundle_of[marker_id]
        if marker_id not in self._singles:
            size = self.sizes.get(marker_id, self.size_m)
            if size is None:
                self.unsized.add(marker_id)
                return None
            name = self._name_of.get(marker_id, f"{self.family}-{marker_id}")
            self._singles[marker_id] = marker_body(name, marker_id, size)
        return self._singles[marker_id]

    def _within_px2(self, body: Body) -> float:
        """How much worse than the best an unrefined candidate may fit and still be
        refined as a rival: the ambiguity gap, with a margin, at the body's noise."""
        state = self._state.get(body.name) or _BodyState()
        return 1.5 * AMBIGUITY_GAP * max(self._sigma2(state), self._prior_sigma2)

    def _solve_singles(self, singles: list[tuple[Body, list[int]]],
                       seen: dict[int, np.ndarray]) -> list[tuple[list[pose.Solution], float]]:
        """Each lone marker's solutions and module size (px), all markers at once."""
        if not singles:
            return []
        corners = np.stack([seen[ids[0]] for _, ids in singles])
        sizes = np.array([self._marker_frame(body, ids[0])[1] for body, ids in singles])
        within = np.array([self._within_px2(body) for body, _ in singles])
        solutions = pose.solve_squares(corners, sizes, self._K, within)
        module_px = np.sqrt(_quad_areas(corners)) / self._modules
        return list(zip(solutions, module_px.tolist(), strict=True))

    def _solve_bundle(self, body: Body, ids: list[int], seen: dict[int, np.ndarray],
                      ) -> tuple[list[pose.Solution], float]:
        """A bundle's solutions from the candidates of its biggest marker in view, and
        that marker's module size (px)."""
        areas = _quad_areas(np.stack([seen[i] for i in ids]))
        biggest = ids[int(np.argmax(areas))]
        T_marker_body, size = self._marker_frame(body, biggest)
        candidates = [_moved(R, t, T_marker_body)
                      for R, t in pose.square_candidates(seen[biggest], size, self._K)]
        solutions = pose.solve(np.concatenate([body.corners[i] for i in ids]),
                               np.concatenate([seen[i] for i in ids]), self._K, candidates,
                               within_px2=self._within_px2(body))
        return solutions, float(np.sqrt(areas.max())) / self._modules

    def _finish(self, bodies: list[tuple[Body, list[int]]],
                solved: list[tuple[list[pose.Solution], float]], t_ns: int,
                seen: dict[int, np.ndarray],
                noise: dict[int, np.ndarray] | None) -> list[Estimate]:
        """The estimates of bodies of as many corners each: per body the noise pooled and
        the ambiguity judged (a bundle's from its corners' joint covariance, where
        known: :func:`_weighted_gap`); then, all bodies at once, the chosen poses
        weighted by their corners' covariances (a bundle's markers' joint:
        :func:`bundle_covariance` of their corners ``seen``) and their own covariances."""
        weights = self._information(bodies, seen, noise)
        picks, kept = [], []
        for (body, ids), (solutions, module_px), weight in zip(bodies, solved, weights,
                                                                 strict=True):
            if not solutions:
                continue
            state = self._state.setdefault(body.name, _BodyState())
            state.add(solutions[0].rss_px2, solutions[0].dof)
            sigma2 = max(self._sigma2(state), corner_floor_px(module_px) ** 2)
            gap = None
            if weight is not None and len(ids) > 1 and len(solutions) > 1:
                solutions, gap = _weighted_gap(solutions, weight)
            picks.append(_Pick(body, ids, solutions, module_px, sigma2,
                               *self._judge(solutions, sigma2, module_px, state, t_ns, gap,
                                            lone=len(ids) == 1)))
            kept.append(weight)
        if not picks:
            return []
        fit = pose.Fits.of([p.chosen for p in picks])
        information = None if weights[0] is None else np.stack(kept)
        if information is not None:
            fit = pose.reweigh(fit, information)
        sigmas = np.sqrt([p.sigma2 for p in picks])

        def covariances(f: pose.Fits, rows: slice) -> np.ndarray:
            if information is not None:
                return pose.weighted_covariance(f, information[rows])
            return pose.covariance(f, sigmas[rows])

        out = []
        for k, (p, cov) in enumerate(zip(picks, covariances(fit, slice(None)), strict=True)):
            chosen = fit.solution(k)
            if p.ambiguity == "covered" and len(p.solutions) == 1:
                cov = _met(cov, chosen, self._meet(p.sigma2, p.module_px))
            elif p.ambiguity == "covered":
                cov = _covered(
                    cov, chosen, p.solutions,
                    lambda s, k=k: covariances(pose.Fits.of([s]), slice(k, k + 1))[0],
                    p.flip_probability)
            out.append(Estimate(p.body.name, t_ns, chosen.rotation, chosen.tvec, cov,
                                float(sigmas[k]),
                                float(np.sqrt(chosen.rss_px2 / (2 * chosen.n_points))),
                                p.ambiguity, tuple(p.ids), p.gap, p.flip_probability))
        return out

    def _information(self, bodies: list[tuple[Body, list[int]]], seen: dict[int, np.ndarray],
                     noise: dict[int, np.ndarray] | None) -> list[np.ndarray | None]:
        """Per body its corners' joint inverse covariance (a lone marker's from ``noise``,
        a bundle's from :func:`bundle_covariance`); all None unless ``noise`` has every
        marker's."""
        if noise is None or not bodies or not all(i in noise for _, ids in bodies for i in ids):
            return [None] * len(bodies)
        return list(np.linalg.inv(np.stack(
            [noise[ids[0]] if len(ids) == 1 else
             bundle_covariance([noise[i] for i in ids], [seen[i] for i in ids], self._modules)
             for _, ids in bodies])))

    def _meet(self, sigma2: float, module_px: float) -> float:
        """The tilt (rad) within which this marker's two solutions cannot be told apart
        (:func:`apparent_tilt` at the body's corner noise, no less than the prior's)."""
        return apparent_tilt(math.sqrt(max(sigma2, self._prior_sigma2)),
                             module_px * self._modules)

    def _sigma2(self, state: _BodyState) -> float:
        """The corner noise variance pooled over the body's recent fits."""
        prior_dof = max(FULL_DOF - state.dof, PRIOR_DOF)
        return (max(state.rss, 0.0) + prior_dof * self._prior_sigma2) / (state.dof + prior_dof)

    def _marker_frame(self, body: Body, marker_id: int) -> tuple[np.ndarray, float]:
        """(T_marker_body, side) of one of the body's markers, cached."""
        key = (body.name, marker_id)
        if key not in self._frames:
            corners = body.corners[marker_id]
            self._frames[key] = (np.linalg.inv(marker_in_body(corners)),
                                 float(np.linalg.norm(corners[1] - corners[0])))
        return self._frames[key]

    def _judge(self, solutions: list[pose.Solution], sigma2: float, module_px: float,
               state: _BodyState, t_ns: int, gap: float | None = None,
               lone: bool = True) -> tuple[pose.Solution, str, float, float]:
        """(the solution reported, how it was chosen, the χ² gap to the other, the chance
        that the other is the true one); the body's branch evidence moved on to this
        frame.  The gap is ``gap`` where given (a bundle's, :func:`_weighted_gap`), else
        the two fits' residual sums of squares apart in units of ``sigma2``."""
        best = solutions[0]
        other = solutions[1] if len(solutions) > 1 else None
        # judged at no less than the calibration's pixel noise: a noise estimate from a
        # few residual dof can be small by chance, and a gap it inflates is a silent flip
        if gap is None:
            gap = float("inf") if other is None else \
                (other.rss_px2 - best.rss_px2) / max(sigma2, self._prior_sigma2)
        meet = self._meet(sigma2, module_px)
        if lone and other is None and _tilt(best) < meet:
            # both solutions refined to one minimum: the tag faces the camera within what
            # its corners can tell (_met; a bundle's markers spread over its plate tell
            # its tilt to first order)
            self._move_branch(state, best.rotation, 0.0, t_ns)
            return best, "covered", gap, 0.5
        if gap > AMBIGUITY_GAP:  # outweighs anything history carries
            self._move_branch(state, best.rotation, min(gap / 2, _DECISIVE), t_ns)
            return best, "none", gap, _flip(gap / 2)
        carried = self._carried(state, best, other, t_ns, meet)
        llr = carried + gap / 2
        chosen = best if llr >= 0 else other
        self._move_branch(state, chosen.rotation, abs(llr), t_ns)
        if carried * llr > 0 and abs(llr) >= HISTORY_LLR:
            return chosen, "history", gap, _flip(abs(llr))
        return chosen, "covered", gap, _flip(abs(llr))

    @staticmethod
    def _move_branch(state: _BodyState, rotation: np.ndarray, llr: float, t_ns: int) -> None:
        """The favourite branch now at ``rotation`` with ``llr``; the track's mean square
        angular speed updated by the turn from the previous branch, if recent."""
        dt = (t_ns - state.branch_ns) / 1e9
        if state.branch is not None and 0 < dt <= HISTORY_S:
            speed2 = (pose.rotation_angle(rotation, state.branch) / dt) ** 2
            state.turn2 += TURN_WEIGHT * (speed2 - state.turn2)
        state.branch, state.llr, state.branch_ns = rotation, llr, t_ns

    @staticmethod
    def _carried(state: _BodyState, best: pose.Solution, other: pose.Solution,
                 t_ns: int, meet_rad: float) -> float:
        """The log-likelihood ratio of ``best`` against ``other`` that the body's earlier
        frames carry: their favourite's, through one possible switch of the branches
        (:func:`branch_switch`, for the turn the track's angular speed makes in the
        interval, or the one seen now if larger; ``meet_rad``: :func:`apparent_tilt`),
        signed by which solution continues it; 0 when none does clearly."""
        dt = (t_ns - state.branch_ns) / 1e9
        if state.branch is None or not 0 <= dt <= HISTORY_S:
            return 0.0
        d_best = pose.rotation_angle(best.rotation, state.branch)
        d_other = pose.rotation_angle(other.rotation, state.branch)
        near, far = min(d_best, d_other), max(d_best, d_other)
        separation = pose.rotation_angle(best.rotation, other.rotation)
        if near >= HISTORY_SIDE * separation:
            return 0.0
        turn = max(math.sqrt(state.turn2) * dt, near, TURN_FLOOR_RAD)
        p = branch_switch(near, far, separation, turn, meet_rad)
        x = min(state.llr, _DECISIVE)
        kept = math.log(((1 - p) * math.exp(x) + p) / (p * math.exp(x) + 1 - p))
        return kept if d_best <= d_other else -kept


def _flip(llr: float) -> float:
    """The chance of the other solution for a log-likelihood ratio ``llr`` (>= 0) of the
    chosen one against it (0 where there is no other)."""
    return 0.0 if math.isinf(llr) else 1 / (1 + math.exp(min(llr, 700.0)))
