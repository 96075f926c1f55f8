"""The spatial relationship graph (SRG): pure computation on numpy, no I/O.

``from agent.srg import Graph`` for the graph and pose queries; ``agent.geometry`` for
SE(3) poses, quaternions (x, y, z, w) and covariance propagation; ``agent.srg.errors`` for
the exceptions a query raises (all ``LookupError`` or ``ValueError``).
"""

from __future__ import annotations

from typing import Any

__all__ = ["Graph", "PoseResult"]

_LAZY = {"Graph": "agent.srg.graph", "PoseResult": "agent.result"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'agent.srg' has no attribute {name!r}")
