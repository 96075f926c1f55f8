"""uma agent: the per-host daemon and the SDK that services and clients import.

The public API is what ``__all__`` lists (``from agent import Service, Client``); the
sub-packages say where the rest runs: ``agent.daemon`` (the per-host daemon),
``agent.sdk`` (in a service's or client's process), ``agent.protocol`` (what crosses a
process boundary), ``agent.runtime`` (every process), ``agent.cli`` (the ``uma``
command) and ``agent.srg`` (the spatial relationship graph, pure numpy).  Names are
imported lazily so that importing the pure parts (``agent.srg``) never pulls in Zenoh.
"""

from __future__ import annotations

from typing import Any

__all__ = ["Client", "Graph", "Match", "Measurement", "PoseResult", "Service", "Subscription",
           "UmaError"]

_LAZY = {
    "Service": "agent.sdk.service",            # declare needs and abilities, publish
    "Client": "agent.sdk.client",              # pose queries and subscriptions
    "Subscription": "agent.sdk.subscription",  # what Client.subscribe returns
    "Match": "agent.protocol.registration",    # an ability a need is connected to
    "Measurement": "schemas.codec",            # what a need's on_sample receives
    "PoseResult": "agent.srg.result",          # what a query returns
    "Graph": "agent.srg.graph",                # the SRG, offline
    "UmaError": "agent.errors",                # every error explained to the user
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'agent' has no attribute {name!r}")
