"""Logging that a peer's bad input cannot flood."""

from __future__ import annotations

import logging
import time


class RateLimitedLog:
    """One log line per (subject, reason) per ``interval`` seconds, with a count of the
    repeats it swallowed: bad input from a peer must not flood the log."""

    def __init__(self, logger: logging.Logger, interval: float = 10.0) -> None:
        self.logger = logger
        self.interval = interval
        self._last: dict[tuple[str, str], tuple[float, int]] = {}

    def warning(self, subject: str, reason: str) -> bool:
        """Log ``subject: reason`` unless logged recently; True if it was logged."""
        now = time.monotonic()
        k = (subject, reason[:200])
        last, swallowed = self._last.get(k, (-1e18, 0))
        if now - last < self.interval:
            self._last[k] = (last, swallowed + 1)
            return False
        if len(self._last) > 10_000:
            self._last.clear()
        self._last[k] = (now, 0)
        more = f" ({swallowed} similar since)" if swallowed else ""
        self.logger.warning("%s: %s%s", subject, reason, more)
        return True
