"""The latency cost of a secured site: TLS with mutual authentication and the router's
access control (``uma deploy config``) against plain TCP, measured in the same run.

Three Zenoh routers run on loopback, each a ``uma router`` process: plain TCP (the anchor),
TLS with mTLS, and TLS with mTLS and the access control of ``uma deploy config``.  For each,
two client sessions of this process attach to it with the certificates of two agent hosts
``a`` and ``b`` (uma's own session settings, :mod:`agent.runtime.session`), and

1. **query**: ``a`` asks ``uma/R/agent/b/query`` and ``b``'s queryable answers a 200-byte
   reply: the round trip of a ``get`` through the router;
2. **stream**: ``a`` publishes ``pose6d`` samples on ``uma/R/data/a/cam/pose`` at 200 Hz
   and ``b`` subscribes: publication to delivery (one clock, one process).

Rounds of the three variants are interleaved, each going first in turn, so that the load
of a shared machine falls on all of them alike.  Prints median and p99 of each, and each
variant's ratio to plain TCP.

Usage: python bench/bench_tls.py [--queries N] [--samples N] [--rounds N] [--json]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from loopback import free_port
from summary import cpu_model, median_p99, report

from agent.deploy.certs import SiteSpec, create_site
from agent.deploy.zenoh_config import write_configs
from agent.runtime.processes import stop_processes
from agent.runtime.session import close_session, open_session
from schemas.codec import decode_measurement, encode_pose

REALM = "bench"
VARIANTS = ("tcp", "tls", "tls_acl")
ROOT = Path(__file__).resolve().parents[1]




class Variant:
    """One router and the two sessions attached to it."""

    def __init__(self, name: str, directory: Path) -> None:
        self.name = name
        port = free_port()
        scheme = "tcp" if name == "tcp" else "tls"
        self.endpoint = f"{scheme}/127.0.0.1:{port}"
        self.query: list[float] = []
        self.stream: list[float] = []
        router_cfg, self.member_cfg = self._configs(directory)
        args = [sys.executable, "-m", "agent.cli", "router", "--listen", self.endpoint]
        if router_cfg:
            args += ["--config", router_cfg]
        self.router = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE,
                                       stderr=subprocess.PIPE, text=True)
        line = self.router.stdout.readline()
        if "listening on" not in line:
            raise SystemExit(f"the {name} router did not start: {self.router.stderr.read()}")
        self.a = open_session("client", None, [self.endpoint], base_file=self.member_cfg["a"])
        self.b = open_session("client", None, [self.endpoint], base_file=self.member_cfg["b"])

    def _configs(self, directory: Path) -> tuple[str | None, dict[str, str | None]]:
        if self.name == "tcp":
            return None, {"a": None, "b": None}
        spec = SiteSpec(site=self.name, router="r", hosts=["a", "b"],
                        addresses={"r": ["127.0.0.1"]})
        root = directory / self.name
        create_site(root, spec, days=1)
        write_configs(root, spec, REALM, [self.endpoint], [self.endpoint])
        router = root / "hosts" / "r" / "router.json5"
        if self.name == "tls":  # the same TLS, no access control
            text = router.read_text().replace('"enabled": true', '"enabled": false')
            router.write_text(text)
        return str(router), {h: str(root / "hosts" / h / "service.json5") for h in "ab"}

    def close(self) -> None:
        close_session(self.a)
        close_session(self.b)
        stop_processes([self.router])


def measure_queries(v: Variant, n: int) -> None:
    key = f"uma/{REALM}/agent/b/query"
    reply = b"x" * 200
    queryable = v.b.declare_queryable(key, lambda q: q.reply(key, reply))
    try:
        for _ in range(3):  # warm-up: routes and caches
            list(v.a.get(key, timeout=2.0))
        for _ in range(n):
            t0 = time.perf_counter()
            got = [r for r in v.a.get(key, timeout=2.0) if r.ok is not None]
            dt = time.perf_counter() - t0
            if got:
                v.query.append(dt * 1e6)
    finally:
        queryable.undeclare()


def measure_stream(v: Variant, n: int, rate_hz: float = 200.0) -> None:
    key = f"uma/{REALM}/data/a/cam/pose"
    done = threading.Event()
    seen: list[float] = []

    def on_sample(sample) -> None:
        now = time.time_ns()
        m = decode_measurement(sample.payload.to_bytes())
        if m.seq is not None and m.seq > 0:
            seen.append((now - m.t_ns) / 1e3)
        if len(seen) >= n:
            done.set()

    sub = v.b.declare_subscriber(key, on_sample)
    pub = v.a.declare_publisher(key)
    try:
        time.sleep(0.2)
        pub.put(encode_pose(time.time_ns(), [0, 0, 0], [0, 0, 0, 1], seq=0))  # warm-up
        for i in range(n):
            pub.put(encode_pose(time.time_ns(), [0.1, 0.2, 0.3], [0, 0, 0, 1], seq=i + 1))
            time.sleep(1.0 / rate_hz)
        done.wait(2.0)
    finally:
        pub.undeclare()
        sub.undeclare()
    v.stream.extend(seen)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--queries", type=int, default=300, help="queries per variant and round")
    ap.add_argument("--samples", type=int, default=300, help="samples per variant and round")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds")
    ap.add_argument("--json", action="store_true", help="also print one JSON object")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        variants = [Variant(name, Path(tmp)) for name in VARIANTS]
        try:
            for k in range(args.rounds):
                for v in variants[k % 3:] + variants[:k % 3]:  # each goes first in turn
                    measure_queries(v, args.queries)
                    measure_stream(v, args.samples)
        finally:
            for v in variants:
                v.close()
    figures: dict[str, object] = {"cpu": cpu_model()}
    anchor = {kind: median_p99(getattr(variants[0], kind), "us") for kind in ("query", "stream")}
    for v in variants:
        for kind in ("query", "stream"):
            samples = getattr(v, kind)
            stats = median_p99(samples, "us")
            figures[f"{kind}_{v.name}_median_us"] = stats["median_us"]
            figures[f"{kind}_{v.name}_p99_us"] = stats["p99_us"]
            figures[f"{kind}_{v.name}_n"] = len(samples)
            figures[f"{kind}_{v.name}_ratio_to_tcp"] = (
                stats["median_us"] / anchor[kind]["median_us"])
    report(figures, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
