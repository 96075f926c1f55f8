"""What the checks against hostile peers cost where they run.

Each row times a check and, as its anchor in the same run, the work that path did before
it: a received pose's decode (the subscription's per-sample work) for the future-time and
sequence-gap checks; ``peek_time`` for the monitor's ``peek_time_seq``; decoding a
control message's body for its signature check; decoding a summary for its validation.
Figures are per call, median and p99 over batches of ``--calls`` calls.

    python bench/bench_hardening.py [--batches 200] [--calls 200] [--json]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

from summary import cpu_model, median_p99, report

from agent.attributes import SUMMARY_ERRORS
from agent.protocol import keys
from agent.protocol.query import decode_summary
from agent.protocol.registration import Match, control_message, parse_control
from agent.protocol.sequence import SequenceGaps, too_far_ahead
from schemas.codec import (
    decode_measurement,
    decode_message,
    encode_message,
    encode_pose,
    peek_time,
    peek_time_seq,
)


def per_call_us(fn: Callable[[], object], batches: int, calls: int) -> list[float]:
    """Per-call time (us) of ``fn`` in each of ``batches`` batches of ``calls`` calls."""
    out = []
    for _ in range(batches):
        t0 = time.perf_counter_ns()
        for _ in range(calls):
            fn()
        out.append((time.perf_counter_ns() - t0) / calls / 1e3)
    return out


def summary_bytes(links: int) -> bytes:
    attrs = {"latency_s": 0.01, "frequency_hz": 100.0, "pos_std_m": 0.001, "hops": 1}
    frames = [f"f{i}/x" for i in range(links + 1)]
    return encode_message({"agent": "hostA", "rev": 3, "instance": "i", "frames": frames,
                           "components": [frames],
                           "links": [{"a": frames[i], "b": frames[i + 1],
                                      "attrs": dict.fromkeys(SUMMARY_ERRORS, attrs)}
                                     for i in range(links)]})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, default=200)
    ap.add_argument("--calls", type=int, default=200)
    ap.add_argument("--json", action="store_true", help="also print one JSON line")
    args = ap.parse_args()
    b, n = args.batches, args.calls
    pose = encode_pose(time.time_ns(), [0.1, 0.2, 0.3], [0, 0, 0, 1], seq=7)
    gaps = SequenceGaps()
    seq = iter(range(1, 10**9))
    key = bytes(range(16))
    m = Match(keys.data("lab", "hostB", "cam", "pose"), "hostB", "cam", "pose", "pose6d",
              ("ivy/world", "alice/head"), {"latency_s": 0.01})
    ctl = control_message(key, 7, 3, "head", [m], True)
    body = decode_message(ctl)["body"]
    summary = summary_bytes(100)

    def sample_checks() -> None:
        too_far_ahead(time.time_ns(), time.time_ns())
        gaps.see(next(seq))

    rows = {
        "sample decode (anchor)": per_call_us(lambda: decode_measurement(pose), b, n),
        "sample checks: future + gap": per_call_us(sample_checks, b, n),
        "peek_time (anchor)": per_call_us(lambda: peek_time(pose), b, n),
        "peek_time_seq": per_call_us(lambda: peek_time_seq(pose), b, n),
        "control body decode (anchor)": per_call_us(lambda: decode_message(body), b, n // 4),
        "control verify + decode": per_call_us(lambda: parse_control(ctl, "lab", key), b,
                                               n // 4),
        "summary 100 links decode (anchor)": per_call_us(lambda: decode_message(summary),
                                                         b // 4, 4),
        "summary 100 links validated": per_call_us(lambda: decode_summary(summary), b // 4, 4),
    }
    figures: dict[str, object] = {"cpu": cpu_model()}
    for name, samples in rows.items():
        for k, v in median_p99(samples, "us").items():
            figures[f"{name} {k}"] = v
    ratio = figures["sample checks: future + gap median_us"] / figures[
        "sample decode (anchor) median_us"]
    figures["sample checks / decode"] = ratio
    figures["peek_time_seq / peek_time"] = (figures["peek_time_seq median_us"]
                                            / figures["peek_time (anchor) median_us"])
    figures["control verify / body decode"] = (figures["control verify + decode median_us"]
                                               / figures["control body decode (anchor) median_us"])
    figures["summary validated / decode"] = (
        figures["summary 100 links validated median_us"]
        / figures["summary 100 links decode (anchor) median_us"])
    report(figures, args.json)


if __name__ == "__main__":
    main()
