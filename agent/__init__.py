"""uma agent: the per-host daemon and the SDK that services and clients import.

``from agent import Service, Client``.  Names are imported lazily so that importing the
pure parts (``agent.srg``) never pulls in Zenoh.
"""

from __future__ import annotations

from typing import Any

__all__ = ["Client", "Service"]

_LAZY = {"Service": "agent.sdk.service", "Client": "agent.sdk.client"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'agent' has no attribute {name!r}")
