"""Figures of a fault on a stream: what a consumer (``agent_helpers.svc --each-sample``)
received around a fault, by the producer's sequence numbers and the harness's receive
times (``_mono``, the test process's monotonic clock, as ``time.monotonic()`` around the
fault)."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise
from typing import Any


@dataclass
class FaultFigures:
    """One fault's figures: ``recover_s`` from the end of the fault to the first sample
    after it, ``gap_s`` the longest time without a sample, ``lost`` the samples never
    received (gaps in the sequence), and whether any came twice or out of order."""

    name: str
    recover_s: float
    gap_s: float
    lost: int
    received: int
    duplicates: int
    reordered: int
    detect_s: float | None = None

    def line(self) -> str:
        detect = "-" if self.detect_s is None else f"{self.detect_s:.2f} s"
        return (f"FAULT {self.name}: detect {detect}, recover {self.recover_s:.2f} s, "
                f"longest gap {self.gap_s:.2f} s, lost {self.lost} of "
                f"{self.lost + self.received}, duplicates {self.duplicates}, "
                f"reordered {self.reordered}")


def samples(events: list[dict[str, Any]], source: str) -> list[dict[str, Any]]:
    return [ev for ev in events if ev.get("event") == "sample" and ev["source"] == source]


def figures(name: str, events: list[dict[str, Any]], source: str, fault_start: float,
            fault_end: float, until: float) -> FaultFigures:
    """The figures of ``source``'s samples received between ``fault_start`` minus 1 s and
    ``until`` (the fault lasted ``fault_start`` .. ``fault_end``)."""
    got = [ev for ev in samples(events, source) if fault_start - 1.0 <= ev["_mono"] <= until]
    if not got:
        raise AssertionError(f"{name}: no sample of {source} around the fault")
    after = [ev for ev in got if ev["_mono"] > fault_end]
    if not after:
        raise AssertionError(f"{name}: no sample of {source} after the fault ended")
    seqs = [ev["seq"] for ev in got]
    times = [ev["_mono"] for ev in got]
    duplicates = len(seqs) - len(set(seqs))
    reordered = sum(1 for a, b in pairwise(seqs) if b < a)
    unique = sorted(set(seqs))
    lost = sum(b - a - 1 for a, b in pairwise(unique))
    gap = max(b - a for a, b in pairwise(times)) if len(times) > 1 else 0.0
    return FaultFigures(name, after[0]["_mono"] - fault_end, gap, lost, len(unique),
                        duplicates, reordered)
