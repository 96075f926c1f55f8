"""``uma services`` at site scale: N hosts in network namespaces, one agent each
with K services in one process (10 Hz each by default), and ``uma services --json`` run
from a host of its own against the first agent.  Needs root (``ip netns``).

Reports: the time to form the realm (agents started to the first listing with all
services; also when every agent listened and every service process had started), the
wall time of ``uma services`` (process start to exit, as a person sees it; median / p99 of
``--runs``), the same command's phases measured inside one process (start-up and imports,
session open, ``collect``, close) and, apart, one liveliness query for the agents and one
query for every agent's snapshot; the machine's load; the CPU of the agents and of the
service processes (% of one core, while idle and publishing).  The issue's goal: ``uma services``
lists all 200 services of 20 agents within 1 s.

    python bench/bench_site_scale.py [--agents 20] [--services 10] [--rate 10] [--runs 10]
        [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import uuid
from pathlib import Path

from summary import median_p99, report

ROOT = Path(__file__).resolve().parents[1]
#: the harness (tests/agent_helpers) is imported by the functions that use it, so that the
#: probe mode, which times the imports of `uma services`, does not count its imports
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]
CPU_WINDOW_S = 5.0


def process_age_s() -> float:
    """Seconds since this process started (10 ms resolution: clock ticks of /proc)."""
    started = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
    uptime = float(Path("/proc/uptime").read_text().split()[0])
    return uptime - started / os.sysconf("SC_CLK_TCK")


def probe(realm: str, connect: str) -> int:
    """Child mode, run on the client host: the phases of one ``uma services``, in s (this
    mode imports only what ``uma services`` does)."""
    # what `uma services` imports (main: its grammar)
    from agent.cli import main, services  # noqa: F401
    from agent.protocol import keys
    from agent.runtime.session import close_session, open_session, query
    from agent.sdk import inventory
    startup = process_age_s()
    t_import = time.perf_counter()
    session = open_session("client", None, [connect], realm, require_connection=True)
    t_open = time.perf_counter()
    listing = inventory.collect_realm(session, realm, 2.0, settle_s=0.0)  # as a client does
    t_collect = time.perf_counter()
    agents = inventory.live_agents(session, realm, 2.0)
    t_live = time.perf_counter()
    replies = query(session, keys.all_agent_services(realm), 2.0)
    t_snap = time.perf_counter()
    close_session(session)
    t_close = time.perf_counter()
    print(json.dumps({
        "startup_and_import_s": startup, "open_s": t_open - t_import,
        "collect_s": t_collect - t_open, "close_s": t_close - t_snap,
        "liveliness_query_s": t_live - t_collect, "snapshot_query_s": t_snap - t_live,
        "agents": len(listing["agents"]), "live": len(agents), "snapshots": len(replies),
        "services": sum(len(a["services"]) for a in listing["agents"])}))
    return 0


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "unknown"


def spread(name: str, values: list[float], unit: str) -> dict[str, float]:
    """Mean, max and total of per-process figures, keyed ``<name>_mean_<unit>`` etc."""
    return {f"{name}_mean_{unit}": statistics.fmean(values), f"{name}_max_{unit}": max(values),
            f"{name}_total_{unit}": sum(values)}


def measure(args: argparse.Namespace) -> dict[str, object]:
    from agent_helpers import scale
    from agent_helpers.site import Site
    realm = f"bench{uuid.uuid4().hex[:8]}"
    site = Site(args.agents + 1).build()
    try:
        started = time.monotonic()
        realm_ = scale.start(site, realm)
        agents_s = time.monotonic() - started
        scale.add_services(realm_, args.services, args.rate)
        services_s = time.monotonic() - started
        realm_.wait_listed(args.services)
        figures: dict[str, object] = {"cpu": cpu_model(), "load_1min": os.getloadavg()[0],
                                      "agents": args.agents,
                                      "services_per_agent": args.services,
                                      "rate_hz": args.rate,
                                      "agents_listening_s": agents_s,
                                      "services_started_s": services_s,
                                      "realm_formed_s": time.monotonic() - started}
        figures |= spread("agent_cpu", scale.cpu_percent(realm_.agents, CPU_WINDOW_S), "pct")
        figures |= spread("services_process_cpu",
                          scale.cpu_percent(realm_.services, CPU_WINDOW_S), "pct")
        walls, complete = [], 0
        for _ in range(args.runs):
            listing, wall = realm_.services_json()
            walls.append(wall)
            complete += scale.complete(listing, args.agents, args.services)
        figures |= {"runs": args.runs, "complete_listings": complete}
        figures |= {f"uma_services_wall_{k}": v for k, v in median_p99(walls, "s").items()}
        phases = [json.loads(site.run(realm_.client, [
            __file__, "--probe", realm, realm_.seed.endpoint()], 60).stdout)
            for _ in range(args.runs)]
        for key in ("startup_and_import_s", "open_s", "collect_s", "close_s", "liveliness_query_s",
                    "snapshot_query_s"):
            figures[f"phase_{key[:-2]}_median_s"] = statistics.median(p[key] for p in phases)
        return figures
    finally:
        site.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", type=int, default=20)
    ap.add_argument("--services", type=int, default=10, help="services per agent")
    ap.add_argument("--rate", type=float, default=10.0, help="Hz per service")
    ap.add_argument("--runs", type=int, default=10, help="runs of uma services")
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    ap.add_argument("--probe", nargs=2, metavar=("REALM", "CONNECT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.probe:
        return probe(*args.probe)
    from agent_helpers.site import unavailable

    reason = unavailable()
    if reason:
        print(f"bench_site_scale: {reason}", file=sys.stderr)
        return 2
    report(measure(args), args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
