"""Unit tests of agent.daemon.matching, one rule at a time."""

from __future__ import annotations

import math

import pytest

from agent.daemon.matching import (
    Offer,
    OfferIndex,
    Requirement,
    judge,
    match,
    match_all,
)
from schemas.models import Ability, Need


def offer(service: str, agent: str = "a", name: str = "pose", type_: str = "pose6d",
          edge=("ivy/world", "alice/head"), key=None, **attrs) -> Offer:
    ab = Ability(name=name, type=type_, edge=None if key else edge, key=key, attributes=attrs)
    return Offer.of(f"uma/r/data/{agent}/{service}/{name}", agent, service, ab)


def need(**kw) -> Requirement:
    kw.setdefault("name", "head")
    kw.setdefault("type", "pose6d")
    kw.setdefault("edge", ("ivy/world", "*/head"))
    return Requirement.of("consumer", Need(**kw))


def chosen_services(result) -> list[str]:
    return [c.offer.service_id for c in result.chosen]


def test_type_must_be_equal() -> None:
    idx = OfferIndex([offer("p", type_="position3d"), offer("q")])
    assert chosen_services(match(need(), idx, "a")) == ["q"]


def test_edge_wildcards_stay_within_one_segment() -> None:
    idx = OfferIndex([offer("deep", edge=("ivy/world", "x/alice/head")),
                      offer("other", edge=("ivy/world", "alice/hand")),
                      offer("good", edge=("ivy/world", "bob/head"))])
    r = match(need(), idx, "a")
    assert chosen_services(r) == ["good"]
    assert r.rejected == {}


def test_keyed_ability_matches_on_the_child_pattern() -> None:
    idx = OfferIndex([offer("rig", type_="accel_raw", key="marvin/accel"),
                      offer("cam", type_="accel_raw", key="marvin/other")])
    r = match(need(type="accel_raw", edge=("*", "marvin/accel")), idx, "a")
    assert chosen_services(r) == ["rig"]


def test_predicate_filters_and_missing_attribute_disqualifies() -> None:
    idx = OfferIndex([offer("slow", frequency_hz=10), offer("fast", frequency_hz=100),
                      offer("unknown")])
    r = match(need(where="frequency_hz >= 30"), idx, "a")
    assert chosen_services(r) == ["fast"]
    assert r.rejected["predicate false"] == 1
    assert r.rejected["predicate: no value for 'frequency_hz'"] == 1


def test_preference_is_minimised_and_missing_values_rank_last() -> None:
    idx = OfferIndex([offer("mid", latency_s=0.02), offer("best", latency_s=0.005),
                      offer("none"), offer("worst", latency_s=0.1)])
    r = match(need(prefer="latency_s", max_count=4), idx, "a")
    assert chosen_services(r) == ["best", "mid", "worst", "none"]
    assert r.chosen[0].score == pytest.approx(0.005)
    assert math.isinf(r.chosen[-1].score)


def test_local_wins_a_tie_then_current_then_key() -> None:
    idx = OfferIndex([offer("r1", agent="b", latency_s=0.01),
                      offer("l1", agent="a", latency_s=0.01),
                      offer("better_remote", agent="b", latency_s=0.001)])
    assert chosen_services(match(need(prefer="latency_s"), idx, "a")) == ["better_remote"]
    idx.remove("uma/r/data/b/better_remote/pose")
    assert chosen_services(match(need(prefer="latency_s"), idx, "a")) == ["l1"]
    # among equals, the connected one stays
    idx2 = OfferIndex([offer("x", agent="b"), offer("y", agent="b")])
    assert chosen_services(match(need(), idx2, "a")) == ["x"]
    assert chosen_services(match(need(), idx2, "a",
                                 current={"uma/r/data/b/y/pose"})) == ["y"]


def test_multiplicity_min_and_max() -> None:
    idx = OfferIndex([offer(f"s{i}", cost=i) for i in range(5)])
    r = match(need(prefer="cost", min_count=2, max_count=3), idx, "a")
    assert chosen_services(r) == ["s0", "s1", "s2"]
    assert r.satisfied and r.qualified == 5
    r = match(need(where="cost >= 4", min_count=2, max_count=3), idx, "a")
    assert chosen_services(r) == ["s4"]
    assert not r.satisfied


def test_standby_is_the_next_best_after_the_chosen() -> None:
    idx = OfferIndex([offer(f"s{i}", cost=i) for i in range(5)] + [offer("x", cost=9)])
    r = match(need(prefer="cost", where="cost != 1", max_count=2, standby=2), idx, "a")
    assert chosen_services(r) == ["s0", "s2"]
    assert [c.offer.service_id for c in r.standby] == ["s3", "s4"]
    assert match(need(prefer="cost"), idx, "a").standby == ()  # none unless asked for
    few = match(need(prefer="cost", where="cost < 2", standby=3), idx, "a")
    assert chosen_services(few) == ["s0"] and [c.offer.service_id for c in few.standby] == ["s1"]


def test_exactly_min_count_qualified_satisfies_and_one_fewer_does_not() -> None:
    """The boundary of the multiplicity rule: ``qualified == min_count`` is enough."""
    idx = OfferIndex([offer(f"s{i}", cost=i) for i in range(5)])
    r = match(need(where="cost >= 3", min_count=2, max_count=3), idx, "a")
    assert r.qualified == 2 and r.satisfied
    assert chosen_services(r) == ["s3", "s4"]
    r = match(need(where="cost >= 3", min_count=3, max_count=3), idx, "a")
    assert r.qualified == 2 and not r.satisfied


def test_measured_values_judge_a_connected_stream() -> None:
    o = offer("cam", frequency_hz=100, latency_s=0.001)
    req = need(where="frequency_hz >= 30 and latency_s < 0.1")
    assert judge(req, o, {"measured_frequency_hz": 99.0, "measured_latency_s": 0.002}) == (
        True, "")
    assert judge(req, o, {"measured_frequency_hz": 12.0}) == (False, "predicate false")
    assert judge(req, o, {"measured_latency_s": 0.3}) == (False, "predicate false")
    assert o.values["frequency_hz"] == 100.0  # the offer itself is untouched
    explicit = need(where="measured_frequency_hz >= 30")
    assert judge(explicit, o, {"measured_frequency_hz": 12.0})[0] is False


def test_measured_names_stand_for_advertised_ones_when_matching() -> None:
    idx = OfferIndex([offer("slow", frequency_hz=10), offer("fast", frequency_hz=100)])
    r = match(need(where="measured_frequency_hz >= 30"), idx, "a")
    assert chosen_services(r) == ["fast"]


def test_excluded_abilities_are_skipped() -> None:
    idx = OfferIndex([offer("a1", cost=1), offer("a2", cost=2)])
    r = match(need(prefer="cost"), idx, "a", excluded={"uma/r/data/a/a1/pose"})
    assert chosen_services(r) == ["a2"] and r.rejected == {"measured": 1}


def test_a_service_never_matches_itself() -> None:
    idx = OfferIndex([offer("consumer"), offer("consumer", agent="b")])
    assert [c.offer.agent_id for c in match(need(), idx, "a").chosen] == ["b"]


def test_division_by_zero_in_preference_ranks_last_not_first() -> None:
    idx = OfferIndex([offer("zero", cost=0), offer("one", cost=1)])
    r = match(need(prefer="1 / cost", max_count=2), idx, "a")
    assert chosen_services(r) == ["one", "zero"]


def test_index_replace_and_match_all() -> None:
    idx = OfferIndex([offer("p", cost=5)])
    reqs = [need(name="n1"), need(name="n2", where="cost > 3")]
    out = match_all(reqs, idx, "a")
    assert chosen_services(out[("consumer", "n1")]) == ["p"]
    assert chosen_services(out[("consumer", "n2")]) == ["p"]
    idx.add(offer("p", cost=1))  # same key: replaced, not duplicated
    assert len(idx) == 1 and len(idx.by_type["pose6d"]) == 1
    out = match_all(reqs, idx, "a")
    assert chosen_services(out[("consumer", "n2")]) == []
    # the cached candidates follow additions and removals
    idx.add(offer("q", edge=("ivy/world", "bob/head")))
    idx.add(offer("z", edge=("ivy/world", "bob/hand")))
    assert sorted(chosen_services(match(need(max_count=3), idx, "a"))) == ["p", "q"]
    idx.remove("uma/r/data/a/p/pose")
    assert chosen_services(match(need(max_count=3), idx, "a")) == ["q"]
