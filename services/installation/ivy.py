"""IVY's projection surfaces: the faces of the cube, their screens and screen->world maps.

Seed 003 §5.4.3 maps a point ``(X, Y)`` on a screen to the world by a rigid transform per
wall (eq. 5.40)::

    [x, y, z]^T = R_wall [X, Y, Pi_wall]^T - T_wall

with ``R_wall`` the screen axes in world coordinates, ``Pi_wall`` the distance from the
world origin to the wall and ``T_wall`` the offset of the screen origin, one corner of the
screen (thesis table 5.1).  Here the columns of ``R_wall`` are the screen's X axis, its Y
axis and the wall's outward normal, so ``X x Y = normal`` on every wall and a camera behind
a screen always sees it mirrored (the calibration relies on that to order checkerboard
corners).

Only the active area of a screen (``screen_side_m``, centred on its face) shows a laser
spot; the remaining band at the edges is the frame and seams of the cube, where a beam
gives no spot -- the "holes" of thesis fig. 5.14.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent.errors import InvalidInputError

CUBE_SIDE_M = 2.44  # IVY: an 8-ft cube (Hogue 2003, ch. 5)
#: default active screen side: "the 2.29m screen" (Hogue 2003, §5.2) in the 2.44 m cube,
#: leaving a 7.5 cm band of frame and seams at each edge
SCREEN_SIDE_M = 2.29

# face name -> (screen X axis, screen Y axis, outward normal); X x Y = normal
_FACES: dict[str, tuple[tuple[float, ...], ...]] = {
    "front": ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
    "back": ((0, -1, 0), (0, 0, 1), (-1, 0, 0)),
    "left": ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
    "right": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "ceiling": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "floor": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
}
WALL_NAMES = tuple(_FACES)


@dataclass(frozen=True)
class Wall:
    """One face of the cube and its screen, in the terms of eq. 5.40."""

    name: str
    rotation: np.ndarray  # R_wall (3x3): columns screen X, screen Y, outward normal
    translation: np.ndarray  # T_wall (3,), metres
    plane_distance: float  # Pi_wall, metres
    screen_side_m: float  # side of the active (spot-showing) screen area

    @property
    def normal(self) -> np.ndarray:
        """Outward unit normal in world coordinates."""
        return self.rotation[:, 2]

    def to_world(self, xy: np.ndarray) -> np.ndarray:
        """Screen points (n, 2) in metres to world points (n, 3) by eq. 5.40."""
        return screen_to_world(xy, self.rotation, self.translation, self.plane_distance)

    def to_screen(self, points: np.ndarray) -> np.ndarray:
        """World points (n, 3) on the wall's plane to screen coordinates (n, 2)."""
        pts = np.atleast_2d(np.asarray(points, float))
        return ((pts + self.translation) @ self.rotation)[:, :2]

    def on_screen(self, xy: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
        """Which screen points (n, 2) lie on the active area, at least ``margin_m`` inside."""
        return on_active_area(xy, self.screen_side_m, margin_m)

    def to_dict(self) -> dict:
        return {"name": self.name, "rotation": self.rotation.tolist(),
                "translation": self.translation.tolist(),
                "plane_distance": self.plane_distance, "screen_side_m": self.screen_side_m}

    @classmethod
    def from_dict(cls, d: dict) -> Wall:
        R = np.asarray(d["rotation"], float)
        if R.shape != (3, 3) or abs(np.linalg.det(R) - 1.0) > 1e-6:
            raise InvalidInputError(
                f"wall {d.get('name')!r}: rotation must be a proper 3x3 rotation")
        T = np.asarray(d["translation"], float)
        if T.shape != (3,):
            raise InvalidInputError(f"wall {d.get('name')!r}: translation must have 3 values")
        return cls(str(d["name"]), R, T, float(d["plane_distance"]), float(d["screen_side_m"]))


def screen_to_world(xy: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                    plane_distance: float | np.ndarray) -> np.ndarray:
    """Eq. 5.40 for screen points (n, 2) of one wall, or of one wall per point (rotation
    (n, 3, 3), translation (n, 3), plane_distance (n,)): world points (n, 3)."""
    xy = np.atleast_2d(np.asarray(xy, float))
    xyz = np.empty((len(xy), 3))
    xyz[:, :2] = xy
    xyz[:, 2] = plane_distance
    return (rotation @ xyz[:, :, None])[:, :, 0] - translation


def on_active_area(xy: np.ndarray, side_m: float | np.ndarray,
                   margin_m: float = 0.0) -> np.ndarray:
    """Which screen points (n, 2) lie on an active area of side ``side_m`` (one, or (n, 1)
    for one per point), at least ``margin_m`` inside."""
    xy = np.atleast_2d(np.asarray(xy, float))
    return np.all((xy >= margin_m) & (xy <= side_m - margin_m), axis=1)


def make_walls(cube_side_m: float = CUBE_SIDE_M,
               screen_side_m: float = SCREEN_SIDE_M) -> dict[str, Wall]:
    """The six walls of a cube centred on the world origin (z up)."""
    if not 0 < screen_side_m <= cube_side_m:
        raise InvalidInputError(f"screen side {screen_side_m} m must be in (0, cube side "
                                f"{cube_side_m} m]")
    half = cube_side_m / 2
    walls = {}
    for name, (ex, ey, n) in _FACES.items():
        R = np.column_stack([ex, ey, n]).astype(float)
        # screen origin = the corner of the active area at -X, -Y
        T = 0.5 * screen_side_m * (R[:, 0] + R[:, 1])
        walls[name] = Wall(name, R, T, half, screen_side_m)
    return walls


@dataclass(frozen=True)
class BeamHit:
    """Where a beam from inside the cube meets a wall."""

    wall: str
    point: np.ndarray  # (3,) world
    direction: np.ndarray  # (3,) unit beam direction, world
    screen_xy: np.ndarray  # (2,) screen coordinates on that wall
    cos_incidence: float  # direction . outward normal, in (0, 1]
    on_screen: bool  # inside the active area (a spot is visible)


def intersect_beam(walls: dict[str, Wall], origin: np.ndarray, direction: np.ndarray,
                   bulge_m: dict[str, float] | None = None) -> BeamHit:
    """The first wall a ray from ``origin`` (inside the cube) along ``direction`` meets.

    A ray parallel to a wall never meets it; from inside a closed cube it always meets
    another one, so every ray has a hit (maybe off the active screen).  ``bulge_m`` (wall
    name -> metres) bends a fabric screen towards the inside, most at its centre
    (``screen_displacement``); the hit is then on the bent surface, which the tracker's
    planar calibration does not know.
    """
    return intersect_beams(walls, np.asarray(origin, float)[None],
                           np.asarray(direction, float)[None], bulge_m)[0]


def intersect_beams(walls: dict[str, Wall], origins: np.ndarray, directions: np.ndarray,
                    bulge_m: dict[str, float] | None = None) -> list[BeamHit]:
    """``intersect_beam`` for rays (n, 3) at once: a rig's beams meet the walls in every
    simulated frame, so the evaluations spend their time here."""
    o = np.asarray(origins, float).reshape(-1, 3)
    d = np.asarray(directions, float).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    ws = list(walls.values())
    normals = np.array([w.normal for w in ws])
    distance = np.array([w.plane_distance for w in ws])
    cos = d @ normals.T  # (n, walls)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (distance - o @ normals.T) / cos
    s[~((cos > 1e-12) & (s >= 0))] = np.inf
    first = np.argmin(s, axis=1)
    rows = np.arange(len(o))
    for i in np.flatnonzero(~np.isfinite(s[rows, first])):  # only possible from outside
        raise InvalidInputError(f"ray from {o[i].tolist()} along {d[i].tolist()} meets no wall; "
                                "is the origin inside the cube?")
    hit = [ws[k] for k in first]
    c = cos[rows, first]
    p = o + s[rows, first][:, None] * d
    rotation = np.array([w.rotation for w in hit])
    translation = np.array([w.translation for w in hit])
    side = np.array([w.screen_side_m for w in hit])
    amp = np.array([(bulge_m or {}).get(w.name, 0.0) for w in hit])
    if np.any(amp):  # fixed point: the bend varies slowly over the screen
        plane = distance[first] - np.einsum("ij,ij->i", o, normals[first])
        for _ in range(4):
            xy = np.einsum("ij,ijk->ik", p + translation, rotation)[:, :2]
            p = o + ((plane - _displacement(xy, side, amp)) / c)[:, None] * d
    xy = np.einsum("ij,ijk->ik", p + translation, rotation)[:, :2]
    on = on_active_area(xy, side[:, None])
    return [BeamHit(w.name, p[i], d[i], xy[i], float(c[i]), bool(on[i]))
            for i, w in enumerate(hit)]


def _displacement(xy: np.ndarray, side_m: np.ndarray, amplitude_m: np.ndarray) -> np.ndarray:
    """``screen_displacement`` of points (n, 2), each on its own screen."""
    u = 2 * xy / side_m[:, None] - 1
    return amplitude_m * np.prod(np.maximum(0.0, 1 - u ** 2), axis=1)


def screen_displacement(wall: Wall, xy: np.ndarray, amplitude_m: float) -> float:
    """Inward displacement (m) of a fabric screen at screen point ``xy``: a pillow shape,
    ``amplitude_m`` at the centre, zero at the frame."""
    xy = np.asarray(xy, float).reshape(1, 2)
    return float(_displacement(xy, np.array([wall.screen_side_m]), np.array([amplitude_m]))[0])
