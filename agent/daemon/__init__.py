"""Code that runs in the agent daemon, one process per host (``uma agent``).

:mod:`agent.daemon.agent` is the daemon itself, the wiring of the parts the other modules
are: its settings, the registrar of its local services, its view of the realm and its
snapshot, matching needs to abilities, stream monitoring, one subscription per data key
(streams) and its SRG node.

Public: :class:`Agent` and :class:`AgentSettings`, to run an agent inside a process (as
``uma demo`` does); the modules are internal.
"""

from __future__ import annotations

from agent._lazy import lazy_attributes

__all__ = ["Agent", "AgentSettings"]

__getattr__ = lazy_attributes(__name__, {"Agent": "agent.daemon.agent",
                                         "AgentSettings": "agent.daemon.settings"})
