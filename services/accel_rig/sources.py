"""Where the accelerometer voltages come from: the simulator, a CSV replay or a serial line.

Every source yields ``(t_ns, volts)`` samples: ``t_ns`` when the sample was taken (ns since
the epoch, this host's clock), ``volts`` the N amplifier outputs.  The recorded formats are
one sample per line, ``t v_1 ... v_N`` separated by commas or blanks, with ``t`` the
sender's timestamp in seconds; lines starting with ``#`` and a non-numeric header line are
skipped.  The first sample is pinned to the local clock and later ones keep their spacing,
so downstream services see current timestamps.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

import numpy as np

from agent.errors import InvalidInputError
from services.accel_rig.simulator import SensorTruth, simulate
from services.sim.world import sim_time_s

_SPLIT = re.compile(r"[,\s]+")
#: A live simulated source computes samples in chunks of this length (filter warm-up and
#: trajectory evaluation are per chunk).
SIM_CHUNK_S = 0.05


def parse_line(line: str, channels: int, where: str) -> tuple[float, np.ndarray] | None:
    """One recorded sample ``t v_1 .. v_N``; None for comments/blank lines; ``ValueError``
    naming ``where`` (file and line) and what is wrong otherwise."""
    text = line.strip()
    if not text or text.startswith("#"):
        return None
    fields = [f for f in _SPLIT.split(text) if f]
    if len(fields) != channels + 1:
        raise InvalidInputError(f"{where}: expected a timestamp and {channels} voltages, got "
                                f"{len(fields)} fields")
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise InvalidInputError(f"{where}: not a number in {text[:80]!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise InvalidInputError(f"{where}: non-finite value in {text[:80]!r}")
    return values[0], np.array(values[1:])


class LineSource:
    """Samples from lines of text (a CSV file replayed, or a serial device / pipe read live).

    ``speed`` paces a replay (1 = as recorded, 0 = as fast as possible); a live device
    (``speed=None``) is paced by its own output.  Bad lines raise ``ValueError`` from
    ``samples``; the caller decides whether to skip them.
    """

    def __init__(self, stream: TextIO, name: str, channels: int, speed: float | None):
        self.stream = stream
        self.name = name
        self.channels = channels
        self.speed = speed
        self.bad_lines = 0

    @classmethod
    def open(cls, spec: str, channels: int, speed: float) -> LineSource:
        kind, _, target = spec.partition(":")
        if kind not in ("csv", "serial") or not target:
            raise InvalidInputError(f"--source {spec!r}: expected sim, csv:FILE or serial:DEVICE")
        try:
            stream = Path(target).open(encoding="ascii", errors="replace")  # noqa: SIM115
        except OSError as exc:
            raise InvalidInputError(f"--source {spec!r}: cannot open {target!r} ({exc.strerror})") \
                from None
        return cls(stream, target, channels, speed if kind == "csv" else None)

    def samples(self) -> Iterator[tuple[int, np.ndarray] | ValueError]:
        """``(t_ns, volts)`` per good line, the ``ValueError`` of a bad one (not raised, so
        one bad line does not end the stream)."""
        t0_line = t0_wall = None
        for n, line in enumerate(self.stream, start=1):
            try:
                parsed = parse_line(line, self.channels, f"{self.name} line {n}")
            except ValueError as exc:
                if n == 1 and not line.lstrip()[:1].isdigit():
                    continue  # a header line
                self.bad_lines += 1
                yield exc
                continue
            if parsed is None:
                continue
            t, volts = parsed
            if t0_line is None:
                t0_line, t0_wall = t, time.time_ns()
            t_ns = t0_wall + round((t - t0_line) * 1e9)
            if self.speed:
                delay = (t_ns - t0_wall) / self.speed - (time.time_ns() - t0_wall)
                if delay > 0:
                    time.sleep(delay * 1e-9)
            yield t_ns, volts

    def close(self) -> None:
        self.stream.close()


class SimSource:
    """The simulated rig on the head trajectory of ``seed``, sampled at wall-clock time.

    Trajectory time is ``services.sim.world.sim_time_s`` of the sample time, the convention
    every simulator of the world shares, so the samples agree with the ground truth.
    """

    def __init__(self, device: SensorTruth, seed: int, rate_hz: float, trajectory):
        self.device = device
        self.seed = seed
        self.rate_hz = rate_hz
        self.trajectory = trajectory
        self.name = "sim"
        self.bad_lines = 0

    def samples(self) -> Iterator[tuple[int, np.ndarray]]:
        """Samples at multiples of the period, released when their time has come."""
        period_ns = round(1e9 / self.rate_hz)
        k = time.time_ns() // period_ns + 1
        chunk = max(1, round(SIM_CHUNK_S * self.rate_hz))
        while True:
            t0_ns = k * period_ns
            run = simulate(self.trajectory, chunk / self.rate_hz, self.rate_hz,
                           seed=(self.seed * 1_000_003 + k) % 2**63, t0=sim_time_s(t0_ns),
                           sensor=self.device)
            for i in range(chunk):
                t_ns = t0_ns + i * period_ns
                wait = t_ns - time.time_ns()
                if wait > 0:
                    time.sleep(wait * 1e-9)
                yield t_ns, run.volts[i]
            k += chunk

    def close(self) -> None:
        pass
