"""A calibrated rig on disk, and its cameras as the agents' static SRG edges.

``rig.toml`` holds what the tracker needs: per camera its frame name, its intrinsics (an
OpenCV calibration file beside it, ``services.camera.model``'s format), its pose
``world -> camera`` and the pose's 6x6 covariance over ``[dp, phi]``.  ``static_edges``
writes the same poses as ``[[static]]`` tables that ``uma agent --config`` reads (the SRG
takes a position and a rotation std, the square roots of the covariance blocks' mean
diagonals).  A missing, unparsable or incomplete file is a ``RigFileError`` naming the
file and what is wrong.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from agent import geometry as geo
from agent.errors import UmaError
from services.camera.model import load as load_camera
from services.outside_in.rig import RigCamera

Array = np.ndarray


class RigFileError(UmaError):
    """A rig file that cannot be used: says which file and what is wrong."""


def _vec(x: Array) -> str:
    return "[" + ", ".join(f"{float(v):.9g}" for v in np.ravel(x)) + "]"


def save_rig(path: str | Path, cameras: list[RigCamera], covariances: Array, world: str,
             site: str, rms_px: float) -> Path:
    """Write ``rig.toml`` and one intrinsics file per camera beside it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [f'world = "{world}"', f"rms_px = {rms_px:.6g}", ""]
    for cam, cov in zip(cameras, covariances, strict=True):
        intr = path.with_name(f"{path.stem}.{cam.name}.yaml")
        cam.model.save(intr)
        rows = ", ".join(_vec(r) for r in np.asarray(cov))
        lines += ["[[camera]]", f'name = "{cam.name}"', f'frame = "{site}/{cam.name}"',
                  f'intrinsics = "{intr.name}"', f"position = {_vec(cam.position)}",
                  f"quaternion = {_vec(cam.quaternion)}", f"covariance = [{rows}]", ""]
    path.write_text("\n".join(lines))
    return path


def load_rig(path: str | Path) -> tuple[list[RigCamera], Array, dict]:
    """Cameras, their covariances (C, 6, 6) and the file's other settings."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise RigFileError(f"rig file {path} does not exist") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RigFileError(f"rig file {path} is not valid TOML: {exc}") from None
    tables = data.get("camera")
    if not isinstance(tables, list) or len(tables) < 2:
        raise RigFileError(f"rig file {path}: needs two [[camera]] tables at least")
    cams, covs = [], []
    for i, t in enumerate(tables):
        where = f"rig file {path}, camera #{i + 1}"
        for key in ("name", "intrinsics", "position", "quaternion", "covariance"):
            if key not in t:
                raise RigFileError(f"{where}: missing '{key}'")
        try:
            p = geo.check_vector(t["position"], "position").reshape(3)
            q = geo.check_quaternion(t["quaternion"], "quaternion").reshape(4)
            cov = geo.check_covariance(t["covariance"], "covariance")
        except ValueError as exc:
            raise RigFileError(f"{where}: {exc}") from None
        model = load_camera(path.parent / str(t["intrinsics"]))
        cams.append(RigCamera(str(t["name"]), model, p, q / np.linalg.norm(q)))
        covs.append(cov)
    return cams, np.array(covs), {k: v for k, v in data.items() if k != "camera"}


def static_edges(cameras: list[RigCamera], covariances: Array, world: str, site: str) -> str:
    """The cameras as ``[[static]]`` tables of an agent's TOML configuration."""
    out = []
    for cam, cov in zip(cameras, covariances, strict=True):
        pos = float(np.sqrt(np.trace(cov[:3, :3]) / 3))
        rot = float(np.sqrt(np.trace(cov[3:, 3:]) / 3))
        out.append("\n".join(["[[static]]", f'parent = "{world}"', f'child = "{site}/{cam.name}"',
                              f"position = {_vec(cam.position)}",
                              f"quaternion = {_vec(cam.quaternion)}",
                              f"pos_std_m = {pos:.6g}", f"rot_std_rad = {rot:.6g}", ""]))
    return "\n".join(out)
