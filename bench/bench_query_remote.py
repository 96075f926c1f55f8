"""Cross-agent pose queries and streaming on loopback, against a bare Zenoh get.

Starts three agents (separate processes) whose graphs share frames pairwise,
``A: ivy/world -> cam/nw``, ``B: cam/nw -> marvin/rig``, ``C: marvin/rig -> alice/head``
(static edges, plus a measured ``marvin/rig -> alice/head`` published at 100 Hz by a
tracker service process registered with C), and one bare queryable process.  Measures:

1. ``Client.pose("ivy/world", "alice/head")``: a route over all three agents, not kept by
   the client, asked of its first agent A, which answers the whole route (its own segment,
   B's and C's from its supernode cache once they are asked for often; see
   ``agent.daemon.relay``), composed with covariance; median and p99, and the ratio to a
   bare ``get`` round trip to the bare queryable measured in the same run.
   Measured four ways, interleaved: every segment asked at the latest time (C answers
   again what it answered before until the tracker's next sample: queries here come ~10x
   faster than samples); every segment asked at a time 30 ms back, which C interpolates
   afresh each time (the worst case: nothing an agent computed can be reused); the same
   asked of every agent itself (the fan-out, the fallback; one query to the three); and with
   the client's cache of all-static segments (A's and B's here; valid until the agent's
   summary changes), so that only C is asked.  Each kind also reports the CPU time of the
   asking thread per query (median), beside the bare get's: the share of a query that is
   this process's own work rather than waiting for the network and the agents.  Interleaved
   with them, the floor under the query: a clock round trip to the same three agents
   through the same client (the query's fan-out and uma's sessions, no segment work at
   either end), so that the query's ratio splits into the transport's part and uma's;
2. streaming: the time from the tracker's publication of a sample to the composed pose
   reaching ``on_pose`` in this process; median and p99, against the anchor of the same
   run: a bare Zenoh put from the tracker's own session to a subscriber callback in this
   process (half a period after each sample, so the two never queue behind each other).
   Before it, as long again, the tracker's encoded samples at a plain Zenoh callback in
   this process (no subscription yet) against the bare put of that window: the part of
   the ratio that is the publisher's encoding and the agents' handling of a sample on the
   way, before the subscription's own work (decode, mirror, compose).

Both are measured with the client as a Zenoh client of agent A (the default layout: A
routes its queries to B and C and their answers back, and C's samples through A) and as a
peer that meets every agent directly (the all-peers layout, ``UMA_SDK_MODE=peer``), each
against the bare get and put of the same run.  The bare get goes straight to its
queryable, so in the default layout the extra hop through A counts against uma.

Goals: the query (latest and 30 ms back) ≤ 2.0× the bare get in both layouts; streaming
≤ 1.5× the bare one-way.

Usage: python bench/bench_query_remote.py [--queries N] [--stream-seconds S]
       [--client-mode client|peer|both] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np
from loopback import free_port, wait_listening
from summary import cpu_model, median_p99

from agent.protocol import keys
from agent.protocol import query as proto
from agent.runtime.processes import stop_processes
from schemas.codec import peek_time

WORLD, CAM, RIG, HEAD = "ivy/world", "cam/nw", "marvin/rig", "alice/head"
EDGES = {
    "A": [(WORLD, CAM, [1.2, -0.5, 2.3], [0.0, 0.0, 0.38268343, 0.92387953], 0.01)],
    "B": [(CAM, RIG, [0.3, 0.8, -1.1], [0.0, 0.38268343, 0.0, 0.92387953], 0.002)],
    "C": [],
}
AGENTS = ("A", "B", "C")
RATE_HZ = 100.0
PAST_NS = 30_000_000  # "past" queries: between two samples, well inside C's buffer


def _stats(us: list[float]) -> dict:
    return {**median_p99(us, "us"), "n": len(us)}


def run_echo(args: argparse.Namespace) -> None:
    """The baseline: a bare queryable that answers every get with a small payload."""
    from agent.runtime.session import open_session
    with open_session("peer", [args.listen], []) as s:
        q = s.declare_queryable(args.key, lambda query: query.reply(args.key, b"x" * 64))
        signal.sigwait({signal.SIGTERM, signal.SIGINT})
        q.undeclare()


def run_tracker(args: argparse.Namespace) -> None:
    """A tracker service on agent C: publishes rig -> head at 100 Hz, stamped at publication."""
    from agent import Service
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with Service("tracker", realm=args.realm, agent="C", connect=[args.connect]) as svc:
        out = svc.ability("head", type="pose6d", edge=(RIG, HEAD), frequency_hz=RATE_HZ,
                          latency_s=0.001, pos_std_m=0.002)
        svc.start()
        bare = svc.session.declare_publisher(f"bench/{args.realm}/oneway")
        k = 0
        while not stop.is_set():
            k += 1
            out.publish(time.time_ns(), [0.0, 0.01 * np.sin(k / 50), 0.12], [0, 0, 0, 1])
            stop.wait(0.5 / RATE_HZ)
            bare.put(struct.pack("<q", time.time_ns()))
            stop.wait(0.5 / RATE_HZ)


def _config(path: Path, edges) -> str:
    lines = []
    for parent, child, p, q, std in edges:
        lines += ["[[static]]", f'parent = "{parent}"', f'child = "{child}"',
                  f"position = {p}", f"quaternion = {q}", f"pos_std_m = {std}"]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


#: the Zenoh modes the client is measured in: a client of its host's agent (the default
#: layout: the agent routes its queries and streams) and a peer that meets every agent
#: directly (the all-peers layout, ``UMA_SDK_MODE=peer``)
CLIENT_MODES = {"client": ("client",), "peer": ("peer",), "both": ("client", "peer")}
LABELS = {"latest": "3 agents, not kept, asked of A, latest time",
          "past": "3 agents, not kept, asked of A, 30 ms back (interpolated afresh)",
          "past_fan_out": "3 agents each asked (the fan-out), 30 ms back",
          "cached": "static segments cached (only C asked)",
          "clock": "3 agents asked the time only (the fan-out's floor, no segment work)"}


def _ready(c, bare, key: str) -> None:
    """Wait until the route over all three agents and the bare queryable answer, then ask
    the route a few times more as a realm's clients would (A's cache keeps what it is
    asked for often) and let the kept segments' samples arrive."""
    from agent.errors import UmaError
    deadline = time.monotonic() + 30
    c.cache_static_segments = False
    while True:
        try:
            r = c.pose(WORLD, HEAD, error="hops")
            if r.path == [WORLD, CAM, RIG, HEAD] and any(list(bare.get(key, timeout=1.0))):
                break
        except (LookupError, ValueError, UmaError) as exc:
            if time.monotonic() > deadline:
                raise SystemExit(f"setup failed: {exc}") from None
        time.sleep(0.2)
    for _ in range(10):
        c.pose(WORLD, HEAD, at=time.time_ns() - PAST_NS, error="hops")
        time.sleep(0.05)
    time.sleep(1.0)


def _queries(c, bare, key: str, n: int) -> dict:
    """The three kinds of query and the bare get, interleaved (the same machine load)."""
    modes = tuple(LABELS)
    clock = proto.clock_request()
    us: dict[str, list[float]] = {m: [] for m in (*modes, "bare_get")}
    cpu: dict[str, list[float]] = {m: [] for m in us}
    wall, thread = time.perf_counter_ns, time.thread_time_ns
    for i in range(len(modes) * n):
        mode = modes[i % len(modes)]
        c.cache_static_segments = mode == "cached"
        c.queries.relay = mode != "past_fan_out"
        at = time.time_ns() - PAST_NS if mode.startswith("past") else None
        t0, c0 = wall(), thread()
        if mode == "clock":
            whole = len(list(c.queries.answers(clock, AGENTS))) == len(AGENTS)
        else:
            whole = c.pose(WORLD, HEAD, at=at, error="hops").path == [WORLD, CAM, RIG, HEAD]
        t1, c1 = wall(), thread()
        replies = list(bare.get(key, payload=b"q" * 64, timeout=2.0))
        t2, c2 = wall(), thread()
        assert replies and replies[0].ok is not None and whole
        us[mode].append((t1 - t0) / 1000)
        us["bare_get"].append((t2 - t1) / 1000)
        cpu[mode].append((c1 - c0) / 1000)
        cpu["bare_get"].append((c2 - c1) / 1000)
    out = {m: {**_stats(v), "thread_cpu_median_us": float(np.median(cpu[m]))}
           for m, v in us.items()}
    b = out["bare_get"]
    for m in modes:
        out[f"ratio_{m}_to_bare_get"] = out[m]["median_us"] / b["median_us"]
    out["parts_from_a_cache"] = c.queries.cached_parts
    return out


def _streaming(c, realm: str, seconds: float) -> dict:
    """Publication -> composed pose at ``on_pose``, and the bare put -> callback anchor
    between the same processes (the tracker's session and this client's); before that, as
    long again, the tracker's encoded samples at a plain Zenoh callback here (no
    subscription: what the publisher's encoding and the agents' hops cost before the
    subscription's own work), against the bare put of that window."""
    oneway_us: list[float] = []

    def on_bare(sample) -> None:
        sent = struct.unpack("<q", sample.payload.to_bytes())[0]
        oneway_us.append((time.time_ns() - sent) / 1000)
    bare_sub = c.session.declare_subscriber(f"bench/{realm}/oneway", on_bare)
    raw_us: list[float] = []

    def on_raw(sample) -> None:
        now = time.time_ns()
        sent = peek_time(sample.payload.to_bytes(), "pose6d")
        raw_us.append((now - sent) / 1000)
    raw_sub = c.session.declare_subscriber(keys.all_data(realm, "C"), on_raw)
    time.sleep(seconds)
    raw_sub.undeclare()
    raw_anchor, oneway_us[:] = list(oneway_us), []
    latency_us: list[float] = []

    def on_pose(r) -> None:
        published = c.clock.to_remote("C", r.t_ns)
        latency_us.append((time.time_ns() - published) / 1000)
    sub = c.subscribe(WORLD, HEAD, on_pose=on_pose, error="hops")
    time.sleep(seconds)
    sub.close()
    bare_sub.undeclare()
    out = {"streaming": _stats(latency_us) if latency_us else None,
           "bare_put": _stats(oneway_us) if oneway_us else None,
           "raw_sample": _stats(raw_us) if raw_us else None,
           "raw_bare_put": _stats(raw_anchor) if raw_anchor else None}
    if latency_us and oneway_us:
        out["ratio_streaming_to_bare_put"] = (out["streaming"]["median_us"]
                                              / out["bare_put"]["median_us"])
    if raw_us and raw_anchor:
        out["ratio_raw_sample_to_bare_put"] = (out["raw_sample"]["median_us"]
                                               / out["raw_bare_put"]["median_us"])
    return out


def _print(figures: dict) -> None:
    print(f"cpu {figures['cpu']}")
    for mode in CLIENT_MODES["both"]:
        f = figures.get(mode)
        if f is None:
            continue
        b = f["bare_get"]
        print(f"[client as a Zenoh {mode}] bare Zenoh get: median {b['median_us']:.0f} us, "
              f"p99 {b['p99_us']:.0f} us, asking thread's CPU {b['thread_cpu_median_us']:.0f} us")
        for kind, label in LABELS.items():
            q = f[kind]
            print(f"[client as a Zenoh {mode}] cross-agent query, {label}: median "
                  f"{q['median_us']:.0f} us, p99 {q['p99_us']:.0f} us, ratio "
                  f"{f[f'ratio_{kind}_to_bare_get']:.2f}, asking thread's CPU "
                  f"{q['thread_cpu_median_us']:.0f} us"
                  + (" (goal <= 2.0)" if kind in ("latest", "past") else ""))
        print(f"[client as a Zenoh {mode}] segments answered from A's cache: "
              f"{f['parts_from_a_cache']}")
        o, s, r = f["bare_put"], f["streaming"], f["raw_sample"]
        if r and f["raw_bare_put"]:
            print(f"[client as a Zenoh {mode}] the tracker's encoded sample at a plain Zenoh "
                  f"callback here (no subscription, before it): median {r['median_us']:.0f} "
                  f"us, p99 {r['p99_us']:.0f} us, ratio {f['ratio_raw_sample_to_bare_put']:.2f}"
                  f" to the bare put of that window (median "
                  f"{f['raw_bare_put']['median_us']:.0f} us)")
        if o:
            print(f"[client as a Zenoh {mode}] bare Zenoh put -> subscriber callback: median "
                  f"{o['median_us']:.0f} us, p99 {o['p99_us']:.0f} us ({o['n']} puts)")
        if s:
            line = (f"[client as a Zenoh {mode}] streaming, publication -> composed pose: "
                    f"median {s['median_us']:.0f} us, p99 {s['p99_us']:.0f} us ({s['n']} poses)")
            if o:
                line += (f", ratio {f['ratio_streaming_to_bare_put']:.2f} to the bare put "
                         "(goal <= 1.5)")
            print(line)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--queries", type=int, default=1000)
    ap.add_argument("--stream-seconds", type=float, default=5.0)
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    ap.add_argument("--client-mode", choices=sorted(CLIENT_MODES), default="both",
                    help="the client's Zenoh mode: a client of agent A (the default layout), "
                         "a peer of every agent, or both in turn (default)")
    ap.add_argument("--role", default="main", choices=["main", "echo", "tracker"],
                    help=argparse.SUPPRESS)
    ap.add_argument("--listen", help=argparse.SUPPRESS)
    ap.add_argument("--connect", help=argparse.SUPPRESS)
    ap.add_argument("--key", help=argparse.SUPPRESS)
    ap.add_argument("--realm", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == "echo":
        return run_echo(args)
    if args.role == "tracker":
        return run_tracker(args)

    from agent.runtime.session import open_session
    from agent.sdk.client import Client

    # a SIGTERM ends the run through `finally`, which stops the agents it started
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    realm = f"bench{uuid.uuid4().hex[:8]}"
    ports = {name: free_port() for name in (*AGENTS, "echo")}
    ep = {name: f"tcp/127.0.0.1:{p}" for name, p in ports.items()}
    # a long lease: on a loaded machine a process stalled for more than the default 1 s
    # lease loses its links, and its tokens vanish mid-benchmark (failure detection is not
    # what this benchmark measures)
    os.environ.setdefault("UMA_LEASE_MS", "10000")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs: list[subprocess.Popen] = []
    tmp = Path(tempfile.mkdtemp(prefix="uma-bench-"))
    me = [sys.executable, str(Path(__file__).resolve())]
    try:
        for name in AGENTS:
            cmd = [sys.executable, "-m", "agent.cli", "agent", "--realm", realm, "--id", name,
                   "--listen", ep[name], "--config", _config(tmp / f"{name}.toml", EDGES[name])]
            if name != "A":
                cmd += ["--connect", ep["A"]]
            procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL))
        key = f"bench/{realm}/echo"
        procs.append(subprocess.Popen([*me, "--role", "echo", "--listen", ep["echo"], "--key",
                                       key], env=env))
        procs.append(subprocess.Popen([*me, "--role", "tracker", "--realm", realm,
                                       "--connect", ep["C"]], env=env))
        wait_listening([ports[name] for name in ("A", "echo")], 60.0)
        figures: dict = {"cpu": cpu_model()}
        with open_session("peer", None, [ep["echo"]]) as bare:
            for mode in CLIENT_MODES[args.client_mode]:
                with Client(realm=realm, connect=[ep["A"]], timeout=2.0, mode=mode) as c:
                    _ready(c, bare, key)
                    figures[mode] = {**_queries(c, bare, key, args.queries),
                                     **_streaming(c, realm, args.stream_seconds)}
    finally:
        stop_processes(procs)
    _print(figures)
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
