"""Connection and failover times of uma's matching, real processes on loopback.

One agent (``uma agent``, its own process) and pose producers (this script with
``--producer``, their own processes, 200 Hz).  The consumer is a ``Service`` in this process.

- **start -> connected**: from ``Service(...).start()`` of a new consumer to its need being
  connected (``wait_matched``) and to its first sample (the first, cold, run of the process
  is reported apart: it pays imports and first-use costs).  Baseline: a plain Zenoh session
  opened and subscribed straight to the producer's data key, to its first sample (what
  the transport alone costs, without registration and matching).
- **failover**: the preferred producer is SIGKILLed; time from the kill to the first sample
  from the backup.  Baseline: the time to the DELETE of the killed service's liveliness
  token as a plain Zenoh subscriber sees it (the detection floor Zenoh gives).  Then the
  same with a *frozen* producer (SIGSTOP: no socket closes, the 1 s lease decides).
  After each run a new preferred producer is started and the consumer moves back to it.

    python bench/bench_failover.py [--runs 12] [--freeze-runs 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

from summary import median_p99

from agent.runtime.processes import stop_processes

ROOT = str(Path(__file__).resolve().parents[1])
RATE_HZ = 200.0


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def producer(args: argparse.Namespace) -> int:
    """Child mode: publish a pose at RATE_HZ until killed."""
    from agent.sdk.service import Service
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with Service(args.producer, realm=args.realm, agent="bench", connect=[args.connect]) as svc:
        out = svc.ability("pose", type="pose6d", edge=("ivy/world", "alice/head"),
                          latency_s=args.latency)
        svc.start()
        print("ready", flush=True)
        while not stop.wait(1.0 / RATE_HZ):
            out.publish(time.time_ns(), [0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0])
    return 0


class Bench:
    def __init__(self, realm: str, ep: str) -> None:
        self.realm, self.ep = realm, ep
        self.procs: list[subprocess.Popen] = []

    def spawn(self, *args: str, wait_for: str) -> subprocess.Popen:
        env = dict(os.environ, PYTHONUNBUFFERED="1",
                   PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
        p = subprocess.Popen([sys.executable, *args], env=env, cwd=ROOT, text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        self.procs.append(p)
        deadline = time.monotonic() + 30
        for line in p.stdout:
            if wait_for in line:
                return p
            if time.monotonic() > deadline:
                break
        raise RuntimeError(f"{args} did not start (exit {p.poll()})")

    def start_producer(self, sid: str, latency: float) -> subprocess.Popen:
        return self.spawn(__file__, "--producer", sid, "--realm", self.realm, "--connect",
                          self.ep, "--latency", str(latency), wait_for="ready")

    def stop_all(self) -> None:
        stop_processes(self.procs)


class Consumer:
    """A consumer Service in this process that timestamps the first sample per source."""

    def __init__(self, sid: str, realm: str, ep: str) -> None:
        from agent.sdk.service import Service
        self.first: dict[str, float] = {}
        self.event = threading.Event()
        self.svc = Service(sid, realm=realm, agent="bench", connect=[ep])
        self.svc.need("head", type="pose6d", edge=("ivy/world", "*/head"),
                      prefer="latency_s", on_sample=self.on_sample)

    def on_sample(self, m) -> None:
        if m.source not in self.first:
            self.first[m.source] = time.perf_counter()
            self.event.set()

    def wait_first(self, source: str, timeout: float = 20.0) -> float:
        deadline = time.monotonic() + timeout
        while source not in self.first:
            if time.monotonic() > deadline:
                raise RuntimeError(f"no sample from {source} within {timeout} s")
            self.event.wait(0.05)
            self.event.clear()
        return self.first[source]


def measure_connect(b: Bench, runs: int) -> tuple[list[float], list[float], list[float]]:
    from agent.protocol import keys
    from agent.runtime.session import open_session
    to_match, to_sample, direct = [], [], []
    key = keys.data(b.realm, "bench", "cam0", "pose")
    for i in range(runs):
        t0 = time.perf_counter()
        c = Consumer(f"probe{i}", b.realm, b.ep)
        c.svc.start()
        c.svc.wait_matched("head", timeout=20)
        t1 = time.perf_counter()
        t2 = c.wait_first("cam0")
        c.svc.close()
        to_match.append(t1 - t0)
        to_sample.append(t2 - t0)
        got = threading.Event()
        t0 = time.perf_counter()
        with open_session(connect=[b.ep]) as s:
            sub = s.declare_subscriber(key, lambda _s, ev=got: ev.set())
            got.wait(20)
            direct.append(time.perf_counter() - t0)
            sub.undeclare()
    return to_match, to_sample, direct


def measure_failover(b: Bench, runs: int, sig: int = signal.SIGKILL, tag: str = "best",
                     ) -> tuple[list[float], list[float]]:
    """Kill (or freeze, ``SIGSTOP``) the preferred producer ``runs`` times; returns the
    times to the backup's first sample and to the token's DELETE."""
    import zenoh

    from agent.protocol import keys
    from agent.runtime.session import open_session
    failover, detect = [], []
    deleted: dict[str, float] = {}
    watcher = open_session(connect=[b.ep])

    def on_token(smp: zenoh.Sample) -> None:
        if smp.kind == zenoh.SampleKind.DELETE:
            deleted[str(smp.key_expr).rsplit("/", 1)[-1]] = time.perf_counter()
    sub = watcher.liveliness().declare_subscriber(keys.service_tokens(b.realm, "bench"),
                                                  on_token)
    c = Consumer("consumer", b.realm, b.ep)
    c.svc.start()
    try:
        for i in range(runs):
            best = f"{tag}{i}"
            p = b.start_producer(best, latency=0.001)
            c.svc.wait_matched("head", timeout=20,
                               until=lambda ms, s=best: [m.service_id for m in ms] == [s])
            c.wait_first(best)
            time.sleep(0.2)  # samples of the backup from before the move are delivered
            c.first.pop("cam0", None)
            t_kill = time.perf_counter()
            p.send_signal(sig)
            t_backup = c.wait_first("cam0")
            p.kill()  # a frozen one too (SIGKILL ends stopped processes)
            p.wait(5)
            failover.append(t_backup - t_kill)
            deadline = time.monotonic() + 5
            while best not in deleted and time.monotonic() < deadline:
                time.sleep(0.01)
            if best in deleted:
                detect.append(deleted[best] - t_kill)
    finally:
        c.svc.close()
        sub.undeclare()
        watcher.close()
    return failover, detect


def stats(name: str, xs: list[float], out: dict[str, float]) -> None:
    """Adds ``<name>_median_ms`` and ``<name>_p99_ms`` of durations ``xs`` in seconds."""
    for k, v in median_p99([1e3 * x for x in xs], "ms").items():
        out[f"{name}_{k}"] = v


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=12, help="runs per measurement (>= 10)")
    ap.add_argument("--freeze-runs", type=int, default=5,
                    help="runs with a frozen (SIGSTOP) producer, ~1 s each (lease)")
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    ap.add_argument("--producer", help=argparse.SUPPRESS)
    ap.add_argument("--realm", help=argparse.SUPPRESS)
    ap.add_argument("--connect", help=argparse.SUPPRESS)
    ap.add_argument("--latency", type=float, default=0.01, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.producer:
        return producer(args)

    realm = f"bench{uuid.uuid4().hex[:8]}"
    ep = free_endpoint()
    b = Bench(realm, ep)
    try:
        b.spawn("-m", "agent.cli", "agent", "--realm", realm, "--id", "bench", "--listen", ep,
                wait_for="listening on")
        b.start_producer("cam0", latency=0.01)  # the backup, always there
        to_match, to_sample, direct = measure_connect(b, args.runs + 1)
        cold = to_match.pop(0)  # the first Service of a process pays imports and warm-up
        to_sample.pop(0)
        direct.pop(0)
        failover, detect = measure_failover(b, args.runs)
        frozen, lease = measure_failover(b, args.freeze_runs, signal.SIGSTOP, "frozen")
    finally:
        b.stop_all()
    figures: dict[str, float] = {"runs": args.runs, "cold_start_to_connected_ms": 1e3 * cold}
    stats("start_to_connected", to_match, figures)
    stats("start_to_first_sample", to_sample, figures)
    stats("baseline_direct_subscribe_first_sample", direct, figures)
    stats("failover_sigkill_to_backup_sample", failover, figures)
    stats("baseline_zenoh_token_delete", detect, figures)
    if frozen:
        stats("failover_sigstop_to_backup_sample", frozen, figures)
        stats("sigstop_token_delete_lease", lease, figures)
    figures["failover_over_detection_ratio"] = (
        figures["failover_sigkill_to_backup_sample_median_ms"]
        / figures["baseline_zenoh_token_delete_median_ms"])
    for k, v in figures.items():
        print(f"{k:48s} {v:.3f}" if isinstance(v, float) else f"{k:48s} {v}")
    if args.json:
        print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
