"""Cross-agent pose queries: routes over supernode summaries, composed from segments.

Each agent publishes a summary of its SRG (:mod:`agent.srg.supernode`): its frames, its
boundary frames and the attributes of its best local paths between them.  A frame id known
to two agents links them.  The planner joins all summaries into one graph whose edges are
those links (labelled with their agent), ranks routes from source to target for the error
function (Dijkstra/Yen as in the local SRG: additive functions sum the links' values,
path-level ones are evaluated on the joined attributes of k candidate routes), merges
consecutive links of one agent into a single *segment*, and leaves it to the caller
(:mod:`agent.sdk.query`) to ask each owning agent for its segment at ``t`` and to compose
the answers (:mod:`agent.srg.composition`).  Pure: no I/O, no wire format (summaries
arrive parsed, by :mod:`agent.protocol.query`).

Routes through agents that have left the realm are never tried; when only such routes
exist, :class:`RouteError` names the segments and agents that are missing.

Work per plan is bounded (a peer may forge summaries of many links): at most
``MAX_LINKS_PER_AGENT`` links of one agent and ``MAX_PLAN_LINKS`` in all are considered,
taken agent by agent outward from the agents that hold the source or the target frame
(nearest first; in one layer, the agents with the fewest links first).
What is left out is counted and said in a rate-limited log line (the planner's only
output besides its result).  Only links that can carry this plan count: both ends the
source, the target or a frame another agent also holds.  A link to a frame only its own
agent knows is a dead end for any other query (a route through it would merge into that
agent's link between the two frames beside it), and an agent of 1,000 frames summarises
1,000 such links (bounded to the first 66, they could hide the source's own link).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent.attributes import combine
from agent.protocol.query import Summary
from agent.runtime.logs import RateLimitedLog
from agent.srg import paths
from agent.srg.errorfn import ErrorFunction
from agent.srg.errors import SrgLookupError, UnknownFrameError, UnreachableError, list_names

#: candidate routes ranked for path-level error functions
ROUTE_CANDIDATES = 16
#: links considered per plan: of one agent (an agent with 12 boundary frames has 66), in all
MAX_LINKS_PER_AGENT = 66
MAX_PLAN_LINKS = 512

_log = RateLimitedLog(logging.getLogger("uma.client"))
Link = tuple[tuple[str, str, str], dict[str, dict[str, Any]]]  # (agent, a, b), attributes


class RouteError(SrgLookupError):
    """Every route between the frames needs an agent that is gone or failed."""


class SegmentError(SrgLookupError):
    """One agent could not deliver its segment (no answer, or its own lookup failed)."""

    def __init__(self, segment: Segment, reason: str, missing: bool) -> None:
        self.segment = segment
        self.missing = missing  # the agent did not answer at all
        super().__init__(f"segment {segment} failed: {reason}")


@dataclass(frozen=True)
class Segment:
    """The part of a route one agent computes: ``source -> target`` in its own graph."""

    agent: str
    source: str
    target: str

    def __str__(self) -> str:
        return f"{self.source} -> {self.target} of agent {self.agent!r}"


@dataclass
class Route:
    segments: list[Segment]
    value: float
    attributes: dict[str, Any] = field(default_factory=dict)

    @property
    def agents(self) -> list[str]:
        return list(dict.fromkeys(s.agent for s in self.segments))


def _link_value(fn: ErrorFunction, attrs: Mapping[str, dict[str, Any]]) -> float:
    """A link's error: its best local path for a built-in; for an expression, the best of the
    paths the summary describes."""
    if fn.key in attrs:
        return fn.path_value(attrs[fn.key])
    return min(fn.path_value(a) for a in attrs.values())


def _link_attrs(fn: ErrorFunction, attrs: Mapping[str, dict[str, Any]]) -> dict[str, Any]:
    if fn.key in attrs:
        return attrs[fn.key]
    return min(attrs.values(), key=fn.path_value)


def joined_attributes(parts: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Attributes of a route from its links' (for ranking; the answer has the exact ones):
    latencies, costs, hops and covariance traces add, standard deviations add in quadrature."""
    out = combine(parts, np.zeros(3), None)
    out["accuracy"] = sum(p.get("accuracy", 0.0) for p in parts)
    out["pos_std_m"] = math.sqrt(sum(p.get("pos_std_m", 0.0) ** 2 for p in parts))
    out["rot_std_rad"] = math.sqrt(sum(p.get("rot_std_rad", 0.0) ** 2 for p in parts))
    return out


def plan_routes(summaries: Mapping[str, Summary], source: str, target: str,
                fn: ErrorFunction, k: int = 8) -> list[Route]:
    """Routes from ``source`` to ``target``, best first, through every known agent (alive or
    not: the caller skips the dead ones but names them when nothing else is left)."""
    known = set().union(*(s.frames for s in summaries.values())) if summaries else set()
    for frame in (source, target):
        if frame not in known:
            raise UnknownFrameError(frame, known)
    routes: list[Route] = []
    adj: dict[str, list] = {}
    link_attrs: dict[tuple, dict] = {}
    for key, attrs in considered_links(summaries, source, target):
        link_attrs[key] = attrs
        adj.setdefault(key[1], []).append((key[2], key, True))
        adj.setdefault(key[2], []).append((key[1], key, False))
    if source in adj and target in adj:
        if fn.additive:
            found = paths.k_shortest(adj, source, target,
                                     lambda key: _link_value(fn, link_attrs[key]), k)
        else:
            found = paths.k_shortest(adj, source, target, lambda key: 1.0,
                                     max(k, ROUTE_CANDIDATES))
        for path in found:
            parts = [_link_attrs(fn, link_attrs[key]) for key, _ in path.steps]
            joined = joined_attributes(parts)
            segments = _merge(path)
            routes.append(Route(segments, fn.path_value(joined), joined))
    linked = {tuple(r.segments) for r in routes}
    for s in summaries.values():
        # one agent holds both frames but neither is a boundary frame, so no link describes
        # its local path: that agent answers alone, and a local answer is preferred
        if any(source in c and target in c for c in s.components):
            direct = [Segment(s.agent, source, target)]
            if tuple(direct) not in linked:
                routes.append(Route(direct, -math.inf))
    if not routes:
        raise UnreachableError(source, target, _reach(adj, summaries, source),
                               _reach(adj, summaries, target))
    unique: dict[tuple, Route] = {}
    for route in sorted(routes, key=lambda r: r.value):
        unique.setdefault(tuple(route.segments), route)
    return list(unique.values())[: max(k, 1)]


def considered_links(summaries: Mapping[str, Summary], source: str,
                     target: str) -> list[Link]:
    """The links a plan from ``source`` to ``target`` considers (module docstring: which,
    and the bounds): agents in layers outward from those holding either end, the agents
    with the fewest links first in each layer (a forged summary tends to have many)."""
    holders: dict[str, list[str]] = {}
    for agent, s in summaries.items():
        for frame in s.frames:
            holders.setdefault(frame, []).append(agent)
    layer = set(holders.get(source, ())) | set(holders.get(target, ()))
    seen = set(layer)
    links: list[Link] = []
    dropped = 0

    def carries(frame: str) -> bool:
        return frame in (source, target) or len(holders.get(frame, ())) > 1

    while layer:
        following: set[str] = set()
        for agent in sorted(layer, key=lambda a: (len(summaries[a].links), a)):
            s = summaries[agent]
            room = max(0, min(MAX_LINKS_PER_AGENT, MAX_PLAN_LINKS - len(links)))
            useful = [(a, b, attrs) for a, b, attrs in s.links if carries(a) and carries(b)]
            links.extend(((agent, a, b), attrs) for a, b, attrs in useful[:room])
            dropped += max(0, len(useful) - room)
            following.update(x for f in s.frames for x in holders[f] if x not in seen)
        seen |= following
        layer = following
    if dropped:
        _log.warning(f"plan {source} -> {target}", f"{dropped} links of the agents' summaries "
                     f"left out (at most {MAX_LINKS_PER_AGENT} per agent, {MAX_PLAN_LINKS} "
                     "in all)")
    return links


def _reach(adj: Mapping, summaries: Mapping[str, Summary], frame: str) -> set[str]:
    out = paths.reachable(adj, frame) if frame in adj else {frame}
    for s in summaries.values():
        for c in s.components:
            if frame in c:
                out |= c
    return out


def _merge(path: paths.Path) -> list[Segment]:
    """Consecutive links of one agent become one segment (that agent finds its best path)."""
    segments: list[Segment] = []
    for i, (key, _) in enumerate(path.steps):
        agent = key[0]
        a, b = path.frames[i], path.frames[i + 1]
        if segments and segments[-1].agent == agent:
            segments[-1] = Segment(agent, segments[-1].source, b)
        else:
            segments.append(Segment(agent, a, b))
    return segments


def usable_routes(routes: Sequence[Route], alive: set[str], source: str,
                  target: str) -> list[Route]:
    """The routes whose agents are all alive; ``RouteError`` names what is missing if none."""
    ok = [r for r in routes if set(r.agents) <= alive]
    if ok:
        return ok
    best = routes[0]
    missing = [str(s) for s in best.segments if s.agent not in alive]
    gone = sorted({s.agent for s in best.segments if s.agent not in alive})
    raise RouteError(
        f"no route from {source!r} to {target!r}: the best route needs segment(s) "
        f"{'; '.join(missing)}, but agent(s) {list_names(gone)} left the realm, and no "
        f"other route exists ({len(routes)} considered)")


def with_departed(exc: UnreachableError, summaries: Mapping[str, Summary],
                  alive: set[str]) -> SrgLookupError:
    """An unreachable pair, naming the departed agents that held frames of either side: the
    link between the two sides was most likely one of their segments."""
    sides = exc.source_side | exc.target_side
    gone = sorted(a for a, s in summaries.items() if a not in alive and s.frames & sides)
    if not gone:
        return exc
    return RouteError(f"{exc}; agent(s) {list_names(gone)} left the realm and held frames "
                      f"of these parts: the missing segment was probably theirs")


def with_silent(exc: UnknownFrameError, summaries: Mapping[str, Summary],
                alive: set[str]) -> UnknownFrameError:
    """An unknown frame, naming the agents that are there (their token) but did not answer
    with their summary (frozen, or unreachable from here): the frame may be theirs."""
    silent = sorted(alive - set(summaries))
    if not silent:
        return exc
    out = UnknownFrameError(exc.frame, ())
    out.args = (f"frame {exc.frame!r} is not known to any agent that answered; agent(s) "
                f"{list_names(silent)} did not answer (frozen, or unreachable from here) "
                f"and may hold it; {exc}",)
    return out
