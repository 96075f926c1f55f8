"""The safe expression language: grammar, types, evaluation, errors with positions, no eval."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.expr import MAX_DEPTH, MAX_LENGTH, ExprError, parse

VALUES = {"a": 2.0, "b": 3.0, "c": -4.0, "static": 1.0, "flag": True, "zero": 0.0}


@pytest.mark.parametrize(("text", "expected"), [
    ("1", 1.0), ("2.5e-1", 0.25), (".5", 0.5), ("3.", 3.0),
    ("1 + 2 * 3", 7.0), ("(1 + 2) * 3", 9.0), ("8 / 2 / 2", 2.0), ("10 - 2 - 3", 5.0),
    ("-a * b", -6.0), ("- - a", 2.0), ("-(a + b)", -5.0),
    ("min(a, b, c)", -4.0), ("max(a, b, c)", 3.0), ("min(a)", 2.0), ("abs(c)", 4.0),
    ("max(a, 2 * b) - abs(c) / 2", 4.0),
    ("a < b", True), ("a <= 2", True), ("a > b", False), ("b >= 3", True),
    ("a == 2", True), ("a != 2", False),
    ("a < b and b < 1", False), ("a < b or b < 1", True), ("not a < b", False),
    ("true", True), ("false or true", True), ("not false and false", False),
    ("a < b or b < 1 and false", True),  # and binds tighter than or
    ("static == true", True), ("not zero", True), ("flag and a > 1", True),
    ("min(1, 2) == 1", True), ("a * 0.5 + 1 >= a", True),
])
def test_evaluates_like_arithmetic(text: str, expected: float | bool) -> None:
    value = parse(text).evaluate(VALUES)
    assert value == expected
    assert type(value) is type(expected) or isinstance(expected, float)


def test_names_and_predicate_flags() -> None:
    e = parse("frequency_hz >= 100 and latency_s <= 0.01")
    assert e.names == {"frequency_hz", "latency_s"}
    assert e.is_predicate
    assert e.text == "frequency_hz >= 100 and latency_s <= 0.01"
    assert e.evaluate({"frequency_hz": 120, "latency_s": 0.005}) is True
    assert e.evaluate({"frequency_hz": 60, "latency_s": 0.005}) is False
    assert not parse("latency_s + 0.1 * pos_std_m").is_predicate
    assert not parse("static").is_predicate  # a bare name's type is unknown until evaluated
    assert parse("(a < b)").is_predicate
    assert parse("min(a, b)").names == {"a", "b"}
    # min/max/abs are names unless called
    assert parse("max + 1").evaluate({"max": 1.0}) == 2.0


def test_names_restricted_when_given() -> None:
    assert parse("a + b", names=["a", "b"]).names == {"a", "b"}
    with pytest.raises(ExprError) as err:
        parse("a + freq", names=["a", "b"])
    assert err.value.position == 4
    assert str(err.value).startswith("unknown name 'freq' at 4 (known: a, b)")


@pytest.mark.parametrize(("text", "position", "fragment"), [
    ("", 0, "empty expression"),
    ("   ", 0, "empty expression"),
    ("a +", 3, "got end of expression"),
    ("(a + b", 6, "expected ')'"),
    ("a + b)", 5, "expected an operator or the end"),
    ("a b", 2, "got 'b'"),
    ("2a", 1, "got 'a'"),
    ("a = 1", 2, "use '=='"),
    ("a && b", 2, "use 'and'"),
    ("a || b", 2, "use 'or'"),
    ("!a", 0, "use 'not'"),
    ("a ** 2", 2, "powers are not supported"),
    ("a $ b", 2, "unexpected character '$'"),
    ("'a'", 0, "unexpected character"),
    ("a < b < c", 6, "cannot be chained"),
    ("1 + true", 4, "'+' needs a number, got a boolean"),
    ("-(a < b)", 1, "unary '-' needs a number"),
    ("not 3", 4, "'not' needs a boolean, got a number"),
    ("1 and a", 0, "'and' needs a boolean"),
    ("a or 2", 5, "'or' needs a boolean"),
    ("true < 1", 0, "'<' needs a number"),
    ("true == 1", 5, "compares a boolean with a number"),
    ("min(a < b, 1)", 4, "min() needs a number"),
    ("abs(a, b)", 0, "abs() takes 1 argument"),
    ("abs()", 4, "expected a number"),
    ("foo(a)", 0, "unknown function 'foo'"),
    ("__import__(a)", 0, "unknown function '__import__'"),
    ("a.b", 1, "unexpected character '.'"),
    ("1e999", 0, "out of range"),
    ("min(a,)", 6, "expected a number"),
])
def test_errors_point_at_the_culprit(text: str, position: int, fragment: str) -> None:
    with pytest.raises(ExprError) as err:
        parse(text)
    e = err.value
    assert e.position == position, str(e)
    assert fragment in str(e)
    assert isinstance(e, ValueError)
    # the message quotes the text and puts a caret under the position
    lines = str(e).splitlines()
    assert f" at {position}" in lines[0]
    assert lines[1] == f"  {text}"
    assert lines[2] == "  " + " " * position + "^"


def test_limits() -> None:
    long = "a + " * (MAX_LENGTH // 4) + "a"
    with pytest.raises(ExprError, match=f"longer than {MAX_LENGTH}"):
        parse(long)
    assert parse("(" * (MAX_DEPTH - 1) + "1" + ")" * (MAX_DEPTH - 1)).evaluate({}) == 1.0
    with pytest.raises(ExprError, match="nested deeper"):
        parse("(" * (MAX_DEPTH + 1) + "1" + ")" * (MAX_DEPTH + 1))
    with pytest.raises(ExprError, match="nested deeper"):
        parse("-" * (MAX_DEPTH + 5) + "1")
    with pytest.raises(ExprError, match="nested deeper"):
        parse("not " * (MAX_DEPTH + 5) + "true")
    with pytest.raises(ExprError, match="expected a string"):
        parse(42)  # type: ignore[arg-type]


def test_evaluation_errors_name_the_culprit() -> None:
    e = parse("frequency_hz >= 30 and latency_s < 1")
    with pytest.raises(ExprError) as err:
        e.evaluate({"frequency_hz": 60})
    assert "no value for 'latency_s'" in str(err.value)
    assert err.value.position == e.text.index("latency_s")
    with pytest.raises(ExprError) as err:
        parse("a / (b - 3)").evaluate(VALUES)
    assert "division by zero" in str(err.value)
    assert err.value.position == 2
    # short-circuit: the right side is not needed, so its missing value is no error
    assert parse("a > 1 or missing > 0").evaluate(VALUES) is True


def test_no_python_evaluation_of_user_text() -> None:
    for text in ("().__class__", "__import__('os').system('true')", "[1]", "{}", "lambda: 1",
                 "a if b else c", "a[0]", "a; b", "1 # comment"):
        with pytest.raises(ExprError):
            parse(text)


def test_expr_equality_and_repr() -> None:
    assert parse("a + 1") == parse("a + 1")
    assert hash(parse("a + 1")) == hash(parse("a + 1"))
    assert parse("a + 1") != parse("a+1")
    assert repr(parse("a")) == "Expr('a')"


# --------------------------------------------------------------------------- properties

_NAMES = ["a", "b", "c"]
_ENV = {"a": 1.5, "b": -2.0, "c": 0.25}


def _leaf() -> st.SearchStrategy[tuple[str, float]]:
    numbers = st.floats(0, 1e3, allow_nan=False).map(lambda x: (repr(x), x))
    names = st.sampled_from(_NAMES).map(lambda n: (n, _ENV[n]))
    return numbers | names


def _combine(children: st.SearchStrategy[tuple[str, float]]) -> st.SearchStrategy:
    def binary(op: str):
        fns = {"+": lambda x, y: x + y, "-": lambda x, y: x - y, "*": lambda x, y: x * y}
        return st.tuples(children, children).map(
            lambda t: (f"({t[0][0]} {op} {t[1][0]})", fns[op](t[0][1], t[1][1])))
    neg = children.map(lambda t: (f"-{t[0]}", -t[1]))
    call = st.sampled_from(["min", "max"]).flatmap(lambda f: st.lists(children, min_size=1,
                                                                      max_size=3).map(
        lambda args: (f"{f}({', '.join(a[0] for a in args)})",
                      (min if f == "min" else max)(a[1] for a in args))))
    absolute = children.map(lambda t: (f"abs({t[0]})", abs(t[1])))
    return binary("+") | binary("-") | binary("*") | neg | call | absolute


@settings(max_examples=150, deadline=None)
@given(st.recursive(_leaf(), _combine, max_leaves=12))
def test_random_arithmetic_matches_a_reference(tree: tuple[str, float]) -> None:
    text, expected = tree
    value = parse(text, names=_NAMES).evaluate(_ENV)
    if math.isfinite(expected):
        assert value == pytest.approx(expected, rel=1e-12, abs=1e-12)


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet=st.sampled_from(list("ab1.e+-*/<>=!()notrufalsdmix, ")), max_size=30))
def test_arbitrary_text_raises_only_expr_error(text: str) -> None:
    try:
        e = parse(text)
    except ExprError as exc:
        assert 0 <= exc.position <= len(text)
        return
    try:
        value = e.evaluate(dict.fromkeys(e.names, 1.0))
    except ExprError:
        return
    assert isinstance(value, bool) == e.is_predicate
