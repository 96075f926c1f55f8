"""What the checks against hostile peers cost where they run.

Each row times a check and, as its anchor in the same run, the work that path did before
it: a received pose's decode (the subscription's per-sample work) for the stamp rule
(``stamp_refusal``) and sequence-gap checks; ``peek_time`` for the monitor's
``peek_time_seq``; decoding a control message's body for its signature check; decoding a
summary for its validation; decoding a register request for the registration gate (size,
peek, proof of the key, rate); handing a liveliness token event to the worker's queue for
the token coalescer (rate, coalescing).  Figures are per call, median and p99 over
batches of ``--calls`` calls.  One row runs two agents in this process over loopback: a
published snapshot is applied only once its agent confirmed it (asked and answered), timed
from the publishing agent's change to the other's view, against the same publication
reaching a plain subscriber of the other agent's session (``--snapshots`` rounds).

    python bench/bench_hardening.py [--batches 200] [--calls 200] [--snapshots 100] [--json]
"""

from __future__ import annotations

import argparse
import os
import queue
import threading
import time
from collections.abc import Callable

from bench_host_load import free_endpoint
from summary import cpu_model, median_p99, report

from agent.attributes import SUMMARY_ERRORS
from agent.protocol import keys
from agent.protocol.query import decode_summary
from agent.protocol.registration import (
    Match,
    control_message,
    parse_control,
    parse_register_request,
    peek_register,
    register_request,
)
from agent.protocol.sequence import SequenceGaps, stamp_refusal
from agent.runtime.limits import Coalescer, SenderLimits
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


def snapshot_confirmation_ms(rounds: int) -> dict[str, list[float]]:
    """Milliseconds from agent B's change to A's view applying it (confirmed by asking B)
    and, as the anchor, to the publication reaching a subscriber of A's session."""
    from agent.daemon.agent import Agent
    from agent.daemon.settings import AgentSettings
    realm = f"hardening{os.getpid()}"
    ep = free_endpoint()
    a = Agent(AgentSettings(realm=realm, agent_id="A", listen=[ep]))
    b = Agent(AgentSettings(realm=realm, agent_id="B", connect=[ep], listen=[free_endpoint()]))
    a.start()
    b.start()
    arrived = threading.Event()
    out: dict[str, list[float]] = {"published": [], "confirmed": []}
    try:
        wait_until(lambda: "B" in a.view.remote, 10.0)
        assert a.session is not None
        sub = a.session.declare_subscriber(keys.agent_services(realm, "B"),
                                           lambda _: arrived.set())
        for _ in range(rounds):
            revision = a.view.remote["B"].revision
            arrived.clear()
            t0 = time.perf_counter()
            b._worker.put(setattr, b, "_snapshot_dirty", True)
            arrived.wait(5.0)
            out["published"].append((time.perf_counter() - t0) * 1e3)
            wait_until(lambda old=revision: a.view.remote["B"].revision != old, 5.0)
            out["confirmed"].append((time.perf_counter() - t0) * 1e3)
        sub.undeclare()
    finally:
        b.close()
        a.close()
    return out


def wait_until(test: Callable[[], bool], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not test():  # bounded: timeout
        if time.monotonic() > deadline:
            raise TimeoutError("the agents did not get there in time")
        time.sleep(0.0002)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, default=200)
    ap.add_argument("--calls", type=int, default=200)
    ap.add_argument("--snapshots", type=int, default=100,
                    help="snapshot changes timed from one agent to another")
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
        stamp_refusal(time.time_ns(), time.time_ns(), time.time_ns())
        gaps.see(next(seq))

    desc = encode_message({"service_id": "cam", "agent_id": "hostA", "abilities": [
        {"name": "pose", "type": "pose6d", "edge": ["ivy/world", "alice/head"],
         "attributes": {"frequency_hz": 100.0, "latency_s": 0.005}}]})
    request = register_request(desc, "inst", 3, {"head": ["k"]}, key, bytes(16))
    unlimited = SenderLimits(1e12, 1e12, (1e12, 1e12))

    def registration_gate() -> None:
        claim = peek_register(request)
        assert claim is not None and claim.proof is not None and claim.proof.verifies(key)
        unlimited.allow(claim.service_id)

    work: queue.Queue = queue.Queue()
    tokens = Coalescer(lambda fn: work.put_nowait(fn) or True, lambda _: None, unlimited,
                       lambda *_: None)
    token_keys = [f"uma/lab/svc/hostA/s{i}" for i in range(64)]
    counter = iter(range(10**9))

    def token_put() -> None:
        work.put_nowait(next(counter))
        work.get_nowait()

    def token_offer() -> None:
        i = next(counter)
        tokens.offer(token_keys[i % 64], "hostA", i)
        if i % 64 == 63:
            work.get_nowait()()

    rows = {
        "sample decode (anchor)": per_call_us(lambda: decode_measurement(pose), b, n),
        "sample checks: stamp rule + gap": per_call_us(sample_checks, b, n),
        "peek_time (anchor)": per_call_us(lambda: peek_time(pose), b, n),
        "peek_time_seq": per_call_us(lambda: peek_time_seq(pose), b, n),
        "control body decode (anchor)": per_call_us(lambda: decode_message(body), b, n // 4),
        "control verify + decode": per_call_us(lambda: parse_control(ctl, "lab", key), b,
                                               n // 4),
        "summary 100 links decode (anchor)": per_call_us(lambda: decode_message(summary),
                                                         b // 4, 4),
        "summary 100 links validated": per_call_us(lambda: decode_summary(summary), b // 4, 4),
        "register request decode (anchor)": per_call_us(
            lambda: parse_register_request(request, "hostA"), b // 4, n // 4),
        "registration gate": per_call_us(registration_gate, b // 4, n // 4),
        "token event queued (anchor)": per_call_us(token_put, b, n),
        "token event coalesced": per_call_us(token_offer, b, n),
    }
    figures: dict[str, object] = {"cpu": cpu_model()}
    for name, samples in rows.items():
        for k, v in median_p99(samples, "us").items():
            figures[f"{name} {k}"] = v
    snapshots = snapshot_confirmation_ms(args.snapshots)
    for name, label in (("published", "snapshot published, at A's subscriber (anchor)"),
                        ("confirmed", "snapshot confirmed and applied by A")):
        for k, v in median_p99(snapshots[name], "ms").items():
            figures[f"{label} {k}"] = v
    ratio = figures["sample checks: stamp rule + gap median_us"] / figures[
        "sample decode (anchor) median_us"]
    figures["sample checks / decode"] = ratio
    figures["peek_time_seq / peek_time"] = (figures["peek_time_seq median_us"]
                                            / figures["peek_time (anchor) median_us"])
    figures["control verify / body decode"] = (figures["control verify + decode median_us"]
                                               / figures["control body decode (anchor) median_us"])
    figures["summary validated / decode"] = (
        figures["summary 100 links validated median_us"]
        / figures["summary 100 links decode (anchor) median_us"])
    figures["registration gate / request decode"] = (
        figures["registration gate median_us"]
        / figures["register request decode (anchor) median_us"])
    figures["token coalesced / queued"] = (figures["token event coalesced median_us"]
                                           / figures["token event queued (anchor) median_us"])
    figures["snapshot confirmed / published"] = (
        figures["snapshot confirmed and applied by A median_ms"]
        / figures["snapshot published, at A's subscriber (anchor) median_ms"])
    report(figures, args.json)


if __name__ == "__main__":
    main()
