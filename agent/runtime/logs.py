"""Logging that a peer's bad input cannot flood.

A hostile or buggy peer can send thousands of bad messages, each with its own error text
(a byte value, a position, a forged id in quotes).  Keyed on that text, every message
would be a "new" warning.  So a warning is keyed on
its sender (``subject``) and the *kind* of its reason: the text with numbers and quoted
values replaced by placeholders.  Three bounds hold whatever the peers send:

- one line per (subject, kind) per ``interval`` seconds, the next one saying how many
  similar warnings it swallowed meanwhile;
- at most ``burst`` lines per ``interval`` in all (a flood of distinct senders, e.g.
  forged keys), the rest counted and reported in one line when the next window opens;
- at most ``max_keys`` (subject, kind) entries remembered, least recently seen forgotten
  first (their swallowed counts go into that report rather than being lost).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections import OrderedDict

#: a quoted value (repr of a string or bytes) or a number (int, float, hex): one pass
_DETAIL = re.compile(r"""'[^']*'|"[^"]*"|0x[0-9a-fA-F]+|\d+(?:\.\d+)?(?:[eE][-+]?\d+)?""")
#: characters of a reason that decide its kind (the rest is detail)
KIND_CHARS = 160


def kind_of(reason: str) -> str:
    """The kind of an error text: its words, with quoted values and numbers as ``#``
    (``"byte 0xc1 at 17 in 'a'"`` and ``"byte 0x92 at 3 in 'b'"`` are one kind)."""
    return _DETAIL.sub("#", reason[:4 * KIND_CHARS])[:KIND_CHARS]


class RateLimitedLog:
    """Rate-limited warnings about bad input (module docstring for the bounds).

    ``seen`` counts every warning asked for, ``logged`` the lines written: their
    difference is what was swallowed and reported as counts."""

    def __init__(self, logger: logging.Logger, interval: float = 10.0, *, burst: int = 20,
                 max_keys: int = 1024) -> None:
        self.logger = logger
        self.interval = interval
        self.burst = burst
        self.max_keys = max_keys
        self.seen = 0
        self.logged = 0
        #: (subject, kind) -> [time of its last line, warnings swallowed since]
        self._last: OrderedDict[tuple[str, str], list[float]] = OrderedDict()
        self._window = (-1e18, 0)  # start of the current window, lines written in it
        self._unreported = 0  # swallowed by the burst bound or forgotten entries
        self._lock = threading.Lock()  # Zenoh calls from several threads at once

    def warning(self, subject: str, reason: str) -> bool:
        """Log ``subject: reason`` unless a warning of its kind from ``subject`` was logged
        in the last ``interval`` s or the burst is spent; True if it was logged."""
        with self._lock:
            return self._warning(subject, reason)

    def _warning(self, subject: str, reason: str) -> bool:
        now = time.monotonic()
        self.seen += 1
        k = (subject, kind_of(reason))
        entry = self._last.get(k)
        if entry is not None:
            self._last.move_to_end(k)
            if now - entry[0] < self.interval:
                entry[1] += 1
                return False
        if not self._take_line(now):
            self._unreported += 1
            return False
        swallowed = int(entry[1]) if entry is not None else 0
        self._last[k] = [now, 0]
        self._forget_oldest()
        more = f" ({swallowed} similar since)" if swallowed else ""
        self.logger.warning("%s: %s%s", subject, reason, more)
        self.logged += 1
        return True

    def _take_line(self, now: float) -> bool:
        """Whether this window's burst allows one more line (reporting what the last window
        swallowed when a new one opens)."""
        start, lines = self._window
        if now - start >= self.interval:
            if self._unreported:
                self.logger.warning("%d more warnings about bad input were not logged in "
                                    "the last %.0f s (more than %d lines or senders)",
                                    self._unreported, self.interval, self.burst)
                self.logged += 1
                self._unreported = 0
            start, lines = now, 0
        if lines >= self.burst:
            self._window = (start, lines)
            return False
        self._window = (start, lines + 1)
        return True

    def _forget_oldest(self) -> None:
        while len(self._last) > self.max_keys:
            _, (_, swallowed) = self._last.popitem(last=False)
            self._unreported += int(swallowed)
