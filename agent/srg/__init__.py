"""The spatial relationship graph (SRG): pure computation on numpy, no I/O.

``from agent.srg import Graph`` for the graph and pose queries; ``agent.srg.geometry`` for
SE(3) poses, quaternions (x, y, z, w) and covariance propagation.
"""

from __future__ import annotations

from typing import Any

__all__ = ["Graph"]


def __getattr__(name: str) -> Any:
    if name == "Graph":
        from agent.srg.graph import Graph

        return Graph
    raise AttributeError(f"module 'agent.srg' has no attribute {name!r}")
