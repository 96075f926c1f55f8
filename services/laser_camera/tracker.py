"""The laser-dot tracker pipeline, pure (no I/O): camera images in, a rig pose or a reason
for having none out.

``LaserTracker(calibration).process(images, t)`` runs, per frame set (Hogue 2003, fig. 5.2):

1. dot detection in every image (``detection``), undistortion, image -> screen
   homography, screen -> world (eq. 5.40); dots near a screen's edge are dropped (a spot
   clipped by the frame has a biased centroid) and dots seen by two overlapping cameras
   merged;
2. with four or more dots, every 4-subset and all 24 labelings scored by eq. 5.6
   (``pose``); labelings above ``max_labeling_error`` are impossible geometries;
3. a labeling is kept only if its four dots fit one pose within their covariance: four
   dots on their walls hold eight coordinates for six of pose, and the two left over
   (where the fourth beam meets its dot, given the pose of the other three) are a
   chi-square test of 2 dof against each dot's noise and installation error -- eps of
   eq. 5.6 screens out impossible geometries but has no scale, and a labeling that
   takes a stray blob a few centimetres from a true dot scores an eps only a little worse;
4. the choice among the survivors -- the true labeling and its reflection always score
   alike -- by temporal coherence: the sum of that chi-square and the pose's Mahalanobis
   distance from the pose predicted at constant velocity from the last two (the error
   quaternion of eqs. 5.10-5.11, given a scale by the head's acceleration); with no
   recent pose, by the upright assumption of the thesis' initialisation (the head's up
   axis, the rig's z, is the one closer to the world's up; the reflection turns that
   axis to the horizontal, so knowing which wall the user faces, the thesis' second
   assumption, is not needed with this housing);
5. the margin: a labeling is published only if every other surviving labeling whose pose
   lies outside the chosen pose's covariance scores clearly worse (``min_margin``, or
   ``init_margin_cos`` of up-axis cosine at initialisation); else the frame set is
   ambiguous and gives no pose -- a confident wrong pose is worse than none;
6. gating: a pose far from the prediction, or that moved or turned faster than a head
   can, is refused;
7. a 6x6 covariance by first-order propagation of each dot's measured uncertainty;
8. the pose corrected by the installation's errors estimated so far from the fourth beam's
   misses (``installation_estimate``; ``estimate_installation``, on by default), its
   covariance carrying what that estimate has not pinned down instead of the tolerances.

Anything that prevents a pose (fewer than four dots, no consistent labeling, dots that
fit no pose, an ambiguous labeling, a gated jump, ...) yields ``NoPose`` with the reason,
counted in ``tracker.counts`` -- never an exception.

``label_dots(result)`` gives the labeled dots of the frame set, for one-dot-at-a-time
(SCAAT) fusion: a pose's four, and without a pose the dots it can label by each spot's
predicted position (temporal coherence), each with its noise and installation std.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import lru_cache
from itertools import combinations
from typing import Any, NamedTuple

import numpy as np
from scipy.special import gammaincinv

from agent import geometry as geo
from agent.errors import InvalidInputError
from agent.runtime import compiled_twin
from services.installation.laser_housing import BEAM_DIRECTIONS
from services.laser_camera.calibration import Calibration, CameraCalibration
from services.laser_camera.detection import STD, UV, detect_dots, detect_dots_in
from services.laser_camera.installation_estimate import InstallationEstimate
from services.laser_camera.pose import (
    LabeledPose,
    candidate_poses,
    frames_from_points,
)

#: why a frame set gave no pose
NO_POSE_REASONS = ("too_few_dots", "too_many_dots", "no_consistent_labeling",
                   "inconsistent_dots", "ambiguous_labeling", "not_upright", "gated_jump",
                   "residual_jump", "unconfirmed_labeling", "degenerate")
#: the reasons that refuse a frame set whose dots were all there: the labeling gate
GATE_REASONS = ("inconsistent_dots", "ambiguous_labeling", "gated_jump", "residual_jump",
                "unconfirmed_labeling")
#: the refusals that hold a frame set's dots themselves in doubt: none of them is labeled
#: by the prediction either (``LaserTracker.label_dots``)
DOUBTED_DOTS_REASONS = (*GATE_REASONS, "no_consistent_labeling")


@dataclass(frozen=True)
class TrackerParams:
    """Tuning of the tracker; defaults suit IVY and human head motion."""

    max_labeling_error: float = 0.08  # eps of eq. 5.6 (sum of cosines + m^2 + 0/1)
    #: a dot this close to a screen's edge may be clipped by it (a biased centroid): it is
    #: kept with more uncertainty, so a pose is still possible, at its cost: the centroid
    #: bias of a Gaussian spot the edge cuts there (``clipped_spot_bias``), at most
    #: ``edge_std_m``, which is also the bias of a spot centred on the edge (std 5 mm)
    edge_guard_m: float = 0.012
    edge_std_m: float = 0.004
    merge_world_m: float = 0.03  # dots of overlapping cameras closer than this are one
    max_dots: int = 8  # more candidates than this: no pose (C(8, 4) = 70 subsets at most)
    max_angular_speed_dps: float = 500.0  # gating: faster turns are refused
    max_speed_mps: float = 3.0  # gating: faster moves are refused
    gate_margin_deg: float = 3.0
    gate_margin_m: float = 0.05
    coherence_s: float = 0.3  # beyond this gap without a pose, re-initialise (upright)
    min_upright_cos: float = 0.3  # initialisation needs the rig's z within ~73 deg of up
    #: a labeling's dots must fit its pose: chi-square (2 dof) of the fourth beam's miss
    #: against the dots' whole covariance at most this (chi2(2)'s 1 - 1e-4 quantile)
    max_residual_chi2: float = 18.4
    #: a pose must lie this near the predicted one: Mahalanobis distance squared (6 dof)
    #: under the motion model below at most this (chi2(6)'s 1 - 1e-4 quantile)
    max_prediction_chi2: float = 27.9
    #: the constant-velocity prediction misses by the head's acceleration: 1 sigma per
    #: axis (fast head turns reach some 1,000-3,000 deg/s^2); with one pose only, held,
    #: it misses by the head's speed
    accel_std_mps2: float = 10.0
    angular_accel_std_dps2: float = 2000.0
    speed_std_mps: float = 1.0
    angular_speed_std_dps: float = 200.0
    #: a rival labeling (its pose outside the chosen one's covariance) must score this
    #: much worse (chi-square + prediction distance, i.e. -2 log likelihood: e^-5 as likely)
    #: or the frame set is ambiguous; at initialisation its up axis must be this much less
    #: upright (cosine) unless its chi-square alone is that much worse
    min_margin: float = 10.0
    init_margin_cos: float = 0.25
    #: the fourth beam's miss is mostly the installation's error, which holds from frame
    #: set to frame set: a labeling is published only if its miss agrees with the last one
    #: kept within the dots' noise, plus this share of the installation's part per metre
    #: the dots moved since (the bent screens and turned cameras change it over tens of
    #: centimetres: on seeds 1-5 the change over 9 frame sets, dots 0.3 m on, was about
    #: 0.4 of it), plus all of it for a dot now on another wall
    residual_drift_per_m: float = 2.0
    #: a rival whose pose lies within the chosen pose's covariance (Mahalanobis distance
    #: squared, 6 dof, at most this: chi2(6)'s 1 - 1e-4 quantile) is the same answer
    same_pose_chi2: float = 27.9
    #: a blob nearer a spot than this is part of it for the detector (a spot is some 5
    #: mm wide, std): a labeling is published with its own covariance only if its fourth
    #: dot's miss would show a stray blob farther away in the place of any dot that fixes
    #: the pose; else with the covariance widened by every pose such a blob could give
    #: (``_unseen_stray``), never a confident wrong pose
    stray_min_m: float = 0.01
    #: ... and a labeling that confirms a held one (a start's) is refused for that until
    #: this many frame sets in a row held it with continuous misses, and that one widened:
    #: a blob in one frame set of a start is refused where it can be, while noisier dots
    #: (a calibration that states no error gets ``calib_sigma_m``), whose miss can rarely
    #: show such a blob, cannot hold a start without bound
    start_confirm_sets: int = 3
    #: calibration error of a dot on the screen (1 sigma) when the file does not tell
    calib_sigma_m: float = 0.0005
    #: the miss's change test takes the dots' assumed frame-to-frame noise scaled down to
    #: what the changes of the last this many frame sets that passed it show (an upper
    #: bound, ``_NoiseScale``): an assumed noise above the dots' (a calibration that states
    #: no error gets ``calib_sigma_m`` per dot, a homography's error that holds from frame
    #: set to frame set) lets stray blobs a centimetre long pass the test, so almost every
    #: pose left widened by the cover; and the dots' std is taken up, for every test and
    #: the pose's covariance, where those changes show more noise than assumed beyond
    #: doubt (``_NoiseScale.excess``); 0: the assumed noise as it is
    noise_pool_changes: int = 150
    #: errors the dots cannot reveal, added to every pose covariance (1 sigma, per axis;
    #: default: none -- the installation's tolerances below model them dot by dot)
    model_pos_std_m: float = 0.0
    model_rot_std_rad: float = 0.0
    #: tolerances of the installation (1 sigma), each moving a dot on its wall: the
    #: housing's beam directions and their miss distance from P0, the fabric screens' bend
    #: at their centres, and the cameras' turn since calibration seen on the screen
    #: (docs/SIMULATION.md; ``TrackerParams.ideal()`` for an ideal installation)
    housing_dir_std_rad: float = math.radians(0.02)
    housing_offset_std_m: float = 0.0005
    screen_bulge_std_m: float = 0.002
    camera_residual_std_m: float = 0.0006
    #: ... seen from the cameras' optical centres when the tracker knows them (from the
    #: calibration): each camera turned by this much about each axis, which moves a dot
    #: far from the camera's axis more (instead of ``camera_residual_std_m``)
    camera_turn_std_rad: float = math.radians(0.015)
    #: while tracking, each dot is looked for only in a window of this half-size (pixels)
    #: around its predicted position (Dorfmueller-Ulhaas §2); 0: always the full frame
    roi_half_px: int = 24
    #: a full-frame pass at least this often picks up dots the windows cannot (a dot
    #: entering a camera's view, a second camera seeing a dot in an overlap)
    roi_refresh_s: float = 0.5
    #: a dot of a frame set without a pose gets the label of the nearest predicted spot
    #: (``label_dots``) if that is within this distance (m) plus ``label_gate_mps`` times
    #: the age of the sightings it was predicted from: at 15 Hz on seeds 1-10 the
    #: prediction was off by up to ~1.5 m/s times that age (a fast head, one or more frame
    #: sets without a pose), while the predicted spots of two labels on a wall were at
    #: least 1.8 m apart (the beams are orthogonal)
    label_gate_m: float = 0.05
    label_gate_mps: float = 1.5
    #: estimate the installation's errors online from the fourth beam's miss and correct
    #: each pose and its dots by the estimate so far (``installation_estimate``); the
    #: pose's covariance then carries the estimate's remaining error instead of the whole
    #: tolerances.  False: every pose carries the whole tolerances as covariance
    estimate_installation: bool = True
    #: the miss's noise in the estimate: the dots' own plus this (1 sigma, per axis), for
    #: what holds over a few frame sets but is no parameter (a spot's centroid bias where
    #: the projected imagery crosses it, the screen maps' error beyond a homography's)
    estimate_miss_floor_m: float = 0.0002
    #: a frame set's miss enters the estimate only if it agrees with the estimate so far:
    #: chi-square (2 dof) of its innovation at most this (chi2(2)'s 1 - 1e-4 quantile, as
    #: ``max_residual_chi2``, which is the same test against the tolerances alone)
    estimate_gate_chi2: float = 18.4

    def __post_init__(self) -> None:
        if self.max_dots < 4:
            raise InvalidInputError("max_dots must be at least 4")
        if self.coherence_s <= 0 or self.max_labeling_error <= 0:
            raise InvalidInputError("coherence_s and max_labeling_error must be positive")
        if min(self.max_residual_chi2, self.max_prediction_chi2, self.same_pose_chi2,
               self.accel_std_mps2,
               self.angular_accel_std_dps2, self.speed_std_mps,
               self.angular_speed_std_dps) <= 0 or min(self.min_margin,
                                                       self.init_margin_cos) < 0:
            raise InvalidInputError("the labeling gate's chi-square bounds and motion stds must be "
                                    "positive, its margins >= 0")
        if self.model_pos_std_m < 0 or self.model_rot_std_rad < 0:
            raise InvalidInputError("model_pos_std_m and model_rot_std_rad must be >= 0")
        if not self.stray_min_m > 0:
            raise InvalidInputError("stray_min_m must be positive")
        if self.start_confirm_sets < 2:
            raise InvalidInputError("start_confirm_sets must be at least 2 (a held labeling "
                                    "is confirmed by a later frame set)")
        if self.roi_half_px < 0 or self.roi_refresh_s < 0:
            raise InvalidInputError("roi_half_px and roi_refresh_s must be >= 0")
        if self.noise_pool_changes < 0:
            raise InvalidInputError("noise_pool_changes must be >= 0")
        if not self.residual_drift_per_m > 0:
            raise InvalidInputError("residual_drift_per_m must be positive")
        if not (self.estimate_miss_floor_m >= 0 and self.estimate_gate_chi2 > 0):
            raise InvalidInputError("estimate_miss_floor_m must be >= 0 and estimate_gate_chi2 "
                                    "positive")
        if not (self.label_gate_m > 0 and self.label_gate_mps >= 0):
            raise InvalidInputError("label_gate_m must be positive and label_gate_mps >= 0")
        if min(self.housing_dir_std_rad, self.housing_offset_std_m, self.screen_bulge_std_m,
               self.camera_residual_std_m, self.camera_turn_std_rad) < 0:
            raise InvalidInputError("the installation's tolerances must be >= 0")

    @classmethod
    def ideal(cls, **overrides) -> TrackerParams:
        """Parameters for an ideal installation: no tolerances beyond the dots' own, so
        no installation to estimate either (unless ``estimate_installation`` is given)."""
        return cls(**{"housing_dir_std_rad": 0.0, "housing_offset_std_m": 0.0,
                      "screen_bulge_std_m": 0.0, "camera_residual_std_m": 0.0,
                      "camera_turn_std_rad": 0.0, "estimate_installation": False,
                      **overrides})


@dataclass(frozen=True)
class WorldDots:
    """Dots of one frame set in world coordinates."""

    points: np.ndarray  # (n, 3)
    std_m: np.ndarray  # (n,) in-plane standard deviation of each dot
    walls: list[str]  # wall of each dot
    axes: np.ndarray  # (n, 2, 3) the wall's in-plane unit axes (for error propagation)
    cameras: list[str]
    #: (n,) how far a bending screen moves at each dot, relative to its centre (0..1; None:
    #: unknown, taken as 1)
    bend: np.ndarray | None = None
    #: (n, 3) the optical centre of the camera that saw each dot (None: unknown; then a
    #: camera's turn moves a dot by ``camera_residual_std_m`` and a bent screen's parallax
    #: towards the camera is not modelled)
    eyes: np.ndarray | None = None
    #: (n,) the part of ``std_m`` a dot has for lying within ``edge_guard_m`` of its
    #: screen's edge (None: none): a clipped spot's centroid is biased by where the edge
    #: cuts it, which moves with the spot, not from frame set to frame set
    edge_m: np.ndarray | None = None


@dataclass(frozen=True)
class PoseEstimate:
    """A rig pose (``marvin/laser_rig`` in ``ivy/world``) from one frame set."""

    t: float
    position: np.ndarray  # (3,) P0, metres
    quaternion: np.ndarray  # (4,) xyzw
    covariance: np.ndarray  # (6, 6) over xi = [rho, phi], left perturbation
    dots: dict[int, np.ndarray]  # diode label -> world point of its spot
    dot_std_m: dict[int, float]  # diode label -> in-plane std of that spot
    labeling_error: float  # eps of the chosen labeling
    n_dots: int  # candidates detected
    reinitialised: bool  # chosen by the upright rule, not temporal coherence
    #: the part of ``covariance`` that persists from frame to frame (the installation's
    #: tolerances and the model error): no number of frames averages it away
    systematic: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    timing_s: dict[str, float] = field(default_factory=dict)
    #: diode label -> per-axis in-plane std of that spot's installation error (the dot's
    #: share of ``systematic``)
    dot_systematic_std_m: dict[int, float] = field(default_factory=dict)
    #: the pose's error per one standard deviation of each direction of the installation
    #: estimate's remaining error (:func:`installation_sensitivity`), where the tracker
    #: corrected the pose by its online estimate; None: not corrected
    sensitivity: dict[str, np.ndarray] | None = None
    #: the pose's error per one standard deviation of each installation parameter's draw,
    #: which every run in the same installation shares (:func:`installation_draw_sensitivity`),
    #: where the tracker corrected the pose by its online estimate; None: not corrected
    draw_sensitivity: dict[str, np.ndarray] | None = None

    @property
    def ok(self) -> bool:
        return True


@dataclass(frozen=True)
class LabeledDots:
    """The labeled laser spots of one frame set, for one-dot-at-a-time (SCAAT) fusion."""

    t: float
    labels: list[int]  # diode label of each spot
    points: np.ndarray  # (n, 3) world
    std_m: np.ndarray  # (n,) per-axis in-plane std of the detection and calibration noise
    #: (n,) per-axis in-plane std of the installation's error at each spot: it holds from
    #: frame to frame, so a filter must not average it away
    systematic_std_m: np.ndarray
    #: True: labeled by the predicted pose (the frame set gave none), False: the pose's own
    predicted: bool


@dataclass(frozen=True)
class NoPose:
    """No pose for this frame set, and why (one of ``NO_POSE_REASONS``)."""

    t: float
    reason: str
    n_dots: int
    detail: str = ""
    timing_s: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return False


class LaserTracker:
    """Rig poses from synchronous camera images, with temporal coherence between calls."""

    def __init__(self, calibration: Calibration | None, params: TrackerParams | None = None):
        """``calibration`` may be None for a tracker fed world-frame dots (``solve``)."""
        self.calibration = calibration
        self.params = params or TrackerParams()
        self.counts: Counter[str] = Counter()
        #: detection passes: "full" frame or "roi" (predicted windows only)
        self.passes: Counter[str] = Counter()
        self._last: PoseEstimate | None = None
        self._prev: PoseEstimate | None = None  # the pose before ``_last``: its motion
        self._dots: WorldDots | None = None  # the dots of the last frame set solved
        #: the fourth beam's miss of the last labeling published or held for confirmation
        self._miss: _Miss | None = None
        #: diode label -> its last two labeled sightings (t, world point, wall)
        self._spots: dict[int, tuple[tuple[float, np.ndarray, str], ...]] = {}
        self._seen = _SeenDots()
        #: the last fit's miss model (``_miss_model``): a frame set asks for it twice
        self._model: tuple[_Fit, WorldDots, tuple] | None = None
        self._keys: list[str] = []
        self._keys_of: object = None  # the estimate ``_keys`` name
        self._screens = None if calibration is None else _Screens(
            calibration.cameras, self.params.calib_sigma_m)
        #: the installation's errors estimated from the fourth beam's misses (None: off);
        #: the installation does not change when tracking starts again, so ``reset`` keeps it
        self.installation = InstallationEstimate(self.params.estimate_gate_chi2) \
            if self.params.estimate_installation else None
        #: the share of the dots' assumed noise their misses' changes show; the dots'
        #: noise does not change when tracking starts again, so ``reset`` keeps it
        self.noise = _NoiseScale(self.params.noise_pool_changes)

    def reset(self) -> None:
        """Forget the previous pose: the next one is chosen by the upright rule (and its
        dots found in the full frames)."""
        self._last = self._prev = None
        self._miss = None
        self._spots = {}
        self._seen = _SeenDots()

    # ------------------------------------------------------------------ pipeline

    def process(self, images: Mapping[str, np.ndarray], t: float) -> PoseEstimate | NoPose:
        """One frame set (camera name -> 8-bit image) taken at ``t`` seconds.

        While tracking, the dots are looked for only in windows around their predicted
        positions; the full frames are searched when that finds less than it expects,
        gives no pose, or the last full pass is older than ``roi_refresh_s``."""
        t0 = time.perf_counter()
        result: PoseEstimate | NoPose | None = None
        pose_s = 0.0
        if self._roi_due(t):
            self.passes["roi"] += 1
            found = self._detect_windows(images, t)
            if found is not None:
                result, pose_s = self._solve(self._to_world(found), t)
                if result.ok:
                    self._seen.update(found, t, full=False)
        if result is None or not result.ok:
            self.passes["full"] += 1
            found = self._detections(images)
            self._seen.update(found, t, full=True)
            result, full_pose_s = self._solve(self._to_world(found), t)
            pose_s += full_pose_s
        t1 = time.perf_counter()
        self._count(result)
        return replace(result, timing_s={"detect": t1 - t0 - pose_s, "pose": pose_s,
                                         "total": t1 - t0})

    def detect(self, images: Mapping[str, np.ndarray]) -> WorldDots:
        """World-frame dots of all images, searched in full; unknown camera names raise
        ``ValueError``."""
        return self._to_world(self._detections(images))

    def locate(self, detections: Mapping[str, np.ndarray]) -> WorldDots:
        """World-frame dots of pixel detections given per camera (rows ``U, V, FLUX,
        AREA, STD`` of ``detection``), as ``detect`` finds them in images: for a
        simulation that skips the images."""
        return self._to_world(detections)

    def _detections(self, images: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Each camera's pixel dots, searched in the full frame."""
        return {name: detect_dots(img, self._camera(name, img).detector)
                for name, img in images.items()}

    def _roi_due(self, t: float) -> bool:
        """Whether this frame set may be searched in windows only: tracking, with a recent
        full pass."""
        p, last = self.params, self._last
        return (p.roi_half_px > 0 and last is not None and 0 <= t - last.t <= p.coherence_s
                and 0 <= t - self._seen.full_t < p.roi_refresh_s)

    def _detect_windows(self, images: Mapping[str, np.ndarray],
                        t: float) -> dict[str, np.ndarray] | None:
        """Each camera's pixel dots found in the windows around its predicted dots, or None
        when a window lost its dot or cut a spot (then the full frames are searched)."""
        half = self.params.roi_half_px
        found = {}
        for name, img in images.items():
            cal = self._camera(name, img)
            centres = self._seen.predict(name, t, half)
            if not centres:
                continue
            boxes = [(round(u) - half, round(v) - half, round(u) + half + 1, round(v) + half + 1)
                     for u, v in centres]
            det, whole = detect_dots_in(img, boxes, cal.detector)
            if not whole or not _all_found(centres, det, half):
                return None
            found[name] = det
        return found

    def _camera(self, name: str, img: np.ndarray) -> CameraCalibration:
        """The calibration of camera ``name``, checked against its image."""
        if self.calibration is None:
            raise InvalidInputError("this tracker has no camera calibration; it can only solve() "
                                    "world-frame dots")
        i = self._screens.index.get(name)
        cal = self.calibration.camera(name) if i is None else self._screens.cameras[i]
        if getattr(img, "shape", None) != (cal.height, cal.width):
            raise InvalidInputError(f"camera {name}: image of shape {getattr(img, 'shape', None)}"
                                    f" but calibrated for ({cal.height}, {cal.width}) gray")
        return cal

    def _to_world(self, detections: Mapping[str, np.ndarray]) -> WorldDots:
        """World-frame dots of each camera's detected pixel dots (cameras already checked
        by ``_camera``)."""
        return _merge_duplicates(self._screens.to_world(detections, self.params),
                                 self.params.merge_world_m)

    def solve(self, dots: WorldDots, t: float) -> PoseEstimate | NoPose:
        """The pose from world-frame dots (``detect``'s output), with temporal coherence."""
        result = self._choose(dots, t)
        self._count(result)
        return result

    def _count(self, result: PoseEstimate | NoPose) -> None:
        self.counts["pose" if result.ok else result.reason] += 1

    def _solve(self, dots: WorldDots, t: float) -> tuple[PoseEstimate | NoPose, float]:
        """``_choose`` and the seconds it took."""
        t0 = time.perf_counter()
        return self._choose(dots, t), time.perf_counter() - t0

    def _choose(self, dots: WorldDots, t: float) -> PoseEstimate | NoPose:
        """``solve`` without counting the result: a window pass may be retried in full."""
        p = self.params
        if self.noise.excess > 1.0:  # dots noisier than they say (``_NoiseScale``)
            dots = _noise_taken_up(dots, self.noise.excess)
        self._dots = dots
        n = len(dots.points)
        if n < 4:
            return NoPose(t, "too_few_dots", n, f"{n} dot(s) visible, need 4")
        if n > p.max_dots:
            return NoPose(t, "too_many_dots", n, f"{n} candidates > max_dots {p.max_dots}")
        fits = self._fits(dots, t)
        if isinstance(fits, NoPose):
            return fits
        last = self._last
        tracking = last is not None and 0 <= t - last.t <= p.coherence_s
        picked = self._pick_tracking(fits, t, n) if tracking else _pick_upright(fits, t, n, p)
        if isinstance(picked, NoPose):
            return picked
        k, lead = picked
        best, idx, sys_cov = fits[k].pose, fits[k].idx, fits[k].installation
        try:
            J = _pose_jacobian(dots, idx, best.position, frames=fits[k].frames)
            cov, systematic = _covariance(J, dots.std_m[idx], best.position, p, sys_cov)
        except ValueError as exc:
            return NoPose(t, "degenerate", n, str(exc))
        rival = _rival([f.pose for f in fits], k, lead, cov, p.min_margin, p.same_pose_chi2)
        if rival is not None:
            return NoPose(t, "ambiguous_labeling", n, rival)
        cov = self._confirm(fits[k], dots, t, n, cov, J)
        if isinstance(cov, NoPose):
            return cov
        sys_std = np.sqrt(0.5 * np.trace(sys_cov, axis1=1, axis2=2))
        est = PoseEstimate(
            t, best.position, best.quaternion, cov,
            {k + 1: dots.points[i] for k, i in enumerate(idx)},
            {k + 1: float(dots.std_m[i]) for k, i in enumerate(idx)},
            best.error, n, not tracking, systematic,
            dot_systematic_std_m={k + 1: float(s) for k, s in enumerate(sys_std)})
        self._prev = last if tracking else None
        self._last = est
        self._remember(t, [1, 2, 3, 4], dots.points[idx], [dots.walls[i] for i in idx])
        return est if self.installation is None else self._corrected(est, fits[k], dots, idx, J)

    def _corrected(self, est: PoseEstimate, fit: _Fit, dots: WorldDots, idx: list[int],
                   J: np.ndarray) -> PoseEstimate:
        """``est`` corrected by the installation's estimate, after that took this frame
        set's miss (if it agrees with the estimate so far: ``estimate_gate_chi2``).

        Each parameter moves the four dots by ``D`` per std (:func:`_dot_moves`, each
        screen map's error included), the miss by ``Jm D`` and the pose by
        ``Jp D``: the pose is moved back by ``Jp D mean``, its systematic covariance is
        ``Jp D P (Jp D)^T`` (P the estimate's remaining covariance) instead of the whole
        tolerances', and each dot is moved back by ``D mean`` with ``D P D^T`` as its
        installation error.  The tracker's own gating and prediction keep the measured
        pose (``_last``): the next frame set's candidates are measured ones too.  ``J``:
        the pose's Jacobian (:func:`_pose_jacobian`) at ``est``."""
        p, estimate = self.params, self.installation
        p0 = np.asarray(est.position, float)
        names, D, H, noise = self._miss_model(fit, dots)
        if not estimate.update(fit.miss, noise, names, H):
            self.counts["installation_miss_refused"] += 1
        at, mean, rows = estimate.rows(names)
        S = J @ D.reshape(8, -1)  # J's column 2k + a: dot k along its wall's axis a
        shift = S @ mean  # xi form: the pose's error the estimate explains
        dphi = shift[3:]
        position = p0 - (shift[:3] - geo.skew3(p0) @ dphi)
        quaternion = geo.quat_multiply(geo.rotvec_to_quat(-dphi), est.quaternion)
        root, draw = _estimate_columns(S, at, rows, estimate)
        systematic = draw[:, at] @ S.T + _model_covariance(p0, p)  # S P S^T
        systematic = 0.5 * (systematic + systematic.T)
        points, dot_std = _corrected_dots(dots, idx, D, mean, rows[:, at])
        return replace(
            est, position=position, quaternion=quaternion / np.linalg.norm(quaternion),
            covariance=est.covariance - est.systematic + systematic, systematic=systematic,
            dots={k + 1: points[k] for k in range(len(idx))},
            dot_systematic_std_m={k + 1: float(dot_std[k]) for k in range(len(idx))},
            # each column a row of a contiguous copy: views into a transposed array cost
            # twice as much to make, and a pose holds some ninety of each
            sensitivity=dict(zip(self._estimate_keys(), root.T.copy(), strict=True)),
            draw_sensitivity=dict(zip(estimate.names, draw.T.copy(), strict=True)))

    def _estimate_keys(self) -> list[str]:
        """The sensitivity's name of each of the estimate's parameters (``"estimate "`` and
        its name), in its order: built once per parameter, since an estimate only ever
        appends parameters, not per frame set (some ninety strings); built afresh for
        another estimate put in ``installation``."""
        if self._keys_of is not self.installation:
            self._keys, self._keys_of = [], self.installation
        names = self.installation.names
        self._keys += [f"estimate {name}" for name in names[len(self._keys):]]
        return self._keys

    def _miss_model(self, fit: _Fit, dots: WorldDots,
                    ) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
        """The installation parameters that move the fit's dots, those moves
        (``_moves``), the miss's sensitivity to each (2, len(names): dmiss per std) and
        the miss's noise as the estimate takes it."""
        if self._model is not None and self._model[0] is fit and self._model[1] is dots:
            return self._model[2]
        names, D = self._moves(dots, fit.idx, [1, 2, 3, 4], fit.pose.position,
                               fit.pose.quaternion, fit.slopes)
        H = fit.jacobian.reshape(8, 2).T @ D.reshape(8, -1)  # sum over each dot's axes
        noise = fit.random + self.params.estimate_miss_floor_m ** 2 * np.eye(2)
        model = names, D, H, noise
        self._model = fit, dots, model
        return model

    def _moves(self, dots: WorldDots, idx: list[int], labels: list[int], p0: np.ndarray,
               quaternion: np.ndarray, slopes: _DotSlopes | None = None,
               ) -> tuple[tuple[str, ...], np.ndarray]:
        """How far each dot ``idx`` (diodes ``labels``, rig at ``p0``, ``quaternion``) moves
        along its wall's axes per one std of each installation parameter that moves it, the
        screen maps' included: the parameters' names and the moves (dots, 2 axes, params).
        ``slopes``: the dots' :class:`_DotSlopes` at ``p0`` if already taken."""
        return _dot_moves(dots, idx, labels, p0, quaternion, self.params, slopes, self._screens)

    def _fits(self, dots: WorldDots, t: float) -> list[_Fit] | NoPose:
        """The labelings of every 4-subset whose geometry fits the housing (eps of eq.
        5.6), which, while tracking, a head could have reached since the last pose, and
        whose dots fit one pose (``residual_chi2``)."""
        p, n, last = self.params, len(dots.points), self._last
        cands = [(c, [subset[i] for i in c.order])
                 for subset in combinations(range(n), 4)
                 for c in candidate_poses(dots.points[list(subset)], p.max_labeling_error)]
        if not cands:
            return NoPose(t, "no_consistent_labeling", n,
                          f"no labeling of {n} dots fits the housing (eps > "
                          f"{p.max_labeling_error})")
        if last is not None and 0 <= t - last.t <= p.coherence_s:
            cands = [(c, idx) for c, idx in cands if self._within_reach(c, t)]
            if not cands:
                return NoPose(t, "gated_jump", n, "every labeling moved or turned faster "
                              f"than a head can since the last pose {t - last.t:.3f} s ago")
        miss, random, systematic, jacobian, installation, slopes, (p0s, Rs) = \
            _fourth_beam_parts(dots, [idx for _, idx in cands], [c.position for c, _ in cands],
                               p)
        chi2 = _chi2(miss, random + systematic.sum(axis=1))
        fits = [_Fit(c, idx, float(chi2[j]), miss[j], random[j], systematic[j], jacobian[j],
                     installation[j], slopes.four(j), (p0s[j], Rs[j]))
                for j, (c, idx) in enumerate(cands) if chi2[j] <= p.max_residual_chi2]
        return fits or NoPose(t, "inconsistent_dots", n, "no labeling's dots fit one pose: "
                              f"residual chi-square {float(np.min(chi2)):.1f} > "
                              f"{p.max_residual_chi2:g}")

    def _confirm(self, fit: _Fit, dots: WorldDots, t: float, n: int, cov: np.ndarray,
                 J: np.ndarray) -> NoPose | np.ndarray:
        """The chosen labeling's fourth-beam miss against the last one kept (``_miss``):
        the pose's covariance ``cov`` (``J``: its Jacobian) to publish if they agree, else
        why not.

        The miss is mostly the installation's error, the same from one frame set to the
        next while the same diodes' dots stay on the same walls; a stray blob taken for a
        lost spot moves it by up to the whole chi-square gate (centimetres where a screen
        is seen obliquely) and is refused (``residual_jump``), the last published miss
        kept.  A labeling whose miss cannot be compared (dots moved far or two of them to
        other walls: ``_Miss.change``) stands on its chi-square, the prediction and the
        installation's estimate, which predicts the miss at the new dots within its
        remaining covariance (``_unexplained_miss``; a miss it does not explain is
        refused and held for the next frame set to confirm); it is not held otherwise, as
        one after a loss must not be: holding those lengthened the optical gaps a fusion
        bridges (seed 103 at 15 Hz: 2.1 -> 10 mm RMSE).  The first labeling after a start
        (``reset``) has no miss at all: it is held until the next frame set confirms it
        (``unconfirmed_labeling``); a held miss that the next one does not confirm is
        replaced by it (either may be the stray).  Where a stray blob in the frame set
        could pass the miss's test unseen (``_unseen_stray``: against the last miss, or
        the estimate's prediction where the last cannot be compared), a labeling that
        confirms a held one is refused up to ``start_confirm_sets`` frame sets held in a
        row; that one, and such a labeling while tracking (the prediction cannot tell a
        centimetre within a frame set either), is published with its covariance widened
        to cover every pose the blob could give.  The change test takes both frame sets'
        noise as the changes before showed it (``_NoiseScale``), so dots said to be
        noisier than they are do not let a blob pass unseen.  Where the dots' noise
        outweighs the installation's part (an ideal installation) the chi-square of
        ``_fits`` is as sharp, and nothing is held."""
        p, last = self.params, self._miss
        noise, edge, edge_m = _edge_parts(dots, fit)
        now = _Miss(t, tuple(dots.walls[i] for i in fit.idx), dots.points[fit.idx], fit.miss,
                    noise, fit.systematic, edge, edge_m, excess=self.noise.excess)
        if np.trace(fit.systematic.sum(axis=0) + edge.sum(axis=0)) <= np.trace(noise):
            self._miss = replace(now, confirmed=True)  # the chi-square alone is as sharp
            return cov
        change = None if last is None or t <= last.t else last.change(
            now, p.residual_drift_per_m, self.noise.scale)
        chi2, S, assumed = (None, None, None) if change is None else change
        bound = p.max_residual_chi2
        if chi2 is None and last is not None and last.confirmed:
            unexplained, S, bound = self._unexplained_miss(fit, dots)
            if unexplained is not None:
                self._miss = now
                return NoPose(t, "residual_jump", n, unexplained)
        elif chi2 is None:
            self._miss = now
            return NoPose(t, "unconfirmed_labeling", n, "a labeling's first frame set is held "
                          "until the next one confirms where its fourth dot lies")
        elif chi2 > p.max_residual_chi2:
            if not last.confirmed:
                self._miss = now
            return NoPose(t, "residual_jump", n, "the fourth dot's miss moved off the last "
                          f"frame set's: chi-square {chi2:.1f} > {p.max_residual_chi2:g}")
        else:
            self.noise.add(assumed)
        unseen = _unseen_stray(fit, J, S, cov, p, bound)
        if unseen is None:
            self._miss = replace(now, confirmed=True)
            return cov
        held = last.held + 1
        if unseen.cover is None or not (last.confirmed or held >= p.start_confirm_sets):
            if not last.confirmed:
                self._miss = replace(now, held=held)
            return NoPose(t, "ambiguous_labeling", n, unseen.detail)
        self._miss = replace(now, confirmed=True)
        self.counts["covered_stray"] += 1
        return cov + unseen.cover

    def _unexplained_miss(self, fit: _Fit, dots: WorldDots,
                          ) -> tuple[str | None, np.ndarray, float]:
        """Why the installation's estimate does not explain the fit's miss (chi-square of
        its innovation above ``estimate_gate_chi2``), None if it does or there is no
        estimate; and the covariance and bound the miss was tested under (without an
        estimate: the fit's own chi-square against the whole tolerances).  Where the last
        miss cannot be compared (the dots moved far, changed walls), the estimate still
        predicts the installation's part of the miss at the new dots, within its remaining
        covariance instead of the whole tolerances."""
        p = self.params
        if self.installation is None:
            return None, fit.random + fit.systematic.sum(axis=0), p.max_residual_chi2
        names, _, H, noise = self._miss_model(fit, dots)
        chi2, S = self.installation.innovation_chi2(fit.miss, noise, names, H)
        if chi2 <= p.estimate_gate_chi2:
            return None, S, p.estimate_gate_chi2
        return ("the fourth dot's miss disagrees with the installation's estimate: "
                f"chi-square {chi2:.1f} > {p.estimate_gate_chi2:g}"), S, p.estimate_gate_chi2

    def _pick_tracking(self, fits: list[_Fit], t: float,
                       n: int) -> tuple[int, np.ndarray] | NoPose:
        """Temporal coherence: the fit with the least chi-square plus distance from the
        predicted pose, and how much worse each fit scores than it (its lead)."""
        d2 = self._prediction_distance(t, [f.pose for f in fits])
        score = np.array([f.chi2 for f in fits]) + d2
        k = int(np.argmin(score))
        if d2[k] > self.params.max_prediction_chi2:
            return NoPose(t, "gated_jump", n, "no labeling near the predicted pose: "
                          f"Mahalanobis distance squared {d2[k]:.1f} > "
                          f"{self.params.max_prediction_chi2:g}")
        return k, score - score[k]

    # ------------------------------------------------------------------ labeled dots

    def label_dots(self, result: PoseEstimate | NoPose) -> LabeledDots:
        """The labeled dots of the frame set ``result`` came from (the last one solved).

        With a pose, its four dots.  Without one (fewer than four dots seen, or four
        too nearly degenerate to solve), each dot gets the label whose predicted spot on
        the dot's own wall is nearest, within ``label_gate_m``, one dot per label
        (temporal coherence, Hogue 2003 §5.3: a head moves little in a frame).  A label's
        spot is predicted from its last two labeled sightings on that wall at their
        velocity, which chains through a run of frame sets without a pose; failing that,
        as the beam hit of the pose predicted from the last two.  A dot that gets no label
        is counted in ``counts`` under ``dot_unlabeled_<why>``, never passed on with a
        guessed label.  A frame set refused because its dots disagree with the housing,
        with one pose, with the last miss or with a head's reach (``DOUBTED_DOTS_REASONS``)
        passes on no dot: the prediction would label the dot the gate caught and pass it
        on with its noise's std as if it were sound.  With the installation's estimate the
        dots are corrected by it as a pose's are (through the predicted pose's beams),
        each with the estimate's remaining error as its installation std."""
        if isinstance(result, PoseEstimate):
            labels = sorted(result.dots)
            return LabeledDots(result.t, labels, np.array([result.dots[k] for k in labels]),
                               np.array([result.dot_std_m[k] for k in labels]),
                               np.array([result.dot_systematic_std_m[k] for k in labels]),
                               predicted=False)
        dots = self._dots if self._dots is not None else _no_dots()
        n, t = len(dots.points), result.t
        if n > self.params.max_dots:
            self.counts["dot_unlabeled_too_many_dots"] += n
            return _labeled(t, dots, [], [], np.zeros(3), self.params)
        if result.reason in DOUBTED_DOTS_REASONS:
            self.counts["dot_unlabeled_frame_set_refused"] += n
            return _labeled(t, dots, [], [], np.zeros(3), self.params)
        pose = self._predict(t)
        predictions = [[self._predicted_spot(dots, i, label, t, pose)
                        for label in BEAM_DIRECTIONS] for i in range(n)]
        idx, labels = _nearest_spots(dots.points, predictions, self.params)
        if not any(p is not None for row in predictions for p in row):
            self.counts["dot_unlabeled_no_recent_pose"] += n
        else:
            self.counts["dot_unlabeled_no_spot_within_gate"] += n - len(idx)
        self.counts["dot_labeled_by_prediction"] += len(idx)
        self._remember(t, labels, dots.points[idx], [dots.walls[i] for i in idx])
        p0 = pose[0] if pose is not None else (
            self._last.position if self._last is not None else np.zeros(3))
        labeled = _labeled(t, dots, idx, labels, p0, self.params)
        if self.installation is None or not idx or pose is None:
            return labeled
        names, D = self._moves(dots, idx, labels, p0, pose[1])
        points, dot_std = _corrected_dots(dots, idx, D, self.installation.mean(names),
                                          self.installation.covariance(names))
        return replace(labeled, points=points, systematic_std_m=dot_std)

    def _predicted_spot(self, dots: WorldDots, i: int, label: int, t: float,
                        pose: tuple[np.ndarray, np.ndarray] | None
                        ) -> tuple[np.ndarray, float] | None:
        """Where diode ``label``'s spot should be at ``t`` if it lies on dot ``i``'s wall,
        and the age (s) of what that is predicted from: moved on from its last two
        sightings there, else the predicted pose's beam hit; None if neither is known."""
        seen = self._spots.get(label, ())
        spot = _moved_on(seen, dots.walls[i], t, self.params.coherence_s)
        if spot is not None:
            return spot, t - seen[-1][0]
        hit = None if pose is None else _beam_hit(dots, i, pose[0], geo.quat_to_matrix(pose[1]),
                                                 BEAM_DIRECTIONS[label])
        return None if hit is None else (hit, t - self._last.t)

    def _remember(self, t: float, labels: list[int], points: np.ndarray,
                  walls: list[str]) -> None:
        """Keep each label's last two sightings (time, point, wall)."""
        for label, point, wall in zip(labels, points, walls, strict=True):
            self._spots[label] = (*self._spots.get(label, ())[-1:], (t, point, wall))

    def _predict(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The rig pose (P0, quaternion) at ``t`` moved on from the last pose at the
        motion between the last two (held if there is only one); None beyond
        ``coherence_s`` after the last pose."""
        last, prev = self._last, self._prev
        if last is None or not 0 <= t - last.t <= self.params.coherence_s:
            return None
        p0, q = last.position, last.quaternion
        if prev is not None and last.t > prev.t:
            k = (t - last.t) / (last.t - prev.t)
            p0 = p0 + k * (last.position - prev.position)
            turn = geo.quat_to_rotvec(geo.quat_multiply(last.quaternion,
                                                        geo.quat_conjugate(prev.quaternion)))
            q = geo.quat_multiply(geo.rotvec_to_quat(k * turn), q)
        return p0, q

    def _within_reach(self, pose: LabeledPose, t: float) -> bool:
        """Whether a head could have turned and moved from the last pose to ``pose`` by
        ``t`` (``max_angular_speed_dps``, ``max_speed_mps``, plus the gate's margins).
        Plain floats: numpy's per-call overhead on two quaternions costs more than this."""
        p, last = self.params, self._last
        dt = t - last.t
        cos_half = abs(sum(a * b for a, b in zip(last.quaternion.tolist(),
                                                 pose.quaternion.tolist(), strict=True)))
        turn = math.degrees(2 * math.acos(min(cos_half, 1.0)))
        return (turn <= p.max_angular_speed_dps * dt + p.gate_margin_deg
                and math.dist(pose.position, last.position)
                <= p.max_speed_mps * dt + p.gate_margin_m)

    def _prediction_distance(self, t: float, poses: list[LabeledPose]) -> np.ndarray:
        """Each pose's Mahalanobis distance squared (6 dof) from the pose ``_predict``
        gives at ``t``, under the covariance of that prediction.

        Moved on at constant velocity from the last two poses (``h`` apart) by ``d``, the
        prediction misses by ``a d (d + h) / 2`` for an acceleration ``a``; held (one pose
        only), by ``v d``.  The poses' own random errors add, the last one's weighted
        ``1 + (1 + k)^2 + k^2`` (``k = d / h``: the last, the extrapolated difference, the
        new pose), at least twice when held."""
        p = self.params
        p0, q = self._predict(t)
        last, prev = self._last, self._prev
        d = t - last.t
        if prev is not None and last.t > prev.t:
            h = last.t - prev.t
            reach = 0.5 * d * (d + h)
            pos_std, rot_std = p.accel_std_mps2 * reach, math.radians(
                p.angular_accel_std_dps2) * reach
            k = d / h
            weight = 1 + (1 + k) ** 2 + k ** 2
        else:
            pos_std, rot_std = p.speed_std_mps * d, math.radians(p.angular_speed_std_dps) * d
            weight = 2.0
        C = weight * geo.se3_to_decoupled(last.position, last.covariance - last.systematic)
        C[_DIAG3, _DIAG3] += pos_std ** 2
        C[_DIAG3 + 3, _DIAG3 + 3] += rot_std ** 2
        e = np.array([np.concatenate([c.position - p0, geo.quat_to_rotvec(
            geo.quat_multiply(c.quaternion, geo.quat_conjugate(q)))]) for c in poses])
        return np.einsum("ni,ni->n", e, np.linalg.solve(C, e.T).T)


class _Screens:
    """Every camera's image -> world map, its constants kept as plain floats: a frame set
    holds four to six dots, and on arrays that small numpy's per-call overhead, not the
    arithmetic, was the cost (cProfile of the bench's tracked frame sets: 19 % of the
    pipeline in some thirty numpy calls per frame set, batched over all cameras' dots)."""

    def __init__(self, cameras: list[CameraCalibration], calib_sigma_m: float):
        self.cameras = cameras
        self.index = {c.name: i for i, c in enumerate(cameras)}
        self.axes = np.array([c.wall.rotation[:, :2].T for c in cameras])  # in-plane axes
        self.eyes = np.array([c.centre_world() for c in cameras])
        #: each camera's wall's screen -> world transform and side, and its map's accuracy
        self.translation = np.array([c.wall.translation for c in cameras], float)
        self.rotation = np.array([c.wall.rotation for c in cameras], float)
        self.side = np.array([c.wall.screen_side_m for c in cameras], float)
        self.sigma = np.array([c.screen_sigma_m(calib_sigma_m) for c in cameras])
        self.maps = [_ScreenMap(tuple(np.ravel(c.H).tolist()),
                                tuple(np.ravel(c.wall.rotation).tolist()),
                                tuple(np.ravel(c.wall.translation).tolist()),
                                float(c.wall.plane_distance), float(c.wall.screen_side_m),
                                c.screen_sigma_m(calib_sigma_m)) for c in cameras]

    def map_bases(self, points: np.ndarray, cams: list[int]) -> np.ndarray:
        """How far each dot ``points`` (k, 3) seen by camera ``cams[k]`` moves along its
        wall's axes per one standard deviation of each of that camera's screen map
        parameters (k, 2, 8): the map's error as a small change of its homography
        (``dX = a + b x + c y - X (g x + h y)``, x, y the screen point scaled to [-1, 1]),
        each of its eight coefficients with the calibration's reported per-axis accuracy
        (``screen_sigma_m``) as its std."""
        screen = np.einsum("ki,kij->kj", points + self.translation[cams],
                           self.rotation[cams])[:, :2]
        xy = 2 * screen / self.side[cams][:, None] - 1
        terms = np.concatenate([np.ones((len(xy), 1)), xy, xy.take(_SQUARES_A, 1)
                                * xy.take(_SQUARES_B, 1)], axis=1)  # 1, x, y, xx, xy, yy
        return ((self.sigma[cams][:, None] * terms) @ _MAP_TERMS).reshape(len(xy), 2, 8)

    def to_world(self, detections: Mapping[str, np.ndarray], p: TrackerParams) -> WorldDots:
        """The dots on the active screens, before duplicates are merged."""
        cams: list[int] = []
        dots: list[tuple[list[float], float, float, float]] = []
        for name, d in detections.items():
            if not len(d):
                continue
            i = self.index[name]
            und = self.cameras[i].undistort(d[:, UV]).tolist()
            for (x, y), std_px in zip(und, d[:, STD].tolist(), strict=True):
                dot = self.maps[i].world_dot(x, y, std_px, p)
                if dot is not None:
                    cams.append(i)
                    dots.append(dot)
        if not dots:
            return _no_dots()
        points, std, bend, edge = zip(*dots, strict=True)
        return WorldDots(np.array(points), np.array(std),
                         [self.cameras[i].wall.name for i in cams], self.axes[cams],
                         [self.cameras[i].name for i in cams], np.array(bend), self.eyes[cams],
                         np.array(edge))


@dataclass(frozen=True)
class _ScreenMap:
    """One camera's undistorted pixel -> screen homography (eq. 5.39) and its wall's
    screen -> world transform (eq. 5.40), row-major."""

    H: tuple[float, ...]
    rotation: tuple[float, ...]
    translation: tuple[float, ...]
    plane_m: float
    side_m: float
    sigma_m: float  # the image -> screen map's calibration error (1 sigma, per axis)

    def world_dot(self, x: float, y: float, std_px: float,
                  p: TrackerParams) -> tuple[list[float], float, float, float] | None:
        """The world point of the dot at undistorted pixel ``(x, y)``, its in-plane std
        (the pixel std scaled by the map's Jacobian, the calibration's, and a clipped
        spot's bias near the screen's edge), how far the bending screen moves there
        (0..1) and its edge std (0 away from the edge); None off the active area."""
        h0, h1, h2, h3, h4, h5, h6, h7, h8 = self.H
        w = h6 * x + h7 * y + h8
        if w == 0.0:  # the horizon of the screen's plane: no point on it
            return None
        sx, sy = (h0 * x + h1 * y + h2) / w, (h3 * x + h4 * y + h5) / w
        side, g = self.side_m, p.edge_guard_m
        if not (0.0 <= sx <= side and 0.0 <= sy <= side):
            return None
        inside = min(sx, side - sx, sy, side - sy)
        edge = 0.0 if inside >= g else clipped_spot_bias(inside, p.edge_std_m)
        # the Jacobian of the homography: (H[:2, :2] - screen point x H[2, :2]) / w
        scale = math.sqrt(abs((h0 - sx * h6) / w * ((h4 - sy * h7) / w)
                              - (h1 - sx * h7) / w * ((h3 - sy * h6) / w)))
        std = math.sqrt((std_px * scale) ** 2 + self.sigma_m ** 2 + edge ** 2)
        ux, uy = 2 * sx / side - 1, 2 * sy / side - 1
        bend = max(0.0, 1 - ux ** 2) * max(0.0, 1 - uy ** 2)
        r, t, z = self.rotation, self.translation, self.plane_m
        point = [r[0] * sx + r[1] * sy + r[2] * z - t[0], r[3] * sx + r[4] * sy + r[5] * z - t[1],
                 r[6] * sx + r[7] * sy + r[8] * z - t[2]]
        return point, std, bend, edge


class _SeenDots:
    """Each camera's pixel dots in the last two frame sets: where to look next.

    A camera holds one or two dots: plain floats, not arrays -- numpy's per-call overhead
    on such tiny arrays cost more than the arithmetic (cProfile on the bench's frames)."""

    def __init__(self) -> None:
        self.full_t = -math.inf  # time of the last full-frame pass
        self._last: dict[str, list[list[float]]] = {}
        self._last_t = -math.inf
        self._prev: dict[str, list[list[float]]] = {}
        self._prev_t = -math.inf

    def update(self, detections: Mapping[str, np.ndarray], t: float, full: bool) -> None:
        self._prev, self._prev_t = self._last, self._last_t
        self._last = {name: d[:, UV].tolist() for name, d in detections.items() if len(d)}
        self._last_t = t
        if full:
            self.full_t = t

    def predict(self, name: str, t: float, gate_px: float) -> list[list[float]]:
        """Where camera ``name``'s dots will be at ``t`` ([u, v] each): each moves on at its
        pixel velocity since the nearest dot of the frame set before, if one was that
        near."""
        last = self._last.get(name, [])
        prev = self._prev.get(name)
        if prev is None or not last or not self._prev_t < self._last_t:
            return last
        ratio = (t - self._last_t) / (self._last_t - self._prev_t)
        out = []
        for u, v in last:
            du, dv = min(((u - pu, v - pv) for pu, pv in prev), key=lambda s: math.hypot(*s))
            if not math.hypot(du, dv) <= gate_px:
                du = dv = 0.0
            out.append([u + du * ratio, v + dv * ratio])
        return out


def _all_found(centres: list[list[float]], det: np.ndarray, half: float) -> bool:
    """Whether every window (``half`` around each centre) holds a detected dot."""
    found = det[:, UV].tolist()
    return bool(found) and all(any(max(abs(u - x), abs(v - y)) <= half + 0.5
                                   for x, y in found) for u, v in centres)


def _no_dots() -> WorldDots:
    return WorldDots(np.zeros((0, 3)), np.zeros(0), [], np.zeros((0, 2, 3)), [], np.zeros(0))


def _moved_on(seen: tuple[tuple[float, np.ndarray, str], ...], wall: str, t: float,
              horizon_s: float) -> np.ndarray | None:
    """A spot at ``t`` moved on from its last two sightings ``seen`` at their velocity, if
    both were on ``wall`` and neither gap exceeds ``horizon_s``; else None."""
    if len(seen) < 2:
        return None
    (t0, p0, w0), (t1, p1, w1) = seen
    if w0 != wall or w1 != wall or not (0 < t1 - t0 <= horizon_s and 0 <= t - t1 <= horizon_s):
        return None
    return p1 + (p1 - p0) * ((t - t1) / (t1 - t0))


def _beam_hit(dots: WorldDots, i: int, p0: np.ndarray, R: np.ndarray,
              beam: np.ndarray) -> np.ndarray | None:
    """Where the beam ``beam`` (rig frame) of a rig at (``p0``, ``R``) meets the plane of
    dot ``i``'s wall; None if it runs parallel to it or away from it."""
    normal = np.cross(dots.axes[i, 0], dots.axes[i, 1])
    height = float(normal @ (dots.points[i] - p0))  # the wall's distance from P0
    d = R @ beam
    nd = float(normal @ d)
    if nd <= 1e-6 or height <= 0:
        return None
    return p0 + (height / nd) * d


def _nearest_spots(points: np.ndarray,
                   predictions: list[list[tuple[np.ndarray, float] | None]],
                   p: TrackerParams) -> tuple[list[int], list[int]]:
    """Dot indices and their diode labels: each dot's nearest predicted spot
    (``predictions[i][label - 1]``: the spot and the age of its prediction) within the
    gate for that age, nearest pairs first, every dot and label used once."""
    pairs = [(float(np.linalg.norm(pred[0] - points[i])), i, label,
              p.label_gate_m + p.label_gate_mps * pred[1])
             for i, row in enumerate(predictions)
             for label, pred in zip(BEAM_DIRECTIONS, row, strict=True) if pred is not None]
    idx: list[int] = []
    labels: list[int] = []
    for dist, i, label, gate in sorted(pairs):
        if dist <= gate and i not in idx and label not in labels:
            idx.append(i)
            labels.append(label)
    return idx, labels


def _labeled(t: float, dots: WorldDots, idx: list[int], labels: list[int], p0: np.ndarray,
             params: TrackerParams) -> LabeledDots:
    """``LabeledDots`` of the dots ``idx`` labeled ``labels``, their installation error
    as seen from P0 at ``p0``."""
    sys_var = _installation_variance(dots, idx, p0, params) if idx else np.zeros(0)
    return LabeledDots(t, labels, dots.points[idx].reshape(-1, 3), dots.std_m[idx],
                       np.sqrt(sys_var), predicted=True)


def _corrected_dots(dots: WorldDots, idx: list[int], D: np.ndarray, mean: np.ndarray,
                    P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The dots ``idx`` moved back by the installation's estimate (``D``: each dot's move
    along its wall's axes per parameter, ``mean`` and ``P`` the estimate over those
    parameters), and the per-axis std of each dot's installation error left (D P D^T)."""
    shift = D @ mean
    rows = D.reshape(-1, D.shape[-1])  # (dot, axis) rows: only D P D^T's diagonal is needed
    var = np.einsum("im,im->i", rows @ P, rows).reshape(len(D), 2).sum(axis=1)
    points = dots.points[idx] - np.einsum("ka,kai->ki", shift, dots.axes[idx])
    return points, np.sqrt(0.5 * var)


def _truncated_means() -> tuple[np.ndarray, np.ndarray]:
    """Where a unit Gaussian spot whose centre lies ``x`` inside a straight edge has the
    centroid of its part inside (``x + phi(x) / Phi(x)``, increasing in ``x``), and the
    bias ``phi(x) / Phi(x)`` of that centroid, on a grid of ``x``."""
    x = np.linspace(-6.0, 8.0, 561)
    phi = np.exp(-0.5 * x * x) / math.sqrt(2 * math.pi)
    Phi = 0.5 * (1 + np.array([math.erf(v / math.sqrt(2)) for v in x]))
    return x + phi / Phi, phi / Phi


_CENTROIDS, _BIASES = _truncated_means()


def clipped_spot_bias(inside_m: float, edge_std_m: float) -> float:
    """How far a Gaussian spot's centroid is pulled inwards by a screen's edge that cuts
    it, given where the centroid lies (``inside_m`` from the edge): the truncated mean's
    bias at the spot centre that puts the centroid there.  The spot's std is the one
    whose bias when centred on the edge is ``edge_std_m`` (``edge_std_m * sqrt(pi / 2)``);
    the result is capped at ``edge_std_m``.  A dot 6 mm inside carries 1.7 mm, 10 mm
    inside 0.32 mm: a flat ``edge_std_m`` over the whole guard band would hide a stray
    blob 2 cm from another dot from the fourth beam's miss."""
    sigma = edge_std_m * math.sqrt(math.pi / 2)
    if sigma <= 0.0:
        return 0.0
    bias = sigma * float(np.interp(inside_m / sigma, _CENTROIDS, _BIASES))
    return min(edge_std_m, bias)


def _merge_duplicates(d: WorldDots, tol: float) -> WorldDots:
    """One dot per spot: overlapping cameras (the split floor and ceiling) see some twice."""
    n = len(d.points)
    same_wall = [(i, j) for i in range(n) for j in range(i + 1, n) if d.walls[i] == d.walls[j]]
    if not same_wall:  # the usual frame set: each dot on its own wall
        return d
    keep = np.ones(n, bool)
    pts, std = d.points.copy(), d.std_m.copy()
    edge = np.zeros(n) if d.edge_m is None else d.edge_m.copy()
    for i, j in same_wall:
        if keep[i] and keep[j] and np.linalg.norm(pts[i] - pts[j]) < tol:
            wi, wj = 1 / std[i] ** 2, 1 / std[j] ** 2
            pts[i] = (wi * pts[i] + wj * pts[j]) / (wi + wj)
            std[i] = 1 / np.sqrt(wi + wj)
            edge[i] = np.hypot(wi * edge[i], wj * edge[j]) / (wi + wj)
            keep[j] = False
    if keep.all():
        return d
    k = np.flatnonzero(keep)
    return WorldDots(pts[k], std[k], [d.walls[i] for i in k], d.axes[k],
                     [d.cameras[i] for i in k], None if d.bend is None else d.bend[k],
                     None if d.eyes is None else d.eyes[k], edge[k])


def _installation_variance(dots: WorldDots, idx: list[int], p0: np.ndarray,
                           p: TrackerParams) -> np.ndarray:
    """Per-axis in-plane variance (m^2) each dot ``idx`` gets from the installation's
    tolerances, averaged over the wall's two axes (half the trace of
    :func:`_installation_covariance`): what a dot's published std says."""
    cov = _installation_covariance(dots, idx, p0, p)
    return 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])


def _installation_covariance(dots: WorldDots, idx: list[int], p0: np.ndarray,
                             p: TrackerParams) -> np.ndarray:
    """In-plane covariance (n, 2, 2) over the wall's two axes that each dot ``idx`` gets
    from the installation's tolerances.

    A beam turned by ``d`` (two components, each ``housing_dir_std_rad``) or missing P0 by
    ``o`` moves its dot by ``r d`` or ``o`` across the beam: across the beam's in-plane
    direction ``u`` as it is, along ``u`` stretched by ``1 / cos(incidence)``.  A screen
    bent inwards by ``w`` (times the bend's shape at the dot) meets the beam early, by
    ``w tan(incidence)`` back along ``u``, and the camera behind it sees that spot off the
    plane: the calibrated homography puts it where the camera's ray meets the plane,
    another ``w`` times the ray's in-plane slope -- both one vector times ``w``.  A camera
    turned by ``theta`` since calibration moves the dot where its turned ray meets the
    plane: ``dX = dr - r (n . dr) / (n . r)``, ``dr = theta x r``, ``r`` from the camera's
    centre to the dot, more far from the camera's axis.  Dots whose camera is unknown get
    the bend without its parallax and ``camera_residual_std_m`` in both axes."""
    idx = list(idx)
    return _installation_covariances(
        dots.points[idx], dots.axes[idx], None if dots.bend is None else dots.bend[idx],
        None if dots.eyes is None else dots.eyes[idx], np.asarray(p0, float), p)[0]


def _installation_covariances(x: np.ndarray, A: np.ndarray, bend: np.ndarray | None,
                              eyes: np.ndarray | None, p0: np.ndarray,
                              p: TrackerParams) -> tuple[np.ndarray, _DotSlopes]:
    """:func:`_installation_covariance` of dots ``x`` (k, 3) on walls with in-plane axes
    ``A`` (k, 2, 3), seen from ``eyes`` (k, 3) or None, for a rig at ``p0`` ((3,) or one
    per dot), all at once (a frame set's labelings hold a few dozen dots), and the dots'
    :class:`_DotSlopes` it took (the chosen labeling's estimate moves its dots by them).
    Compiled where the laser kernels are built (``KERNELS``)."""
    if KERNELS is not None:
        k, empty = len(x), _EMPTY
        cov, bend_slopes = np.empty((k, 2, 2)), np.empty((k, 2))
        turn = None if eyes is None else np.empty((k, 2, 3))
        KERNELS.installation_covariances(
            x, A, empty if bend is None else np.ascontiguousarray(bend, float),
            empty if eyes is None else eyes, np.ascontiguousarray(p0, float), cov,
            bend_slopes, empty if turn is None else turn, p.housing_dir_std_rad,
            p.housing_offset_std_m, p.screen_bulge_std_m, p.camera_turn_std_rad,
            p.camera_residual_std_m)
        return cov, _DotSlopes(bend_slopes, turn)
    n = geo.cross(A[:, 0], A[:, 1])  # outward
    d = x - p0
    r = np.sqrt(np.einsum("ki,ki->k", d, d))
    dn = np.abs(np.einsum("ki,ki->k", n, d))
    c = np.minimum(np.maximum(dn / r, 0.05), 1.0)  # cos(incidence)
    across = (r * p.housing_dir_std_rad) ** 2 + p.housing_offset_std_m ** 2
    Ad = np.einsum("kai,ki->ka", A, d)
    norm = np.sqrt(np.einsum("ka,ka->k", Ad, Ad))
    u = np.where((norm > 0)[:, None], Ad / np.where(norm > 0, norm, 1.0)[:, None], [1.0, 0.0])
    cov = across[:, None, None] * (np.eye(2) + (1 / c ** 2 - 1)[:, None, None]
                                   * (u[:, :, None] * u[:, None]))
    shape = np.ones(len(x)) if bend is None else np.asarray(bend, float)
    slopes = _slopes(x, A, n, Ad, dn, r, eyes)
    slope = slopes.bend
    if eyes is None:
        cov += p.camera_residual_std_m ** 2 * np.eye(2)
    else:
        J = slopes.turn
        cov += p.camera_turn_std_rad ** 2 * np.einsum("kat,kbt->kab", J, J)
    return cov + (p.screen_bulge_std_m * shape)[:, None, None] ** 2 * (
        slope[:, :, None] * slope[:, None]), slopes


class _DotSlopes(NamedTuple):
    """How far each of a pose's dots moves on its wall per metre its screen bends inwards
    (``bend``, (k, 2): :func:`_bend_slopes`) and per radian its camera turns (``turn``,
    (k, 2, 3): :func:`_turn_jacobians`; None where the cameras are unknown): the chosen
    pose's covariance and its installation estimate's moves take the same ones."""

    bend: np.ndarray
    turn: np.ndarray | None

    def four(self, j: int) -> _DotSlopes:
        """The slopes of dots ``4 j .. 4 j + 3``: labeling ``j``'s, of a stack of them."""
        return _DotSlopes(self.bend[4 * j:4 * j + 4],
                          None if self.turn is None else self.turn[4 * j:4 * j + 4])


def _slopes(x: np.ndarray, A: np.ndarray, n: np.ndarray, Ad: np.ndarray, dn: np.ndarray,
            r: np.ndarray, eyes: np.ndarray | None) -> _DotSlopes:
    """:class:`_DotSlopes` from the dots' geometry (as :func:`_installation_covariances`)."""
    return _DotSlopes(_bend_slopes(x, A, n, Ad, dn, r, eyes),
                      None if eyes is None else _turn_jacobians(x, A, n, eyes))


def _bend_slopes(x: np.ndarray, A: np.ndarray, n: np.ndarray, Ad: np.ndarray, dn: np.ndarray,
                 r: np.ndarray, eyes: np.ndarray | None) -> np.ndarray:
    """How far each dot moves on its wall (k, 2) per metre its screen bends inwards: the
    beam's hit moves back along the beam, and the camera behind the screen sees the
    off-plane spot along its ray (``_installation_covariance``)."""
    slope = -Ad / np.maximum(dn, 0.05 * r)[:, None]
    if eyes is None:
        return slope
    back = x - eyes
    nb = np.einsum("ki,ki->k", n, back)
    return slope + np.einsum("kai,ki->ka", A, -back) / np.abs(nb)[:, None]


def _turn_jacobians(x: np.ndarray, A: np.ndarray, n: np.ndarray, eyes: np.ndarray,
                    ) -> np.ndarray:
    """How far each dot moves on its wall (k, 2, 3) per radian its camera turns about each
    world axis: where the turned ray meets the plane, ``dX = dr - r (n . dr) / (n . r)``."""
    back = x - eyes
    nb = np.einsum("ki,ki->k", n, back)
    turned = back[:, _TURNED] * _TURNED_SIGN  # (k, 3 turns, 3): dr = e_t x r per turn axis
    towards = np.einsum("kti,ki->kt", turned, n)
    moved = turned - towards[:, :, None] * back[:, None] / nb[:, None, None]
    return np.einsum("kai,kti->kat", A, moved)


#: ``e_t x r`` for each world axis ``t`` (rows) as signed components of ``r``:
#: (0, -r_z, r_y), (r_z, 0, -r_x), (-r_y, r_x, 0)
_TURNED = np.array([[0, 2, 1], [2, 0, 0], [1, 0, 0]])
_TURNED_SIGN = np.array([[0.0, -1.0, 1.0], [1.0, 0.0, -1.0], [-1.0, 1.0, 0.0]])


@dataclass(frozen=True)
class _Fit:
    """A labeling whose dots fit one pose."""

    pose: LabeledPose
    idx: list[int]  # dot index of diodes 1..4
    chi2: float  # ``residual_chi2``
    miss: np.ndarray  # (2,) ``fourth_beam_residuals``: the fourth dot's miss, its
    random: np.ndarray  # (2, 2) covariance from the dots' noise
    systematic: np.ndarray  # (4, 2, 2) and from each dot's installation tolerances
    jacobian: np.ndarray  # (4, 2, 2) its change per metre each dot moves along each wall axis
    installation: np.ndarray  # (4, 2, 2) each dot's in-plane installation covariance
    slopes: _DotSlopes  # the dots' slopes that covariance took
    #: the frames (P0 (9, 3), R (9, 3, 3)) of its dots and their perturbed copies
    frames: tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class _Miss:
    """A labeling's fourth-beam miss in one frame set, and what it depends on."""

    t: float
    walls: tuple[str, ...]  # the walls of diodes 1..4's dots
    points: np.ndarray  # (4, 3) those dots
    miss: np.ndarray  # (2,)
    random: np.ndarray  # (2, 2) from the dots' noise, new in every frame set
    systematic: np.ndarray  # (4, 2, 2) from each dot's installation tolerances
    edge: np.ndarray  # (4, 2, 2) from each dot's edge std (``_edge_parts``)
    edge_m: np.ndarray  # (4,) each dot's edge std
    confirmed: bool = False  # published (it agreed with the miss before it)
    #: the factor its dots' noise variance took (``_NoiseScale.excess``)
    excess: float = 1.0
    #: frame sets held in a row up to this one, each miss passing the change test
    #: against the one before (``start_confirm_sets``)
    held: int = 1

    def change(self, later: _Miss, drift_per_m: float, noise_scale: float = 1.0,
               ) -> tuple[float, np.ndarray, float] | None:
        """Chi-square (2 dof) of the miss's change to ``later`` and its covariance, both
        frame sets' noise scaled by ``noise_scale`` (``_NoiseScale``), and its chi-square
        under the noise as assumed, without the ``excess`` each frame set's noise took
        (what the scale and the excess are estimated from); or None if the change
        cannot show a stray blob: the dots moved so far (``1 / drift_per_m``) that the
        installation's part may have changed whole, or more than one dot changed walls.
        Its covariance: both frame sets' noise, the installation's part of each dot that
        stayed on its wall times ``drift_per_m`` per metre the dots moved, and all of it
        (both frame sets', independent) for a dot on another wall.  A dot near its
        screen's edge adds its edge part as far as the dot moved: a clipped spot's
        centroid bias changes by at most the spot's move (the derivative of a truncated
        spot's mean is below 1), so by its edge std only once it moved that far; counted
        as new noise in both frame sets instead, a 4 mm dot's part would hide a stray blob
        2 cm from another dot."""
        each = np.linalg.norm(later.points - self.points, axis=1)
        moved = float(np.max(each))
        other = [a != b for a, b in zip(self.walls, later.walls, strict=True)]
        if drift_per_m * moved >= 1.0 or sum(other) > 1:
            return None
        both = self.systematic + later.systematic  # (4, 2, 2)
        share = np.where(other, 1.0, 0.5 * (drift_per_m * moved) ** 2)
        edge_m = np.maximum(self.edge_m, later.edge_m)
        edge_share = np.where(other, 1.0, np.minimum(
            1.0, 0.5 * (each / np.where(edge_m > 0, edge_m, 1.0)) ** 2))
        noise = self.random + later.random
        drift = np.einsum("k,kij->ij", share, both)
        edge = np.einsum("k,kij->ij", edge_share, self.edge + later.edge)
        d = (later.miss - self.miss)[None]
        S = noise_scale * noise + drift + edge
        chi2 = float(_chi2(d, S[None])[0])
        if noise_scale == 1.0 and self.excess == 1.0 and later.excess == 1.0:
            return chi2, S, chi2  # the noise as assumed: the same sum
        said = self.random / self.excess + later.random / later.excess + drift + edge
        return chi2, S, float(_chi2(d, said[None])[0])


class _NoiseScale:
    """How much of the dots' assumed frame-to-frame noise the fourth beam's miss shows: an
    upper bound on ``kappa``, the dots' noise variance over the assumed one, from the
    chi-squares (under the assumed noise) of the last ``window`` changes of the miss the
    change test passed; at most 1, and 1 until they bound it below; at least
    ``_NOISE_SCALE_FLOOR`` (noise-free dots, a simulation's exact hits, would leave the
    test only the installation's part, singular where the dots stood still).

    With the noise ``kappa R`` (``R`` as assumed, both frame sets') and the installation's
    and edge parts ``D`` as assumed, a change's chi-square under ``S = R + D`` is a sum of
    two chi-square(1) terms weighted by the eigenvalues of ``(kappa R + D) S^-1``, each at
    least ``min(kappa, 1)``: their sum over ``n`` changes is at least ``kappa`` times the
    sum of ``n`` chi-square(2).  Consecutive changes share a frame set's miss (each
    component's changes correlate by -1/2), which makes that sum vary 1 + 2 (1/2)^2 = 1.5
    times as much as independent ones' (mean ``2 n``, variance ``6 n``); matching both,
    it is about ``1.5 chi2(dof)`` with ``dof = 2 n / 1.5``, so ``sum / (1.5 chi2_p(dof))``
    lies below ``kappa`` with probability about ``p`` (``_NOISE_BOUND_P``; simulated
    consecutive changes put it at 0.04 p for one change, rising to 0.9 p at 150).  Blobs
    the test passes only raise the bound.

    Where the dots are noisier than assumed (``kappa > 1``) each weight is at most
    ``kappa``, so the same sum over ``1.5 chi2_(1-p)(dof)`` exceeds ``kappa`` with
    probability about ``p``: a lower bound (blobs the test passes raise it too, towards
    more noise).  Once it exceeds 1, ``excess`` is the sum's mean per change over 2 (the
    weights lie between 1 and ``kappa``) and the dots' std is taken up by its root, for
    every test and the pose's covariance; else 1.  The change test refuses changes
    above its gate, so where the dots understate their noise the estimate lags it."""

    def __init__(self, window: int):
        self._chi2: deque[float] = deque(maxlen=window)
        self._sum = 0.0  # of ``_chi2``, kept as they come and go (read every frame set)
        #: 1 / (1.5 chi2_p(dof)) of n = 1 .. window changes (chi2_p(k) = 2 P^-1(k / 2, p))
        self._inverse = (1 / (3 * gammaincinv(np.arange(1, window + 1) / 1.5,
                                              _NOISE_BOUND_P))).tolist()
        #: 1 / (1.5 chi2_(1-p)(dof)): the lower bound's
        self._lower = (1 / (3 * gammaincinv(np.arange(1, window + 1) / 1.5,
                                            1 - _NOISE_BOUND_P))).tolist()
        #: the bound on ``kappa``, at most 1 (1 before any change)
        self.scale = 1.0
        #: the estimate of ``kappa`` where its lower bound exceeds 1, else 1
        self.excess = 1.0

    def add(self, chi2: float) -> None:
        """One change's chi-square under the assumed noise (no-op with no window)."""
        window = self._chi2.maxlen
        if not window:
            return
        if len(self._chi2) == window:
            self._sum -= self._chi2[0]
        self._chi2.append(chi2)
        self._sum += chi2
        bound = self._sum * self._inverse[len(self._chi2) - 1]
        self.scale = min(1.0, max(bound, _NOISE_SCALE_FLOOR))
        n = len(self._chi2)
        self.excess = max(1.0, self._sum / (2 * n)) if self._sum * self._lower[n - 1] > 1.0 \
            else 1.0


#: the chance that ``_NoiseScale``'s bound lies below the dots' noise
_NOISE_BOUND_P = 1e-3
#: ... and the least share of the assumed noise variance it keeps
_NOISE_SCALE_FLOOR = 0.01


class _Unseen(NamedTuple):
    """A stray blob the miss's change cannot show: why, and what covers it."""

    detail: str
    #: (6, 6; xi form) added to the pose's covariance, every pose such a blob could give
    #: lies within its 1-sigma ellipsoid; None where a blob could move the pose without
    #: bound (a dot's move the miss does not see)
    cover: np.ndarray | None


def _unseen_stray(fit: _Fit, J: np.ndarray, S: np.ndarray, cov: np.ndarray,
                  p: TrackerParams, bound: float) -> _Unseen | None:
    """Whether the miss's test (covariance ``S``, chi-square at most ``bound``) cannot
    vouch for the fit's pose (covariance ``cov``, Jacobian ``J``: :func:`_pose_jacobian`):
    a stray blob in the place of one of the dots that fix the pose (diodes 1-3), at least
    ``stray_min_m`` from it, could pass the test yet put the pose outside its covariance
    (Mahalanobis distance squared above ``same_pose_chi2``); None if none could.  ``S``
    is wide where a dot near its screen's edge moved (its clipped centroid), the dots
    moved far since the last miss (the installation's part), or the dots are noisy.

    Per dot, with ``A = Jp^T C^-1 Jp`` and ``B = Jm^T S^-1 Jm`` (the pose's and the miss's
    change per move of the dot along its wall), the move the test passes that moves the
    pose most is the generalised eigenvector ``v`` of ``(A, B)`` with the largest
    eigenvalue ``lam``, scaled to ``v^T B v = bound``: it is harmful if ``lam`` exceeds
    the ratio of the two bounds, and a blob if ``|v| >= stray_min_m`` (no move the test
    passes is that long where ``bound`` over ``B``'s least eigenvalue is less: most frame
    sets).  Every move the test passes changes the miss by ``m`` with ``m^T S^-1 m`` at
    most ``bound`` and the pose by ``Jp Jm^-T m``: the cover is that map of ``bound S``,
    summed over the harmful dots.  A dot whose ``Jm`` is singular has a move the miss
    does not see at all: the blob is unbounded, and no cover is given.  An ``S`` that is
    not positive definite (or not finite) is no test a chi-square can pass, as ``_chi2``
    takes it: it vouches for nothing, and no cover is given either."""
    Jm = fit.jacobian[:3]  # (dot, wall axis, miss component)
    longest = _longest_passing_moves(Jm, S)
    if longest is None:
        return _Unseen("the fourth dot's miss was tested under a covariance that is not "
                       "positive definite: it cannot show a stray blob", None)
    if math.inf in longest:
        k = longest.index(math.inf)
        return _Unseen(f"a stray blob beside diode {k + 1}'s dot could move the pose along "
                       "a line the fourth dot's miss does not see (its Jacobian is singular)",
                       None)
    if bound * max(longest) < p.stray_min_m ** 2:
        return None
    B = np.einsum("kai,ij,kbj->kab", Jm, np.linalg.inv(S), Jm)
    a = np.linalg.det(B)  # > 0: S > 0 and Jm regular
    Jp = J.reshape(6, 4, 2)[:, :3]
    A = np.einsum("pka,pq,qkb->kab", Jp, np.linalg.inv(cov), Jp)
    # the largest root of det(A - lam B) = 0, a quadratic per dot
    b = A[:, 0, 0] * B[:, 1, 1] + A[:, 1, 1] * B[:, 0, 0] - A[:, 0, 1] * B[:, 1, 0] \
        - A[:, 1, 0] * B[:, 0, 1]
    lam = (b + np.sqrt(np.maximum(b * b - 4 * a * np.linalg.det(A), 0.0))) / (2 * a)
    M = A - lam[:, None, None] * B  # singular: v spans its null space
    rows = np.stack([np.stack([-M[:, 0, 1], M[:, 0, 0]], -1),
                     np.stack([-M[:, 1, 1], M[:, 1, 0]], -1)], 1)  # (dot, row, 2)
    v = rows[np.arange(3), np.argmax(np.einsum("kra,kra->kr", rows, rows), axis=1)]
    length = np.sqrt(bound * np.einsum("ka,ka->k", v, v) / np.einsum("ka,kab,kb->k", v, B, v))
    harmful = (lam * bound > p.same_pose_chi2) & (length >= p.stray_min_m)
    if not harmful.any():
        return None
    k = int(np.argmax(np.where(harmful, lam, -np.inf)))
    G = np.einsum("pka,kia->kpi", Jp[:, harmful], np.linalg.inv(Jm[harmful]))  # Jp Jm^-T
    cover = bound * np.einsum("kpi,ij,kqj->pq", G, S, G)
    return _Unseen(f"a stray blob {length[k] * 100:.1f} cm from diode {k + 1}'s dot would "
                   f"move the pose {np.sqrt(lam[k] * bound):.1f} sigma, unseen by the fourth "
                   "dot's miss", 0.5 * (cover + cover.T))


def _longest_passing_moves(Jm: np.ndarray, S: np.ndarray) -> list[float] | None:
    """Per dot (``Jm``: (3, wall axis, miss component)), the squared length of the
    longest move along its wall whose change of the miss ``m`` has ``m^T S^-1 m = 1``:
    one over the least eigenvalue of ``B = Jm^T S^-1 Jm``; inf where ``Jm`` is singular
    (a move the miss does not see); None where ``S`` is not positive definite and finite
    (no such move is defined).  On plain floats: it runs for every labeling
    published, and numpy's per-call overhead on 2 x 2 matrices costs more than this."""
    (s00, s01), (s10, s11) = S.tolist()
    det_s = s00 * s11 - s01 * s10
    if not (s00 > 0.0 and det_s > 0.0 and math.isfinite(det_s)):
        return None
    i00, i01, i10, i11 = s11 / det_s, -s01 / det_s, -s10 / det_s, s00 / det_s
    out = []
    for (m00, m01), (m10, m11) in Jm.tolist():
        det_m = m00 * m11 - m01 * m10
        # a 2 x 2 matrix's determinant over its squared norm is about its condition's
        # inverse
        if not abs(det_m) > (m00 * m00 + m01 * m01 + m10 * m10 + m11 * m11) / _SINGULAR_COND:
            out.append(math.inf)
            continue
        b00 = m00 * (i00 * m00 + i01 * m01) + m01 * (i10 * m00 + i11 * m01)
        b11 = m10 * (i00 * m10 + i01 * m11) + m11 * (i10 * m10 + i11 * m11)
        half = 0.5 * (b00 + b11)
        det_b = det_m * det_m / det_s
        # 1 / least = largest / det_b: no cancellation where the two differ by far
        largest = half + math.sqrt(max(half * half - det_b, 0.0))
        out.append(largest / det_b if det_b > 0 else math.inf)
    return out


#: a dot's miss Jacobian (2 x 2) about this ill-conditioned has a move the miss does not
#: see
_SINGULAR_COND = 1e8


def _noise_taken_up(dots: WorldDots, excess: float) -> WorldDots:
    """``dots`` with their noise variance taken up by ``excess`` (``_NoiseScale``); the part
    of their std for lying near a screen's edge (``edge_m``) as it is: a clipped spot's
    bias, which the miss's changes do not show and ``_edge_parts`` takes out whole."""
    edge_sq = 0.0 if dots.edge_m is None else dots.edge_m ** 2
    return replace(dots, std_m=np.sqrt(excess * (dots.std_m ** 2 - edge_sq) + edge_sq))


def _edge_parts(dots: WorldDots, fit: _Fit) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fit's miss covariance from the dots' noise without their edge std (2, 2), each
    dot's part from its edge std (4, 2, 2), and those stds (4,): the edge std is a clipped
    spot's bias, which holds while the spot moves little (``_Miss.change``)."""
    e = np.zeros(4) if dots.edge_m is None else dots.edge_m[fit.idx]
    if not e.any():
        return fit.random, np.zeros((4, 2, 2)), e
    edge = np.einsum("kai,k,kaj->kij", fit.jacobian, e ** 2, fit.jacobian)
    return fit.random - edge.sum(axis=0), edge, e


def _pick_upright(fits: list[_Fit], t: float, n: int,
                  p: TrackerParams) -> tuple[int, np.ndarray] | NoPose:
    """Initialisation, the user standing upright (thesis §5.3): the fit whose rig z is
    nearest the world's up; a rival is beaten by being ``init_margin_cos`` less upright,
    else by its chi-square alone (``inf`` / chi-square difference: its lead)."""
    ups = np.array([float(geo.quat_rotate(f.pose.quaternion, [0.0, 0.0, 1.0])[2])
                    for f in fits])
    k = int(np.argmax(ups))
    if ups[k] < p.min_upright_cos:
        return NoPose(t, "not_upright", n, "initialisation needs an upright head "
                      f"(best up-axis cosine {ups[k]:.2f})")
    chi2 = np.array([f.chi2 for f in fits])
    return k, np.where(ups[k] - ups >= p.init_margin_cos, np.inf, chi2 - chi2[k])


def residual_chi2(dots: WorldDots, orders: list[list[int]], origins: list[np.ndarray],
                  p: TrackerParams) -> np.ndarray:
    """Chi-square (2 dof) of each labeling's dots against one pose: ``orders[j]`` the dot
    indices of diodes 1..4, ``origins[j]`` its P0 (for the installation's error); inf
    where a labeling's dots give no frame (:func:`fourth_beam_residuals`)."""
    r, random, systematic, _ = fourth_beam_residuals(dots, orders, origins, p)
    return _chi2(r, random + systematic.sum(axis=1))


def fourth_beam_residuals(dots: WorldDots, orders: list[list[int]], origins: list[np.ndarray],
                          p: TrackerParams, step_m: float = 1e-5,
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where each labeling's fourth dot lies off beam 4 of the pose its first three fix, (m,
    2), and that miss's covariance: the part from the dots' noise, new in every frame set
    (m, 2, 2), and each dot's part from the installation's tolerances, which a frame set
    shares with the next ones while the dot stays on its wall (m, 4, 2, 2); and the miss's
    change per metre each dot moves along each of its wall's axes (m, 4, 2, 2:
    :func:`_miss_jacobians`), which the chosen labeling's estimate and gates take again.

    The dots of diodes 1-3 fix the pose (six coordinates, six unknowns); the residual is
    where the fourth dot lies off beam 4 of that pose, across the beam (its components
    along the rig's x and y, times nothing: metres at the dot).  Its covariance comes by
    numeric Jacobian from all four dots' in-plane errors.  NaN where a labeling's dots
    give no frame."""
    return _fourth_beam_parts(dots, orders, origins, p, step_m)[:4]


def _fourth_beam_parts(dots: WorldDots, orders: list[list[int]], origins: list[np.ndarray],
                       p: TrackerParams, step_m: float = 1e-5,
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                  _DotSlopes, tuple[np.ndarray, np.ndarray]]:
    """:func:`fourth_beam_residuals`, and each labeling's dots' installation covariance (m,
    4, 2, 2) and :class:`_DotSlopes` (over the m * 4 dots, labeling by labeling) it took,
    and the frames of its dots' perturbed copies (:func:`_miss_jacobians`): the chosen
    labeling's pose covariance and estimate take them again."""
    m = len(orders)
    if not m:
        return (np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2, 2)),
                np.zeros((0, 4, 2, 2)), np.zeros((0, 4, 2, 2)),
                _DotSlopes(np.zeros((0, 2)), None), (np.zeros((0, 9, 3)), np.zeros((0, 9, 3, 3))))
    idx = np.array(orders)  # (m, 4)
    r, Jd, frames = _miss_jacobians(dots, idx, step_m)
    flat = idx.ravel()
    installation, slopes = _installation_covariances(
        dots.points[flat], dots.axes[flat], None if dots.bend is None else dots.bend[flat],
        None if dots.eyes is None else dots.eyes[flat], np.repeat(np.asarray(origins, float),
                                                                  4, axis=0), p)
    installation = installation.reshape(m, 4, 2, 2)
    systematic = np.einsum("mkai,mkab,mkbj->mkij", Jd, installation, Jd)
    random = np.einsum("mkai,mk,mkaj->mij", Jd, dots.std_m[idx] ** 2, Jd)
    return r, random, systematic, Jd, installation, slopes, frames


def _miss_jacobians(dots: WorldDots, idx: np.ndarray, step_m: float = 1e-5,
                    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """The fourth beam's miss of each labeling (the dot indices of diodes 1..4, (m, 4)),
    (m, 2), and its change per metre each dot moves along each of its wall's axes (m, 4,
    2, 2: dot, wall axis, miss component), by numeric Jacobian; and the frames (P0 (m, 9,
    3), R (m, 9, 3, 3)) of each labeling's dots and their eight perturbed copies, which
    the chosen labeling's pose Jacobian takes again (:func:`_pose_jacobian`)."""
    m = len(idx)
    P = dots.points[idx]
    axes = dots.axes[idx].reshape(m, 8, 3)  # dot k moves along axes[:, 2k], axes[:, 2k + 1]
    Q = np.repeat(P[:, None], 9, axis=1)
    Q[:, _PERTURBED_COPY, _PERTURBED_DOT] += step_m * axes
    p0, R = frames_from_points(Q.reshape(m * 9, 4, 3))
    ray = (Q[:, :, 3] - p0.reshape(m, 9, 3))  # P0 -> the fourth dot
    r = np.einsum("mcij,mci->mcj", R.reshape(m, 9, 3, 3)[..., :2], ray)  # across beam 4
    J = (r[:, 1:] - r[:, :1]) / step_m  # (m, 8, 2)
    return r[:, 0], J.reshape(m, 4, 2, 2), (p0.reshape(m, 9, 3), R.reshape(m, 9, 3, 3))


def _chi2(r: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``r_j^T S_j^-1 r_j`` of each residual (m, 2) under its covariance (m, 2, 2); inf where
    either is not finite or ``S`` is singular (a determinant not above 0).  In closed form:
    ``np.linalg.solve`` and ``det`` on 2 x 2 blocks cost more in their argument handling
    than the arithmetic."""
    a, b, c, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 0], S[:, 1, 1]
    r0, r1 = r[:, 0], r[:, 1]
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        det = a * d - b * c
        chi2 = (d * r0 * r0 - (b + c) * r0 * r1 + a * r1 * r1) / det
        return np.where((det > 0) & np.isfinite(det) & np.isfinite(chi2), chi2, np.inf)


def _rival(poses: list[LabeledPose], k: int, lead: np.ndarray, cov: np.ndarray,
           min_margin: float, same_chi2: float) -> str | None:
    """Why the chosen pose ``poses[k]`` (covariance ``cov``, xi form) is ambiguous: a
    rival whose pose lies outside that covariance (Mahalanobis distance squared above
    ``same_chi2``) scores less than ``min_margin`` worse (``lead``); None if none does.
    A rival inside the covariance is the same answer: publishing either is honest."""
    best = poses[k]
    C = geo.se3_to_decoupled(best.position, cov)
    for j, c in enumerate(poses):
        if j == k or lead[j] >= min_margin:
            continue
        e = np.concatenate([c.position - best.position, geo.quat_to_rotvec(
            geo.quat_multiply(c.quaternion, geo.quat_conjugate(best.quaternion)))])
        d2 = float(e @ np.linalg.solve(C, e))
        if d2 > same_chi2:
            return (f"two labelings fit: the runner-up scores {lead[j]:.1f} worse (margin "
                    f"{min_margin:g}) and lies {math.sqrt(d2):.1f} sigma from the best "
                    f"({np.linalg.norm(e[:3]) * 100:.1f} cm, "
                    f"{math.degrees(np.linalg.norm(e[3:])):.2f} deg)")
    return None


def _covariance(J: np.ndarray, std_m: np.ndarray, p0: np.ndarray, params: TrackerParams,
                installation_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """6x6 pose covariances (xi form): the whole, and its systematic part.

    Propagated by numeric Jacobian of the closed-form solution (each dot moves along its
    wall's two axes) from the dots' in-plane errors: their detection and calibration noise,
    new in every frame, and the installation's tolerances (``installation_cov``, per dot
    over its wall's axes: :func:`_installation_covariance`), which hold
    for the whole run; plus the model error the dots cannot show, systematic too.  A
    filter that averages frames must keep the systematic part apart
    (docs/FUSION_TUNING.md).  ``J``: the pose's Jacobian (:func:`_pose_jacobian`) at the
    dots, whose in-plane noise stds are ``std_m``."""
    random = (J * np.repeat(std_m ** 2, 2)) @ J.T
    Jd = J.reshape(6, 4, 2)  # pose row, dot, its wall axis
    systematic = np.einsum("ika,kab,jkb->ij", Jd, installation_cov, Jd) \
        + _model_covariance(p0, params)
    whole = random + systematic
    return 0.5 * (whole + whole.T), 0.5 * (systematic + systematic.T)


def _estimate_columns(S: np.ndarray, at: np.ndarray, rows: np.ndarray,
                      estimate: InstallationEstimate) -> tuple[np.ndarray, np.ndarray]:
    """``S`` (6 x len(at); its columns the parameters at the estimate's indices ``at``,
    whose rows of the estimate's covariance are ``rows``) times a root of the estimate's
    whole remaining covariance P, and ``S`` times P itself, each one column per parameter
    in the estimate's own order (``estimate.names``).

    Why the whole covariance in one fixed order: a consumer (the alignment) takes each
    named column of the root for one shared source across the poses it holds, which is
    true only if every pose factors the same covariance in the same order, whatever
    parameters its own dots see.  Why ``S P``: the estimate's error is ``P theta`` (theta
    the installation's draw, in stds, prior N(0, I)) less what this run's misses' noise
    left in it, so ``S P`` is what of the pose's error every run in the same installation
    shares; the rest is the run's own."""
    every = np.zeros((S.shape[0], len(estimate.names)))
    every[:, at] = S
    return every @ estimate.root(), S @ rows


def _model_covariance(p0: np.ndarray, params: TrackerParams) -> np.ndarray | float:
    """The model error the dots cannot show (xi form, 6 x 6), or 0 where there is none."""
    if not (params.model_pos_std_m or params.model_rot_std_rad):
        return 0.0
    model = np.zeros((6, 6))
    model[_DIAG3, _DIAG3] = params.model_pos_std_m ** 2
    model[_DIAG3 + 3, _DIAG3 + 3] = params.model_rot_std_rad ** 2
    return geo.decoupled_to_se3(p0, model)


def _pose_jacobian(dots: WorldDots, idx: list[int], p0: np.ndarray, step_m: float = 1e-5,
                   frames: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The pose's change (6, 8; xi form) per metre each dot ``idx`` moves along each of its
    wall's two axes (column ``2k + a``), by numeric Jacobian of the closed-form solution.
    ``frames``: the frames (P0 (9, 3), R (9, 3, 3)) of the dots and their perturbed copies
    (:func:`_miss_jacobians`) if already taken."""
    if frames is None:
        P = dots.points[idx]
        axes = dots.axes[idx].reshape(8, 3)  # dot k moves along axes[2k], axes[2k + 1]
        Q = np.repeat(P[None], 9, axis=0)
        Q[_PERTURBED_COPY, _PERTURBED_DOT] += step_m * axes
        frames = frames_from_points(Q)
    p, R = frames
    if np.isnan(R[:, 0, 0]).any():  # a perturbed copy without a frame is NaN throughout
        raise InvalidInputError("pose: the dots define no frame (P3 on the line P1P2)")
    dR = R[1:] @ R[0].T  # world-frame (left) rotation error, small: read it off the skew part
    dR = dR.reshape(8, 9)
    dphi = 0.5 * (dR.take(_SKEW_PLUS, 1) - dR.take(_SKEW_MINUS, 1))
    J = np.concatenate([p[1:] - p[0], dphi], axis=1).T / step_m  # (6, 8)
    # the decoupled -> xi map of geo.decoupled_to_se3, applied to J once for both
    J[:3] += geo.skew3(p0) @ J[3:]
    return J


def installation_sensitivity(dots: WorldDots, estimate: PoseEstimate, p: TrackerParams,
                             ) -> dict[str, np.ndarray]:
    """The pose's error (6,; xi form, as ``covariance``) per one standard deviation of each
    of the installation's parameters that moves its dots: each beam's tilt and miss of P0
    across it (two rig-fixed axes each), each screen's bend, each camera's turn (three
    world axes; two wall axes of ``camera_residual_std_m`` where the camera is unknown).
    A pose corrected by the tracker's online estimate (``estimate_installation``) carries
    its own: the estimate's remaining error, one column per direction of it.

    Why: ``systematic`` says how large the installation's error of one pose is, not how
    the errors of two poses relate.  Two poses share a parameter's error through the
    parameter, each with its own sensitivity, so a consumer that combines poses from
    different places (an alignment over many stations) needs the sensitivities: their
    outer products summed over the parameters give ``systematic`` less the model error,
    the same dot by dot as :func:`_installation_covariance` (but where a beam meets its
    wall within 3 degrees of grazing, where that clamps the stretch).  ``dots`` are the
    frame set ``estimate`` was solved from."""
    if estimate.sensitivity is not None:
        return estimate.sensitivity
    labels = sorted(estimate.dots)
    idx = [int(np.flatnonzero(np.all(dots.points == estimate.dots[label], axis=1))[0])
           for label in labels]
    p0 = np.asarray(estimate.position, float)
    Jd = _pose_jacobian(dots, idx, p0).reshape(6, 4, 2)
    names, D = _dot_moves(dots, idx, labels, p0, estimate.quaternion, p)
    return {name: np.einsum("pka,ka->p", Jd, D[..., j].copy()) for j, name in enumerate(names)}


def installation_draw_sensitivity(dots: WorldDots, estimate: PoseEstimate, p: TrackerParams,
                                  ) -> dict[str, np.ndarray]:
    """The pose's error (6,; xi form) per one standard deviation of each installation
    parameter's draw, which every run in the same installation shares: without the online
    estimate the same as :func:`installation_sensitivity`; with it ``S P``, what of the
    draw the estimate has not taken out (``_estimate_columns``), by the parameters' names.

    Why apart from :func:`installation_sensitivity`: with the estimate, what two poses of
    one run share (the estimate's remaining error, noise of the run's misses included) is
    not what two runs in the same installation share (only the draw), and a consumer that
    judges many runs of one installation together (the alignment's evaluation, its band
    of a seed's trials) needs the latter."""
    if estimate.draw_sensitivity is not None:
        return estimate.draw_sensitivity
    return installation_sensitivity(dots, estimate, p)


def _dot_moves(dots: WorldDots, idx: list[int], labels: list[int], p0: np.ndarray,
               quaternion: np.ndarray, p: TrackerParams, slopes: _DotSlopes | None = None,
               screens: _Screens | None = None) -> tuple[tuple[str, ...], np.ndarray]:
    """How far each dot ``idx`` (diodes ``labels``, rig at ``p0``, ``quaternion``) moves
    along its wall's two axes per one standard deviation of each of the installation's
    parameters (:func:`installation_sensitivity` names them), and with ``screens`` of
    each of its camera's screen map's (:meth:`_Screens.map_bases`): the parameters' names
    and the moves (dots, 2 axes, parameters); a parameter that moves none of the dots is
    left out.  ``slopes``: the dots' :class:`_DotSlopes` at ``p0`` if already taken.

    Each dot's moves are one block (its beam's four parameters, its screen's bend, its
    camera's turn, its camera's map: :func:`_move_blocks`, or its compiled twin), computed
    for all dots at once and scattered into the columns :func:`_move_layout` keeps for the
    dots' labels, walls and cameras: a frame set's four dots see some sixty parameters,
    and numpy's per-call overhead, not the arithmetic, is the cost of building them
    parameter by parameter."""
    x, A = dots.points[idx], dots.axes[idx]
    k4 = len(idx)
    eyes = None if dots.eyes is None else dots.eyes[idx]
    cams = () if screens is None else tuple(screens.index.get(dots.cameras[i]) for i in idx)
    mapped = tuple(c is not None for c in cams)
    names, src, dst, width, across = _move_layout(
        tuple(labels), tuple(dots.walls[i] for i in idx), tuple(dots.cameras[i] for i in idx),
        eyes is not None, mapped)
    shape = np.ones(k4) if dots.bend is None else np.asarray(dots.bend, float)[idx]
    if slopes is None:  # as the fits take them
        slopes = _installation_covariances(x, A, None, eyes, np.asarray(p0, float), p)[1]
    out = np.zeros(k4 * 2 * len(names))
    if KERNELS is None:
        out[dst] = _move_blocks(x, A, p0, quaternion, across, shape, slopes, p, width,
                                screens, cams).take(src)
    else:
        maps = (screens.translation, screens.rotation, screens.side, screens.sigma) \
            if any(mapped) else (_EMPTY,) * 4
        KERNELS.dot_moves(
            x, A, np.ascontiguousarray(p0, float), np.ascontiguousarray(quaternion, float),
            across, shape, slopes.bend, _EMPTY if slopes.turn is None else slopes.turn,
            *maps, src, dst, out, cams or (None,) * k4, width, p.housing_dir_std_rad,
            p.housing_offset_std_m, p.screen_bulge_std_m, p.camera_turn_std_rad,
            p.camera_residual_std_m)
    return names, out.reshape(k4, 2, len(names))


def _move_blocks(x: np.ndarray, A: np.ndarray, p0: np.ndarray, quaternion: np.ndarray,
                 across: np.ndarray, shape: np.ndarray, slopes: _DotSlopes, p: TrackerParams,
                 width: int, screens: _Screens | None, cams: tuple[int | None, ...],
                 ) -> np.ndarray:
    """Each dot's block of moves (k, 2 axes, ``width``): per beam tilt a, offset a, tilt b,
    offset b (``_BEAM_NAMES``' order; ``across`` (k, 2, 3): the beam's two rig axes across
    it), its screen's bend (``shape`` at the dot), its camera's turn (or residual), and
    where ``cams`` holds any camera its map's eight coefficients."""
    n = geo.cross(A[:, 0], A[:, 1])
    d = x - p0
    r = np.sqrt(np.einsum("ki,ki->k", d, d))
    dn = np.einsum("ki,ki->k", n, d)
    k4 = len(x)
    unit = d / r[:, None]
    nd = np.where(dn < 0, -1.0, 1.0) * np.maximum(np.abs(dn) / r, 0.05)  # cos(incidence)
    # two rig-fixed axes across each beam, in the world, made square to the beam as it is
    across = np.einsum("ij,kaj->kai", geo.quat_to_matrix(quaternion), across)
    across -= np.einsum("kai,ki->ka", across, unit)[..., None] * unit[:, None]
    on_wall = across - np.einsum("kai,ki->ka", across, n)[..., None] * (unit / nd[:, None])[:, None]
    beam = np.einsum("kbi,kai->kab", A, on_wall)  # dot k's move (b) per unit across (a)
    blocks = np.empty((k4, 2, width))
    scale = np.stack([r * p.housing_dir_std_rad, np.full(k4, p.housing_offset_std_m)], -1)
    blocks[..., :4] = (beam.transpose(0, 2, 1)[..., None] * scale[:, None, None]).reshape(
        k4, 2, 4)
    blocks[..., 4] = slopes.bend * (p.screen_bulge_std_m * shape)[:, None]
    if slopes.turn is None:
        blocks[..., 5:7] = p.camera_residual_std_m * np.eye(2)
    else:
        blocks[..., 5:8] = p.camera_turn_std_rad * slopes.turn
    if any(c is not None for c in cams):
        blocks[..., width - 8:] = screens.map_bases(x, [c or 0 for c in cams])
    return blocks


@lru_cache(maxsize=4096)
def _move_layout(labels: tuple[int, ...], walls: tuple[str, ...], cameras: tuple[str, ...],
                 turn: bool, mapped: tuple[bool, ...],
                 ) -> tuple[tuple[str, ...], np.ndarray, np.ndarray, int, np.ndarray]:
    """The parameters that move dots of diodes ``labels`` on ``walls`` seen by ``cameras``
    (their turn known: ``turn``; their screen maps held where ``mapped``), in the order
    :func:`_dot_moves` names them: each beam's, then each dot's screen bend and camera
    turn, then each dot's camera map, a parameter shared by two dots (a screen, a camera)
    named once; and where each dot's block of moves goes: flat indices into the blocks
    (dots, 2, ``width``) and into the moves (dots, 2, parameters); and each dot's beam's
    two rig axes across it (dots, 2, 3).  Depends on the dots' labels, walls and cameras
    alone, which a tracked head keeps for many frame sets.  (Read-only: shared by every
    call with the same key.)"""
    axes = ("turn x", "turn y", "turn z") if turn else ("residual 0", "residual 1")
    width = 5 + len(axes) + (8 if any(mapped) else 0)
    groups = [(k, _BEAM_NAMES[label], 0) for k, label in enumerate(labels)]
    for k, (wall, camera) in enumerate(zip(walls, cameras, strict=True)):
        groups += [(k, [f"screen {wall} bend"], 4),
                   (k, [f"camera {camera} {axis}" for axis in axes], 5)]
    groups += [(k, [f"camera {camera} map {j}" for j in range(8)], width - 8)
               for k, camera in enumerate(cameras) if mapped and mapped[k]]
    names: list[str] = []
    column: dict[str, int] = {}
    places = []  # (dot, block column, parameter column)
    for k, group, first in groups:
        j = column.setdefault(group[0], len(names))
        if j == len(names):
            column.update((name, j + m) for m, name in enumerate(group))
            names += group
        places += [(k, first + m, j + m) for m in range(len(group))]
    m = len(names)
    src = [(2 * k + a) * width + b for a in range(2) for k, b, _ in places]
    dst = [(2 * k + a) * m + j for a in range(2) for k, _, j in places]
    out = (np.array(src, np.int64), np.array(dst, np.int64),
           _ACROSS_BEAM[np.array(labels, int) - 1])
    for a in out:
        a.flags.writeable = False
    return tuple(names), out[0], out[1], width, out[2]


#: the compiled twin of ``_dot_moves``' blocks and scatter (None: the numpy code runs)
KERNELS: Any = compiled_twin("services.laser_camera._kernels", "UMA_LASER_PURE_PYTHON")
#: what the compiled twin takes for an array not there (no screen maps, eyes, bend)
_EMPTY = np.zeros(0)
#: per beam label, its parameters' names in ``_dot_moves``' order
_BEAM_NAMES = {label: [f"beam {label} {kind} {axis}"
                       for axis in "ab" for kind in ("tilt", "offset")]
               for label in BEAM_DIRECTIONS}
#: per beam (label - 1), two unit axes of the rig frame across it (beams +y, -y, -x, +z)
_ACROSS_BEAM = np.array([[e for e in np.eye(3) if abs(e @ b) < 0.5]
                         for b in (np.asarray(BEAM_DIRECTIONS[k], float)
                                   for k in sorted(BEAM_DIRECTIONS))])


def _map_terms() -> np.ndarray:
    """A screen map's moves per coefficient (2 axes x 8, flattened) as a 0/1 selection of
    the terms (1, x, y, xx, xy, yy) of the dot's screen point, ``dX = a + b x + c y - X (g x
    + h y)`` along each axis: a product with it gives the terms exactly (times 1, plus 0)."""
    out = np.zeros((6, 16))
    for j, term in enumerate([0, 1, 2, -1, -1, -1, 3, 4, -1, -1, -1, 0, 1, 2, 4, 5]):
        if term >= 0:
            out[term, j] = 1.0
    return out


_MAP_TERMS = _map_terms()
#: the screen point's quadratic terms xx, xy, yy as products of its coordinates
_SQUARES_A, _SQUARES_B = np.array([0, 0, 1]), np.array([0, 1, 1])
#: the skew part of a rotation's small error, as flat indices into the row-major 3 x 3:
#: component j is R[(2, 0, 1)[j], (1, 2, 0)[j]] minus its transposed entry (flat indices
#: take one ``take`` each, where a row and column index pair takes a slower fancy index)
_SKEW_PLUS = np.array([7, 2, 3])
_SKEW_MINUS = np.array([5, 6, 1])
_DIAG3 = np.arange(3)
#: the covariance's eight perturbed copies of the four dots: copy 1 + 2k + a moves dot k
#: along its wall's axis a
_PERTURBED_COPY = 1 + np.arange(8)
_PERTURBED_DOT = np.repeat(np.arange(4), 2)
