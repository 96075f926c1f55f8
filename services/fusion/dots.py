"""Single-dot SCAAT updates from the laser tracker's labeled dots, shared by the fusion
service's dot mode and ``uma eval fusion --optical dots``.

Each labeled dot is one 2-D measurement (Welch & Bishop, *SCAAT: Incremental Tracking with
Incomplete Information*, SIGGRAPH 1997): the predicted beam of its diode meets the wall the
dot lies on (Hogue 2003 ch. 6: "intersect the laser beam with the walls of IVY").  The walls
are the display's measured geometry as the laser tracker's calibration file holds it (one
wall per camera, eq. 5.40), the file the tracker itself maps its dots with, never the
simulator's truth.

A dot's error has two parts: detection and calibration noise, new in every frame, and the
installation's tolerances (the housing's beams, the bent screens, the cameras turned since
calibration), which move the dot by the same amount from frame to frame while it stays on
the same part of a screen.  The update weighs each dot by both, as the pose update weighs a
pose by its whole covariance (docs/FUSION_TUNING.md says why).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.fusion.ekf import FusionEKF
from services.installation.ivy import Wall
from services.installation.laser_housing import BEAM_DIRECTIONS
from services.laser_camera.calibration import Calibration
from services.laser_camera.tracker import LabeledDots


def display_walls(calibration: Calibration) -> list[Wall]:
    """The display's walls, each once (two cameras may share one, as the split floor)."""
    walls: dict[str, Wall] = {}
    for cam in calibration.cameras:
        walls.setdefault(cam.wall.name, cam.wall)
    return list(walls.values())


def load_walls(path: str) -> list[Wall]:
    """The display's walls from the laser tracker's calibration file (dot mode's walls)."""
    return display_walls(Calibration.load(path))


def wall_of(walls: Sequence[Wall], point: np.ndarray) -> Wall:
    """The wall whose plane the point lies on: the face of the cube it is closest to (the
    largest component along an outward normal)."""
    return max(walls, key=lambda w: float(w.normal @ point))


def update_dots(ekf: FusionEKF, dots: LabeledDots, walls: Sequence[Wall],
                mount: tuple[np.ndarray, np.ndarray]) -> int:
    """One SCAAT update per labeled dot at ``dots.t``, weighed by its random and its
    installation error; returns how many the filter accepted (the rest it gated)."""
    accepted = 0
    for label, point, std, sys_std in zip(dots.labels, dots.points, dots.std_m,
                                          dots.systematic_std_m, strict=True):
        wall = wall_of(walls, point)
        accepted += ekf.update_dot(dots.t, point, std, BEAM_DIRECTIONS[label],
                                   (wall.normal, float(wall.normal @ point)),
                                   wall.rotation[:, :2].T, mount, sys_std)
    return accepted
