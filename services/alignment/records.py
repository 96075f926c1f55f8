"""Files of the alignment service: recorded pose pairs (CSV) in, calibration (TOML) out.

Pose-pair CSV (``--from-file``): a header row naming the 16 columns below (in any order,
extra columns ignored), then one row per pair of samples, one of each tracker::

    t_a, pa_x, pa_y, pa_z, qa_x, qa_y, qa_z, qa_w,   t_b, pb_x, pb_y, pb_z, qb_x, qb_y, qb_z, qb_w

``t_a`` / ``t_b`` are seconds in each tracker's own clock, ``pa``/``qa`` the pose of
sensor a in world a (metres, unit quaternion x, y, z, w), ``pb``/``qb`` the pose of sensor b
in world b.  Rows need not be synchronous: each half is one sample of its stream, and the
time offset is estimated (``t_b = t_a + offset``).  For static stations (a robot stopping
at each pose), write the same time in both, one row per station.

Calibration file: a TOML fragment with one ``[[static]]`` table (the agent configuration's
format, ``agent.daemon.settings.check_static_edge``), loadable by ``uma agent --config FILE`` or
pasted into a host's config; the fit's figures are kept as comments.
"""

from __future__ import annotations

import csv
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from services.alignment.pipeline import AlignmentResult
from services.alignment.solvers import AlignmentError
from services.alignment.timesync import PoseSeries

COLUMNS = ("t_a", "pa_x", "pa_y", "pa_z", "qa_x", "qa_y", "qa_z", "qa_w",
           "t_b", "pb_x", "pb_y", "pb_z", "qb_x", "qb_y", "qb_z", "qb_w")
_MAX_ROWS = 10_000_000


def write_pose_pairs(path: str | Path, a: PoseSeries, b: PoseSeries) -> None:
    """Write two equally long streams as pose-pair rows (full float precision)."""
    if len(a) != len(b):
        raise AlignmentError(f"pose pairs need equally long streams, got {len(a)} and {len(b)}")
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for k in range(len(a)):
            w.writerow([repr(float(v)) for v in (
                a.t[k], *a.position[k], *a.quaternion[k], b.t[k], *b.position[k],
                *b.quaternion[k])])


def read_pose_pairs(path: str | Path) -> tuple[PoseSeries, PoseSeries]:
    """The two streams of a pose-pair CSV; ``AlignmentError`` names the line and column."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as exc:
        raise AlignmentError(f"cannot read pose pairs {str(path)!r}: {exc}") from None
    if not rows:
        raise AlignmentError(f"{path}: empty file; expected a header: {','.join(COLUMNS)}")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise AlignmentError(f"{path}: missing column(s) {', '.join(missing)} in the header "
                             f"(expected {','.join(COLUMNS)})")
    if len(rows) - 1 > _MAX_ROWS:
        raise AlignmentError(f"{path}: more than {_MAX_ROWS} rows")
    index = [header.index(c) for c in COLUMNS]
    data = np.empty((len(rows) - 1, len(COLUMNS)))
    for n, row in enumerate(rows[1:]):
        data[n] = [_number(row, i, c, path, n + 2) for i, c in zip(index, COLUMNS, strict=True)]
    a = PoseSeries(data[:, 0], data[:, 1:4], data[:, 4:8], f"{path} stream a")
    b = PoseSeries(data[:, 8], data[:, 9:12], data[:, 12:16], f"{path} stream b")
    return a, b


def _number(row: list[str], i: int, column: str, path: str | Path, line: int) -> float:
    try:
        value = float(row[i])
    except IndexError:
        raise AlignmentError(f"{path}:{line}: row has {len(row)} fields, no {column}") from None
    except ValueError:
        raise AlignmentError(f"{path}:{line}: {column} is not a number: {row[i]!r}") from None
    if not math.isfinite(value):
        raise AlignmentError(f"{path}:{line}: {column} is {value} (NaN/inf poses are refused)")
    return value


def calibration_toml(result: AlignmentResult, parent: str, child: str) -> str:
    """The ``[[static]]`` fragment for edge ``parent -> child`` (= sensor_a -> sensor_b)."""
    s = result.summary()

    def floats(v: list[float]) -> str:
        return "[" + ", ".join(repr(float(x)) for x in v) + "]"

    return "\n".join([
        f"# uma tracker alignment (AX = XB), {time.strftime('%Y-%m-%dT%H:%M:%S%z')}",
        f"# method {s['method']}, {s['pairs_inlier']} of {s['pairs_selected']} motion pairs "
        f"consistent, {s['stations']} stations, axis spread {s['axis_spread_deg']:.1f} deg",
        f"# residual rms: {math.degrees(s['residual_rot_rad']):.4f} deg, "
        f"{s['residual_pos_m'] * 1e3:.3f} mm; time offset b - a: "
        f"{s['time_offset_s'] * 1e3:.2f} ms",
        "# std: RMS per axis of the bootstrap covariance",
        "[[static]]",
        f"parent = {_toml_string(parent)}",
        f"child = {_toml_string(child)}",
        f"position = {floats(s['position'])}",
        f"quaternion = {floats(s['quaternion'])}    # x, y, z, w",
        f"pos_std_m = {float(s['pos_std_m'])!r}",
        f"rot_std_rad = {float(s['rot_std_rad'])!r}",
        "",
    ])


def _toml_string(text: str) -> str:
    if any(c in text for c in '"\\\n\r'):
        raise AlignmentError(f"frame id {text!r} cannot be written to the calibration file")
    return f'"{text}"'


def write_calibration(path: str | Path, result: AlignmentResult, parent: str, child: str,
                      ) -> None:
    """Write the fragment atomically (a crash never leaves a half-written file)."""
    path = Path(path)
    text = calibration_toml(result, parent, child)
    fd, tmp = tempfile.mkstemp(dir=path.parent or Path("."), prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise AlignmentError(f"cannot write calibration file {str(path)!r}: {exc}") from None
