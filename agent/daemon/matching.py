"""Needs/Abilities matching (DWARF's service manager rule), pure: no I/O, no clocks.

An agent matches each need of its local services against every ability of the realm:

1. **type** equal;
2. **edge** fits the need's edge patterns (``*`` within one segment, ``frame_matches``); an
   ability published under a ``key`` instead of an edge (``accel_raw``, ``image``, ...) fits
   when the key matches the need's *child* pattern;
3. **predicate** (``where``) true over the ability's advertised numeric attributes.  The
   names ``measured_frequency_hz`` / ``measured_latency_s`` stand for the advertised
   ``frequency_hz`` / ``latency_s`` here; what was really measured on a connected stream is
   judged by the agent (``agent.daemon.monitor``), with a grace period, through ``judge``: there the
   measured values *replace* ``frequency_hz`` / ``latency_s``, so ``frequency_hz >= 30``
   holds the rate really delivered to account.  An ability lacking a name the predicate uses
   does not qualify;
4. **rank** by the preference (``prefer``, minimised) over the advertised attributes only
   (ranking one ability by measured and another by advertised values would make needs
   flap); an ability lacking a name it uses ranks after all that have it; then local
   before remote, then the currently connected one
   (no needless moves between equals), then the data key (a total, stable order);
5. **multiplicity**: the best ``max_count`` are chosen; the need is *satisfied* when at least
   ``min_count`` qualify; the next ``standby`` qualified ones are its standby (the service
   keeps them subscribed and delivers their samples while a chosen one is silent).

Abilities the agent has *excluded* for a need (their measured rate/latency failed the
predicate for longer than the grace period) are skipped.

Speed: needs are compiled once (``Requirement``) and ``OfferIndex`` keeps, per distinct
(type, edge patterns), the abilities that fit, updated incrementally as abilities come and
go; a match then costs one compiled predicate and preference call per fitting ability.
A result remembers what it was computed from (the need, its exclusions and current keys,
whether its candidates were complete), and the index journals the abilities it gained or
lost (``take_touched``), so after one change ``rematch`` keeps the result of every need
whose edge patterns fit no touched ability and patches the others with the touched
abilities alone (matching anew only when a chosen or standby ability changed or left,
since the next best is not kept): a change in a realm of 10,000 abilities and 1,000 needs
costs a few predicate calls per need it concerns, not one per need and ability.
``bench/bench_matching.py`` and ``bench/bench_scale.py`` measure it.

Bounds: abilities come from any peer of the realm, so the index keeps at most
``MAX_CANDIDATES`` fitting abilities per pattern (the first that came; later ones are
refused and counted in ``refused`` and reported through ``on_refused``; a removal lets the
pattern be searched again) and at most ``MAX_PATTERNS`` patterns (least recently used
forgotten first, recomputed when asked again).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache

from schemas import expr
from schemas.models import Ability, Need, frame_matches

Values = Mapping[str, float]
#: Measured attributes and the advertised attribute each one overrides.
MEASURED_OVERRIDES = {"measured_frequency_hz": "frequency_hz",
                      "measured_latency_s": "latency_s"}
#: abilities kept per need pattern, and need patterns kept (module docstring)
MAX_CANDIDATES = 1024
MAX_PATTERNS = 1024
#: abilities journalled between two ``take_touched``: beyond, everything is matched again
#: (as cheap as sifting a longer journal), and an index nobody reads stays bounded
MAX_TOUCHED = 1024
Pattern = tuple[str, str, str]  # (type, parent pattern, child pattern)
#: a journalled offer: the version added (True) or removed (False)
Touch = tuple["Offer", bool]


@dataclass(frozen=True, slots=True)
class Offer:
    """One ability somewhere in the realm, flattened for matching.

    ``key`` (its data key) identifies it uniquely; ``values`` are its numeric attributes
    (computed once, when the descriptor arrives).
    """

    key: str
    agent_id: str
    service_id: str
    ability: Ability
    values: Mapping[str, float]
    type: str
    #: ``(parent, child)`` of an edge ability, ``(None, key)`` of a keyed one
    target: tuple[str | None, str]

    @classmethod
    def of(cls, key: str, agent_id: str, service_id: str, ability: Ability) -> Offer:
        a = ability
        target = (a.edge[0], a.edge[1]) if a.edge is not None else (None, str(a.key))
        return cls(key, agent_id, service_id, a, advertised_values(a.attributes.numeric()),
                   a.type, target)


@dataclass(frozen=True, slots=True)
class Requirement:
    """A need compiled for matching (expressions parsed once by ``schemas.models.Need``)."""

    service_id: str
    need: Need
    where: expr.Expr | None
    prefer: expr.Expr | None

    @classmethod
    def of(cls, service_id: str, need: Need) -> Requirement:
        return cls(service_id, need, need.where_expr, need.prefer_expr)

    @property
    def name(self) -> str:
        return self.need.name


@dataclass(frozen=True, slots=True)
class Choice:
    """A chosen ability and why: its score under the preference, whether it is local."""

    offer: Offer
    score: float
    local: bool


@dataclass(frozen=True)
class MatchResult:
    """The outcome for one need: the chosen abilities (best first), its standby (the next
    best, module docstring) and a tally of why the other abilities of its type and edge
    were rejected."""

    requirement: Requirement
    chosen: tuple[Choice, ...]
    qualified: int
    rejected: Mapping[str, int] = field(default_factory=dict)
    #: the data keys excluded and current when it was computed, and its candidates
    #: (``OfferIndex.searched``): what ``rematch`` relies on
    excluded: frozenset[str] = frozenset()
    current: frozenset[str] = frozenset()
    searched: tuple[int, bool] = field(default=(0, True), compare=False)
    standby: tuple[Choice, ...] = ()

    @property
    def satisfied(self) -> bool:
        return self.qualified >= self.requirement.need.min_count

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(c.offer.key for c in self.chosen)


class OfferIndex:
    """The realm's abilities by data key and type, with the candidates of each need pattern.

    ``candidates(need)`` (type + edge patterns) is computed once per distinct pattern and then
    kept up to date by ``add``/``remove``, so a re-match after one ability changed tests the
    edge patterns of that ability only.  ``on_refused(pattern, key, refused)`` is told of
    each ability a full pattern refuses (module docstring, "Bounds").
    """

    def __init__(self, offers: Iterable[Offer] = (), *, max_candidates: int = MAX_CANDIDATES,
                 max_patterns: int = MAX_PATTERNS,
                 on_refused: Callable[[Pattern, str, int], None] | None = None) -> None:
        self.by_key: dict[str, Offer] = {}
        self.by_type: dict[str, dict[str, Offer]] = {}
        self.max_candidates, self.max_patterns = max_candidates, max_patterns
        self.on_refused = on_refused
        #: abilities a full pattern refused (each time the pattern was searched)
        self.refused = 0
        self._candidates: OrderedDict[Pattern, dict[str, Offer]] = OrderedDict()
        self._full: set[Pattern] = set()  # patterns that refused an ability
        #: each kept pattern's search: a new number whenever it is searched anew
        self._search: dict[Pattern, int] = {}
        self._searches = 0
        #: offers added or removed since ``take_touched`` (None: too many)
        self._touched: list[Touch] | None = []
        for o in offers:
            self.add(o)

    def take_touched(self) -> list[Touch] | None:
        """The offers added (True) or removed (False) since the last call, in order (a
        replacement is both), and a fresh journal; None when more than ``MAX_TOUCHED``
        were: then any need may have changed."""
        touched, self._touched = self._touched, []
        return touched

    def _touch(self, offer: Offer, present: bool) -> None:
        if self._touched is not None:
            self._touched.append((offer, present))
            if len(self._touched) > MAX_TOUCHED:
                self._touched = None

    def add(self, offer: Offer) -> None:
        """Add or replace (same data key) an offer."""
        self.remove(offer.key)
        self._touch(offer, True)
        self.by_key[offer.key] = offer
        self.by_type.setdefault(offer.type, {})[offer.key] = offer
        for pattern, found in self._candidates.items():
            if pattern[0] == offer.type and _fits(pattern[1], pattern[2], offer):
                self._admit(pattern, found, offer)

    def remove(self, key: str) -> None:
        old = self.by_key.pop(key, None)
        if old is None:
            return
        self._touch(old, False)
        del self.by_type[old.type][key]
        for pattern, found in list(self._candidates.items()):
            if pattern[0] == old.type and found.pop(key, None) is not None and (
                    pattern in self._full):
                del self._candidates[pattern]  # room again: search anew when asked
                del self._search[pattern]
                self._full.discard(pattern)

    def __len__(self) -> int:
        return len(self.by_key)

    def candidates(self, need: Need) -> Iterable[Offer]:
        """Offers of the need's type whose edge (or key) fits its patterns."""
        pattern = (need.type, need.edge[0], need.edge[1])
        found = self._candidates.get(pattern)
        if found is not None:
            self._candidates.move_to_end(pattern)
            return found.values()
        found = self._candidates[pattern] = {}
        self._searches += 1
        self._search[pattern] = self._searches
        for o in self.by_type.get(need.type, {}).values():
            if _fits(need.edge[0], need.edge[1], o):
                self._admit(pattern, found, o)
        if len(self._candidates) > self.max_patterns:
            oldest, _ = self._candidates.popitem(last=False)
            del self._search[oldest]
            self._full.discard(oldest)
        return found.values()

    def searched(self, need: Need) -> tuple[int, bool]:
        """The need's pattern's search (its number changes whenever the candidates are
        searched anew) and whether every fitting offer is among them (no bound refused
        one).  While a bound refuses, the candidates change only by a new search (a
        removal empties the pattern; additions are refused)."""
        self.candidates(need)
        pattern = (need.type, need.edge[0], need.edge[1])
        return self._search[pattern], pattern not in self._full

    def _admit(self, pattern: Pattern, found: dict[str, Offer], offer: Offer) -> None:
        if len(found) < self.max_candidates:
            found[offer.key] = offer
            return
        self.refused += 1
        self._full.add(pattern)
        if self.on_refused is not None:
            self.on_refused(pattern, offer.key, self.refused)


@lru_cache(maxsize=65536)
def _frame_fits(pattern: str, frame: str) -> bool:
    return frame_matches(pattern, frame)


def _fits(parent_pattern: str, child_pattern: str, offer: Offer) -> bool:
    parent, child = offer.target
    return _frame_fits(child_pattern, child) and (
        parent is None or _frame_fits(parent_pattern, parent))


def _candidate_of(need: Need, offer: Offer) -> bool:
    """Whether the offer fits the need's type and edge patterns (bounds aside)."""
    return offer.type == need.type and _fits(need.edge[0], need.edge[1], offer)


def advertised_values(attributes: Values) -> dict[str, float]:
    """An ability's numeric attributes plus the ``measured_*`` names standing for their
    advertised counterparts (so a predicate using them can match before any measurement)."""
    values = dict(attributes)
    for measured_name, advertised in MEASURED_OVERRIDES.items():
        if advertised in values:
            values[measured_name] = values[advertised]
    return values


def measured_values(offer: Offer, measured: Values) -> Values:
    """The values a predicate judges a connected stream by: the advertised ones, with what
    was measured replacing both the ``measured_*`` names and their advertised twins."""
    values = dict(offer.values)
    for name, value in measured.items():
        values[name] = value
        advertised = MEASURED_OVERRIDES.get(name)
        if advertised is not None:
            values[advertised] = value
    return values


def qualifies(req: Requirement, values: Values) -> tuple[bool, str]:
    """``(True, "")`` if the predicate holds, else ``(False, reason)``."""
    if req.where is None:
        return True, ""
    try:
        ok = bool(req.where.evaluate(values))
    except expr.ExprError as exc:
        return False, f"predicate: {exc.reason}"
    return ok, "" if ok else "predicate false"


def score(req: Requirement, values: Values) -> float:
    """The preference value (minimised); ``inf`` when the offer lacks a name it uses."""
    if req.prefer is None:
        return 0.0
    try:
        v = float(req.prefer.evaluate(values))
    except expr.ExprError:
        return math.inf
    return v if math.isfinite(v) else math.inf


def judge(req: Requirement, offer: Offer, measured: Values) -> tuple[bool, str]:
    """Whether a connected stream's *measured* values still satisfy the need's predicate."""
    return qualifies(req, measured_values(offer, measured))


Ranked = tuple[float, int, int, str, Choice]


def _rank(req: Requirement, offer: Offer, local_agent: str, excluded: Collection[str],
          current: Collection[str]) -> Ranked | str | None:
    """One candidate's verdict for a need: its rank (sorted by its first four fields), or
    why it was rejected, or None for the need's own service's ability (never a match)."""
    if offer.service_id == req.service_id and offer.agent_id == local_agent:
        return None
    if offer.key in excluded:
        return "measured"
    ok, reason = qualifies(req, offer.values)
    if not ok:
        return reason
    s = score(req, offer.values)
    local = offer.agent_id == local_agent
    return (s, 0 if local else 1, 0 if offer.key in current else 1, offer.key,
            Choice(offer, s, local))


def _result(req: Requirement, ranked: list[Ranked], qualified: int, rejected: dict[str, int],
            excluded: Collection[str], current: Collection[str],
            searched: tuple[int, bool]) -> MatchResult:
    ranked.sort(key=lambda r: r[:4])
    n, standby = req.need.max_count, req.need.standby
    chosen = tuple(r[4] for r in ranked[:n])
    return MatchResult(req, chosen, qualified, rejected, frozenset(excluded),
                       frozenset(current), searched, tuple(r[4] for r in ranked[n:n + standby]))


def match(req: Requirement, index: OfferIndex, local_agent: str, *,
          excluded: Collection[str] = (), current: Collection[str] = ()) -> MatchResult:
    """Match one need against the realm (see the module docstring for the rules).

    ``excluded``: data keys this need must not use; ``current``: data keys it is connected
    to now (kept on ties).  A service never matches its own abilities.
    """
    rejected: dict[str, int] = {}
    ranked: list[Ranked] = []
    for offer in index.candidates(req.need):
        r = _rank(req, offer, local_agent, excluded, current)
        if isinstance(r, str):
            rejected[r] = rejected.get(r, 0) + 1
        elif r is not None:
            ranked.append(r)
    return _result(req, ranked, len(ranked), rejected, excluded, current,
                   index.searched(req.need))


def rematch(previous: MatchResult | None, req: Requirement, index: OfferIndex,
            local_agent: str, touched: list[Touch] | None, *,
            excluded: Collection[str] = (), current: Collection[str] = ()) -> MatchResult:
    """What ``match`` gives now, from ``previous`` and the offers ``touched`` since it was
    computed (``OfferIndex.take_touched``; None: unknown): ``previous`` itself when no
    touched offer fits the need's patterns, or when a bound refused candidates then and
    the same search holds them now (they did not change); else ``previous`` patched with
    the touched offers; else (the need, its exclusions or current keys changed, a bound
    refuses candidates, a chosen ability changed or left) a match anew."""
    if (previous is None or touched is None or previous.requirement != req
            or previous.excluded != frozenset(excluded)
            or previous.current != frozenset(current)):
        return match(req, index, local_agent, excluded=excluded, current=current)
    need = req.need
    mine = [(o, present) for o, present in touched if _candidate_of(need, o)]
    if not mine:
        return previous
    search, complete = index.searched(need)
    if not previous.searched[1] and search == previous.searched[0]:
        return previous
    patched = _patch(previous, index, local_agent, mine) if (
        complete and previous.searched[1]) else None
    return patched if patched is not None else match(req, index, local_agent,
                                                     excluded=excluded, current=current)


def _patch(previous: MatchResult, index: OfferIndex, local_agent: str,
           touched: list[Touch]) -> MatchResult | None:
    """``previous`` with each touched key's version before (the first journalled, if it
    was a removal) taken out and its version now (if it fits) put in; None when a chosen
    or standby ability is among them (the next best is not kept).  Both results'
    candidates must be complete (every fitting offer).  The best ``max_count + standby``
    of the kept and the new are the best of all: every other candidate ranked after the
    kept ones, which are all still there."""
    req = previous.requirement
    need = req.need
    before: dict[str, Offer | None] = {}
    for offer, present in touched:
        before.setdefault(offer.key, None if present else offer)
    kept = previous.chosen + previous.standby
    if any(c.offer.key in before for c in kept):
        return None
    ex, cur = previous.excluded, previous.current
    ranked = [r for c in kept
              if isinstance(r := _rank(req, c.offer, local_agent, ex, cur), tuple)]
    qualified, rejected = previous.qualified, dict(previous.rejected)
    for key, old in before.items():
        new = index.by_key.get(key)
        if new is not None and not _candidate_of(need, new):
            new = None
        for offer, sign in ((old, -1), (new, 1)):
            r = None if offer is None else _rank(req, offer, local_agent, ex, cur)
            if isinstance(r, str):
                rejected[r] = rejected.get(r, 0) + sign
                if not rejected[r]:
                    del rejected[r]
            elif r is not None:
                qualified += sign
                if sign > 0:
                    ranked.append(r)
    return _result(req, ranked, qualified, rejected, ex, cur, index.searched(need))


def match_all(reqs: Iterable[Requirement], index: OfferIndex, local_agent: str, *,
              excluded: Mapping[tuple[str, str], Collection[str]] | None = None,
              current: Mapping[tuple[str, str], Collection[str]] | None = None,
              ) -> dict[tuple[str, str], MatchResult]:
    """Match many needs; keys of ``excluded``/``current`` and of the result are
    ``(service_id, need name)``."""
    return rematch_all(reqs, index, local_agent, {}, None, excluded=excluded, current=current)


def rematch_all(reqs: Iterable[Requirement], index: OfferIndex, local_agent: str,
                previous: Mapping[tuple[str, str], MatchResult], touched: list[Touch] | None,
                *, excluded: Mapping[tuple[str, str], Collection[str]] | None = None,
                current: Mapping[tuple[str, str], Collection[str]] | None = None,
                ) -> dict[tuple[str, str], MatchResult]:
    """``match_all`` after a change, each need through ``rematch`` from its ``previous``
    result (``touched``: as ``index.take_touched()`` gave it)."""
    excluded = excluded or {}
    current = current or {}
    out = {}
    for req in reqs:
        k = (req.service_id, req.name)
        ex, cur = excluded.get(k, ()), current.get(k, ())
        out[k] = rematch(previous.get(k), req, index, local_agent, touched, excluded=ex,
                         current=cur)
    return out
