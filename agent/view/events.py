"""What changed between two looks at a realm, as lines of the view's event log.

A look is a :class:`Digest` of the realm as ``uma services`` collects it (pure data, so the
diff is a pure function): who is there, and which abilities every need is matched to, with
the reasons its agent gave for excluding a stream.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

NeedId = tuple[str, str, str]  # agent, service, need


@dataclass(frozen=True)
class Digest:
    """The parts of a realm whose changes are events."""

    agents: frozenset[str] = frozenset()
    services: frozenset[tuple[str, str]] = frozenset()
    matches: dict[NeedId, frozenset[str]] = field(default_factory=dict)
    excluded: dict[NeedId, dict[str, str]] = field(default_factory=dict)


def digest(realm: dict[str, Any]) -> Digest:
    """The digest of a realm as :func:`agent.collect_realm` returns it."""
    services, matches, excluded = set(), {}, {}
    for a in realm["agents"]:
        for s in a["services"]:
            services.add((a["agent_id"], s["service_id"]))
            for n in s["needs"]:
                nid = (a["agent_id"], s["service_id"], n["name"])
                matches[nid] = frozenset(match_name(m) for m in n["matches"])
                excluded[nid] = dict(n.get("excluded", {}))
    return Digest(frozenset(a["agent_id"] for a in realm["agents"]), frozenset(services),
                  matches, excluded)


def match_name(m: dict[str, Any]) -> str:
    """``agent/service/ability`` of a match."""
    return f"{m['agent_id']}/{m['service_id']}/{m['ability']}"


def changes(old: Digest, new: Digest) -> list[str]:
    """The event lines that lead from ``old`` to ``new``: arrivals, departures, re-matches
    (with why the old match went, when the realm says)."""
    lines = [f"agent {a} joined the realm" for a in sorted(new.agents - old.agents)]
    lines += [f"agent {a} left the realm" for a in sorted(old.agents - new.agents)]
    lines += [f"service {s} came on agent {a}" for a, s in sorted(new.services - old.services)]
    lines += [f"service {s} left agent {a}" for a, s in sorted(old.services - new.services)
              if a in new.agents]
    for nid in sorted(new.matches):
        was, now = old.matches.get(nid), new.matches[nid]
        if was is None or was == now:
            continue
        lines.append(_rematch(nid, was, now, new))
    return lines


def _rematch(nid: NeedId, was: frozenset[str], now: frozenset[str], new: Digest) -> str:
    name = f"{nid[0]}/{nid[1]}.{nid[2]}"
    gone = sorted(was - now)
    why = "; ".join(f"{g}: {_why(g, nid, new)}" for g in gone)
    if not now:
        return f"need {name} lost its match ({why}): no route"
    head = f"need {name} re-matched to {', '.join(sorted(now))}"
    return f"{head} (was {', '.join(sorted(was)) or 'nothing'}{'; ' + why if why else ''})"


def _why(match: str, nid: NeedId, new: Digest) -> str:
    """Why the need no longer uses ``match``: its agent's exclusion reason, or its service
    or agent left, or another ability ranks better."""
    agent, service, ability = match.split("/", 2)
    for key, reason in new.excluded.get(nid, {}).items():
        if key.endswith(f"/{agent}/{service}/{ability}"):
            return f"excluded, {reason}"
    if agent not in new.agents:
        return "its agent left"
    if (agent, service) not in new.services:
        return "its service left"
    return "another ability ranks better or it no longer matches"
