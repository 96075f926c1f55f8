"""Zenoh callbacks that never let an exception reach Zenoh.

zenoh-python prints a full traceback ("callback error") for every exception a callback
raises, with no limit: a bug hit by every sample, or a peer's message that trips one, floods
the process's stderr.  :func:`guarded` wraps a callback so an exception is logged through a
:class:`agent.runtime.logs.RateLimitedLog` instead: one line per kind of failure per
interval, naming the callback, the exception and where it was raised, with a count.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from typing import Any, TypeVar

from agent.runtime.logs import RateLimitedLog

T = TypeVar("T")


def guarded(fn: Callable[[T], Any], where: str, bad: RateLimitedLog) -> Callable[[T], None]:
    """``fn`` for Zenoh to call: what it raises is logged rate-limited under ``where`` (e.g.
    the key it listens on), never raised into Zenoh's thread."""
    def call(arg: T) -> None:
        try:
            fn(arg)
        except Exception as exc:  # Zenoh would print every traceback: say it once in a while
            bad.warning(where, f"{_name(fn)} failed: {type(exc).__name__}: {exc}"
                        f"{_origin(exc)}")
    return call


def _name(fn: Callable[..., Any]) -> str:
    return getattr(fn, "__qualname__", None) or repr(fn)


def _origin(exc: BaseException) -> str:
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return ""
    last = frames[-1]
    return f" (at {last.filename.rsplit('/', 1)[-1]}:{last.lineno} in {last.name})"
