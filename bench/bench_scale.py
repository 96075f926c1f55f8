"""How uma's cost grows with the size of a realm.

Four sweeps, each row with its growth factor (``xN``: the figure divided by the previous
row's, the first row of a sweep is its anchor):

- **frames per agent** (10, 100, 1,000; 2 agents), **agents** (2, 5, 10, 20; 10 frames
  each) and **samples per agent** (200 and 1,000 samples/s: 2 and 10 services at 100 Hz;
  2 agents, 10 frames): real ``uma agent`` processes on loopback (``bench/scale_realm.py``),
  each with one process of 2 services (or 10) at 100 Hz.  The agents' CPU per 1,000
  samples/s is read at 1,000 samples/s per agent too: at 200 the fixed cost of an agent
  (its threads' ticks, registrations, summaries) weighs five times as much per sample.
  Per row: ``Client.pose`` across two agents (median,
  p99), a subscription's latency (sample time to ``on_pose``), the agents' CPU per 1,000
  samples/s they receive (% of one core; and of that, the part in Zenoh's own runtime
  threads: links and routing, beyond what uma's Python can save), the realm's CPU (agents
  and service processes) against the 2 cores and how busy the machine was, the agents'
  RSS, the largest summary
  in bytes as sent and spelt out, and a new service's ``start()`` to its need's first sample
  (its source publishes every 10 ms).
- **summary** (in-process): one host's SRG of F frames with B frames shared with other
  agents (a room's world frame and markers, cameras mounted statically, every object
  tracked by one camera, the first ones by two: a cycle, where error functions pick
  different paths): ``summarize``'s time, the summary's links and its bytes spelt out
  (as agents sent it before) and compact (``agent.protocol.query.summary_to_wire``).
- **matching** (in-process, ``agent/daemon/matching.py`` as ``bench_matching.py``):
  abilities x needs up to 10,000 x 1,000, one full re-match (cold: index built), one
  after a change (warm) and the incremental one after a change (only the needs it concerns).

The machine is shared: absolute times are noisy, growth factors less so; the CPU model and
the load average at the start and end are printed.

    python bench/bench_scale.py [--quick] [--skip-realm | --skip-inprocess]
        [--frames 10 100 1000] [--agents 2 5 10 20] [--form-s 600] [--json]
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import msgpack
from bench_matching import realm as matching_realm
from bench_matching import timed
from summary import cpu_model, median_p99

from agent.daemon.matching import OfferIndex, match_all, rematch_all
from agent.errors import UmaError
from agent.protocol.query import decode_summary, summary_to_wire
from agent.srg import Graph
from agent.srg.supernode import summarize
from schemas.codec import encode_message

FULL = {"frames": (10, 100, 1000), "agents": (2, 5, 10, 20), "services": (2, 10),
        "summary_frames": ((10, 1), (100, 1), (1000, 1)),
        "summary_shared": ((100, 1), (100, 2), (100, 4)),
        "matching": ((100, 10), (1000, 100), (10000, 1000)),
        "queries": 100, "seconds": 5.0, "repeat": 3}
QUICK = {"frames": (10,), "agents": (2,), "services": (2,), "summary_frames": ((10, 1), (20, 1)),
         "summary_shared": ((10, 1), (10, 2)),
         "matching": ((50, 5), (100, 10)), "queries": 10, "seconds": 1.0, "repeat": 2}
#: a row's figures whose growth is reported, per sweep
GROWTH = {
    "realm": ("query_median_ms", "subscription_median_ms", "agent_cpu_pct_per_1k_samples_s",
              "realm_cpu_pct", "agent_rss_mb_median", "summary_bytes_max",
              "summary_bytes_spelt_out_max", "new_need_connected_ms", "formed_s"),
    "summary": ("summarize_ms", "links", "bytes_spelt_out", "bytes_compact"),
    "matching": ("cold_median_ms", "warm_median_ms", "incremental_median_ms"),
}


def host_graph(frames: int, shared: int, seen_twice: int = 2) -> tuple[Graph, list[str]]:
    """A host's SRG of ``frames`` frames, ``shared`` of them known to other agents (module
    docstring), and those shared frames."""
    g = Graph()
    ports = ["room/world"] + [f"room/m{j}" for j in range(shared - 1)]
    for j, marker in enumerate(ports[1:]):
        g.add_static(ports[0], marker, [j, 0.0, 0.0], [0, 0, 0, 1], pos_std_m=0.001)
    local = frames - shared
    cams = max(1, local // 2)
    for k in range(cams):
        g.add_static(ports[0], f"h/cam{k}", [k, 1.0, 2.0], [0, 0, 0, 1],
                     pos_std_m=0.001 * (1 + k % 7))
    for k in range(local - cams):
        for c in {k % cams, (k + 1) % cams} if k < seen_twice else {k % cams}:
            g.add_measurement(f"h/cam{c}", f"h/obj{k}", 1, [0, 0, 1.0], [0, 0, 0, 1],
                              source=f"s{k}/c{c}", latency_s=0.005 * (1 + c % 3),
                              frequency_hz=30.0 * (1 + c % 4), pos_std_m=0.002 * (1 + c % 5))
    return g, ports


def summary_row(frames: int, shared: int) -> dict[str, Any]:
    """One host's summary: its cost to compute and its size spelt out and compact (the
    compact one is checked to read the same)."""
    g, ports = host_graph(frames, shared)
    t = time.perf_counter()
    s = summarize(g, ports) | {"agent": "h", "rev": 1, "instance": "0123456789ab"}
    took = time.perf_counter() - t
    compact = encode_message(summary_to_wire(s))
    spelt = msgpack.packb({"v": 1, **s})  # unchecked: it may exceed a message's 1 MiB
    if len(spelt) <= 1 << 20 and decode_summary(compact) != decode_summary(spelt):
        raise RuntimeError("the compact summary reads differently: benchmark invalid")
    return {"frames": len(g.frames()), "shared": shared, "summarize_ms": took * 1e3,
            "links": len(s["links"]), "bytes_spelt_out": len(spelt),
            "bytes_compact": len(compact), "spelt_out_over_compact": len(spelt) / len(compact)}


def matching_row(abilities: int, needs: int, repeat: int) -> dict[str, Any]:
    """One full re-match (a fresh index), one full re-match after a single change, and the
    incremental one after a single change, as an agent does (``rematch_all``: only the
    needs the changed ability can concern)."""
    offers, reqs = matching_realm(abilities, needs, seed=1)
    match_all(reqs, OfferIndex(offers), "host0")  # untimed: first calls import and compile
    cold = timed(lambda: match_all(reqs, OfferIndex(offers), "host0"), repeat)
    index, changing = OfferIndex(offers), iter(offers * (2 * repeat + 2))

    def one_change() -> None:
        index.add(next(changing))
        match_all(reqs, index, "host0")
    warm = timed(one_change, repeat)
    results = match_all(reqs, index, "host0")
    index.take_touched()

    def one_incremental_change() -> None:
        nonlocal results
        index.add(next(changing))
        results = rematch_all(reqs, index, "host0", results, index.take_touched())
    incremental = timed(one_incremental_change, repeat)
    if results != match_all(reqs, index, "host0"):
        raise RuntimeError("the incremental re-match differs from the full one: invalid")
    out: dict[str, Any] = {"abilities": abilities, "needs": needs}
    for name, xs in (("cold", cold), ("warm", warm), ("incremental", incremental)):
        out |= {f"{name}_{k}": v for k, v in median_p99([1e3 * x for x in xs], "ms").items()}
    return out


def with_growth(rows: list[dict[str, Any]], figures: Sequence[str]) -> list[dict[str, Any]]:
    """Each row with ``<figure>_x``: its figure over the previous row's (None: not
    comparable, a figure missing or zero)."""
    for prev, row in itertools.pairwise(rows):
        for key in figures:
            a, b = prev.get(key), row.get(key)
            ok = isinstance(a, int | float) and isinstance(b, int | float) and a
            row[f"{key}_x"] = b / a if ok else None
    return rows


def show(name: str, rows: list[dict[str, Any]], figures: Sequence[str]) -> None:
    """A sweep's rows, one line each: its size, then every figure with its growth."""
    print(f"\n{name}", flush=True)
    for row in rows:
        size = " ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                        for k, v in row.items()
                        if k in ("agents", "frames_per_agent", "samples_per_agent_s", "frames",
                                 "shared", "abilities", "needs"))
        parts = [size]
        for key in figures:
            v, x = row.get(key), row.get(f"{key}_x")
            text = "-" if v is None else f"{v:.4g}"
            parts.append(f"{key} {text}" + (f" (x{x:.2f})" if x is not None else ""))
        print("  " + "; ".join(parts), flush=True)
        extra = {k: row[k] for k in ("agent_zenoh_cpu_pct_per_1k_samples_s",
                                     "query_p99_ms", "subscription_p99_ms", "machine_busy_pct",
                                     "agents_cpu_pct_total", "agent_rss_mb_max", "query_failed",
                                     "subscription_poses", "subscription_refused",
                                     "agent_restarts", "load_1min",
                                     "cold_p99_ms",
                                     "spelt_out_over_compact") if k in row}
        if extra:
            print("    " + ", ".join(f"{k} {v:.4g}" for k, v in extra.items()), flush=True)


def sweep(name: str, sizes: Sequence[Any], run: Callable[[Any], dict[str, Any]],
          figures: Sequence[str]) -> list[dict[str, Any]]:
    """Run every size (a failing row is reported and the sweep goes on)."""
    rows = []
    for size in sizes:
        try:
            rows.append(dict(run(size)))  # a copy: growth factors are added to it
        except (RuntimeError, OSError, LookupError, ValueError, UmaError) as exc:
            print(f"{name} {size}: {exc}", file=sys.stderr, flush=True)
            rows.append({"size": str(size), "error": str(exc)[:300]})
    with_growth(rows, figures)
    show(name, rows, figures)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: tiny sizes, short windows")
    ap.add_argument("--skip-realm", action="store_true", help="in-process sweeps only")
    ap.add_argument("--skip-inprocess", action="store_true", help="realm sweeps only")
    ap.add_argument("--frames", type=int, nargs="*", help="frames per agent (2 agents) to run")
    ap.add_argument("--agents", type=int, nargs="*", help="agents (10 frames each) to run")
    ap.add_argument("--services", type=int, nargs="*",
                    help="services per agent at 100 Hz (2 agents, 10 frames) to run")
    ap.add_argument("--form-s", type=float, default=600.0, help="bound on forming a realm")
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    a = ap.parse_args()
    plan = dict(QUICK if a.quick else FULL)
    plan |= {k: getattr(a, k) for k in ("frames", "agents", "services")
             if getattr(a, k) is not None}
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # the realms' `finally`s run
    out: dict[str, Any] = {"cpu": cpu_model(), "load_at_start": os.getloadavg()}
    print(f"cpu: {out['cpu']}\nload average at start: {out['load_at_start']}", flush=True)
    if not a.skip_inprocess:
        summary = functools.cache(lambda size: summary_row(*size))  # a row both sweeps share
        out["summary"] = sweep("summary by frames (one host, in-process)",
                               plan["summary_frames"], summary, GROWTH["summary"])
        out["summary_shared"] = sweep("summary by shared frames (one host, in-process)",
                                      plan["summary_shared"], summary, GROWTH["summary"])
        out["matching"] = sweep("matching (abilities x needs, in-process)", plan["matching"],
                                lambda an: matching_row(*an, plan["repeat"]),
                                GROWTH["matching"])
    if not a.skip_realm:
        from scale_realm import measure

        # the row both sweeps share (2 agents, 10 frames) runs once
        realm = functools.cache(lambda size: measure(*size[:2], plan["queries"],
                                                     plan["seconds"], a.form_s, *size[2:]))
        out["frames"] = sweep("frames per agent (2 agents, loopback)",
                              [(2, f) for f in plan["frames"]], realm, GROWTH["realm"])
        out["agents"] = sweep("agents (10 frames each, loopback)",
                              [(n, 10) for n in plan["agents"]], realm, GROWTH["realm"])
        out["services"] = sweep("samples per agent (2 agents, 10 frames, loopback; goal: agent "
                                "CPU <= 10 % of a core per 1,000 samples/s)",
                                [(2, 10) if s == 2 else (2, 10, s) for s in plan["services"]],
                                realm, GROWTH["realm"])
    out["load_at_end"] = os.getloadavg()
    print(f"\nload average at end: {out['load_at_end']}", flush=True)
    if a.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
