"""One frame set at a time: every camera's blobs in, every body's pose out.

Dorfmüller-Ulhaas §2, fig. 5, with the filter's prediction doing what the paper says it
is for:

* **Tracked bodies** (the filter runs): each marker's predicted position at each
  camera's own exposure time is projected into that camera, and the blob nearest it
  within ``gate_px`` is taken -- unless another blob is nearly as near, or the blob is
  claimed by another marker (of this body or another): such a blob is used by none.  No
  search, no triangulation, and no identity can swap: a marker is only ever looked for
  where its own body predicts it.
* **Lost bodies**: the blobs nobody took are matched between cameras and triangulated
  (``triangulation``), each lost body is searched among the points by its distance
  signature (``bodies``), its pose found by absolute orientation.
* Either way the pose is then refined against every camera's 2D observations at one
  time, the set's mean exposure time, with the filter's motion bringing each camera's
  observations to it (``pose``); observations further than ``outlier_px`` from
  the fit, or than ``outlier_sigmas`` of their own std, are dropped one by one.  A pose
  needs rays from 2 cameras at least.  The fit then updates the filter (``motion``),
  whose pose and covariance are the output.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.outside_in.blobs import Blobs
from services.outside_in.bodies import RigidBody, identify
from services.outside_in.health import HealthParams, RigHealth
from services.outside_in.motion import ImmFilter, MotionConfig
from services.outside_in.pose import Motion, PoseFit, Rows, absolute_orientation, refine_rows
from services.outside_in.rig import RigCamera, RigImages
from services.outside_in.triangulation import MatchParams, match_and_triangulate

Array = np.ndarray
#: a tracked marker takes the nearest blob within this many stds of its predicted image's
#: spread, when that is wider than ``TrackerParams.gate_px``
GATE_SIGMAS = 3.0


@dataclass(frozen=True)
class CameraFrame:
    """The blobs one camera found in one image, and when it was exposed (s)."""

    camera: int
    t: float
    blobs: Blobs


@dataclass(frozen=True)
class TrackerParams:
    match: MatchParams = field(default_factory=MatchParams)
    motion: MotionConfig = field(default_factory=MotionConfig)
    identify_tolerance_m: float = 0.005   # distance signature tolerance when searching
    confirm_px: float = 1.0               # a body found from three points: another of its
                                          # markers must image this near a blob
    gate_px: float = 5.0                  # blob distance to a predicted marker
    ambiguity_ratio: float = 0.6          # nearest / second nearest blob must be below it
    outlier_px: float = 0.4               # an observation further from the fit is dropped,
    outlier_sigmas: float = 5.0           # ... or further than this many of its stds
    max_rms_px: float = 1.0               # a fit with a larger rms is refused
    min_observations: int = 4             # marker images a fit needs: three fit any pose
                                          # exactly (rms 0), so a wrong claim of one of
                                          # them could not be told from a right one
    lost_after: int = 5                   # frame sets without a pose before a new search
    health: HealthParams = field(default_factory=HealthParams)


@dataclass(frozen=True)
class BodyEstimate:
    """A body's pose at ``t`` (filtered), with how it was measured."""

    body: str
    t: float
    p: Array
    q: Array
    cov: Array                  # (6, 6) over [dp, phi] (decoupled)
    cameras: int                # cameras whose rays the pose was fitted to
    markers: int                # identified marker images
    rms_px: float
    acquired: bool              # found by search this frame set (not by prediction)
    blobs: dict[int, dict[int, int]]   # camera -> marker -> blob index
    fit: PoseFit

    @property
    def cov_se3(self) -> Array:
        """The covariance over uma's SE(3) left perturbation (for the SRG)."""
        return geo.decoupled_to_se3(self.p, self.cov)


@dataclass(frozen=True)
class _SetBlobs:
    """A frame set's blobs in arrays over all its cameras, from which each body's claims
    become the rows of its fit (``pose.Rows``) by indexing, not per marker."""

    stack: Array    # (rig cameras, 13) each camera's ``RigCamera.stack_row``
    offset: Array   # (rig cameras,) where each camera's blobs start in xy and std_px
    xy: Array       # (n, 2) undistorted normalised coordinates
    std_px: Array   # (n,)
    dt_s: Array     # (rig cameras,) each camera's exposure time less the set's time

    @staticmethod
    def of(cameras: list[RigCamera], frames: list[CameraFrame], norm: dict[int, Array],
           t_ref: float) -> _SetBlobs:
        offset, dt = np.zeros(len(cameras), int), np.zeros(len(cameras))
        at = 0
        for f in frames:
            offset[f.camera], dt[f.camera] = at, f.t - t_ref
            at += len(f.blobs)
        return _SetBlobs(np.array([c.stack_row for c in cameras]), offset,
                         np.concatenate([norm[f.camera] for f in frames]).reshape(-1, 2),
                         np.concatenate([f.blobs.std_px for f in frames]).astype(float), dt)

    def rows(self, pairs: dict[tuple[int, int], tuple[int, int]]
             ) -> tuple[Rows, Array, Array]:
        """``(camera, marker) -> (camera, blob)`` as a fit's rows (each camera's
        together, in the order given), each row's place among ``pairs`` and its blob."""
        n = len(pairs)
        cam = np.fromiter((c for c, _ in pairs), int, n)
        marker = np.fromiter((m for _, m in pairs), int, n)
        blob = np.fromiter((b for _, b in pairs.values()), int, n)
        order = np.argsort(cam, kind="stable")
        cam, marker, blob = cam[order], marker[order], blob[order]
        at = self.offset[cam] + blob
        return (Rows(cam, self.stack[cam], marker, self.xy[at], self.std_px[at],
                     self.dt_s[cam]), order, blob)


@dataclass
class _Track:
    body: RigidBody
    filter: ImmFilter
    missed: int = 0
    #: the furthest marker's distance (m) from the body's origin
    reach: float = field(init=False)

    def __post_init__(self) -> None:
        self.reach = float(np.max(np.linalg.norm(self.body.markers, axis=1)))


class OutsideInTracker:
    """Tracks rigid bodies with a calibrated rig of marker cameras."""

    def __init__(self, cameras: list[RigCamera], bodies: list[RigidBody],
                 params: TrackerParams | None = None):
        if len(cameras) < 2:
            raise InvalidInputError(
                f"an outside-in rig needs 2 cameras at least, got {len(cameras)}")
        self.cameras = list(cameras)
        self.images = RigImages(self.cameras)
        self.params = params or TrackerParams()
        self.tracks = [_Track(b, ImmFilter(self.params.motion)) for b in bodies]
        self.counts = {"tracked": 0, "acquired": 0, "refused_fit": 0, "refused_filter": 0,
                       "ambiguous_blobs": 0}
        self.health = RigHealth(len(self.cameras), self.params.health)
        #: the tracked bodies' markers predicted at a time and where they image in every
        #: camera, kept until the next frame set
        self._ahead: dict[float, tuple[Array, Array]] = {}

    def process(self, frames: list[CameraFrame], search: bool = True) -> list[BodyEstimate]:
        """Poses of the bodies found in one set of frames (one per camera at most); with
        ``search`` false the lost bodies are not searched for in it (a search costs
        several frame sets' tracking: its caller may spread them out)."""
        self._ahead = {}
        seen = [f for f in frames if len(f.blobs)]
        # a camera flagged as bumped measures nothing until it is re-estimated: its rays
        # are off by its turn, which a fit to it and one other camera cannot tell (a
        # 0.5 deg turn put such poses 16-20 mm off); its blobs still go to the health
        # check that re-estimates it
        flagged = set(self.health.flagged)
        frames = [f for f in seen if f.camera not in flagged]
        if not frames:
            self._miss_all(set())
            return []
        # the pose's time: where the cameras' exposures measure it (with unsynchronised
        # cameras the newest exposure's pose would be theirs moved by the filter's
        # velocity, less certain and, on the simulator's smooth paths, less accurate)
        t_ref = float(np.mean([f.t for f in frames]))
        self._forget_stale(t_ref)
        norm = {f.camera: self.cameras[f.camera].normalize(f.blobs.uv) for f in frames}
        blobs = _SetBlobs.of(self.cameras, frames, norm, t_ref)
        claims = self._predicted_claims(frames)
        used = {cb for mine in claims.values() for cb in mine.values()}
        out: list[BodyEstimate] = []
        done: set[int] = set()
        for k, mine in claims.items():
            est = self._estimate(self.tracks[k], mine, blobs, t_ref, acquired=False)
            if est is not None:
                out.append(est)
                done.add(k)
        lost = [k for k, tr in enumerate(self.tracks)
                if k not in done and (not tr.filter.ready or tr.missed >= self.params.lost_after)]
        if lost and search:
            out += self._acquire(lost, blobs, norm, used, t_ref, done)
        self._miss_all(done)
        self._check_cameras(t_ref, seen, out)
        return out

    @property
    def searching(self) -> bool:
        """Whether a body is lost (or not found yet): the cameras' whole images are needed
        to find it, not only the windows around the tracked bodies' markers."""
        return any(not tr.filter.ready or tr.missed >= self.params.lost_after
                   for tr in self.tracks)

    def predicted_images(self, times: dict[int, float]) -> dict[int, Array]:
        """Where the tracked bodies' markers will image in each camera at its time
        (``camera -> t``): n x 2 distorted pixels of those in front of it and inside its
        image, the windows its detector need look in (Dorfmüller-Ulhaas §2: the
        prediction projected into the images finds the markers of the next frame)."""
        out = {}
        for t in set(times.values()):   # synchronised cameras share their next exposure
            got = self._ahead.get(t)
            if got is None:
                world = self._tracked_markers(t)
                z, uv = self.images.depth_and_pixels(world)
                got = self._ahead[t] = uv, (z > 0.05) & self.images.inside(uv)
            uv, visible = got
            out.update((c, uv[c][visible[c]]) for c, tc in times.items() if tc == t)
        return out

    def _forget_stale(self, t: float) -> None:
        """Forget the bodies whose filter last measured them more than its ``max_gap_s``
        before ``t``: the filter would not gate a pose against so old a prediction but start
        again from it, and the prediction's spread, far wider than the markers' spacing,
        widens the gate until any blobs near it make a fit (a hand 0.6 s unseen was fitted
        to six wrong marker images 71 mm / 74 deg off); a forgotten body is searched for."""
        for track in self.tracks:
            if track.filter.ready and t - track.filter.t > self.params.motion.max_gap_s:
                track.filter.reset()

    def _tracked_markers(self, t: float) -> Array:
        """The tracked bodies' markers in the world at ``t`` (n, 3)."""
        tracked = [tr for tr in self.tracks
                   if tr.filter.ready and tr.missed < self.params.lost_after]
        return (np.vstack([_markers_at(tr, t) for tr in tracked]) if tracked
                else np.zeros((0, 3)))

    def _check_cameras(self, t: float, frames: list[CameraFrame],
                       out: list[BodyEstimate]) -> None:
        """Feed the rig's health and put re-estimated cameras in place (``health``)."""
        markers = {tr.body.name: tr.body.markers for tr in self.tracks}
        poses = [(e.fit.p, e.fit.R, markers[e.body], e.blobs) for e in out if not e.acquired]
        moved = self.health.observe(t, self.images, {f.camera: f.blobs.uv for f in frames},
                                    poses)
        for c, cam in moved:
            self.cameras[c] = cam
        if moved:
            self.images = RigImages(self.cameras)

    # ---------------------------------------------------------------- association

    def _predicted_claims(self, frames: list[CameraFrame]
                          ) -> dict[int, dict[tuple[int, int], tuple[int, int]]]:
        """Per tracked body, ``(camera, marker) -> (camera, blob)`` for every marker whose
        predicted image has one unambiguous blob; blobs claimed twice go to no one.  All
        cameras at once: each marker's nearest and second nearest blob in each image."""
        p = self.params
        tracked = [(k, tr) for k, tr in enumerate(self.tracks)
                   if tr.filter.ready and tr.missed < p.lost_after]
        if not tracked:
            return {}
        bounds = np.cumsum([0, *(len(track.body.markers) for _, track in tracked)])
        sizes = np.diff(bounds)
        cams = np.array([f.camera for f in frames])
        z = np.empty((len(frames), bounds[-1]))
        uv = np.empty((len(frames), bounds[-1], 2))
        for t in {f.t for f in frames}:   # synchronised cameras share a time
            at = np.flatnonzero([f.t == t for f in frames])
            world = np.vstack([_markers_at(track, t) for _, track in tracked])
            z[at], uv[at] = self.images.depth_and_pixels(world, cams[at])
        # a marker's gate: gate_px, or GATE_SIGMAS of its predicted image's spread where
        # the prediction is less sure (a body just found, whose motion is not known yet;
        # frame sets skipped on a busy host): a fixed gate lost such bodies again and again.
        # The spread at the set's last exposure serves all its cameras: it is the widest
        # (it grows with the time predicted over), and a covariance prediction per body
        # and exposure time cost 8 unsynchronised cameras a sixth of their tracking CPU
        t_last = max(f.t for f in frames)
        spread = np.repeat([_spread_m(track, t_last) for _, track in tracked], sizes)
        focal = np.array([self.cameras[c].K[0, 0] for c in cams])[:, None]
        gate = np.maximum(p.gate_px, GATE_SIGMAS * focal * spread / np.maximum(z, 0.05))
        # every camera's blobs, padded with blobs infinitely far
        blobs = np.full((len(frames), max(len(f.blobs) for f in frames), 2), np.inf)
        for i, f in enumerate(frames):
            blobs[i, :len(f.blobs)] = f.blobs.uv
        diff = uv[:, :, None, :] - blobs[:, None, :, :]
        d = np.sqrt(np.add.reduce(diff * diff, axis=3))        # (frames, markers, blobs)
        nearest = np.argmin(d, axis=2)
        if d.shape[2] > 1:
            near, second = np.moveaxis(np.partition(d, 1, axis=2)[..., :2], 2, 0)
        else:
            near, second = d[..., 0], np.full(d.shape[:2], np.inf)
        ambiguous = near > p.ambiguity_ratio * second
        # markers near a blob, of bodies wholly in front of the camera
        front = np.minimum.reduceat(z, bounds[:-1], axis=1) > 0.05
        taken = ~(near > gate) & np.repeat(front, sizes, axis=1)
        self.counts["ambiguous_blobs"] += int(np.count_nonzero(taken & ambiguous))
        fi, mi = np.nonzero(taken & ~ambiguous)           # in the frames' and markers' order
        bi = nearest[fi, mi]
        # a blob claimed by two markers (of one body or two) goes to neither
        _, first, count = np.unique(fi * blobs.shape[1] + bi, return_inverse=True,
                                    return_counts=True)
        twice = count[first] > 1
        self.counts["ambiguous_blobs"] += int(np.count_nonzero(twice))
        body = np.searchsorted(bounds, mi, side="right") - 1
        claims: dict[int, dict[tuple[int, int], tuple[int, int]]] = {}
        for f, m, b, k in zip(fi[~twice].tolist(), mi[~twice].tolist(), bi[~twice].tolist(),
                              body[~twice].tolist(), strict=True):
            c = frames[f].camera
            claims.setdefault(tracked[k][0], {})[(c, m - int(bounds[k]))] = (c, b)
        return claims

    # ---------------------------------------------------------------- estimation

    def _estimate(self, track: _Track, marker_blobs: dict[tuple[int, int], tuple[int, int]],
                  blobs: _SetBlobs, t_ref: float, acquired: bool,
                  start: tuple[Array, Array] | None = None) -> BodyEstimate | None:
        """Refine the body's pose on ``(camera, marker) -> (camera, blob)`` and update
        its filter; None (counted) when the fit or the filter refuses it."""
        p = self.params
        if start is None:
            p0, R0 = track.filter.predicted_pose(t_ref)
            f = track.filter
            # the filter's motion brings other cameras' observations to t_ref; the fit
            # says how it depends on it, and the filter's update counts that (``motion``)
            motion = Motion(f.v + f.a * (t_ref - f.t), f.omega, f.motion_covariance, f.a)
        else:
            # a body just found: its motion is not known yet, so the fit takes it at rest,
            # and with cameras exposed at different times its covariance holds how far
            # the start's motion uncertainty moves it (the filter starts with both)
            p0, R0 = start
            motion = Motion(np.zeros(3), np.zeros(3), track.filter.start_motion_covariance)
        rows, given, blob = blobs.rows(marker_blobs)
        keep = np.ones(len(rows), bool)
        while True:
            kept = rows.take(keep)
            fit = refine_rows(track.body.markers, kept, p0, R0, motion)
            if fit is None:
                break
            worst, err, sigmas = _worst(fit, kept)
            if err <= p.outlier_px and sigmas <= p.outlier_sigmas:
                break
            keep[np.flatnonzero(keep)[worst]] = False
        if len(rows) - np.count_nonzero(keep) > 1:
            clean = self._without_a_camera(track, rows, p0, R0, motion)
            if clean is not None and (fit is None
                                      or np.count_nonzero(clean[0]) > np.count_nonzero(keep)):
                keep, fit = clean
        if fit is None or fit.rms_px > p.max_rms_px or fit.n_observations < p.min_observations:
            self.counts["refused_fit"] += 1
            return None
        if acquired:
            track.filter.start(t_ref, fit.p, fit.R, fit.cov, fit.sensitivity)
        elif not track.filter.update(t_ref, fit.p, fit.R, fit.cov, fit.sensitivity,
                                     fit.noise_cov, np.concatenate([motion.velocity,
                                                                    motion.omega, motion.accel])):
            self.counts["refused_filter"] += 1
            return None
        self.counts["acquired" if acquired else "tracked"] += 1
        track.missed = -1          # counted up to 0 at the end of the frame set
        by_cam: dict[int, dict[int, int]] = {}
        order = np.flatnonzero(keep)[np.argsort(given[keep])]   # the order they were given
        for c, m, b in zip(rows.camera[order].tolist(), rows.markers[order].tolist(),
                           blob[order].tolist(), strict=True):
            by_cam.setdefault(c, {})[m] = b
        f = track.filter
        return BodyEstimate(track.body.name, t_ref, f.p.copy(), geo.matrix_to_quat(f.R),
                            f.pose_covariance, fit.n_cameras, fit.n_observations, fit.rms_px,
                            acquired, by_cam, fit)

    def _without_a_camera(self, track: _Track, rows: Rows, p0: Array, R0: Array,
                          motion: Motion) -> tuple[Array, PoseFit] | None:
        """The fit without one camera's observations that has no outlier left, for when
        dropping the worst observation one at a time dropped more than that camera's: a
        camera turned since its calibration (bumped, not noticed yet) sees every marker
        a few pixels off, and a near one's sharp blobs outweigh the others, so the other
        cameras' observations went instead (a hand then fitted 16 mm off to it and one
        other).  Of several such fits the one keeping most observations (its rows, as a
        mask of ``rows``); None when there is none."""
        p = self.params
        cams = sorted(set(rows.camera.tolist()))
        best = None
        for c in cams if len(cams) > 2 else ():
            keep = rows.camera != c
            kept = rows.take(keep)
            fit = refine_rows(track.body.markers, kept, p0, R0, motion)
            if fit is None:
                continue
            _, err, sigmas = _worst(fit, kept)
            if (err <= p.outlier_px and sigmas <= p.outlier_sigmas
                    and (best is None or np.count_nonzero(keep) > np.count_nonzero(best[0]))):
                best = (keep, fit)
        return best

    def _acquire(self, lost: list[int], blobs: _SetBlobs, norm: dict[int, Array],
                 used: set[tuple[int, int]], t_ref: float, done: set[int]
                 ) -> list[BodyEstimate]:
        """Search the lost bodies among the points triangulated from unclaimed blobs."""
        cams = sorted(norm)
        keep = [[b for b in range(len(norm[c])) if (c, b) not in used] for c in cams]
        free = [norm[c][kb] for c, kb in zip(cams, keep, strict=True)]
        points = match_and_triangulate([self.cameras[c] for c in cams], free,
                                       self.params.match, keep_ambiguous=True)
        if len(points) < 3:
            return []
        X = np.array([q.X for q in points])
        taken: set[int] = set()
        out = []
        views = [frozenset(q.views) for q in points]
        for k in lost:
            track = self.tracks[k]
            found = self._identify(track.body, X, views, taken, [self.cameras[c] for c in cams],
                                   [norm[c] for c in cams])
            if found is None:
                continue
            idx, R0, p0 = found
            pairs = {(cams[ci], m): (cams[ci], keep[ci][b])
                     for m, i in idx for ci, b in points[i].views}
            est = self._estimate(track, pairs, blobs, t_ref, acquired=True,
                                 start=(p0, R0))
            if est is not None:
                blobs_taken = frozenset().union(*(views[i] for _, i in idx))
                taken.update(j for j, v in enumerate(views) if v & blobs_taken)
                done.add(k)
                out.append(est)
        return out

    def _identify(self, body: RigidBody, X: Array, views: list[frozenset], taken: set[int],
                  cams: list[RigCamera], norm: list[Array]
                  ) -> tuple[list[tuple[int, int]], Array, Array] | None:
        """The body among the points ``X``: ``(marker, point)`` pairs and the pose from
        them, or None.  Four markers at least where the body has them: three points can
        match a triangle of ghosts (rays of two cameras crossing by chance), which
        tracking would then follow.  Three (or only the markers that near-equal
        assignments agree on, ``identify``'s ``agreed``) when the pose from them puts
        another of the body's markers on a blob (``confirm_px``) in two of the cameras
        that saw them: a ghost triangle's pose puts them where no blob is, while a true
        body's further marker may well be imaged but not among the points -- its image run
        together with a neighbour's in one camera, its point millimetres off.  With two
        cameras the far head of some rigs is otherwise never found, or only when such a
        point happens to fall within the tolerance."""
        tol = self.params.identify_tolerance_m
        n = len(body.markers)
        ident = identify(body, X, tol, min_markers=min(4, n), exclude=taken, views=views)
        if ident is None:
            ident = identify(body, X, tol, min_markers=3, exclude=taken, views=views,
                             agreed=True)
        if ident is None:
            return None
        idx = [(m, i) for m, i in enumerate(ident.points) if i >= 0]
        R, p = absolute_orientation(body.markers[[m for m, _ in idx]], X[[i for _, i in idx]])
        if ident.agreed_only or len(idx) < min(4, n):
            others = body.markers[[m for m in range(n) if ident.points[m] < 0]] @ R.T + p
            seen = set().union(*(views[i] for _, i in idx))
            confirmed = sum(_images_on_a_blob(cams[c], others, norm[c], self.params.confirm_px)
                            for c in sorted({c for c, _ in seen}))
            if confirmed < 2:
                return None
        return idx, R, p

    def _miss_all(self, done: set[int]) -> None:
        for k, track in enumerate(self.tracks):
            track.missed = 0 if k in done else track.missed + 1


def _spread_m(track: _Track, t: float) -> float:
    """How far (m, one std) the filter's prediction at ``t`` may put the track's furthest
    marker: its position's and its turn's (times the marker's distance from the body's
    origin) spread, each the root of its covariance's trace (at most sqrt(3) times the
    least certain direction's std, and a tenth of the cost of its eigenvalues)."""
    P = track.filter.predicted(t)[2]
    return float(np.sqrt(np.trace(P[:3, :3])) + track.reach * np.sqrt(np.trace(P[3:, 3:])))


def _markers_at(track: _Track, t: float) -> Array:
    """The track's markers in the world where its filter predicts them at ``t``."""
    p, R = track.filter.predicted_pose(t)
    return track.body.markers @ R.T + p


def _images_on_a_blob(cam: RigCamera, world: Array, xy: Array, within_px: float) -> bool:
    """Whether one of the points ``world`` (n, 3) images within ``within_px`` of a blob
    (``xy``: the camera's blobs, undistorted normalised)."""
    pc = cam.to_camera(world)
    front = pc[:, 2] > 0.05
    if not (len(xy) and front.any()):
        return False
    proj = pc[front, :2] / pc[front, 2:3]
    d = np.linalg.norm(proj[:, None, :] - xy[None, :, :], axis=2)
    return bool(d.min() * cam.focal_px < within_px)


def _worst(fit: PoseFit, rows: Rows) -> tuple[int, float, float]:
    """The observation furthest from the fitted pose for its std: its row, its distance
    in pixels and in stds."""
    sigmas = fit.errors_px / rows.std_px
    i = int(np.argmax(sigmas))
    return i, float(fit.errors_px[i]), float(sigmas[i])
