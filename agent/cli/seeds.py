"""``uma eval NAME --seeds 1-10``: one evaluation over many seeds, and the spread of its figures.

A figure measured on one seed may be a lucky one; run over several, each numeric figure is
reported per seed with its median and its worst value (and the seed that gave it), each
yes/no figure with the seeds on which it held.  "Worst" is the largest value, except for
the figures a plug-in declares better when higher (``EvalPlugin.higher_is_better``: shares,
percentages, counts of successes), where it is the smallest.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

#: more seeds than this is a typo, not an evaluation plan
MAX_SEEDS = 1000
#: leaves that identify a run rather than measure it
_NOT_FIGURES = {"seed"}


def parse_seeds(text: str) -> list[int]:
    """``"1-10"``, ``"3"``, ``"1,4,7-9"`` -> the seeds in order, each once; argparse shows the
    ``ArgumentTypeError``'s message as it is."""
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        lo, sep, hi = part.partition("-")
        try:
            a, b = (int(lo), int(hi)) if sep else (int(part), int(part))
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected seeds like 1-10 or 1,3,5-7 (non-negative integers), got {text!r}"
            ) from None
        if a < 0 or b < a:
            raise argparse.ArgumentTypeError(
                f"seed range {part!r} in {text!r} must go up from a non-negative seed")
        if b - a + 1 + len(seeds) > MAX_SEEDS:
            raise argparse.ArgumentTypeError(f"more than {MAX_SEEDS} seeds in {text!r}")
        seeds += [s for s in range(a, b + 1) if s not in seeds]
    return seeds


def spread(per_seed: dict[int, dict[str, Any]], higher_is_better: frozenset[str] = frozenset()
           ) -> dict[str, dict[str, Any]]:
    """Per flattened figure (``"a.b.c"``): numbers as median, worst and the worst's seed
    (runs where the figure is missing or not finite are counted, not averaged); booleans as
    the seeds where they held and failed.  Strings and lists are per-seed details only."""
    leaves: dict[str, dict[int, Any]] = {}
    names: dict[str, str] = {}  # path -> its leaf key (keys may hold dots themselves)
    for seed, figures in per_seed.items():
        for path, key, value in _flatten(figures):
            leaves.setdefault(path, {})[seed] = value
            names[path] = key
    out: dict[str, dict[str, Any]] = {}
    for path, values in leaves.items():
        if names[path] in _NOT_FIGURES:
            continue
        if all(isinstance(v, bool) for v in values.values()):
            out[path] = {"true_on": sum(values.values()), "of": len(per_seed),
                         "false_seeds": [s for s in per_seed if not values.get(s, False)]}
        elif all(_is_number(v) or v is None for v in values.values()):
            out[path] = _number_spread(names[path] in higher_is_better, values,
                                       list(per_seed))
    return out


def _number_spread(higher_is_better: bool, values: dict[int, Any], seeds: list[int]
                   ) -> dict[str, Any]:
    good = {s: float(v) for s, v in values.items() if v is not None and math.isfinite(v)}
    entry: dict[str, Any] = {"per_seed": [values.get(s) for s in seeds]}
    if good:
        pick = min if higher_is_better else max
        worst_seed = pick(good, key=good.__getitem__)
        vals = sorted(good.values())
        m = len(vals) // 2
        entry.update(median=vals[m] if len(vals) % 2 else 0.5 * (vals[m - 1] + vals[m]),
                     worst=good[worst_seed], worst_seed=worst_seed)
    if len(good) < len(seeds):
        entry["missing_or_not_finite"] = len(seeds) - len(good)
    return entry


def _flatten(figures: dict[str, Any], prefix: str = ""):
    for key, value in figures.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict):
            yield from _flatten(value, path + ".")
        else:
            yield path, key, value


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def format_spread(seeds: list[int], table: dict[str, dict[str, Any]]) -> str:
    """The spread as one line per figure, for people."""
    lines = [f"seeds: {' '.join(map(str, seeds))}"]
    for path, e in table.items():
        if "true_on" in e:
            failed = f" (false on seeds {', '.join(map(str, e['false_seeds']))})" \
                if e["false_seeds"] else ""
            lines.append(f"{path}: true on {e['true_on']} of {e['of']} seeds{failed}")
            continue
        per = " ".join("-" if v is None else f"{v:.4g}" for v in e["per_seed"])
        if len(set(e["per_seed"])) == 1 and "median" in e:
            lines.append(f"{path}: {e['median']:.6g} on every seed")
            continue
        if "median" in e:
            head = f"median {e['median']:.6g}, worst {e['worst']:.6g} (seed {e['worst_seed']})"
        else:
            head = "no finite value"
        lines.append(f"{path}: {head}; per seed: {per}")
    return "\n".join(lines)
