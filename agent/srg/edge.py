"""One edge of the SRG: a static value or a measured time series, with its attributes."""

from __future__ import annotations

from typing import Any

import numpy as np

from agent import geometry as geo
from agent.attributes import nominal_covariance
from agent.srg.buffer import SampleBuffer

#: (parent, child, source): parallel edges between the same frames differ by source
EdgeKey = tuple[str, str, str]


def edge_name(key: EdgeKey) -> str:
    """``parent->child [source]``, the way errors and results name an edge."""
    return f"{key[0]}->{key[1]} [{key[2]}]"


class Edge:
    """The pose of ``child`` in ``parent``: either one static value or a buffer of samples."""

    __slots__ = ("attrs", "buffer", "key", "last_kwargs", "name", "std_cov", "value")

    def __init__(self, key: EdgeKey, attrs: dict[str, Any], *, static_value: tuple | None = None,
                 buffer_s: float = 10.0, max_samples: int = 1000) -> None:
        self.key = key
        self.name = edge_name(key)
        self.attrs = attrs
        self.value = static_value  # (p, q, covariance or None) of a static edge
        self.buffer = None if static_value is not None else SampleBuffer(
            self.name, buffer_s, max_samples)
        self.std_cov = self._std_covariance()
        #: the attribute arguments of the last add_measurement (repeats are not re-checked)
        self.last_kwargs: dict[str, Any] | None = None

    @property
    def parent(self) -> str:
        return self.key[0]

    @property
    def child(self) -> str:
        return self.key[1]

    @property
    def source(self) -> str:
        return self.key[2]

    @property
    def is_static(self) -> bool:
        return self.value is not None

    def set_attributes(self, attrs: dict[str, Any]) -> None:
        self.attrs = attrs
        self.std_cov = self._std_covariance()
        self.last_kwargs = None  # the next sample's attributes are checked again

    def _std_covariance(self) -> tuple[np.ndarray, bool] | None:
        """The decoupled covariance of the std attributes and whether it has a rotation part.

        Precomputed so a sample without its own covariance costs no allocation: with no
        rotation noise the SE(3) form equals the decoupled one at any translation.
        """
        if "covariance" in self.attrs:
            return None
        pos, rot = self.attrs.get("pos_std_m"), self.attrs.get("rot_std_rad")
        if pos is None and rot is None:
            return None
        return geo.covariance_from_std(np.zeros(3), pos, rot), bool(rot)

    def covariance_at(self, p: np.ndarray, sample_cov: np.ndarray | None) -> np.ndarray | None:
        """A sample's covariance, else the one the attributes describe at translation ``p``."""
        if sample_cov is not None:
            return sample_cov
        if "covariance" in self.attrs:
            return self.attrs["covariance"]
        std = self.std_cov
        if std is None:
            return None
        cov, rotates = std
        return geo.decoupled_to_se3(p, cov) if rotates else cov

    def nominal(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The value used to rank paths: the static value, else the newest sample (or identity)."""
        if self.value is not None:
            return self.value
        buf = self.buffer
        if buf is not None and len(buf):
            value = buf.values[-1]
            p, q = np.array(value[:3]), np.array(value[3:])
            return p, q, self.covariance_at(p, buf.covs[-1])
        p = np.zeros(3)
        return p, geo.quat_identity(), nominal_covariance(self.attrs, p)

    def info(self, forward: bool = True) -> dict[str, Any]:
        """The edge as a result reports it."""
        return {"parent": self.parent, "child": self.child, "source": self.source,
                "forward": forward, "static": self.is_static}
