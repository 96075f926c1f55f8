"""Benchmark of one loaded host: N services in P processes publishing at R Hz, agents as
peers on loopback (issue 23's table, same recipe).

Per configuration it reports the agents' CPU (each), the services' CPU and RSS (per
service beyond one process's base), the TCP links of every process, `uma services` and
`uma query` wall time, `Client.pose` median and p99, the time from a new need's `start()`
to its first sample and how many samples that need lost over the window. The anchor,
measured in the same run: bare Zenoh publishers (same processes, same keys, same payload,
same rate, client mode) into one bare wildcard subscriber. "Above publishing" is uma's
total CPU (agents + services) minus the bare publishers' alone: the strict reading (the
bare subscriber's CPU is reported beside it, not subtracted).

    python bench/bench_host_load.py [--services 100] [--per-process 10] [--rate 100]
        [--agents 3] [--seconds 10] [--table] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

from summary import cpu_model, median_p99

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from agent.runtime.processes import established_tcp, stop_processes  # noqa: E402

TABLE = [(10, 100.0), (50, 100.0), (100, 100.0), (10, 10.0), (100, 10.0)]
SINK = ("import sys, time, zenoh, json\n"
        "from agent.runtime.session import open_session\n"
        "s = open_session('peer', [sys.argv[1]], [])\n"
        "n = [0]\n"
        "sub = s.declare_subscriber(sys.argv[2], lambda smp: n.__setitem__(0, n[0] + 1))\n"
        "print('started', flush=True)\n"
        "sys.stdin.readline()\n"
        "print('received', n[0], flush=True)\n"
        "s.close()\n")


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
    return 0.0


def python(*args: str, stdin: bool = False) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT), UMA_LEASE_MS=os.environ.get(
        "UMA_LEASE_MS", "1000"))
    return subprocess.Popen([sys.executable, *args], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL)


def wait_started(procs: list[subprocess.Popen], timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    for p in procs:
        line = ""
        while "started" not in line:  # bounded: readline returns at EOF, deadline below
            line = p.stdout.readline()
            if not line or time.monotonic() > deadline:
                raise RuntimeError(f"process {p.args[1:3]} did not start (exit {p.poll()})")


def cpu_percent(procs: list[subprocess.Popen], seconds: float) -> list[float]:
    before = [cpu_s(p.pid) for p in procs]
    t0 = time.monotonic()
    time.sleep(seconds)
    dt = time.monotonic() - t0
    return [100 * (cpu_s(p.pid) - b) / dt for p, b in zip(procs, before, strict=True)]


def timed_cli(*args: str, runs: int = 3) -> dict:
    times, ok, last = [], 0, ""
    for _ in range(runs):
        t = time.monotonic()
        out = subprocess.run([sys.executable, "-m", "agent.cli", *args], cwd=ROOT,
                             capture_output=True, text=True, timeout=120)
        times.append(time.monotonic() - t)
        ok += out.returncode == 0
        last = out.stdout if out.returncode == 0 else out.stderr[-300:]
    return {"median_s": statistics.median(times), "max_s": max(times), "ok": ok,
            "runs": runs, "last": last}


def bare_anchor(n: int, k: int, rate: float, seconds: float) -> dict:
    """CPU of bare Zenoh publishers at the same total rate, into one bare subscriber."""
    ep = free_endpoint()
    sink = python("-c", SINK, ep, "uma/bare/data/**", stdin=True)
    procs = [sink]
    try:
        wait_started([sink])
        pubs = [python("bench/host_load_services.py", "bare", "bare", ep, str(i * k), str(k),
                       str(rate), str(seconds + 30), "--bare") for i in range(n // k)]
        procs += pubs
        wait_started(pubs)
        time.sleep(2.0)
        cpu = cpu_percent(procs, seconds)
        return {"publishers_cpu_pct": sum(cpu[1:]), "subscriber_cpu_pct": cpu[0],
                "publisher_rss_mb": sum(rss_mb(p.pid) for p in pubs)}
    finally:
        stop_processes(procs)


def run_config(n: int, k: int, rate: float, n_agents: int, seconds: float) -> dict:
    from agent import Client

    realm = f"load{os.getpid()}x{n}x{int(rate)}"
    eps = [free_endpoint() for _ in range(n_agents)]
    agents = [python("-m", "agent.cli", "agent", "--realm", realm, "--id", f"h{i}",
                     "--listen", ep, *(["--connect", eps[0]] if i else []))
              for i, ep in enumerate(eps)]
    procs = list(agents)
    try:
        for a in agents:  # the agent prints its endpoints once up
            deadline = time.monotonic() + 60
            while "listening on" not in a.stdout.readline():
                if time.monotonic() > deadline or a.poll() is not None:
                    raise RuntimeError("an agent did not start")
        base = python("bench/host_load_services.py", realm, "h0", eps[0], "0", "0", str(rate),
                      str(seconds + 120))
        services = [python("bench/host_load_services.py", realm, "h0", eps[0], str(i * k),
                           str(k), str(rate), str(seconds + 120)) for i in range(n // k)]
        procs += [base, *services]
        wait_started([base, *services])
        time.sleep(3.0)  # registrations, matches and summaries settle
        cpu = cpu_percent(agents + services, seconds)
        links = {"agents": [established_tcp(a.pid) for a in agents],
                 "services": [established_tcp(p.pid) for p in services]}
        rss = [rss_mb(p.pid) for p in services]
        base_rss = rss_mb(base.pid)
        listed = timed_cli("services", "--realm", realm, "--connect", eps[1 % n_agents],
                           "--json")
        count = 0
        if listed["ok"]:
            count = sum(len(a["services"]) for a in json.loads(listed["last"])["agents"])
        query = timed_cli("query", "ivy/world", "obj/0", "--realm", realm, "--connect",
                          eps[-1])
        figures = {"services": n, "per_process": k, "rate_hz": rate, "agents": n_agents,
                   "agents_cpu_pct": [round(c, 1) for c in cpu[:n_agents]],
                   "services_cpu_pct": round(sum(cpu[n_agents:]), 1),
                   "services_rss_mb": round(sum(rss), 1),
                   "rss_per_service_mb": round((sum(rss) - base_rss * len(services)) / n, 2),
                   "process_base_rss_mb": round(base_rss, 1),
                   "tcp_links": links, "max_links_per_service_process": max(links["services"]),
                   "uma_services_s": round(listed["median_s"], 3),
                   "uma_services_ok": f"{listed['ok']}/{listed['runs']}",
                   "uma_services_listed": count,
                   "uma_query_s": round(query["median_s"], 3),
                   "uma_query_ok": f"{query['ok']}/{query['runs']}"}
        with Client(realm=realm, connect=[eps[-1]]) as client:
            lat, failed = [], []
            for _ in range(200):  # bounded
                t = time.perf_counter()
                try:
                    client.pose("ivy/world", f"obj/{n - 1}")
                except (LookupError, ValueError) as exc:  # a saturated host: count, go on
                    failed.append(str(exc)[:120])
                    continue
                lat.append((time.perf_counter() - t) * 1e3)
        figures["client_pose"] = ({k2: round(v, 3) for k2, v in median_p99(lat, "ms").items()}
                                  if lat else {})
        figures["client_pose_failed"] = len(failed)
        figures["client_pose_first_failure"] = failed[0] if failed else None
        figures.update(new_need(realm, eps[0], rate, seconds))
        return figures
    finally:
        stop_processes(procs)


def new_need(realm: str, ep: str, rate: float, seconds: float) -> dict:
    """A fresh service needs one running ability: start() to first sample, and what the
    need then receives over ``seconds`` against what was published."""
    from agent import Service

    got: list[int] = []
    first = threading.Event()

    def on_sample(m) -> None:
        got.append(m.seq)
        first.set()
    svc = Service("newneed", realm=realm, agent="h0", connect=[ep])
    svc.need("obj", type="pose6d", edge=("ivy/world", "obj/0"), on_sample=on_sample)
    t = time.perf_counter()
    svc.start()
    arrived = first.wait(30.0)
    latency_ms = (time.perf_counter() - t) * 1e3 if arrived else None
    time.sleep(seconds)
    svc.close()
    span = (max(got) - min(got) + 1) if got else 0
    return {"new_need_first_sample_ms": None if latency_ms is None else round(latency_ms, 1),
            "need_received": len(got), "need_expected": span,
            "need_lost": span - len(set(got))}


def main() -> int:
    p = argparse.ArgumentParser(prog="bench_host_load", description=__doc__.splitlines()[0])
    p.add_argument("--services", type=int, default=100)
    p.add_argument("--per-process", type=int, default=10)
    p.add_argument("--rate", type=float, default=100.0)
    p.add_argument("--agents", type=int, default=3)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--table", action="store_true", help="run the issue's five rows")
    p.add_argument("--json", action="store_true")
    a = p.parse_args()
    if a.services < 1 or a.per_process < 1 or a.services % a.per_process or a.agents < 1:
        p.error("--services must be a positive multiple of --per-process; --agents >= 1")
    rows = [(n, r) for n, r in TABLE] if a.table else [(a.services, a.rate)]
    out = {"cpu": cpu_model(), "rows": []}
    for n, rate in rows:
        k = min(a.per_process, n)
        row = run_config(n, k, rate, a.agents, a.seconds)
        anchor = bare_anchor(n, k, rate, a.seconds)
        total = sum(row["agents_cpu_pct"]) + row["services_cpu_pct"]
        row["anchor"] = {key: round(v, 1) for key, v in anchor.items()}
        row["uma_cpu_above_publishing_pct"] = round(total - anchor["publishers_cpu_pct"], 1)
        out["rows"].append(row)
        if not a.json:
            print(f"{n} services @ {rate:g} Hz in {n // k} processes, {a.agents} agents: "
                  f"agents {row['agents_cpu_pct']} % CPU, services {row['services_cpu_pct']} %"
                  f" (bare publishers {anchor['publishers_cpu_pct']:.1f} %, uma above them "
                  f"{row['uma_cpu_above_publishing_pct']} %); RSS/service "
                  f"{row['rss_per_service_mb']} MB; links/process "
                  f"{row['max_links_per_service_process']}; uma services "
                  f"{row['uma_services_s']} s ({row['uma_services_listed']} listed), "
                  f"uma query {row['uma_query_s']} s ({row['uma_query_ok']} ok); Client.pose "
                  f"{row['client_pose']} ({row['client_pose_failed']} of 200 failed); "
                  f"new need {row['new_need_first_sample_ms']} ms, lost "
                  f"{row['need_lost']}/{row['need_expected']}", flush=True)
    if a.json:
        print(json.dumps(out))
    else:
        print(f"cpu: {out['cpu']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
