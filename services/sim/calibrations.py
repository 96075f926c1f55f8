"""The simulated installation's calibrations, made once and cached on disk: the laser
tracker's (its cameras calibrated from the rendered calibration images, about 20 s) and the
accelerometer rig's (the static procedure of Hogue 2003, §4.4.2, on the simulated device).

Used by the evaluations and ``uma demo``: a real site calibrates its own installation
(``uma service run laser-camera --calibrate``, ``uma service run accel-rig --calibrate``).
Files live in ``~/.cache/uma`` (``$XDG_CACHE_HOME``), keyed by a hash of the code that made
them, so a calibration made by other code is never reused.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from services.accel_rig import calibration as accel_cal
from services.accel_rig import simulator as accel_sim
from services.sim.world import IvyWorld

log = logging.getLogger("uma.sim")


def calibrated_accelerometers(rate_hz: float, seed: int,
                               device: Any = None) -> tuple[Any, Any]:
    """The simulated device (MARVIN's by default) and its calibration from six static
    orientations (§4.4.2).

    The calibration is handed the device's true noise model and latency and its true
    accelerometer positions (see ``given_by_simulator``): it estimates biases, gains and
    axes only, so the filter's noise and latency model is exact, as a real rig's is not.
    """
    device = device or accel_sim.default_device()
    recordings = [
        accel_cal.StaticRecording(
            accel_sim.axis_down_quaternion(label),
            accel_sim.simulate_static(accel_sim.axis_down_quaternion(label), 2.0, rate_hz,
                                      seed=seed * 100 + i, sensor=device))
        for i, label in enumerate(accel_cal.SIX_POSES)]
    cal = accel_cal.calibrate(device.layout, recordings, rate_hz, device.noise_model(),
                              device.latency_s(rate_hz))
    return device, cal


def laser_calibration(world: IvyWorld, cache: bool) -> Any:
    """The laser tracker's calibration from the world's calibration images.

    Calibrating takes ~20 s, so the result is cached on disk, keyed by a hash of the
    simulator's and the tracker's source: a calibration made by other code is never reused.
    """
    from services.laser_camera.calibration import Calibration, calibrate_sim

    if not cache:
        return calibrate_sim(world)
    return Calibration.load(laser_calibration_file(world))


def laser_calibration_file(world: IvyWorld, announce: bool = False) -> Path:
    """The cached calibration file of ``world``'s cameras, calibrating on a cache miss."""
    import services.installation
    import services.laser_camera
    import services.sim
    from services.laser_camera.calibration import Calibration, calibrate_sim

    return cached_file(laser_calibration_name(world),
                       (services.sim, services.installation, services.laser_camera),
                       Calibration.load,
                       lambda path: calibrate_sim(world).save(path),
                       "calibrating the simulated cameras once (about 20 s)" if announce else "")


def laser_calibration_name(world: IvyWorld) -> str:
    """The cache name of ``world``'s laser calibration: one per installation
    (``IvyWorld.installation``), since the ideal and the realistic installation render other
    calibration images and a calibration records the installation it was made for; worlds
    that differ only in their trajectory or their imperfections' draw share it."""
    import hashlib
    import json

    digest = hashlib.sha1(json.dumps(world.installation, sort_keys=True).encode())
    return f"laser_calibration_{world.config.n_cameras}cam_{digest.hexdigest()[:10]}"


def accel_calibration_file(seed: int = 0, announce: bool = False) -> Path:
    """The cached static calibration (§4.4.2) of the simulated accelerometer device."""
    import services.accel_rig
    from services.accel_rig.sensor import Calibration

    return cached_file(f"accel_calibration_{seed}", (services.accel_rig,), Calibration.load,
                       lambda path: calibrated_accelerometers(
                           accel_sim.DEFAULT_RATE_HZ, seed)[1].save(path),
                       "calibrating the simulated accelerometers once" if announce else "")


def cached_file(name: str, packages: tuple[Any, ...], load: Any, make: Any,
                announce: str = "") -> Path:
    """``~/.cache/uma/<name>_<hash>.json``, made by ``make(path)`` unless a file that
    ``load`` accepts exists.  The hash covers the sources of ``packages``, so a file made by
    other code is never reused; written atomically.

    Processes that miss the cache at once (the test workers, two demos) wait for the first
    to make the file instead of each spending its ~20 s: the cache directory is locked
    while a file is made.  A file ``load`` cannot use, whatever is wrong with it (not JSON,
    another structure: a loader may then fail with any error), is said and made again; a
    temporary file is removed when ``make`` fails, and those left by processes that died
    are removed too."""
    import hashlib

    h = hashlib.sha1()
    for pkg in packages:
        for f in sorted(Path(pkg.__file__).parent.glob("*.py")):
            h.update(f.read_bytes())
    path = _cache_dir() / f"{name}_{h.hexdigest()[:12]}.json"
    if _usable(path, load):
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    with _locked(path.parent):
        if _usable(path, load):  # made by another process while this one waited
            return path
        if announce:
            print(f"{announce}; cached in {path.parent}", flush=True)
        for orphan in path.parent.glob(f"{path.stem}.*.tmp"):  # its writer died mid-write
            orphan.unlink(missing_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        try:
            make(tmp)
            tmp.replace(path)
        finally:
            tmp.unlink(missing_ok=True)
    return path


def _usable(path: Path, load: Any) -> bool:
    """Whether ``path`` exists and ``load`` accepts it; a file it refuses is removed."""
    if not path.exists():
        return False
    try:
        load(path)
        return True
    except Exception as exc:  # a cache file we cannot use is made again, never fatal
        log.warning("cached %s is unusable (%s: %s); making it again", path,
                    type(exc).__name__, exc)
        path.unlink(missing_ok=True)
        return False


@contextlib.contextmanager
def _locked(directory: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``directory`` (released by the kernel if this process
    dies), so only one process at a time writes into it."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "uma"
