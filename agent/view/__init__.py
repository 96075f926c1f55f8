"""``uma view``: a live page of one realm in the browser (agents, services, needs and
abilities, matches and their streams, an event log, the SRG in 3D, a query box).

The view is a client of the realm like any other: an :class:`agent.Client` (realm tracker,
clock offsets, queries), the agents' service snapshots (as ``uma services`` reads them) and
subscriptions to the streams of edge abilities.  The page is drawn with viser (an optional
extra: ``pip install 'uma-tracking[view]'``), at most ``--hz`` times a second.

Modules, one job each: ``command`` (the grammar, light to import), ``app`` (wiring and the
draw loop), ``watch`` (the realm's snapshots, agents, clocks, static edges), ``events``
(what changed between two looks), ``taps`` (the streams of edge abilities), ``space``
(frames' poses in a root frame, trails), ``panels`` (the text of the page) and ``scene``
(the 3D scene and GUI controls).

Public: :func:`import_viser`, viser or an ``UmaError`` saying what to install (``uma demo
--view`` checks it before it starts anything).
"""

from __future__ import annotations

from agent._lazy import lazy_attributes

__all__ = ["import_viser"]

__getattr__ = lazy_attributes(__name__, {"import_viser": "agent.view.app"})
