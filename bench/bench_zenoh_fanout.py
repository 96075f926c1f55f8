"""What Zenoh alone costs for the shape of a cross-agent query, no uma code involved.

A cross-agent pose query is one ``get`` on ``uma/R/agent/*/query`` that three agents answer
(``bench_query_remote.py``).  Here three bare peer processes (B and C connected to A, as
the agents there) each declare a queryable that answers with a segment-sized payload, and
this process asks all three at once -- as a Zenoh client of A (the default layout: A routes
the query and the answers) or as a peer (it meets B and C directly) -- interleaved with a
direct get to a fourth bare queryable, the anchor of ``bench_query_remote``.  The ratio is
the part of that benchmark's ratio that is Zenoh's topology, not uma.

Usage: python bench/bench_zenoh_fanout.py [--gets N] [--json]
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from loopback import free_port, wait_listening, zenoh_config
from summary import cpu_model, median_p99

ANSWER = b"x" * 600  # about a segment answer with covariance and edges





def run_queryable(name: str, listen: str, connect: str | None) -> None:
    """One bare peer answering ``fan/NAME/query`` until SIGTERM."""
    import zenoh
    with zenoh.open(zenoh_config("peer", listen, connect)) as s:
        key = f"fan/{name}/query"
        q = s.declare_queryable(key, lambda query: query.reply(key, ANSWER))
        signal.sigwait({signal.SIGTERM, signal.SIGINT})
        q.undeclare()




def _measure(mode: str, eps: dict[str, str], n: int) -> dict:
    import zenoh
    with zenoh.open(zenoh_config(mode, connect=eps["A"])) as fan, \
            zenoh.open(zenoh_config("peer", connect=eps["E"])) as direct:
        querier = fan.declare_querier("fan/*/query", timeout=2.0,
                                      consolidation=zenoh.ConsolidationMode.NONE)
        deadline = time.monotonic() + 30
        while len([r for r in querier.get() if r.ok is not None]) < 3:
            if time.monotonic() > deadline:
                raise SystemExit("setup failed: the three queryables do not all answer")
            time.sleep(0.2)
        fan_us, one_us = [], []
        for _ in range(n):
            t0 = time.perf_counter_ns()
            got = [r for r in querier.get(payload=b"q" * 100) if r.ok is not None]
            t1 = time.perf_counter_ns()
            one = [r for r in direct.get("fan/E/query", payload=b"q" * 64) if r.ok is not None]
            t2 = time.perf_counter_ns()
            if len(got) != 3 or len(one) != 1:
                raise SystemExit(f"lost answers: {len(got)} of 3, {len(one)} of 1")
            fan_us.append((t1 - t0) / 1000)
            one_us.append((t2 - t1) / 1000)
        querier.undeclare()
    out = {"fan_out_get": median_p99(fan_us, "us"), "direct_get": median_p99(one_us, "us")}
    out["ratio"] = out["fan_out_get"]["median_us"] / out["direct_get"]["median_us"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gets", type=int, default=1500, help="gets per layout (default 1500)")
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    ap.add_argument("--role", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role:
        name, listen, connect = args.role
        return run_queryable(name, listen, None if connect == "-" else connect)
    ports = {name: free_port() for name in "ABCE"}
    eps = {name: f"tcp/127.0.0.1:{port}" for name, port in ports.items()}
    me = [sys.executable, str(Path(__file__).resolve())]
    procs = []
    try:
        for name, connect in (("A", "-"), ("B", eps["A"]), ("C", eps["A"]), ("E", "-")):
            procs.append(subprocess.Popen([*me, "--role", name, eps[name], connect]))
        wait_listening(list(ports.values()))
        figures = {"cpu": cpu_model(),
                   **{mode: _measure(mode, eps, args.gets) for mode in ("client", "peer")}}
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
    print(f"cpu {figures['cpu']}")
    for mode in ("client", "peer"):
        f = figures[mode]
        print(f"[asker as a Zenoh {mode}] get fanned out to 3 peers: median "
              f"{f['fan_out_get']['median_us']:.0f} us, p99 {f['fan_out_get']['p99_us']:.0f} us;"
              f" direct get {f['direct_get']['median_us']:.0f} us; ratio {f['ratio']:.2f}")
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
