"""The simulated IVY world: cube, screens, cameras, the laser housing on a moving head.

``IvyWorld(n_cameras=6, seed=1)`` builds the installation (cameras with their own
intrinsics, distortion and misalignment, from ``install_seed``) and a head trajectory
(from ``seed``).  ``world.render(t)`` returns the eight-bit images of all cameras at time
``t`` with the ground truth; ``world.laser_hits(p, q)`` where the four beams of a rig at
pose ``(p, q)`` meet the walls.  Rendering is deterministic in ``(seed, t)``, whatever the
order of calls.  Everything the tracker may know comes from calibration images
(``intrinsic_views``, ``screen_board``, ``dark_frame``) and the walls' measured geometry,
never from the ``Camera`` objects themselves.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.installation.camera import Camera, place_camera
from services.installation.ivy import (
    CUBE_SIDE_M,
    SCREEN_SIDE_M,
    WALL_NAMES,
    BeamHit,
    Wall,
    intersect_beams,
    make_walls,
)
from services.installation.laser_housing import BEAM_DIRECTIONS, LABELS
from services.sim import mounts
from services.sim.projection import ProjectedContent
from services.sim.render import (
    NoiseBank,
    SensorModel,
    Spot,
    add_spots,
    checkerboard,
    render_plane_pattern,
)
from services.sim.trajectory import HeadTrajectory

#: overlap (m) of the two cameras sharing the floor or the ceiling in the 8-camera layout
SPLIT_OVERLAP_M = 0.1
#: the simulated trajectory's t = 0 in wall-clock time (2026-01-01T00:00:00Z), shared by every
#: process that simulates the same world, so their ground truths agree
SIM_EPOCH_NS = 1_767_225_600_000_000_000


def sim_time_s(t_ns: int) -> float:
    """Trajectory time (s) of a wall-clock timestamp (ns since the Unix epoch)."""
    return (int(t_ns) - SIM_EPOCH_NS) * 1e-9


@dataclass(frozen=True)
class WorldConfig:
    """Physical parameters of the simulation: a realistic installation by default
    (docs/SIMULATION.md says where each value comes from); ``WorldConfig.ideal()`` is the
    ideal one (black screens, a perfect housing and screens, spots of one size)."""

    n_cameras: int = 6  # 6: one per screen; 8: floor and ceiling split in two (the thesis)
    cube_side_m: float = CUBE_SIDE_M
    screen_side_m: float = SCREEN_SIDE_M
    beam_sigma_m: float = 0.0005  # beam at the diode (std); ideal: 1.5 mm everywhere
    #: growth of the beam's std per metre of range: 6 mm diameter (~4 std) at 5 m
    #: (appendix C.2.1)
    beam_divergence_rad: float = 0.0002
    diffusion_sigma_m: float = 0.005  # blur of the rear-projection screen
    spot_energy_dn: float = 3000.0  # integrated DN of one spot: head-on spots saturate
    #: the screen passes the beam's power towards the camera as cos(incidence) ** this
    spot_falloff_exponent: float = 1.0
    exposure_s: float = 0.004  # spots smear while the head moves
    exposure_samples: int = 4
    distractor_rate: float = 0.02  # stray bright blobs per image (reflections, glints)
    sensor: SensorModel = field(default_factory=SensorModel)
    #: brightest projected content behind the notch filter (DN above dark; 0: black screens)
    projection_peak_dn: float = 24.0
    projection_speed_px_s: float = 120.0  # how fast the content moves across the image
    # Imperfections of a real installation that the tracker cannot know (each drawn once
    # per installation from ``install_seed``):
    housing_error_deg: float = 0.02  # std of each beam's direction error
    housing_offset_m: float = 0.0005  # std of each beam's miss distance from the common P0
    screen_bulge_m: float = 0.002  # std of the fabric screens' bend at their centres
    #: std (per axis) of the rotation each camera keeps after calibration: the filter is
    #: put on after the screen homography, and the correcting homography of §5.4.2 rests on
    #: four hand-picked laser spots
    calibration_residual_deg: float = 0.015

    @classmethod
    def ideal(cls, **overrides) -> WorldConfig:
        """Today's ideal installation: black screens, a perfect housing, flat screens,
        cameras exactly where they were calibrated, spots of one size and brightness."""
        return cls(**{"beam_sigma_m": 0.0015, "beam_divergence_rad": 0.0,
                      "spot_falloff_exponent": 0.0, "projection_peak_dn": 0.0,
                      "housing_error_deg": 0.0, "housing_offset_m": 0.0,
                      "screen_bulge_m": 0.0, "calibration_residual_deg": 0.0, **overrides})

    def __post_init__(self) -> None:
        if self.n_cameras not in (6, 8):
            raise InvalidInputError(f"n_cameras must be 6 (one per screen) or 8 (floor and ceiling "
                                    f"split, as in the thesis), got {self.n_cameras}")
        if self.exposure_samples < 1 or self.exposure_s < 0:
            raise InvalidInputError("exposure_s must be >= 0 and exposure_samples >= 1")
        if min(self.housing_error_deg, self.housing_offset_m, self.screen_bulge_m,
               self.calibration_residual_deg, self.projection_peak_dn, self.beam_divergence_rad,
               self.spot_falloff_exponent) < 0:
            raise InvalidInputError("housing_error_deg, housing_offset_m, screen_bulge_m, "
                                    "calibration_residual_deg, projection_peak_dn, "
                                    "beam_divergence_rad and spot_falloff_exponent must be >= 0")


@dataclass
class Frame:
    """One synchronous set of camera images and what really happened."""

    t: float
    images: dict[str, np.ndarray]  # camera name -> (480, 640) uint8
    rig_position: np.ndarray  # ground truth marvin/laser_rig in ivy/world
    rig_quaternion: np.ndarray
    hits: dict[int, BeamHit]  # diode label -> wall hit at t
    image_points: dict[str, dict[int, np.ndarray]]  # camera -> label -> true pixel (u, v)
    n_distractors: int

    @property
    def visible_labels(self) -> set[int]:
        """Diodes whose spot some camera sees."""
        return {k for pts in self.image_points.values() for k in pts}


class IvyWorld:
    """The IVY display with its cameras and a head wearing the laser housing."""

    def __init__(self, n_cameras: int = 6, seed: int = 0, install_seed: int = 0,
                 trajectory: HeadTrajectory | None = None, config: WorldConfig | None = None,
                 ideal: bool = False, imperfection_seed: int | None = None):
        """``ideal``: ``WorldConfig.ideal()`` instead of the realistic default (only
        without ``config``).  ``imperfection_seed`` (default ``install_seed``) draws the
        housing's and screens' errors and the cameras' turn since calibration: none of them
        changes the calibration images, so worlds that differ only in it share one
        calibration."""
        if ideal and config is not None:
            raise InvalidInputError("give ideal=True or a config, not both")
        self.config = config or (WorldConfig.ideal(n_cameras=n_cameras) if ideal
                                 else WorldConfig(n_cameras=n_cameras))
        if config is not None and n_cameras != 6 and config.n_cameras != n_cameras:
            raise InvalidInputError(f"n_cameras={n_cameras} disagrees with config.n_cameras="
                                    f"{config.n_cameras}; give it in one place")
        self.seed = seed
        self.install_seed = install_seed
        self.walls: dict[str, Wall] = make_walls(self.config.cube_side_m,
                                                 self.config.screen_side_m)
        self.cameras: list[Camera] = _install_cameras(self.walls, self.config, install_seed)
        self.trajectory = trajectory or HeadTrajectory(seed)
        flaws = install_seed if imperfection_seed is None else imperfection_seed
        self.beams, self.bulge_m = _imperfections(self.config, flaws)
        self._noise = {c.name: NoiseBank(c, self.config.sensor,
                                         np.random.default_rng([install_seed, i, 7]))
                       for i, c in enumerate(self.cameras)}
        #: the cameras as they are while tracking: moved a little since calibration
        self._tracking = _after_calibration(self.cameras, self.config, flaws)
        self._content = {
            c.name: ProjectedContent(c.width, c.height, self.config.projection_peak_dn,
                                     self.config.projection_speed_px_s,
                                     np.random.default_rng([install_seed, i, 17]))
            for i, c in enumerate(self.cameras) if self.config.projection_peak_dn > 0}

    @property
    def installation(self) -> dict:
        """What fixes the cameras and screens (not the trajectory): a calibration made for
        one world is valid for every world with the same installation."""
        c = self.config
        return {"n_cameras": c.n_cameras, "install_seed": self.install_seed,
                "cube_side_m": c.cube_side_m, "screen_side_m": c.screen_side_m,
                "screen_bulge_m": c.screen_bulge_m}

    # ------------------------------------------------------------------ ground truth

    def rig_pose(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True pose of ``marvin/laser_rig`` in ``ivy/world`` at ``t`` (s): (n, 3), (n, 4)."""
        p_h, q_h = self.trajectory.pose(t)
        return geo.compose(p_h, q_h, *mounts.HEAD_TO_LASER_RIG)

    def laser_hits(self, p: np.ndarray, q: np.ndarray) -> dict[int, BeamHit]:
        """Where the beams of a rig at pose ``(p, q)`` (rig in world) meet the walls."""
        p = geo.check_vector(p, "rig position").reshape(3)
        q = geo.check_quaternion(q, "rig quaternion").reshape(4)
        half = self.config.cube_side_m / 2
        if np.any(np.abs(p) >= half):
            raise InvalidInputError(f"rig position {p.tolist()} is outside the cube (half side "
                                    f"{half} m)")
        R = geo.quat_to_matrix(q)
        offsets = np.array([off for off, _ in self.beams.values()])
        directions = np.array([d for _, d in self.beams.values()])
        hits = intersect_beams(self.walls, p + offsets @ R.T, directions @ R.T, self.bulge_m)
        return dict(zip(self.beams, hits, strict=True))

    # ------------------------------------------------------------------ rendering

    def render(self, t: float, pose: tuple[np.ndarray, np.ndarray] | None = None) -> Frame:
        """All camera images at time ``t`` (s).  The rig follows the trajectory (with
        motion blur over the exposure) unless ``pose`` fixes it (then no blur)."""
        cfg = self.config
        rng = np.random.default_rng([self.seed, round(t * 1e6) & 0xFFFFFFFF, 11])
        if pose is None:
            n = cfg.exposure_samples
            ts = t + cfg.exposure_s * ((np.arange(n) + 0.5) / n - 0.5)
            ps, qs = self.rig_pose(ts)
            p_t, q_t = self.rig_pose(t)
            p_t, q_t = p_t[0], q_t[0]
        else:
            p_t = geo.check_vector(pose[0], "rig position").reshape(3)
            q_t = geo.check_quaternion(pose[1], "rig quaternion").reshape(4)
            ps, qs = p_t[None], q_t[None]
        sub_hits = [(p, self.laser_hits(p, q)) for p, q in zip(ps, qs, strict=True)]
        hits = self.laser_hits(p_t, q_t)
        images: dict[str, np.ndarray] = {}
        n_distractors = 0
        for cam in self._tracking:
            spots = []
            for p, hs in sub_hits:
                spots += [s for h in hs.values()
                          if (s := self._spot(cam, h, p, 1.0 / len(sub_hits))) is not None]
            extra = self._distractors(cam, rng)
            n_distractors += len(extra)
            img = self._noise[cam.name].dark_frame(rng)
            if cam.name in self._content:
                cv2.add(img, self._content[cam.name].crop(t), dst=img)
            add_spots(img, spots + extra, cfg.sensor, rng)
            images[cam.name] = img
        return Frame(t, images, p_t, q_t, hits, self.dot_pixels(hits), n_distractors)

    def dot_pixels(self, hits: dict[int, BeamHit]) -> dict[str, dict[int, np.ndarray]]:
        """The true pixel (u, v) of every beam hit that each camera, as it is while
        tracking, sees: the spots' centres before blur and noise.  A simulation that needs
        the installation's geometry but not the images (``services.alignment.simulate``)
        starts here."""
        return {cam.name: self._seen_by(cam, hits) for cam in self._tracking}

    @staticmethod
    def _seen_by(cam: Camera, hits: dict[int, BeamHit]) -> dict[int, np.ndarray]:
        """The pixels of the hits on ``cam``'s screen that fall in its image (one
        projection for all of them: this runs for every frame of an evaluation)."""
        mine = [k for k, h in hits.items() if h.wall == cam.wall and h.on_screen]
        if not mine:
            return {}
        uv = cam.project(np.array([hits[k].point for k in mine]))
        inside = cam.in_image(uv)
        return {k: uv[i] for i, k in enumerate(mine) if inside[i]}

    def _spot(self, cam: Camera, hit: BeamHit, origin: np.ndarray,
              share: float) -> Spot | None:
        """The image blob of a beam's footprint, if this camera sees it."""
        if hit.wall != cam.wall or not hit.on_screen:
            return None
        uv = cam.project(hit.point[None])[0]
        if not cam.in_image(uv)[0]:
            return None
        cfg = self.config
        wall = self.walls[hit.wall]
        # beam direction in screen coordinates: its in-plane part sets the stretch
        d = wall.rotation.T @ hit.direction
        a = d[:2] / max(np.linalg.norm(d[:2]), 1e-12)
        c = max(hit.cos_incidence, 1e-3)
        beam = cfg.beam_sigma_m + cfg.beam_divergence_rad * np.linalg.norm(hit.point - origin)
        cov_s = beam ** 2 * (np.eye(2) + (1 / c ** 2 - 1) * np.outer(a, a)) \
            + cfg.diffusion_sigma_m ** 2 * np.eye(2)
        J = cam.screen_to_image_jacobian(wall, hit.screen_xy)
        A = np.linalg.inv(J)
        clip = (A, hit.screen_xy - A @ uv, wall.screen_side_m)
        energy = cfg.spot_energy_dn * share * c ** cfg.spot_falloff_exponent
        return Spot(uv, J @ cov_s @ J.T, energy, clip)

    def _distractors(self, cam: Camera, rng: np.random.Generator) -> list[Spot]:
        n = rng.poisson(self.config.distractor_rate)
        out = []
        for _ in range(n):
            uv = rng.uniform([20, 20], [cam.width - 20, cam.height - 20])
            sig = rng.uniform(0.7, 2.5)
            out.append(Spot(uv, sig ** 2 * np.eye(2),
                            self.config.spot_energy_dn * rng.uniform(0.3, 1.5)))
        return out

    # ------------------------------------------------------------------ calibration

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise InvalidInputError(f"no camera {name!r} (cameras: "
                                f"{', '.join(c.name for c in self.cameras)})")

    def dark_frame(self, name: str, seed: int = 0) -> np.ndarray:
        """An image with the lasers off (for the sensor's dark level and noise)."""
        return self._noise[name].dark_frame(np.random.default_rng([seed, 5]))

    def intrinsic_views(self, name: str, n_views: int = 8, seed: int = 0,
                        pattern: tuple[int, int] = (9, 6), square_m: float = 0.06,
                        ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Images of a checkerboard held in front of camera ``name`` in ``n_views`` poses
        (thesis §5.4.1, intrinsic calibration), each with the board's 3D inner-corner
        coordinates (board frame, z = 0) in OpenCV's row-major order."""
        cam = self.camera(name)
        rng = np.random.default_rng([seed, 3])
        na, nb = pattern[0] + 1, pattern[1] + 1
        size = np.array([na, nb]) * square_m
        obj = np.array([[(i + 1) * square_m, (j + 1) * square_m, 0.0]
                        for j in range(pattern[1]) for i in range(pattern[0])])
        views = []
        while len(views) < n_views:
            dist = rng.uniform(0.7, 1.3)
            R = geo.rodrigues(np.radians(rng.uniform(-35, 35, 3) * [1, 1, 0.5]))
            lateral = rng.uniform(-0.4, 0.4, 2) * dist * [1.0, 0.75]
            center_c = np.array([lateral[0], lateral[1], dist])
            # board axes in camera coordinates, board centre at center_c
            a_c, b_c = R[:, 0], R[:, 1]
            origin_c = center_c - 0.5 * (size[0] * a_c + size[1] * b_c)
            to_w = cam.R_cw.T
            origin, a_w, b_w = cam.center + to_w @ origin_c, to_w @ a_c, to_w @ b_c
            corners_w = origin + obj[:, :1] * a_w + obj[:, 1:2] * b_w
            if not cam.in_image(cam.project(corners_w), margin_px=12).all():
                continue
            # the board with its white border covers only this part of the image
            ext = np.array([[-1, -1], [na + 1, -1], [-1, nb + 1], [na + 1, nb + 1]]) * square_m
            uv = cam.project(origin + ext[:, :1] * a_w + ext[:, 1:] * b_w)
            box = (int(np.floor(uv[:, 0].min())) - 4, int(np.ceil(uv[:, 0].max())) + 5,
                   int(np.floor(uv[:, 1].min())) - 4, int(np.ceil(uv[:, 1].max())) + 5)
            img = render_plane_pattern(cam, origin, a_w, b_w,
                                       checkerboard(square_m, (na, nb), border_m=square_m),
                                       box=box)
            views.append((img, obj.copy()))
        return views

    def screen_board(self, name: str, square_m: float = 0.16
                     ) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
        """A checkerboard projected onto camera ``name``'s screen region (thesis §5.4.1,
        fig. 5.12): the image, the inner-corner pattern size and the inner corners' screen
        coordinates (m) in OpenCV's row-major order.  The square counts are one odd, one
        even, so the board's orientation is unambiguous."""
        cam = self.camera(name)
        wall = self.walls[cam.wall]
        x0, x1, y0, y1 = cam.region
        margin = 0.06
        na = int((x1 - x0 - 2 * margin) // square_m)
        nb = int((y1 - y0 - 2 * margin) // square_m)
        if (na + nb) % 2 == 0:
            nb -= 1
        org_xy = np.array([(x0 + x1 - na * square_m) / 2, (y0 + y1 - nb * square_m) / 2])
        origin = wall.to_world(org_xy)[0]
        ex, ey = wall.rotation[:, 0], wall.rotation[:, 1]
        side = wall.screen_side_m
        # the projector lights the rest of the screen dimly; beyond the screen is the frame
        board = checkerboard(square_m, (na, nb), border_m=margin * 0.9, outside=60.0)

        def on_screen(a: np.ndarray, b: np.ndarray, blur_a: np.ndarray,
                      blur_b: np.ndarray) -> np.ndarray:
            X, Y = a + org_xy[0], b + org_xy[1]
            lit = (np.minimum(X, Y) >= 0) & (np.maximum(X, Y) <= side)
            return np.where(lit, board(a, b, blur_a, blur_b), np.nan)

        img = render_plane_pattern(cam, origin, ex, ey, on_screen)
        pattern = (na - 1, nb - 1)
        jj, ii = np.mgrid[0:pattern[1], 0:pattern[0]]
        corners = org_xy + square_m * np.column_stack([ii.ravel() + 1, jj.ravel() + 1])
        return img, pattern, corners


def _imperfections(cfg: WorldConfig, seed: int
                   ) -> tuple[dict[int, tuple[np.ndarray, np.ndarray]], dict[str, float]]:
    """Per beam (offset of its line from P0, direction) in the rig frame, and per wall the
    bend of its screen -- ideal unless the configuration asks for errors."""
    rng = np.random.default_rng([seed, 13])
    beams = {}
    for k in LABELS:
        d = BEAM_DIRECTIONS[k]
        tilt = rng.normal(0, np.radians(cfg.housing_error_deg), 3)
        d = geo.quat_rotate(geo.rotvec_to_quat(tilt - (tilt @ d) * d), d)
        off = rng.normal(0, cfg.housing_offset_m, 3)
        beams[k] = (off - (off @ d) * d, d / np.linalg.norm(d))
    bulge = {name: abs(rng.normal(0, cfg.screen_bulge_m)) for name in sorted(WALL_NAMES)}
    return beams, bulge


def _after_calibration(cams: list[Camera], cfg: WorldConfig, seed: int) -> list[Camera]:
    """The cameras turned by their calibration residual (a small rotation about their
    optical centres): what the calibration images showed is no longer exactly true."""
    rng = np.random.default_rng([seed, 19])
    out = []
    for cam in cams:
        turn = geo.rodrigues(rng.normal(0, np.radians(cfg.calibration_residual_deg), 3))
        out.append(replace(cam, R_cw=turn @ cam.R_cw, _cache={}))
    return out


def _install_cameras(walls: dict[str, Wall], cfg: WorldConfig, seed: int) -> list[Camera]:
    rng = np.random.default_rng([seed, 1])
    S = cfg.screen_side_m
    cams = []
    for name, wall in walls.items():
        if cfg.n_cameras == 8 and name in ("floor", "ceiling"):
            h = S / 2
            cams.append(place_camera(f"{name}1", wall, (0.0, h + SPLIT_OVERLAP_M, 0.0, S), rng))
            cams.append(place_camera(f"{name}2", wall, (h - SPLIT_OVERLAP_M, S, 0.0, S), rng))
        else:
            cams.append(place_camera(name, wall, (0.0, S, 0.0, S), rng))
    return cams
