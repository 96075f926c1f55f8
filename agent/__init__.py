"""uma agent: the per-host daemon and the SDK that services and clients import.

The public API is what ``__all__`` lists (``from agent import Service, Client``) and the
modules ``PUBLIC_MODULES`` names; everything else is internal and may change.  Services,
``uma view`` and ``uma record`` use only these (``tests/test_public_api.py`` checks it):

- ``agent.geometry``: SE(3) poses, quaternions (x, y, z, w), covariance propagation;
- ``agent.errors``: the errors a user sees, all :class:`UmaError`;
- ``agent.runtime``: what a plug-in and a long-running command need (plug-in declarations,
  network options, stopping on signals, sessions, rate-limited logs);
- ``agent.protocol``: the key space and the messages a realm tool reads off the wire;
- ``agent.daemon``: the agent itself, to run one inside a process (``uma demo``);
- ``agent.view`` and ``agent.record``: what their packages offer to others.

The sub-packages say where the rest runs: ``agent.daemon`` (the per-host daemon),
``agent.sdk`` (in a service's or client's process), ``agent.protocol`` (what crosses a
process boundary), ``agent.runtime`` (every process), ``agent.cli`` (the ``uma``
command) and ``agent.srg`` (the spatial relationship graph, pure numpy).  Names are
imported lazily so that importing the pure parts (``agent.srg``, ``agent.geometry``) never
pulls in Zenoh.
"""

from __future__ import annotations

from agent._lazy import lazy_attributes

__all__ = ["Client", "Graph", "Match", "Measurement", "PoseResult", "Service", "Subscription",
           "UmaError", "collect_realm", "live_agents", "settled_agents"]

#: the public modules besides this one; a name in one's ``__all__`` (or, without one, any
#: name not starting with ``_``) is public
PUBLIC_MODULES = ("agent.geometry", "agent.errors", "agent.runtime", "agent.protocol",
                  "agent.protocol.keys", "agent.daemon", "agent.view", "agent.record")

__getattr__ = lazy_attributes(__name__, {
    "Service": "agent.sdk.service",            # declare needs and abilities, publish
    "Client": "agent.sdk.client",              # pose queries and subscriptions
    "Subscription": "agent.sdk.subscription",  # what Client.subscribe returns
    "Match": "agent.protocol.registration",    # an ability a need is connected to
    "Measurement": "schemas.codec",            # what a need's on_sample receives
    "PoseResult": "agent.result",          # what a query returns
    "Graph": "agent.srg.graph",                # the SRG, offline
    "UmaError": "agent.errors",                # every error explained to the user
    "collect_realm": "agent.sdk.inventory",    # every agent's services, needs, matches
    "live_agents": "agent.sdk.inventory",      # agents whose token is visible now
    "settled_agents": "agent.sdk.inventory",   # ... once their set has stopped changing
})
