"""An ability or need change re-matches only the needs it concerns (not every need of
a realm of 10,000 abilities and 1,000 needs), and the result is the
full re-match's, on random realms and random sequences of changes."""

from __future__ import annotations

import random

import pytest
from conftest import seeds

from agent.daemon.matching import (
    MAX_TOUCHED,
    Offer,
    OfferIndex,
    Requirement,
    match_all,
    rematch_all,
)
from schemas.models import Ability, Need

TYPES = ("pose6d", "position3d")
WHERE = (None, "frequency_hz >= 30", "latency_s < 0.02", "confidence > 0.5")
PREFER = (None, "latency_s", "cost", "pos_std_m + latency_s")


def random_offer(rng: random.Random, i: int) -> Offer:
    attrs = {k: v for k, v in (("frequency_hz", rng.choice([10, 30, 100])),
                               ("latency_s", rng.uniform(0.001, 0.04)),
                               ("confidence", rng.random()), ("cost", rng.choice([0, 1, 2])),
                               ("pos_std_m", rng.uniform(0.001, 0.01))) if rng.random() < 0.8}
    ab = Ability(name=f"a{i}", type=rng.choice(TYPES),
                 edge=(f"site{rng.randrange(3)}/cam{rng.randrange(4)}",
                       f"p{rng.randrange(5)}/head"), attributes=attrs)
    agent = f"host{rng.randrange(3)}"
    return Offer.of(f"uma/r/data/{agent}/svc{i}/a{i}", agent, f"svc{i}", ab)


def random_need(rng: random.Random, j: int) -> Requirement:
    need = Need(name=f"n{j}", type=rng.choice(TYPES),
                edge=(rng.choice(["*/cam*", f"site{j % 3}/*", "*/*", "site0/cam1"]),
                      rng.choice(["*/head", f"p{j % 5}/head"])),
                where=rng.choice(WHERE), prefer=rng.choice(PREFER),
                max_count=rng.choice([1, 1, 2]), standby=rng.choice([0, 0, 1, 2]))
    return Requirement.of(f"svc{rng.randrange(40)}", need)


class World:
    """A random realm that changes one step at a time, re-matched incrementally."""

    def __init__(self, seed: int, max_candidates: int) -> None:
        self.rng = rng = random.Random(seed)
        self.offers = [random_offer(rng, i) for i in range(40)]
        self.index = OfferIndex(self.offers, max_candidates=max_candidates)
        self.reqs = [random_need(rng, j) for j in range(25)]
        self.excluded: dict[tuple[str, str], set[str]] = {}
        self.current: dict[tuple[str, str], set[str]] = {}
        self.results = match_all(self.reqs, self.index, "host0")
        self.index.take_touched()

    def step(self) -> None:
        rng, n = self.rng, len(self.offers)
        kind = rng.randrange(6)
        if kind == 0:
            self.index.add(random_offer(rng, n + rng.randrange(1000)))
        elif kind == 1:  # the same ability, new attributes or edge
            old = rng.choice(list(self.index.by_key.values()))
            new = random_offer(rng, 0)
            self.index.add(Offer.of(old.key, old.agent_id, old.service_id, new.ability))
        elif kind == 2 and len(self.index) > 1:
            self.index.remove(rng.choice(list(self.index.by_key)))
        elif kind == 3:  # the monitor excludes (or readmits) a stream
            k = self.key(rng.choice(self.reqs))
            self.excluded[k] = set(rng.sample(list(self.index.by_key), rng.randrange(3)))
        elif kind == 4:  # the agent sent the chosen set: it is current now
            for k, r in self.results.items():
                self.current[k] = set(r.keys)
        elif rng.random() < 0.5:
            self.reqs.append(random_need(rng, len(self.reqs) + rng.randrange(100)))
        else:
            self.reqs.remove(rng.choice(self.reqs))

    @staticmethod
    def key(req: Requirement) -> tuple[str, str]:
        return (req.service_id, req.name)

    def rematch(self) -> dict:
        self.results = rematch_all(self.reqs, self.index, "host0", self.results,
                                   self.index.take_touched(), excluded=self.excluded,
                                   current=self.current)
        return self.results

    def full(self) -> dict:
        return match_all(self.reqs, self.index, "host0", excluded=self.excluded,
                         current=self.current)


@pytest.mark.parametrize("seed", seeds(6))
@pytest.mark.parametrize("max_candidates", [1024, 3])
def test_incremental_rematch_equals_the_full_one(seed: int, max_candidates: int) -> None:
    world = World(seed, max_candidates)
    kept = 0
    for _ in range(150):
        world.step()
        before = dict(world.results)
        assert world.rematch() == world.full()
        kept += sum(1 for k, r in world.results.items() if before.get(k) is r)
    assert kept > 0  # most changes concern few needs: their results were kept


def test_a_change_no_need_pattern_fits_rematches_nothing() -> None:
    world = World(1, 1024)
    before = world.rematch()
    elsewhere = Ability(name="x", type="pose6d", edge=("far/away", "nobody/knows"))
    world.index.add(Offer.of("uma/r/data/host9/x/x", "host9", "x", elsewhere))
    after = world.rematch()
    assert all(after[k] is before[k] for k in before)


def test_more_changes_than_the_journal_holds_rematch_everything() -> None:
    world = World(2, 1024)
    before = world.rematch()
    for i in range(MAX_TOUCHED + 1):
        world.index.add(random_offer(world.rng, 5000 + i))
    assert world.index.take_touched() is None
    after = rematch_all(world.reqs, world.index, "host0", before, None)
    assert after == world.full() and all(after[k] is not before[k] for k in before)
