"""``uma eval NAME --seeds``: seed lists, the spread of per-seed figures, and the CLI."""

from __future__ import annotations

import argparse
import json
import math

import pytest

from agent.cli.seeds import format_spread, parse_seeds, spread
from tests.test_cli import uma


@pytest.mark.parametrize(("text", "seeds"), [
    ("1-10", list(range(1, 11))), ("3", [3]), ("1,4,7-9", [1, 4, 7, 8, 9]),
    (" 2 , 2-3 ", [2, 3]), ("0-0", [0]),
])
def test_seed_lists(text: str, seeds: list[int]) -> None:
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize(("text", "fragment"), [
    ("", "expected seeds like 1-10"), ("a-b", "expected seeds like 1-10"),
    ("1-", "expected seeds like 1-10"), ("5-2", "must go up"), ("-3", "expected seeds"),
    ("0-5000", "more than 1000 seeds"),
])
def test_bad_seed_lists_are_named(text: str, fragment: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=fragment):
        parse_seeds(text)


def test_spread_takes_median_and_worst_in_the_right_direction() -> None:
    per_seed = {
        1: {"seed": 1, "err": {"mean": 1.0}, "share": 0.9, "ok": True, "name": "x"},
        2: {"seed": 2, "err": {"mean": 3.0}, "share": 0.5, "ok": False, "name": "x"},
        3: {"seed": 3, "err": {"mean": 2.0}, "share": 0.7, "ok": True, "name": "x"},
        4: {"seed": 4, "err": {"mean": None}, "share": math.nan, "ok": True, "name": "x"},
    }
    for f in per_seed.values():  # a key holding a dot names one leaf, not a path
        f["cov"] = {"inside (ideal 0.95)": f["share"]}
    table = spread(per_seed, frozenset({"share", "inside (ideal 0.95)"}))
    assert set(table) == {"err.mean", "share", "ok", "cov.inside (ideal 0.95)"}
    assert table["cov.inside (ideal 0.95)"]["worst"] == 0.5
    assert table["err.mean"] == {"per_seed": [1.0, 3.0, 2.0, None], "median": 2.0,
                                 "worst": 3.0, "worst_seed": 2, "missing_or_not_finite": 1}
    assert table["share"]["worst"] == 0.5 and table["share"]["worst_seed"] == 2
    assert table["share"]["median"] == 0.7
    assert table["ok"] == {"true_on": 3, "of": 4, "false_seeds": [2]}
    text = format_spread([1, 2, 3, 4], table)
    assert "err.mean: median 2, worst 3 (seed 2); per seed: 1 3 2 -" in text
    assert "ok: true on 3 of 4 seeds (false on seeds 2)" in text
    same = format_spread([1, 2], spread({1: {"n": 5}, 2: {"n": 5}}))
    assert same.splitlines()[1] == "n: 5 on every seed"


@pytest.mark.parametrize(("args", "fragment"), [
    (["--seeds", "1-x"], "argument --seeds: expected seeds like 1-10"),
    (["--seeds", "1-3", "--seed", "2"], "not allowed with argument"),
])
def test_bad_seeds_on_the_command_line_exit_2(args: list[str], fragment: str) -> None:
    r = uma("eval", "predictor", *args)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert fragment in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.slow
def test_an_eval_over_seeds_reports_each_seed_and_the_spread() -> None:
    r = uma("eval", "alignment", "--seeds", "1-2", "--trials", "1", "--seconds", "20",
            "--json", timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["seeds"] == [1, 2]
    assert set(out["per_seed"]) == {"1", "2"}
    err = out["spread"]["time_offset.abs_error_ms_median"]
    per = [out["per_seed"][s]["time_offset"]["abs_error_ms_median"] for s in ("1", "2")]
    assert err["per_seed"] == per and err["worst"] == max(per)
    assert "seed 2 done (2 of 2)" in r.stderr
