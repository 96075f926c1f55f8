"""Why a pose query failed, as exceptions a user can act on.

Every class is an ``agent.errors.NotFoundError`` (something asked for is not there, a
``LookupError``) or ``InvalidInputError`` (something given is malformed, a ``ValueError``),
both ``UmaError``, so the CLI prints the message and exits 1.  Messages follow
tf2's habit of naming what was asked *and* what exists: the unknown frame and the known
ones, the edge that had no data at ``t`` and whether its data was too old (dropped from
the buffer) or had not arrived yet.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from agent.errors import InvalidInputError, NotFoundError

#: how many names an error message lists before it says "... and N more"
_SHOWN = 12


def list_names(names: Iterable[str], shown: int = _SHOWN) -> str:
    """``a, b, c ... and 7 more`` (sorted), or ``none``."""
    items = sorted(names)
    if not items:
        return "none"
    head = ", ".join(items[:shown])
    return head if len(items) <= shown else f"{head} ... and {len(items) - shown} more"


class SrgLookupError(NotFoundError):
    """Base of the lookups that fail because something is not (yet) in the graph."""


class UnknownFrameError(SrgLookupError):
    """A query named a frame no edge touches."""

    def __init__(self, frame: str, known: Iterable[str]) -> None:
        self.frame = frame
        super().__init__(f"unknown frame {frame!r}; known frames: {list_names(known)}")


class UnknownEdgeError(SrgLookupError):
    """An edge was addressed (attributes, removal) that does not exist."""

    def __init__(self, edge: str, between: Iterable[str] = ()) -> None:
        self.edge = edge
        others = list(between)
        extra = f"; edges between these frames: {list_names(others)}" if others else ""
        super().__init__(f"no edge {edge}{extra}")


class UnreachableError(SrgLookupError):
    """Both frames exist but no chain of edges links them."""

    def __init__(self, source: str, target: str, source_side: Iterable[str],
                 target_side: Iterable[str]) -> None:
        self.source = source
        self.target = target
        self.source_side = frozenset(source_side)
        self.target_side = frozenset(target_side)
        super().__init__(
            f"no path from {source!r} to {target!r}: they are in unconnected parts of the "
            f"graph; {source!r} reaches {list_names(source_side)}; {target!r} reaches "
            f"{list_names(target_side)}")


class EdgeUndefinedError(SrgLookupError):
    """An edge of the chosen path has no value at the requested time."""

    def __init__(self, edge: str, t_ns: int | None, reason: str) -> None:
        self.edge = edge
        self.t_ns = t_ns
        super().__init__(f"edge {edge} has no data at t={t_ns}: {reason}")


class NoSamplesError(EdgeUndefinedError):
    """A measured edge exists (its ability was declared) but no sample has arrived."""

    def __init__(self, edge: str, t_ns: int | None) -> None:
        super().__init__(edge, t_ns, "no sample has arrived yet on this measured edge")


class DataNotYetArrivedError(EdgeUndefinedError):
    """``t`` is later than the edge's newest sample by more than the extrapolation limit."""

    def __init__(self, edge: str, t_ns: int, newest_ns: int, limit_s: float) -> None:
        self.newest_ns = newest_ns
        self.behind_s = (t_ns - newest_ns) / 1e9
        super().__init__(
            edge, t_ns,
            f"data not yet arrived: the newest sample (t={newest_ns}) is {self.behind_s:.6g} s "
            f"before t, more than the extrapolation limit of {limit_s:.6g} s (the source "
            "may be late, slow or stopped)")


class DataTooOldError(EdgeUndefinedError):
    """``t`` is earlier than what the edge's buffer still holds: that data was dropped."""

    def __init__(self, edge: str, t_ns: int, oldest_ns: int, buffer_s: float) -> None:
        self.oldest_ns = oldest_ns
        self.before_s = (oldest_ns - t_ns) / 1e9
        super().__init__(
            edge, t_ns,
            f"data too old: t is {self.before_s:.6g} s before the oldest buffered sample "
            f"(t={oldest_ns}); the buffer keeps {buffer_s:.6g} s")


class NoValidPathError(SrgLookupError):
    """Paths exist, but each candidate has an edge undefined at ``t``."""

    def __init__(self, source: str, target: str, t_ns: int | None,
                 causes: Sequence[EdgeUndefinedError]) -> None:
        self.causes = list(causes)
        lines = "; ".join(f"path {i + 1}: {c}" for i, c in enumerate(self.causes))
        super().__init__(f"no path from {source!r} to {target!r} is defined at t={t_ns} "
                         f"({len(self.causes)} candidates tried): {lines}")


class BadErrorFunctionError(InvalidInputError):
    """An error function that is neither a built-in nor a valid expression."""
