"""A simulated outside-in rig: infrared cameras around a volume, bodies with markers.

What it models, and why:

* **Cameras**: ``n`` cameras on a ring above a 3 x 3 x 2.5 m volume (a typical motion
  capture room), looking at its centre, 640 x 480 with a mildly distorting wide lens
  (OpenCV's model: the tracker undistorts exactly as the simulator distorts).  Each may
  expose with its own phase within the frame period (``synchronized=False``: cheap
  cameras without a sync cable).
* **Markers**: retro-reflective balls of 14 mm.  A ball images as a disk of its
  apparent radius blurred by the lens (``0.5 erfc((d - r) / (sqrt 2 sigma))``), brightest
  near the camera (the ring light falls off with the square of the distance), saturating
  at 255.  Pixel noise is the sensor's: shot noise (``gain`` DN per electron) and read
  noise -- the detector's own noise model (``BlobParams``), so the centroid stds it reports
  are the truth's.  A frame's pixels around its markers are drawn once from their whole
  signal (the background's, every marker's light summed) with fresh noise; the rest of
  the image keeps one frozen noise draw, far below the threshold, where it cannot make a
  blob and no centroid weighs it.
* **Occlusion**: each body has a hull (a sphere at its origin, the markers on stalks
  outside it); a marker whose ray to a camera crosses any hull is hidden.
* **False blobs**: 5 per camera -- three round reflections the size of a marker, an
  elongated one (a shiny rail) and a lamp (large and saturated) -- fixed in the image.
* **Motion**: each body moves on a smooth random path (sums of sinusoids, up to about
  1 m/s and 90 deg/s) in its own part of the volume.

Everything depends only on ``seed`` and time, so runs repeat.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.special import erfc

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.outside_in.bodies import RigidBody
from services.outside_in.rig import RigCamera, look_at

Array = np.ndarray

WIDTH, HEIGHT = 640, 480
#: a body's hull radius (m): what hides its own markers and others'
HULL_M = 0.035
#: exposure times whose bodies' poses a simulation keeps
MAX_SCENES = 4096


@dataclass(frozen=True)
class SimConfig:
    n_cameras: int = 6
    rate_hz: float = 120.0
    synchronized: bool = True
    marker_diameter_m: float = 0.014
    psf_sigma_px: float = 0.6
    peak_dn_at_2m: float = 230.0
    dark_level: float = 8.0
    read_noise: float = 2.0
    gain: float = 0.15
    false_blobs: int = 5
    focal_px: float = 460.0
    distortion: tuple[float, ...] = (-0.08, 0.03, 0.0, 0.0, 0.0)
    speed: float = 1.0               # scales the bodies' motion

    def __post_init__(self) -> None:
        if not 2 <= self.n_cameras <= 16:
            raise InvalidInputError(f"n_cameras must be 2..16, got {self.n_cameras}")
        if not self.rate_hz > 0:
            raise InvalidInputError(f"rate_hz must be positive, got {self.rate_hz}")


def standard_bodies() -> list[RigidBody]:
    """Three bodies of 4-5 markers whose distance signatures tell them apart."""
    return [
        RigidBody("head", np.array([[0.0, 0.0, 0.09], [0.08, 0.02, 0.05], [-0.07, 0.05, 0.04],
                                    [0.01, -0.10, 0.05], [-0.04, -0.04, 0.085]])),
        RigidBody("wand", np.array([[0.0, 0.0, 0.06], [0.16, 0.0, 0.04], [0.09, 0.07, 0.04],
                                    [-0.05, -0.06, 0.05]])),
        RigidBody("hand", np.array([[0.0, 0.06, 0.05], [0.11, -0.02, 0.05],
                                    [-0.03, -0.12, 0.06], [-0.09, 0.03, 0.04],
                                    [0.05, 0.05, 0.07]])),
    ]


def ring_cameras(n: int, config: SimConfig = SimConfig(), seed: int = 0) -> list[RigCamera]:
    """``n`` cameras around the volume at 2.4-2.8 m height, looking at its centre."""
    rng = np.random.default_rng(10_000 + seed)
    f = config.focal_px
    K = np.array([[f, 0, WIDTH / 2 - 0.5], [0, f, HEIGHT / 2 - 0.5], [0, 0, 1.0]])
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n + np.pi / 4 + rng.uniform(-0.1, 0.1)
        eye = np.array([2.3 * np.cos(a), 2.3 * np.sin(a), 2.6 + rng.uniform(-0.2, 0.2)])
        target = np.array([0.0, 0.0, 1.0]) + rng.uniform(-0.2, 0.2, 3)
        Ki = K.copy()
        Ki[0, 0] *= 1 + rng.uniform(-0.02, 0.02)
        Ki[1, 1] = Ki[0, 0] * (1 + rng.uniform(-0.002, 0.002))
        Ki[:2, 2] += rng.uniform(-4, 4, 2)
        out.append(RigCamera.of(f"cam{i}", Ki, np.array(config.distortion, float), eye,
                                look_at(eye, target), WIDTH, HEIGHT))
    return out


@dataclass(frozen=True)
class _Path:
    """A smooth random path: centre + sums of sinusoids for position and rotation."""

    centre: Array
    amp: Array        # (k, 3)
    freq: Array       # (k,)
    phase: Array      # (k, 3)
    rot_amp: Array    # (k, 3)
    rot_phase: Array  # (k, 3)
    rot0: Array       # (3,) rotation vector

    def pose(self, t: float) -> tuple[Array, Array]:
        w = 2 * np.pi * self.freq[:, None] * t
        p = self.centre + np.sum(self.amp * np.sin(w + self.phase), axis=0)
        r = np.sum(self.rot_amp * np.sin(w + self.rot_phase), axis=0)
        q = geo.quat_multiply(geo.rotvec_to_quat(r), geo.rotvec_to_quat(self.rot0))
        return p, q


@dataclass
class Frame:
    """One camera's image at its exposure time, with the truth behind it."""

    camera: int
    t: float
    image: Array
    marker_uv: dict[tuple[int, int], Array]   # (body, marker) -> true pixel, visible only


@dataclass
class Simulation:
    """A rig, its bodies and their motion; renders each camera's frames."""

    seed: int = 1
    config: SimConfig = field(default_factory=SimConfig)
    cameras: list[RigCamera] = field(init=False)
    bodies: list[RigidBody] = field(init=False)

    def __post_init__(self) -> None:
        cfg = self.config
        self.cameras = ring_cameras(cfg.n_cameras, cfg, self.seed)
        self.bodies = standard_bodies()
        rng = np.random.default_rng(self.seed)
        self._paths = [self._path(rng, k) for k in range(len(self.bodies))]
        self._phase = (np.zeros(cfg.n_cameras) if cfg.synchronized
                       else rng.uniform(0, 1 / cfg.rate_hz, cfg.n_cameras))
        #: per camera: its image without markers (one frozen noise draw) and its signal
        self._backgrounds, self._signals = zip(*(self._background(rng) for _ in self.cameras),
                                               strict=True)
        self.hidden: set[int] = set()   # cameras covered (they see nothing but dark)
        self._scenes: dict[float, tuple[list[Array], list[Array]]] = {}

    def _path(self, rng: np.random.Generator, k: int) -> _Path:
        a = 2 * np.pi * k / 3 + rng.uniform(-0.3, 0.3)
        centre = np.array([0.55 * np.cos(a), 0.55 * np.sin(a), 1.2 + 0.2 * k])
        n = 3
        s = self.config.speed
        return _Path(centre, rng.uniform(-0.12, 0.12, (n, 3)) * np.array([1, 1, 0.6]),
                     rng.uniform(0.15, 0.6, n) * s, rng.uniform(0, 2 * np.pi, (n, 3)),
                     rng.uniform(-0.35, 0.35, (n, 3)), rng.uniform(0, 2 * np.pi, (n, 3)),
                     rng.normal(0, 0.4, 3))

    def _background(self, rng: np.random.Generator) -> tuple[Array, Array]:
        """A camera's image without markers (uint8, with noise) and its noise-free
        signal (float DN, the dark level and the false blobs)."""
        cfg = self.config
        noise = rng.normal(0, cfg.read_noise, (HEIGHT, WIDTH))
        img = np.full((HEIGHT, WIDTH), cfg.dark_level)
        yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
        kinds = ["round", "round", "round", "rail", "lamp"][:cfg.false_blobs]
        kinds += ["round"] * (cfg.false_blobs - len(kinds))
        for kind in kinds:
            u, v = rng.uniform(30, WIDTH - 30), rng.uniform(30, HEIGHT - 30)
            if kind == "round":
                r = rng.uniform(1.2, 2.2)
                d = np.hypot(xx - u, yy - v)
                img += rng.uniform(120, 230) * 0.5 * erfc((d - r) / (np.sqrt(2) * 0.6))
            elif kind == "rail":
                ang = rng.uniform(0, np.pi)
                along = (xx - u) * np.cos(ang) + (yy - v) * np.sin(ang)
                across = -(xx - u) * np.sin(ang) + (yy - v) * np.cos(ang)
                d = np.hypot(np.maximum(np.abs(along) - 12, 0), across)
                img += 200 * 0.5 * erfc((d - 1.5) / (np.sqrt(2) * 0.6))
            else:
                d = np.hypot(xx - u, yy - v)
                img += 400 * 0.5 * erfc((d - 14) / (np.sqrt(2) * 2.0))
        return _to8(img + noise), img

    # ------------------------------------------------------------------ truth

    def exposure_time(self, camera: int, index: int) -> float:
        return index / self.config.rate_hz + float(self._phase[camera])

    def body_pose(self, body: int, t: float) -> tuple[Array, Array]:
        """``world -> body`` at ``t``: position and quaternion."""
        return self._paths[body].pose(t)

    def marker_positions(self, t: float) -> list[Array]:
        """Each body's markers in the world at ``t`` ((n_k, 3) each)."""
        out = []
        for k, b in enumerate(self.bodies):
            p, q = self.body_pose(k, t)
            out.append(geo.quat_rotate(q, b.markers) + p)
        return out

    def _scene_at(self, t: float) -> tuple[list[Array], list[Array]]:
        """The bodies' centres and markers at ``t``, read-only, kept for the frames of the
        other cameras exposed at the same time (the poses cost a third of a frame)."""
        got = self._scenes.get(t)
        if got is None:
            if len(self._scenes) >= MAX_SCENES:
                self._scenes.clear()
            centres = [self.body_pose(k, t)[0] for k in range(len(self.bodies))]
            got = self._scenes[t] = (centres, self.marker_positions(t))
            for a in (*got[0], *got[1]):
                a.flags.writeable = False
        return got

    def visible(self, camera: int, t: float) -> dict[tuple[int, int], Array]:
        """``(body, marker) -> world point`` of the markers camera sees at ``t``."""
        cam = self.cameras[camera]
        if camera in self.hidden:
            return {}
        centres, markers = self._scene_at(t)
        out = {}
        for k, pts in enumerate(markers):
            vis = cam.visible(pts, margin_px=3)
            for m in np.nonzero(vis)[0]:
                if not blocked(cam.position, pts[m], centres):
                    out[(k, int(m))] = pts[m]
        return out

    # ------------------------------------------------------------------ images

    def render(self, camera: int, index: int, scene: Scene | None = None) -> Frame:
        """Camera ``camera``'s ``index``-th frame of the bodies (or of ``scene``: what a
        camera sees at a time); the noise depends only on seed, camera and index."""
        cfg = self.config
        t = self.exposure_time(camera, index)
        rng = np.random.default_rng([self.seed, camera, index])
        if camera in self.hidden:
            return Frame(camera, t, np.full((HEIGHT, WIDTH), round(cfg.dark_level), np.uint8),
                         {})
        img = self._backgrounds[camera].copy()
        cam = self.cameras[camera]
        vis = (scene or self.visible)(camera, t)
        truth = {}
        if vis:
            keys = list(vis)
            world = np.array([vis[k] for k in keys])
            uv = cam.project(world)
            depth = cam.to_camera(world)[:, 2]
            light = np.zeros((HEIGHT, WIDTH))
            patched = np.zeros((HEIGHT, WIDTH), bool)
            for key, (u, v), z in zip(keys, uv, depth, strict=True):
                truth[key] = np.array([u, v])
                self._splat(light, patched, cam.focal_px, u, v, z)
            self._expose(img, self._signals[camera], light, patched, rng)
        return Frame(camera, t, img, truth)

    def prerender(self, camera: int, first: int, count: int) -> Replay:
        """Frames ``first .. first + count - 1`` of ``camera``, rendered now and kept as
        what differs from its background, for ``Replay.frame`` to give back at a copy's
        cost."""
        bg = self._backgrounds[camera]
        times, changes = [], []
        for index in range(first, first + count):
            frame = self.render(camera, index)
            idx = np.flatnonzero(frame.image != bg).astype(np.int32)
            times.append(frame.t)
            changes.append((idx, frame.image.ravel()[idx]))
        return Replay(first, times, bg, changes)

    def _splat(self, light: Array, patched: Array, focal: float, u: float, v: float,
               depth: float) -> None:
        """Add one marker's light (DN, no noise) to ``light`` and mark its patch."""
        cfg = self.config
        r = focal * cfg.marker_diameter_m / 2 / depth
        peak = cfg.peak_dn_at_2m * (2.0 / depth) ** 2
        half = int(np.ceil(r + 4 * cfg.psf_sigma_px)) + 1
        x0, x1 = max(round(float(u)) - half, 0), min(round(float(u)) + half + 1, WIDTH)
        y0, y1 = max(round(float(v)) - half, 0), min(round(float(v)) + half + 1, HEIGHT)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        d = np.hypot(xx - u, yy - v)
        light[y0:y1, x0:x1] += peak * 0.5 * erfc((d - r) / (np.sqrt(2) * cfg.psf_sigma_px))
        patched[y0:y1, x0:x1] = True

    def _expose(self, img: Array, background: Array, light: Array, patched: Array,
                rng: np.random.Generator) -> None:
        """The patched pixels of ``img`` (uint8) from their whole signal, the background's
        and the markers', with one draw of the sensor's noise each: light adds (a marker
        over a reflection or another marker's tail is brighter than either), and the
        noise is the pixel's, not one draw of the background's and one of each marker's,
        whose brighter would lift the tails and freeze part of their noise."""
        cfg = self.config
        idx = np.flatnonzero(patched)
        base = background.ravel()[idx]
        signal = base + light.ravel()[idx]
        std = np.sqrt(cfg.gain * (signal - cfg.dark_level) + cfg.read_noise ** 2)
        img.ravel()[idx] = _to8(signal + rng.normal(0, 1, len(idx)) * std)


@dataclass(frozen=True)
class Replay:
    """A camera's frames rendered ahead (``Simulation.prerender``): a real camera hands
    its host a finished image, so a benchmark of the services that replays these pays
    for a copy per frame where live rendering would cost more than the services' work."""

    first: int                            # the first frame's index
    times: list[float]                    # exposure times (s)
    background: Array                     # the camera's image without markers
    changes: list[tuple[Array, Array]]    # per frame: flat pixel indices, their values

    def frame(self, index: int) -> tuple[float, Array] | None:
        """Frame ``index``'s exposure time and image; None outside the rendered ones."""
        k = index - self.first
        if not 0 <= k < len(self.times):
            return None
        img = self.background.copy()
        idx, values = self.changes[k]
        img.ravel()[idx] = values
        return self.times[k], img


#: what a camera sees at a time: ``(camera, t) -> {key: world point}``
Scene = Callable[[int, float], dict]


def _to8(img: Array) -> Array:
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def blocked(eye: Array, point: Array, centres: list[Array]) -> bool:
    """Whether the segment eye -> point crosses a hull sphere (before the point)."""
    d = point - eye
    L = np.linalg.norm(d)
    d = d / L
    for c in centres:
        s = float(np.dot(c - eye, d))
        if 0 < s < L - 0.005 and np.linalg.norm(eye + s * d - c) < HULL_M:
            return True
    return False


@dataclass(frozen=True)
class WandWave:
    """A calibration wand waved through the volume: markers at ``distances`` along it."""

    distances: tuple[float, ...] = (0.0, 0.16, 0.5)
    seed: int = 0

    def markers(self, t: float) -> Array:
        """(3, 3) marker positions at ``t``: the centre wanders over the volume, the
        direction turns through every orientation."""
        ph = np.random.default_rng(20_000 + self.seed).uniform(0, 2 * np.pi, 6)
        c = np.array([1.1 * np.sin(2 * np.pi * 0.037 * t + ph[0]),
                      1.1 * np.sin(2 * np.pi * 0.029 * t + ph[1]),
                      1.25 + 0.8 * np.sin(2 * np.pi * 0.043 * t + ph[2])])
        u = np.array([np.sin(0.61 * t + ph[3]), np.cos(0.47 * t + ph[4]),
                      np.sin(0.37 * t + ph[5])])
        u /= np.linalg.norm(u)
        d = np.asarray(self.distances)
        return c + (d - d[-1] / 2)[:, None] * u

    def scene(self, sim: Simulation) -> Scene:
        """What each camera of ``sim`` sees of the wand (all three markers or none)."""
        def see(camera: int, t: float) -> dict:
            X = self.markers(t)
            vis = sim.cameras[camera].visible(X, margin_px=3)
            return {(0, k): X[k] for k in range(len(X))} if np.all(vis) else {}
        return see


def static_scene(sim: Simulation, points: Array) -> Scene:
    """Markers that do not move (an L-frame on the floor): each camera sees those in view."""
    P = np.asarray(points, float)

    def see(camera: int, t: float) -> dict:
        vis = sim.cameras[camera].visible(P, margin_px=3)
        return {(0, k): P[k] for k in np.nonzero(vis)[0]}
    return see
