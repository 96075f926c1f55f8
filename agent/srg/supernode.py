"""Supernode summaries (Klinker, Bauer 2005, §1.3.3 "Super Nodes"): an agent's SRG condensed.

Other agents need not see every edge of a host, only how well the host can link the frames
that matter across hosts.  A summary lists the agent's frames, its *boundary* frames (those
another agent also knows: a shared frame id is what links two agents' graphs) and, for every
frame and every boundary frame of the same connected part, the attributes of the best local
path between them under each built-in error function.  A planner joins summaries into a
graph whose edges are these links, finds a route, and asks each owning agent for its
segment at the query time.

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from agent.srg.graph import Graph
from agent.srg.result import finite_or_none

#: the error functions whose best local paths a summary describes
SUMMARY_ERRORS = ("hops", "latency", "accuracy", "confidence", "cost")


def summarize(graph: Graph, boundary: Iterable[str]) -> dict[str, Any]:
    """``frames``, ``boundary``, ``components`` and ``links`` of ``graph`` (plain data).

    Each link is ``{"a": frame, "b": boundary frame, "attrs": {error: path attributes}}``;
    infinite attributes (the update rate of an all-static path) are None.
    """
    frames = graph.frames()
    ports = set(boundary).intersection(frames)
    components = graph.components()
    links = []
    for part in components:
        for b in sorted(ports.intersection(part)):
            for a in part:
                if a == b or (a in ports and a < b):
                    continue  # two boundary frames are linked once
                attrs = {e: finite_or_none(graph.best_paths(a, b, e)[0].attributes)
                         for e in SUMMARY_ERRORS}
                links.append({"a": a, "b": b, "attrs": attrs})
    return {"frames": frames, "boundary": sorted(ports), "components": components,
            "links": links}
