"""The least a sample at a tracker's rate can cost on this machine, no uma code involved.

Issue 19's streaming goal is absolute (a median of 200 us from publication to the composed
pose), so it depends on what the machine gives any process that wakes up once per sample.
Two figures, each at several sample rates:

1. a bare Zenoh put from one process to a subscriber callback in another (direct peers on
   loopback, a 100-byte payload stamped at the put): the one-way time at 100 Hz (the
   tracker's rate in ``bench_query_remote``), 1 kHz and 5 kHz;
2. a short stretch of Python (a 10-iteration float loop) timed hot and after the gap
   between samples at those rates, the gap spent busy-waiting: on a virtual machine whose
   caches are shared with other tenants, code that ran 10 ms ago may have to be fetched
   again.

The ratios to the fastest rate say how much of a 100 Hz sample's latency is the machine's
waking up rather than work.

Usage: python bench/bench_idle_floor.py [--puts N] [--json]
"""

from __future__ import annotations

import argparse
import json
import struct
import subprocess
import sys
import time
from pathlib import Path

from loopback import free_port, wait_listening, zenoh_config
from summary import cpu_model, median_p99

RATES_HZ = (100.0, 1000.0, 5000.0)
KEY = "floor/oneway"



def run_publisher(connect: str, puts: int) -> None:
    """Put ``puts`` stamped samples at each rate in turn (a pause between the rates)."""
    import zenoh
    with zenoh.open(zenoh_config(connect=connect)) as s:
        pub = s.declare_publisher(KEY)
        time.sleep(1.0)  # the subscriber's declaration reaches this session
        for rate in RATES_HZ:
            for _ in range(puts):
                pub.put(struct.pack("<qd", time.time_ns(), rate) + b"x" * 84)
                time.sleep(1.0 / rate)
            time.sleep(0.2)


def _oneway(puts: int) -> dict[float, list[float]]:
    """One-way microseconds per rate, received here from a publisher process."""
    import zenoh
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    got: dict[float, list[float]] = {rate: [] for rate in RATES_HZ}

    def on_sample(sample) -> None:
        sent, rate = struct.unpack("<qd", sample.payload.to_bytes()[:16])
        got[rate].append((time.time_ns() - sent) / 1000)
    with zenoh.open(zenoh_config(listen=endpoint)) as s:
        s.declare_subscriber(KEY, on_sample)
        wait_listening([port], 30.0)
        publisher = subprocess.Popen([sys.executable, str(Path(__file__).resolve()),
                                      "--role", "publisher", endpoint, str(puts)])
        try:
            publisher.wait(timeout=60 + puts * sum(1.0 / r for r in RATES_HZ))
        finally:
            if publisher.poll() is None:
                publisher.kill()
                publisher.wait()
        time.sleep(0.2)
    if any(not v for v in got.values()):
        raise SystemExit(f"no sample arrived at some rate: {({r: len(v) for r, v in got.items()})}")
    return got


def _loop() -> float:
    s = 0.0
    for i in range(10):
        s += i * 0.5
    return s


def _after_gap(gap_s: float, n: int) -> list[float]:
    """Microseconds of ``_loop`` run ``n`` times, each after ``gap_s`` of busy-waiting."""
    out = []
    clock = time.perf_counter
    for _ in range(n):
        end = clock() + gap_s
        while clock() < end:
            pass
        t0 = time.perf_counter_ns()
        _loop()
        out.append((time.perf_counter_ns() - t0) / 1000)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--puts", type=int, default=500, help="samples per rate (default 500)")
    ap.add_argument("--json", action="store_true", help="last line: one JSON object")
    ap.add_argument("--role", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role:
        return run_publisher(args.role[1], int(args.role[2]))
    if args.puts < 1:
        ap.error(f"--puts must be at least 1, got {args.puts}")
    oneway = _oneway(args.puts)
    fastest = RATES_HZ[-1]
    figures: dict = {"cpu": cpu_model(), "puts_per_rate": args.puts}
    for rate in RATES_HZ:
        put = median_p99(oneway[rate], "us")
        loop = median_p99(_after_gap(1.0 / rate, min(args.puts, 300)), "us")
        figures[f"{rate:g}_hz"] = {"bare_put": put, "python_loop": loop}
    figures["hot_python_loop"] = median_p99(_after_gap(0.0, 300), "us")
    top = figures[f"{fastest:g}_hz"]["bare_put"]["median_us"]
    print(f"cpu {figures['cpu']}")
    for rate in RATES_HZ:
        f = figures[f"{rate:g}_hz"]
        f["bare_put_ratio_to_fastest"] = f["bare_put"]["median_us"] / top
        print(f"{rate:6g} Hz: bare Zenoh put -> callback median {f['bare_put']['median_us']:6.0f}"
              f" us, p99 {f['bare_put']['p99_us']:6.0f} us ({f['bare_put_ratio_to_fastest']:.2f}x"
              f" the {fastest:g} Hz one); a 10-iteration Python loop after the gap "
              f"{f['python_loop']['median_us']:6.2f} us")
    print(f"the same loop hot: {figures['hot_python_loop']['median_us']:.2f} us")
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
