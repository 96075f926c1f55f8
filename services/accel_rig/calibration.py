"""Calibration from static orientations, Hogue 2003, §4.4.2 (eqs. 4.49-4.63), in least squares.

Held still at a known orientation R_i (rig in world), accelerometer j reads

    v_ij = B_j + k_j n_j . f_i,   f_i = R_i^T (0 - g)  (specific force of a resting rig)

which is linear in the four unknowns ``(B_j, m_j = k_j n_j)``.  The thesis' four poses
(+X, -X, +Y, -Z along gravity) make the 4 x 4 system of eqs. 4.49-4.52 square: the bias is
the mean of the +X/-X readings (eq. 4.53) and the axis follows from the normal equations
(eq. 4.63).  With more poses the same normal equations give the least-squares solution.
Then ``k_j = |m_j|`` (scale, eq. 4.60) and ``n_j = m_j / k_j`` (axis, misalignment
included).  Positions are not observable from static poses; they come from the drawing.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from agent import geometry as geo
from agent.errors import InvalidInputError
from services.accel_rig import sensor as sn
from services.accel_rig.rig import RigLayout
from services.frames import GRAVITY

Array = np.ndarray

#: Seed 003 §4.4.2: the minimum set, +X, -X, +Y and -Z along gravity.
THESIS_POSES = ("+x", "-x", "+y", "-z")
#: All six faces down: least squares, and every axis sees +g and -g.
SIX_POSES = ("+x", "-x", "+y", "-y", "+z", "-z")
#: the calibration orientations by name (``uma eval accel-rig --poses``)
POSE_SETS = {"thesis": THESIS_POSES, "six": SIX_POSES}
#: A pose whose readings wander more than this many noise standard deviations was not still.
MAX_STILL_SIGMAS = 8.0


@dataclass(frozen=True)
class StaticRecording:
    """Voltages (n, N) recorded with the rig still at ``quaternion`` (rig in world, xyzw)."""

    quaternion: Array
    volts: Array


def calibrate(layout: RigLayout, recordings: Sequence[StaticRecording],
              rate_hz: float, noise: sn.NoiseModel | None = None,
              latency_s: float = 0.0) -> sn.Calibration:
    """Estimate every accelerometer's bias, gain and axis from >= 4 static recordings.

    ``layout`` supplies the positions (its axes are replaced by the calibrated ones).  The
    parameter covariance follows from the noise model, the number of samples averaged and
    what quantisation leaves in an average;
    a recording where the rig visibly moved, or a set of orientations that does not
    determine the axes, is refused with the reason.
    """
    noise = sn.NoiseModel() if noise is None else noise
    if len(recordings) < 4:
        raise InvalidInputError(f"calibration needs at least 4 static orientations "
                                f"(Hogue 2003, §4.4.2), got {len(recordings)}")
    n = layout.count
    forces, means, weights = [], [], []
    for i, rec in enumerate(recordings):
        q = geo.check_quaternion(rec.quaternion, f"calibration pose {i + 1} orientation")
        v = sn.check_volts(rec.volts, f"calibration pose {i + 1} voltages")
        if v.ndim != 2 or v.shape[1] != n or v.shape[0] < 1:
            raise InvalidInputError(f"calibration pose {i + 1}: voltages must be (samples, {n}), "
                                    f"got {v.shape}")
        _check_still(v, noise, rate_hz, i)
        forces.append(geo.quat_rotate(geo.quat_conjugate(q), -GRAVITY))
        means.append(v.mean(axis=0))
        weights.append(v.shape[0])
    A = np.hstack([np.ones((len(forces), 1)), np.array(forces)])  # rows [1, f_i^T]
    W = np.array(weights, float)
    normal = A.T @ (W[:, None] * A)
    if np.linalg.cond(normal) > 1e10:
        raise InvalidInputError("calibration orientations do not determine bias and axis: the "
                                "specific forces must span 3D and not all lie on one plane through "
                                "the origin (use e.g. +x -x +y -z down, Hogue 2003, §4.4.2)")
    normal_inv = np.linalg.inv(normal)
    X = normal_inv @ (A.T @ (W[:, None] * np.array(means)))  # (4, N): [B; m]
    bias, m = X[0], X[1:].T
    gain = np.linalg.norm(m, axis=1)
    axes = m / gain[:, None]
    # each pose's mean carries white noise (var / samples) and a quantisation error that
    # averaging does not remove; the weighted least squares maps both onto the parameters
    mean_var = noise.per_sample_var_v2(rate_hz) / W + noise.static_mean_bias_var_v2(rate_hz)
    G = normal_inv @ (A.T * W)
    cov = np.broadcast_to(G @ (mean_var[:, None] * G.T), (n, 4, 4)).copy()
    calibrated = RigLayout(layout.positions, axes, name=layout.name)
    return sn.Calibration(calibrated, bias, gain, cov, noise, latency_s)


def _check_still(v: Array, noise: sn.NoiseModel, rate_hz: float, i: int) -> None:
    """Refuse a recording whose spread is far above the sensor noise: the rig moved."""
    if v.shape[0] < 2:
        return
    expected = np.sqrt(noise.per_sample_var_v2(rate_hz)) + noise.lsb_v
    spread = v.std(axis=0)
    worst = int(np.argmax(spread))
    if spread[worst] > MAX_STILL_SIGMAS * expected:
        raise InvalidInputError(
            f"calibration pose {i + 1}: accelerometer {worst + 1} varies by "
            f"{spread[worst] * 1e3:.2f} mV rms (noise {expected * 1e3:.2f} mV): "
            "the rig was not held still")


@dataclass(frozen=True)
class CalibrationErrors:
    """Per-accelerometer errors of an estimated calibration against the true device."""

    bias_lsb: Array
    scale_percent: Array
    axis_deg: Array

    def worst(self) -> dict[str, float]:
        return {"bias_lsb": float(np.abs(self.bias_lsb).max()),
                "scale_percent": float(np.abs(self.scale_percent).max()),
                "axis_deg": float(np.abs(self.axis_deg).max())}


def calibration_errors(estimate: sn.Calibration, bias_v: Array, gain_v_per_mps2: Array,
                       axes: Array) -> CalibrationErrors:
    """Bias error in LSB, scale error in % and axis error in degrees, per accelerometer."""
    true_axes = np.asarray(axes, float)
    angle = np.arctan2(np.linalg.norm(np.cross(estimate.axes, true_axes), axis=1),
                       np.einsum("ij,ij->i", estimate.axes, true_axes))
    return CalibrationErrors(
        (estimate.bias_v - np.asarray(bias_v, float)) / sn.LSB_V,
        100.0 * (estimate.gain_v_per_mps2 / np.asarray(gain_v_per_mps2, float) - 1.0),
        np.degrees(angle))
