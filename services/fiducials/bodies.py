"""What the fiducial tracker tracks: bodies, each a rigid set of marker corners.

A lone marker is a body of one marker (its corners from
:func:`services.camera.markers.marker_corners`, its frame the marker's own).  A *bundle*
is several markers fixed to one object, solved as one body from all its visible corners:
more corners, wider baselines, no planar ambiguity once two non-coplanar markers show.

Bundles come from a TOML file (``--bundles FILE``)::

    [[bundle]]
    name = "cube"                  # published as markers/cube (or --prefix/cube)
    [[bundle.marker]]
    id = 0
    size = 0.05                    # side of the black square, m
    position = [0.0, 0.0, 0.025]   # the marker's centre in the bundle's frame, m
    rotation = [0.0, 0.0, 0.0]     # the marker's frame in the bundle's, rotation vector, rad

    [[bundle]]
    name = "board"                 # a ChArUco board: its markers in the board's frame
    charuco = { squares = [5, 4], square = 0.04, marker = 0.03, family = "aruco4x4_50" }

A marker's frame is OpenCV's (x right, y up on the print, z out of it).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from agent.errors import InvalidInputError, UmaError
from services.camera import markers


class BundleFileError(UmaError):
    """A bundle file that cannot be used: says which file and what is wrong."""


@dataclass(frozen=True)
class Body:
    """A rigid object: marker id -> its four corners (4, 3) in the body's frame."""

    name: str
    corners: dict[int, np.ndarray]

    @property
    def is_bundle(self) -> bool:
        return len(self.corners) > 1


def marker_body(name: str, marker_id: int, size_m: float) -> Body:
    return Body(name, {marker_id: markers.marker_corners(size_m)})


def marker_in_body(corners: np.ndarray) -> np.ndarray:
    """The 4x4 pose of a marker's own frame in its body's, from its corners there."""
    c = np.asarray(corners, np.float64)
    x = c[1] - c[0]
    y = c[0] - c[3]
    x /= np.linalg.norm(x)
    y -= (y @ x) * x
    y /= np.linalg.norm(y)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, np.cross(x, y)])
    T[:3, 3] = c.mean(0)
    return T


def load_bundles(path: str | Path, family: str) -> list[Body]:
    """The bundles of a TOML file; :class:`BundleFileError` names what is wrong."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise BundleFileError(f"bundle file {path} does not exist") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise BundleFileError(f"{path}: not a TOML file ({exc})") from None
    entries = data.get("bundle")
    if not isinstance(entries, list) or not entries:
        raise BundleFileError(f"{path}: no [[bundle]] tables")
    bodies, seen = [], {}
    for k, entry in enumerate(entries):
        where = f"{path}: bundle {k + 1}"
        try:
            body = _bundle(entry, family)
        except (KeyError, TypeError, ValueError) as exc:
            raise BundleFileError(f"{where}: {exc}") from None
        for marker_id in body.corners:
            if marker_id in seen:
                raise BundleFileError(f"{where}: marker {marker_id} is already in bundle "
                                      f"{seen[marker_id]!r}")
            seen[marker_id] = body.name
        bodies.append(body)
    return bodies


def _bundle(entry: Any, family: str) -> Body:
    if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
        raise InvalidInputError("needs a name")
    name = entry["name"]
    if "charuco" in entry:
        return charuco_body(name, entry["charuco"], family)
    rows = entry.get("marker")
    if not isinstance(rows, list) or not rows:
        raise InvalidInputError(f"{name!r} has no [[bundle.marker]] and no charuco board")
    corners = {}
    for row in rows:
        marker_id, size = int(row["id"]), float(row["size"])
        if size <= 0:
            raise InvalidInputError(f"marker {marker_id}: size must be positive")
        position = np.asarray(row.get("position", (0, 0, 0)), np.float64)
        rotation = np.asarray(row.get("rotation", (0, 0, 0)), np.float64)
        if position.shape != (3,) or rotation.shape != (3,) or \
                not np.all(np.isfinite(np.concatenate([position, rotation]))):
            raise InvalidInputError(f"marker {marker_id}: position and rotation are 3 numbers each")
        R = cv2.Rodrigues(rotation)[0]
        corners[marker_id] = markers.marker_corners(size) @ R.T + position
    return Body(name, corners)


def charuco_body(name: str, spec: Any, family: str) -> Body:
    """A ChArUco board's markers as one body in the board's frame (OpenCV's: origin at
    the top-left corner, y down, z into the board)."""
    board = markers.charuco_board(tuple(spec["squares"]), float(spec["square"]),
                                  float(spec["marker"]), spec.get("family", family))
    if spec.get("family", family) != family:
        raise InvalidInputError(
            f"its markers are {spec['family']}, the tracker's family is {family}")
    return Body(name, {int(i): np.asarray(c, np.float64).reshape(4, 3)
                       for i, c in zip(board.getIds().ravel(), board.getObjPoints(),
                                       strict=True)})
