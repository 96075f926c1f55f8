"""The safe expression language of needs' predicates and preferences (and query error functions).

A need says which abilities it accepts (``where="frequency_hz >= 100 and latency_s <= 0.01"``)
and which it prefers (``prefer="latency_s + 0.1 * pos_std_m"``, minimised).  These strings come
from other hosts, so they are parsed by this small grammar and never by ``eval``:

    expr       := or
    or         := and ("or" and)*
    and        := not ("and" not)*
    not        := "not" not | comparison
    comparison := sum (("<" | "<=" | ">" | ">=" | "==" | "!=") sum)?    # no chaining
    sum        := product (("+" | "-") product)*
    product    := unary (("*" | "/") unary)*
    unary      := "-" unary | primary
    primary    := NUMBER | NAME | "true" | "false" | "(" expr ")"
                | ("min" | "max") "(" expr ("," expr)* ")" | "abs" "(" expr ")"

Numbers are decimal (``3``, ``0.5``, ``.5``, ``1e-3``).  Names are identifiers; ``min``,
``max`` and ``abs`` are functions only when followed by ``(``, so they stay usable as names.

Types are checked when parsing: arithmetic and ordering need numbers, ``and``/``or``/``not``
need booleans, ``==``/``!=`` refuse a boolean against a number.  A name's type is only known
when evaluating; a number is accepted as a boolean there (non-zero is true), so
``not static`` works when ``static`` arrives as 0/1.  ``is_predicate`` is true when the top
node is boolean (a comparison, ``and``/``or``/``not``, ``true``/``false``); a bare name is
not a predicate: write ``static == true``.

Evaluation errors are ``ExprError`` too, with the position of the culprit: a name missing
from the values, and division by zero (an error rather than ``inf`` so that a preference never
silently ranks an ability first or last because of a zero attribute).

The parsed tree is compiled once into nested closures; ``Expr.evaluate`` then costs about a
microsecond per node, which matters in matching loops over thousands of abilities.
Texts are limited to ``MAX_LENGTH`` characters and ``MAX_DEPTH`` levels of nesting.
Pure standard library: the SRG imports this module.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Collection, Mapping

from schemas.errors import UmaError

MAX_LENGTH = 1000
MAX_DEPTH = 40

Value = float | bool
Values = Mapping[str, Value]
_Fn = Callable[[Values], Value]

# Static types of nodes.
_NUM, _BOOL, _ANY = "number", "boolean", "any"

_TOKEN = re.compile(r"""
    (?P<ws>\s+)
  | (?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)
  | (?P<name>[A-Za-z_][A-Za-z0-9_]*)
  | (?P<op><=|>=|==|!=|[-+*/<>(),])
""", re.VERBOSE)
_KEYWORDS = {"and", "or", "not", "true", "false"}
_FUNCTIONS = {"min", "max", "abs"}
_HINTS = {"=": "use '==' to compare", "&": "use 'and'", "|": "use 'or'", "!": "use 'not'",
          "**": "powers are not supported; multiply"}


class ExprError(UmaError, ValueError):
    """A syntax, type or evaluation error, pointing at a 0-based ``position`` in ``text``."""

    def __init__(self, reason: str, text: str, position: int, detail: str = "") -> None:
        self.reason = reason
        self.text = text
        self.position = position
        shown = text if len(text) <= 120 else text[:117] + "..."
        caret = " " * min(position, len(shown)) + "^"
        more = f" ({detail})" if detail else ""
        super().__init__(f"{reason} at {position}{more}\n  {shown}\n  {caret}")


class _Token:
    __slots__ = ("kind", "pos", "text")

    def __init__(self, kind: str, text: str, pos: int) -> None:
        self.kind, self.text, self.pos = kind, text, pos


def _tokenize(text: str) -> list[_Token]:
    tokens = []
    pos = 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            ch = text[pos]
            two = text[pos:pos + 2]
            hint = _HINTS.get(two) or _HINTS.get(ch)
            raise ExprError(f"unexpected character {ch!r}" + (f" ({hint})" if hint else ""),
                            text, pos)
        kind = m.lastgroup or ""
        if kind == "op" and m.group() == "*" and text.startswith("**", pos):
            raise ExprError(f"unexpected '**' ({_HINTS['**']})", text, pos)
        if kind != "ws":
            word = m.group()
            tokens.append(_Token("kw" if kind == "name" and word in _KEYWORDS else kind,
                                 word, pos))
        pos = m.end()
    tokens.append(_Token("end", "", len(text)))
    return tokens


class _Node:
    """A compiled node: its static type, the closure that computes it, where it starts."""

    __slots__ = ("fn", "pos", "type")

    def __init__(self, type_: str, fn: _Fn, pos: int) -> None:
        self.type, self.fn, self.pos = type_, fn, pos


class _Parser:
    def __init__(self, text: str, names: Collection[str] | None) -> None:
        self.text = text
        self.allowed = None if names is None else frozenset(names)
        self.tokens = _tokenize(text)
        self.i = 0
        self.depth = 0
        self.names: set[str] = set()

    # -- helpers
    def error(self, reason: str, pos: int, detail: str = "") -> ExprError:
        return ExprError(reason, self.text, pos, detail)

    @property
    def tok(self) -> _Token:
        return self.tokens[self.i]

    def take(self) -> _Token:
        t = self.tokens[self.i]
        self.i += 1
        return t

    def at(self, *texts: str) -> bool:
        t = self.tok
        return t.kind in ("op", "kw") and t.text in texts

    def expect(self, text: str) -> _Token:
        if not self.at(text):
            raise self.unexpected(f"expected {text!r}")
        return self.take()

    def unexpected(self, wanted: str) -> ExprError:
        t = self.tok
        got = "end of expression" if t.kind == "end" else repr(t.text)
        return self.error(f"{wanted}, got {got}", t.pos)

    def need(self, node: _Node, type_: str, what: str) -> None:
        if node.type not in (type_, _ANY):
            raise self.error(f"{what} needs a {type_}, got a {node.type}", node.pos)

    # -- grammar
    def parse(self) -> _Node:
        if not self.text.strip():
            raise self.error("empty expression", 0)
        node = self.or_()
        if self.tok.kind != "end":
            raise self.unexpected("expected an operator or the end")
        return node

    def or_(self) -> _Node:
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.error(f"nested deeper than {MAX_DEPTH} levels", self.tok.pos)
        node = self.and_()
        while self.at("or"):
            self.take()
            right = self.and_()
            for n in (node, right):
                self.need(n, _BOOL, "'or'")
            a, b = node.fn, right.fn
            node = _Node(_BOOL, lambda v, a=a, b=b: bool(a(v)) or bool(b(v)), node.pos)
        self.depth -= 1
        return node

    def and_(self) -> _Node:
        node = self.not_()
        while self.at("and"):
            self.take()
            right = self.not_()
            for n in (node, right):
                self.need(n, _BOOL, "'and'")
            a, b = node.fn, right.fn
            node = _Node(_BOOL, lambda v, a=a, b=b: bool(a(v)) and bool(b(v)), node.pos)
        return node

    def not_(self) -> _Node:
        if self.at("not"):
            op = self.take()
            self.depth += 1
            if self.depth > MAX_DEPTH:
                raise self.error(f"nested deeper than {MAX_DEPTH} levels", op.pos)
            inner = self.not_()
            self.depth -= 1
            self.need(inner, _BOOL, "'not'")
            f = inner.fn
            return _Node(_BOOL, lambda v, f=f: not f(v), op.pos)
        return self.comparison()

    def comparison(self) -> _Node:
        left = self.sum_()
        if not self.at("<", "<=", ">", ">=", "==", "!="):
            return left
        op = self.take()
        right = self.sum_()
        if self.at("<", "<=", ">", ">=", "==", "!="):
            raise self.error("comparisons cannot be chained; combine them with 'and'",
                             self.tok.pos)
        if op.text in ("==", "!="):
            if {left.type, right.type} == {_NUM, _BOOL}:
                raise self.error(f"'{op.text}' compares a boolean with a number", op.pos)
        else:
            for n in (left, right):
                self.need(n, _NUM, f"'{op.text}'")
        a, b = left.fn, right.fn
        fns: dict[str, _Fn] = {
            "<": lambda v: a(v) < b(v), "<=": lambda v: a(v) <= b(v),
            ">": lambda v: a(v) > b(v), ">=": lambda v: a(v) >= b(v),
            "==": lambda v: a(v) == b(v), "!=": lambda v: a(v) != b(v),
        }
        return _Node(_BOOL, fns[op.text], left.pos)

    def sum_(self) -> _Node:
        node = self.product()
        while self.at("+", "-"):
            op = self.take()
            right = self.product()
            for n in (node, right):
                self.need(n, _NUM, f"'{op.text}'")
            a, b = node.fn, right.fn
            if op.text == "+":
                node = _Node(_NUM, lambda v, a=a, b=b: a(v) + b(v), node.pos)
            else:
                node = _Node(_NUM, lambda v, a=a, b=b: a(v) - b(v), node.pos)
        return node

    def product(self) -> _Node:
        node = self.unary()
        while self.at("*", "/"):
            op = self.take()
            right = self.unary()
            for n in (node, right):
                self.need(n, _NUM, f"'{op.text}'")
            a, b = node.fn, right.fn
            if op.text == "*":
                node = _Node(_NUM, lambda v, a=a, b=b: a(v) * b(v), node.pos)
            else:
                node = _Node(_NUM, self._divide(a, b, op.pos), node.pos)
        return node

    def _divide(self, a: _Fn, b: _Fn, pos: int) -> _Fn:
        text = self.text

        def divide(v: Values) -> Value:
            d = b(v)
            if d == 0:
                raise ExprError("division by zero", text, pos)
            return a(v) / d
        return divide

    def unary(self) -> _Node:
        if self.at("-"):
            op = self.take()
            self.depth += 1
            if self.depth > MAX_DEPTH:
                raise self.error(f"nested deeper than {MAX_DEPTH} levels", op.pos)
            inner = self.unary()
            self.depth -= 1
            self.need(inner, _NUM, "unary '-'")
            f = inner.fn
            return _Node(_NUM, lambda v: -f(v), op.pos)
        return self.primary()

    def primary(self) -> _Node:
        t = self.tok
        if t.kind == "num":
            self.take()
            value = float(t.text)
            if not math.isfinite(value):
                raise self.error(f"number {t.text} is out of range", t.pos)
            return _Node(_NUM, lambda v: value, t.pos)
        if t.kind == "kw" and t.text in ("true", "false"):
            self.take()
            flag = t.text == "true"
            return _Node(_BOOL, lambda v: flag, t.pos)
        if t.kind == "name":
            self.take()
            if self.at("("):
                return self.call(t)
            return self.name(t)
        if self.at("("):
            self.take()
            node = self.or_()
            self.expect(")")
            return _Node(node.type, node.fn, t.pos)
        raise self.unexpected("expected a number, a name, 'true', 'false', '(' or '-'")

    def name(self, t: _Token) -> _Node:
        name = t.text
        if self.allowed is not None and name not in self.allowed:
            known = ", ".join(sorted(self.allowed)) or "none"
            raise self.error(f"unknown name {name!r}", t.pos, f"known: {known}")
        self.names.add(name)
        text = self.text

        def lookup(v: Values) -> Value:
            try:
                return v[name]
            except KeyError:
                raise ExprError(f"no value for {name!r}", text, t.pos) from None
        return _Node(_ANY, lookup, t.pos)

    def call(self, t: _Token) -> _Node:
        if t.text not in _FUNCTIONS:
            raise self.error(f"unknown function {t.text!r}", t.pos, "known: abs, max, min")
        self.expect("(")
        args = [self.or_()]
        while self.at(","):
            self.take()
            args.append(self.or_())
        self.expect(")")
        for n in args:
            self.need(n, _NUM, f"{t.text}()")
        fns = [n.fn for n in args]
        if t.text == "abs":
            if len(args) != 1:
                raise self.error(f"abs() takes 1 argument, got {len(args)}", t.pos)
            f = fns[0]
            return _Node(_NUM, lambda v: abs(f(v)), t.pos)
        pick = min if t.text == "min" else max
        if len(fns) == 1:
            f = fns[0]
            return _Node(_NUM, f, t.pos)
        return _Node(_NUM, lambda v: pick([f(v) for f in fns]), t.pos)


class Expr:
    """A parsed, type-checked, compiled expression; immutable and cheap to evaluate."""

    __slots__ = ("_fn", "is_predicate", "names", "text")

    def __init__(self, text: str, names: frozenset[str], fn: _Fn, is_predicate: bool) -> None:
        self.text = text
        self.names = names
        self.is_predicate = is_predicate
        self._fn = fn

    def evaluate(self, values: Values) -> Value:
        """The value for these attribute values; ``ExprError`` names a missing value."""
        return self._fn(values)

    def __repr__(self) -> str:
        return f"Expr({self.text!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Expr) and other.text == self.text

    def __hash__(self) -> int:
        return hash(self.text)


def parse(text: str, names: Collection[str] | None = None) -> Expr:
    """Parse ``text``; ``names`` are the identifiers it may use (``None``: any).

    Raises ``ExprError`` (a ``ValueError``) whose message quotes the text with a caret.
    """
    if not isinstance(text, str):
        raise ExprError(f"expected a string, got {type(text).__name__}", "", 0)
    if len(text) > MAX_LENGTH:
        raise ExprError(f"longer than {MAX_LENGTH} characters ({len(text)})", text, MAX_LENGTH)
    parser = _Parser(text, names)
    root = parser.parse()
    fn = root.fn
    if root.type == _BOOL:
        inner = fn

        def fn(v: Values) -> Value:
            return bool(inner(v))
    return Expr(text, frozenset(parser.names), fn, root.type == _BOOL)
