"""A camera that was bumped: noticed from its rays, re-estimated from the tracked bodies.

A camera turned or moved since the calibration sees every marker away from where the
other cameras' poses put it: the tracker's fits keep dropping its observations as
outliers, or it finds no blob in its windows at all.  ``RigHealth`` counts, per camera
and over the last ``window`` frame sets, the marker images the tracked poses predict
inside its image (``expected``) and those its fits kept (``used``); a camera whose share
falls below ``min_share`` while the others track disagrees with them beyond what its
covariance allows, and is flagged.

While flagged, the camera's pose is estimated again from the tracked bodies, which the
other cameras keep measuring: their markers in the world against this camera's blobs.  A
bump moves the whole image by about the same few pixels, so the shift is taken as the
median displacement of each predicted marker to its nearest blob (within ``search_px``),
and the blobs within ``match_px`` of the shifted prediction are the correspondences.  Once
``correspondences`` of them are in, ``cv2.solvePnP`` from the old pose then
``cv2.solvePnPRefineLM`` give the new pose; it replaces the old one when it reprojects
within ``max_rms_px``.  Tracking goes on meanwhile with the other cameras.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from agent import geometry as geo
from services.outside_in.rig import RigCamera, RigImages

Array = np.ndarray


@dataclass(frozen=True)
class HealthParams:
    window: int = 60               # frame sets the shares are counted over
    min_expected: int = 40         # predicted marker images needed before judging
    min_share: float = 0.25        # kept / predicted below this: the camera disagrees
    search_px: float = 30.0        # how far a bump may have moved the image
    match_px: float = 1.0          # a blob this near the shifted prediction corresponds
    correspondences: int = 300     # collected before the pose is solved
    max_rms_px: float = 0.3        # the new pose's reprojection rms must be below this


@dataclass
class _Camera:
    expected: deque = field(default_factory=deque)
    used: deque = field(default_factory=deque)
    flagged: bool = False
    world: list = field(default_factory=list)
    pixels: list = field(default_factory=list)


class RigHealth:
    """Per-camera agreement with the tracked bodies, and re-estimation when it is lost."""

    def __init__(self, n_cameras: int, params: HealthParams | None = None):
        self.params = params or HealthParams()
        self.cams = [_Camera(deque(maxlen=self.params.window), deque(maxlen=self.params.window))
                     for _ in range(n_cameras)]
        self.events: list[dict] = []

    @property
    def flagged(self) -> list[int]:
        return [c for c, s in enumerate(self.cams) if s.flagged]

    def observe(self, t: float, images: RigImages, blobs: dict[int, Array],
                poses: list[tuple[Array, Array, Array, dict[int, dict[int, int]]]]
                ) -> list[tuple[int, RigCamera]]:
        """One frame set: ``blobs`` per camera (pixels; ``images.cameras`` the rig's
        cameras), ``poses`` of the tracked bodies as ``(p, R, markers, kept)``
        (``kept``: camera -> marker -> blob).  Returns the cameras re-estimated now,
        ``(index, camera)``."""
        out = []
        cams = list(blobs)
        expected = np.zeros(len(cams), int)
        if poses:
            world = np.vstack([m @ R.T + p for p, R, m, _ in poses])
            z, uv = images.depth_and_pixels(world, cams)
            expected = np.count_nonzero((z > 0.05) & images.inside(uv, cams, margin_px=5),
                                        axis=1)
        for c, uv, seen in zip(cams, blobs.values(), expected.tolist(), strict=True):
            state = self.cams[c]
            cam = images.cameras[c]
            used = sum(len(kept.get(c, {})) for *_, kept in poses)
            state.expected.append(seen)
            state.used.append(used)
            if not state.flagged and self._disagrees(state):
                state.flagged = True
                self.events.append({"t": t, "camera": cam.name, "event": "disagrees"})
            if state.flagged:
                self._collect(state, cam, uv, poses)
                new = self._solve(state, cam)
                if new is not None:
                    out.append((c, new))
                    self.events.append({"t": t, "camera": cam.name, "event": "re-estimated"})
                    self.cams[c] = _Camera(deque(maxlen=self.params.window),
                                           deque(maxlen=self.params.window))
        return out

    def _disagrees(self, s: _Camera) -> bool:
        exp = sum(s.expected)
        return (len(s.expected) == s.expected.maxlen and exp >= self.params.min_expected
                and sum(s.used) < self.params.min_share * exp)

    def _collect(self, s: _Camera, cam: RigCamera, uv: Array, poses: list) -> None:
        if len(uv) == 0 or not poses:
            return
        world = np.vstack([m @ R.T + p for p, R, m, _ in poses])
        world = world[cam.visible(world, margin_px=5)]
        if len(world) == 0:
            return
        pred = cam.project(world)
        d = np.linalg.norm(pred[:, None] - uv[None], axis=2)
        near = np.argmin(d, axis=1)
        close = d[np.arange(len(pred)), near] < self.params.search_px
        if close.sum() < 3:
            return
        shift = np.median(uv[near[close]] - pred[close], axis=0)
        d2 = np.linalg.norm(pred[:, None] + shift - uv[None], axis=2)
        best = np.argmin(d2, axis=1)
        ok = d2[np.arange(len(pred)), best] < self.params.match_px
        s.world += list(world[ok])
        s.pixels += list(uv[best[ok]])

    def _solve(self, s: _Camera, cam: RigCamera) -> RigCamera | None:
        if len(s.world) < self.params.correspondences:
            return None
        W = np.array(s.world, np.float64)
        P = np.array(s.pixels, np.float64)
        rvec, tvec = cam.rvec.copy().reshape(3, 1), cam.t_cw.copy().reshape(3, 1)
        ok, rvec, tvec = cv2.solvePnP(W, P, cam.K, cam.dist, rvec, tvec,
                                      useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            s.world, s.pixels = [], []
            return None
        rvec, tvec = cv2.solvePnPRefineLM(W, P, cam.K, cam.dist, rvec, tvec)
        proj, _ = cv2.projectPoints(W, rvec, tvec, cam.K, cam.dist)
        rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - P) ** 2, axis=1))))
        if rms > self.params.max_rms_px:
            s.world, s.pixels = [], []     # mixed-up correspondences: collect afresh
            return None
        R_cw = cv2.Rodrigues(rvec)[0]
        return cam.moved(-R_cw.T @ tvec.ravel(), geo.matrix_to_quat(R_cw.T))
