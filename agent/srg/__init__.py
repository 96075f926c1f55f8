"""The spatial relationship graph (SRG): pure computation on numpy, no I/O.

``from agent.srg import Graph`` (or ``from agent import Graph``) for the graph and pose
queries; ``agent.geometry`` for SE(3) poses, quaternions (x, y, z, w) and covariance
propagation; ``agent.srg.errors`` for the exceptions a query raises (all ``UmaError``:
``NotFoundError`` or ``InvalidInputError``, a ``LookupError`` or a ``ValueError``).
"""

from __future__ import annotations

from agent._lazy import lazy_attributes

__all__ = ["Graph", "PoseResult"]

__getattr__ = lazy_attributes(__name__, {"Graph": "agent.srg.graph",
                                         "PoseResult": "agent.result"})
