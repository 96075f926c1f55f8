"""Cost of matching 100 needs against 1,000 abilities (one full re-match of an agent).

The realm: 1,000 abilities of mixed types on edges ``site{i}/cam{j} -> person{k}/head`` with
random attributes; 100 needs with wildcard edge patterns, a predicate and a preference.
Measured: ``match_all`` cold (a fresh ``OfferIndex``, i.e. every edge pattern tested) and
warm (the agent's steady state: one ability changed in a kept index, then every need
re-matched, which is what an agent does on every realm change).
Baseline, in the same run: the naive matcher that re-parses the need's expressions and
re-tests every edge pattern for every (need, ability) pair, as a matcher without
compiled needs or an index would.

    python bench/bench_matching.py [--abilities 1000] [--needs 100] [--repeat 30] [--json]
"""

from __future__ import annotations

import argparse
import json
import random
import time

from summary import median_p99

from agent.daemon.matching import Offer, OfferIndex, Requirement, match_all
from schemas import expr
from schemas.models import Ability, Need, frame_matches

TYPES = ("pose6d", "position3d", "rotation3d")
PREDICATES = ("frequency_hz >= 30", "latency_s <= 0.02 and confidence >= 0.5",
              "frequency_hz >= 60 or pos_std_m < 0.01", "not (cost > 5)")
PREFERENCES = ("latency_s", "pos_std_m + 0.1 * latency_s", "cost", "-frequency_hz")


def realm(n_abilities: int, n_needs: int, seed: int) -> tuple[list[Offer], list[Requirement]]:
    rnd = random.Random(seed)
    offers = []
    for i in range(n_abilities):
        attrs = {"frequency_hz": rnd.choice([10, 30, 60, 100, 200]),
                 "latency_s": rnd.uniform(0.001, 0.05), "confidence": rnd.random(),
                 "pos_std_m": rnd.uniform(0.001, 0.05), "cost": rnd.uniform(0, 10)}
        ab = Ability(name=f"a{i}", type=rnd.choice(TYPES),
                     edge=(f"site{i % 7}/cam{i % 13}", f"person{i % 17}/head"),
                     attributes=attrs)
        agent = f"host{i % 10}"
        offers.append(Offer.of(f"uma/bench/data/{agent}/svc{i}/a{i}", agent, f"svc{i}", ab))
    reqs = []
    for j in range(n_needs):
        need = Need(name=f"n{j}", type=rnd.choice(TYPES),
                    edge=(rnd.choice(["*/cam*", f"site{j % 7}/*", "*/*"]),
                          rnd.choice(["*/head", f"person{j % 17}/head", "person1*/*"])),
                    where=rnd.choice(PREDICATES), prefer=rnd.choice(PREFERENCES),
                    max_count=rnd.choice([1, 1, 2, 3]))
        reqs.append(Requirement.of(f"consumer{j % 5}", need))
    return offers, reqs


def naive(reqs: list[Requirement], offers: list[Offer]) -> dict[tuple[str, str], list[str]]:
    """Re-parse and re-test everything per pair (the baseline)."""
    out = {}
    for r in reqs:
        n = r.need
        ranked = []
        for o in offers:
            a = o.ability
            if a.type != n.type or not (frame_matches(n.edge[0], a.edge[0])
                                        and frame_matches(n.edge[1], a.edge[1])):
                continue
            values = a.attributes.numeric()
            try:
                if n.where and not expr.parse(n.where).evaluate(values):
                    continue
                s = float(expr.parse(n.prefer).evaluate(values)) if n.prefer else 0.0
            except expr.ExprError:
                continue
            ranked.append((s, o.agent_id != "host0", o.key))
        ranked.sort()
        out[(r.service_id, n.name)] = [k for _, _, k in ranked[:n.max_count]]
    return out


def timed(fn, repeat: int) -> list[float]:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--abilities", type=int, default=1000)
    ap.add_argument("--needs", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=30, help="timed runs of the fast matcher")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    args = ap.parse_args()
    offers, reqs = realm(args.abilities, args.needs, args.seed)

    index = OfferIndex(offers)
    fast_result = match_all(reqs, index, "host0")
    slow_result = naive(reqs, offers)
    if {k: list(v.keys) for k, v in fast_result.items()} != slow_result:
        raise SystemExit("the fast and the naive matcher disagree: benchmark invalid")

    build = timed(lambda: OfferIndex(offers), max(3, args.repeat // 5))
    cold = timed(lambda: match_all(reqs, OfferIndex(offers), "host0"), args.repeat)
    changing = iter(offers * (args.repeat + 1))

    def one_change() -> None:
        index.add(next(changing))
        match_all(reqs, index, "host0")
    warm = timed(one_change, args.repeat)
    base = timed(lambda: naive(reqs, offers), max(3, args.repeat // 10))
    matched = sum(1 for r in fast_result.values() if r.chosen)
    figures = {
        "abilities": args.abilities, "needs": args.needs, "needs_matched": matched,
        "index_build_median_ms": median_p99([1e3 * x for x in build], "ms")["median_ms"],
    }
    for name, xs in (("match_all_cold", cold), ("match_all_warm", warm),
                     ("baseline_naive", base)):
        for k, v in median_p99([1e3 * x for x in xs], "ms").items():
            figures[f"{name}_{k}"] = v
    figures["speedup_cold"] = (figures["baseline_naive_median_ms"]
                               / figures["match_all_cold_median_ms"])
    figures["speedup_warm"] = (figures["baseline_naive_median_ms"]
                               / figures["match_all_warm_median_ms"])
    for k, v in figures.items():
        print(f"{k:28s} {v:.3f}" if isinstance(v, float) else f"{k:28s} {v}")
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
