"""What a receiver checks of each sample's stamps: samples lost on the way, counted from
the sequence number ``s`` every publisher stamps on its samples (``schemas.codec``; one
counter per ability, from 1), and times too far ahead to be true.

Zenoh delivers one publisher's samples in order, and uma publishes with congestion control
DROP (a slow link must not stall the tracker), so a jump in ``s`` is samples dropped on
the way.  A lower number than the last one is a restarted publisher: counting starts again.
"""

from __future__ import annotations

#: how far ahead of the receiver's clock (after the sender's estimated offset) a sample may
#: be stamped: predictions reach tens of ms ahead; a sample a day ahead would stay the
#: newest of its edge and make every honest one look too old
MAX_AHEAD_NS = 1_000_000_000


#: how far behind the newest sample of its own stream a sample may be stamped: one stream's
#: samples come in order, so one stamped that far back is not of its present (a forged or
#: broken sender); a stream's first sample may be of any past (a recording replayed)
MAX_BEHIND_NS = 10_000_000_000


def too_far_ahead(t_ns: int, now_ns: int) -> bool:
    """Whether a sample stamped ``t_ns`` (receiver's clock) is refused at ``now_ns``."""
    return t_ns > now_ns + MAX_AHEAD_NS


def stamp_refusal(t_ns: int, now_ns: int, newest_ns: int | None = None) -> str | None:
    """Why a sample stamped ``t_ns`` (receiver's clock) is refused at ``now_ns``, None if
    it is not: the one rule every receiver applies (subscriptions, the agent's graph, a
    service's matched needs).  ``newest_ns``: the newest stamp taken from its stream."""
    if t_ns <= 0:
        return "stamped at or before 1970-01-01: not a time"
    if too_far_ahead(t_ns, now_ns):
        return f"stamped {(t_ns - now_ns) / 1e9:.3g} s ahead of this clock"
    if newest_ns is not None and t_ns < newest_ns - MAX_BEHIND_NS:
        return f"stamped {(newest_ns - t_ns) / 1e9:.3g} s behind its stream's newest sample"
    return None


class SequenceGaps:
    """The samples missing from one stream's sequence so far.  A sample that arrived but
    was not taken (refused, malformed: its ``s`` unread) is no loss: :meth:`skip` tells,
    and the next gap is that much smaller."""

    def __init__(self) -> None:
        self.last: int | None = None
        self.lost = 0
        self._skipped = 0

    def skip(self) -> None:
        """A sample of this stream arrived and was not taken."""
        self._skipped += 1

    def see(self, seq: int | None) -> int:
        """Take a sample's ``s`` (None: its publisher numbers none); returns how many were
        lost just before it."""
        if seq is None:
            return 0
        gap = seq - self.last - 1 if self.last is not None and seq > self.last + 1 else 0
        gap, self._skipped = max(0, gap - self._skipped), 0
        self.lost += gap
        self.last = seq
        return gap
