"""The display's own imagery as a camera behind the notch filter sees it.

While the user is tracked, the projectors show moving, textured, bright content on the
very screens the cameras watch.  Each camera's notch filter (peak at 650 nm, Hogue 2003,
§5.2 and appendix C.2.2) passes the laser and only the part of the projector's red primary
that falls into its band, so the content appears as a dim, moving texture under the laser
spots: the spots stand out by a finite contrast, not on black.

The content is a texture per camera (smooth random shapes with soft and hard edges, as
rendered scenes have), drawn once from the installation's seed, larger than the image; a
frame takes a crop whose offset drifts with time, so the content moves across the screen
at ``speed_px_s``.  Adding a crop costs one saturating 8-bit addition per frame.

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import cv2
import numpy as np

#: the texture is this many pixels larger than the image in both directions
PAD = 96


class ProjectedContent:
    """Moving projected imagery behind one camera's notch filter, in DN above dark."""

    def __init__(self, width: int, height: int, peak_dn: float, speed_px_s: float,
                 rng: np.random.Generator):
        self.size = (height, width)
        self.speed = speed_px_s
        self.direction = _unit(rng.normal(size=2))
        self.phase = rng.uniform(0, 2 * PAD, 2)
        self.texture = _texture(height + PAD, width + PAD, peak_dn, rng)

    def crop(self, t: float) -> np.ndarray:
        """The content seen at time ``t`` (s): an 8-bit (height, width) view."""
        # a triangle wave keeps the offset inside the padding while the content moves on
        s = self.phase + self.speed * t * self.direction
        oy, ox = (PAD - np.abs(np.mod(s, 2 * PAD) - PAD)).astype(int)
        return self.texture[oy:oy + self.size[0], ox:ox + self.size[1]]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _texture(h: int, w: int, peak_dn: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth random shading with a few sharp-edged bright shapes, scaled to ``peak_dn``."""
    low = cv2.resize(rng.uniform(0, 1, (h // 48 + 2, w // 48 + 2)), (w, h),
                     interpolation=cv2.INTER_CUBIC)
    img = 0.5 * np.clip(low, 0, 1)
    for _ in range(12):  # windows, objects, text blocks: hard edges at full brightness
        x, y = rng.uniform(0, w), rng.uniform(0, h)
        a, b = rng.uniform(10, 80, 2)
        cv2.rectangle(img, (int(x - a), int(y - b)), (int(x + a), int(y + b)),
                      float(rng.uniform(0.5, 1.0)), -1)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)  # the projector's and the lens' blur
    return np.clip(np.rint(peak_dn * img), 0, 255).astype(np.uint8)
