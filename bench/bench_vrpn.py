"""The VRPN bridges: the latency each adds, and how many VRPN clients one vrpn-out serves.

Real processes on loopback: one agent, ``uma service run vrpn-out`` and ``uma service run
vrpn-in``; this script is the uma source and sink and the VRPN client and server, and
times everything on this host's one clock.

- **out**: this process publishes a uma pose (a ``Service`` ability, 100 Hz) whose x is its
  sequence number; vrpn-out streams it (``--serve``); this process's VRPN client (TCP)
  receives it.  Latency: receive time minus publish time.
- **in**: this process is a VRPN server sending Pos_Quat reports (100 Hz, x = sequence
  number); vrpn-in (UDP handshake) publishes them; a ``Service`` need of this process
  receives them.  Latency: receive time minus send time.
- **anchor**: a bare Zenoh publication from this process to a subscriber in a child
  process, both Zenoh clients of the agent like the services: one uma hop without uma.
- **clients**: N VRPN clients (TCP, read by one child process) of one vrpn-out while the
  source publishes at 300 Hz; N is served when every client gets at least 90 % of the
  reports the source published and vrpn-out uses under 90 % of one core.  A straight line
  through vrpn-out's CPU against N (served rows) gives its cost per client and report and
  the N one whole core would serve (extrapolated: a loaded host never gives it that core).

    python bench/bench_vrpn.py [--samples 1000] [--clients 1,10,50,100,200,300] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import selectors
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

from summary import cpu_model, median_p99, report

from agent.runtime.processes import stop_processes
from services.vrpn import protocol as vp

ROOT = str(Path(__file__).resolve().parents[1])
RATE_HZ = 100.0
CLIENT_RATE_HZ = 300.0
SERVED_SHARE = 0.9


def free_port() -> int:
    """A port free for TCP and UDP (a VRPN server takes both)."""
    for _ in range(50):
        with socket.socket() as t, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
            t.bind(("127.0.0.1", 0))
            port = t.getsockname()[1]
            try:
                u.bind(("127.0.0.1", port))
                return port
            except OSError:
                continue
    raise RuntimeError("no free port")


# ------------------------------------------------------------------ child modes

def zenoh_subscriber(ep: str, key: str, count: int) -> int:
    """Child: receive ``count`` bare Zenoh samples (payload: publish time in ns), print
    their latencies (ns) as JSON."""
    from agent.runtime.session import open_session
    got: list[int] = []
    done = threading.Event()

    def on_sample(smp) -> None:
        got.append(time.time_ns() - int(bytes(smp.payload.to_bytes())))
        if len(got) >= count:
            done.set()
    session = open_session("client", connect=[ep])
    sub = session.declare_subscriber(key, on_sample)
    print("ready", flush=True)
    done.wait(120)
    sub.undeclare()
    print(json.dumps(got[:count]), flush=True)
    session.close()
    return 0


def readers(port: int, n: int, warm_s: float, seconds: float) -> int:
    """Child: ``n`` VRPN TCP clients; print each one's rate of Pos_Quat reports over
    ``seconds`` after ``warm_s`` (counted by bytes: every report is one 88-byte message)."""
    sel = selectors.DefaultSelector()
    socks = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port))
        s.sendall(vp.cookie())
        s.setblocking(False)
        sel.register(s, selectors.EVENT_READ, len(socks))
        socks.append(s)
    print("ready", flush=True)
    counted = [0] * n
    start = time.monotonic() + warm_s
    end = start + seconds
    while (now := time.monotonic()) < end:
        for key, _ in sel.select(0.05):
            data = key.fileobj.recv(1 << 20)
            if now >= start:
                counted[key.data] += len(data)
    rates = [c / (24 + 64) / (time.monotonic() - start) for c in counted]
    print(json.dumps(rates), flush=True)
    for s in socks:
        s.close()
    return 0


# ------------------------------------------------------------------ the bench

class Bench:
    def __init__(self) -> None:
        self.realm = f"bench{uuid.uuid4().hex[:8]}"
        self.ep = f"tcp/127.0.0.1:{free_port()}"
        self.procs: list[subprocess.Popen] = []

    def spawn(self, *args: str, wait_for: str, stderr: bool = False) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, *args], cwd=ROOT, text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             env=dict(os.environ, PYTHONUNBUFFERED="1"))
        self.procs.append(p)
        stream = p.stderr if stderr else p.stdout
        deadline = time.monotonic() + 60
        for line in stream:
            if wait_for in line:  # uma logs on stderr; child modes answer on stdout
                threading.Thread(target=p.stderr.read, daemon=True).start()
                return p
            if time.monotonic() > deadline:
                break
        raise RuntimeError(f"{args[:4]} did not say {wait_for!r}")

    def uma(self, *args: str, wait_for: str) -> subprocess.Popen:
        return self.spawn("-m", "agent.cli", *args, wait_for=wait_for, stderr=True)

    def service(self, name: str, *args: str, wait_for: str) -> subprocess.Popen:
        return self.uma("service", "run", name, "--realm", self.realm, "--agent", "bench",
                        "--connect", self.ep, *args, wait_for=wait_for)

    def close(self) -> None:
        stop_processes(self.procs, 5.0)


class Source:
    """A uma pose ability publishing x = sequence number; remembers when each went out."""

    def __init__(self, bench: Bench, frame: str, rate_hz: float) -> None:
        from agent import Service
        self.svc = Service(f"src{frame.split('/')[1]}", realm=bench.realm, agent="bench",
                           connect=[bench.ep])
        self.handle = self.svc.ability("pose", type="pose6d", edge=("bench/world", frame),
                                       frequency_hz=rate_hz)
        self.svc.start()
        self.rate_hz = rate_hz
        self.sent: list[int] = []
        self.stop = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        tick = time.monotonic()
        while not self.stop.is_set():
            t = time.time_ns()
            self.sent.append(t)
            self.handle.publish(t, [float(len(self.sent) - 1), 0.0, 0.0], [0, 0, 0, 1])
            tick = max(tick + period, time.monotonic() - 0.1)
            self.stop.wait(max(0.0, tick - time.monotonic()))

    def close(self) -> None:
        self.stop.set()
        self.svc.close()


def vrpn_receiver(port: int, sent: list[int], count: int, timeout: float) -> list[int]:
    """A VRPN TCP client of tracker ``Src``: latency (ns) of ``count`` reports."""
    out: list[int] = []
    dec = vp.StreamDecoder()
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(vp.cookie())
        s.settimeout(timeout)
        first = s.recv(vp.COOKIE_SIZE, socket.MSG_WAITALL)
        vp.check_cookie(first)
        types: dict[int, str] = {}
        while len(out) < count:
            data = s.recv(65536)
            now = time.time_ns()
            for m in dec.feed(data):
                if m.type == vp.TYPE_DESCRIPTION:
                    types[m.sender] = vp.decode_name(m.payload)
                elif types.get(m.type) == vp.POS_QUAT:
                    out.append(now - sent[int(vp.decode_pos_quat(m.payload).position[0])])
    return out


def measure_out(b: Bench, samples: int) -> list[int]:
    src = Source(b, "bench/out", RATE_HZ)
    port = free_port()
    b.service("vrpn-out", "--serve", "Src=bench/world:bench/out", "--port", str(port),
              "--bind", "127.0.0.1", wait_for="tracker Src streams")
    try:
        vrpn_receiver(port, src.sent, 50, 30)  # warm-up
        return vrpn_receiver(port, src.sent, samples, 30)
    finally:
        src.close()


def measure_in(b: Bench, samples: int) -> list[int]:
    from agent import Service
    from services.vrpn.server import TrackerServer
    port = free_port()
    server = TrackerServer(["Src"], "127.0.0.1", port)
    sent: list[int] = []
    got: list[int] = []
    done = threading.Event()
    stop = asyncio.Event()

    async def serve() -> None:
        await server.start()
        while not stop.is_set():
            t = time.time_ns()
            sent.append(t)
            server.report(0, t, [float(len(sent) - 1), 0.0, 0.0], [0, 0, 0, 1])
            await asyncio.sleep(1.0 / RATE_HZ)
        await server.close()
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_until_complete, args=(serve(),), daemon=True)
    thread.start()

    def on_sample(m) -> None:
        got.append(time.time_ns() - sent[int(m.position[0])])
        if len(got) >= samples + 50:
            done.set()
    b.service("vrpn-in", "--tracker", f"Src@127.0.0.1:{port}", "--edge",
              "bench/world:bench/in", wait_for="connected (UDP handshake)")
    with Service("sink", realm=b.realm, agent="bench", connect=[b.ep]) as sink:
        sink.need("in", type="pose6d", edge=("bench/world", "bench/in"), on_sample=on_sample)
        sink.start()
        done.wait(120)
    loop.call_soon_threadsafe(stop.set)
    thread.join(5)
    return got[50:samples + 50]


def measure_anchor(b: Bench, samples: int) -> list[int]:
    from agent.runtime.session import open_session
    key = f"bench/{b.realm}/anchor"
    child = b.spawn(__file__, "--zenoh-sub", b.ep, key, str(samples + 50), wait_for="ready")
    session = open_session("client", connect=[b.ep])
    pub = session.declare_publisher(key)
    time.sleep(0.5)  # the subscriber's declaration reaches the agent
    result: list[int] = []
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(1.0 / RATE_HZ):
            pub.put(str(time.time_ns()).encode())
    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    for line in child.stdout:
        if line.startswith("["):
            result = json.loads(line)
            break
    stop.set()
    thread.join(2)
    session.close()
    return result[50:]


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure_clients(b: Bench, ladder: list[int], seconds: float) -> list[dict[str, float]]:
    src = Source(b, "bench/many", CLIENT_RATE_HZ)
    port = free_port()
    out = b.service("vrpn-out", "--serve", "Src=bench/world:bench/many", "--port",
                    str(port), "--bind", "127.0.0.1", wait_for="tracker Src streams")
    rows = []
    try:
        for n in ladder:
            warm = 1.0 + n / 200
            child = b.spawn(__file__, "--readers", str(port), str(n), str(warm), str(seconds),
                            wait_for="ready")
            time.sleep(warm)
            sent0, cpu0, t0 = len(src.sent), cpu_seconds(out.pid), time.monotonic()
            time.sleep(seconds)
            sent1, cpu1, t1 = len(src.sent), cpu_seconds(out.pid), time.monotonic()
            rates = json.loads(next(line for line in child.stdout if line.startswith("[")))
            child.wait(30)
            source_hz = (sent1 - sent0) / (t1 - t0)
            rows.append({"clients": n, "source_hz": source_hz,
                         "worst_client_share": min(rates) / source_hz,
                         "vrpn_out_cpu_core": (cpu1 - cpu0) / (t1 - t0)})
    finally:
        src.close()
    return rows


def per_client_cost(rows: list[dict[str, float]]) -> dict[str, float]:
    """vrpn-out's CPU per client from the served rows (a straight line through CPU against
    clients), and the clients one whole core would serve at that cost: on a loaded host
    vrpn-out never gets a whole core, so the measured count stops short of it."""
    import numpy as np
    if len({r["clients"] for r in rows}) < 2:
        return {}
    slope, base = np.polyfit([r["clients"] for r in rows],
                             [r["vrpn_out_cpu_core"] for r in rows], 1)
    if slope <= 0:
        return {}
    return {"vrpn_out_cpu_us_per_client_report": float(slope / CLIENT_RATE_HZ * 1e6),
            "clients_per_core_extrapolated": float((1.0 - base) / slope)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=1000, help="latency samples per path")
    ap.add_argument("--clients", default="1,10,50,100,200,300",
                    help="numbers of VRPN clients to try (comma-separated)")
    ap.add_argument("--seconds", type=float, default=3.0, help="window per client count")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--zenoh-sub", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--readers", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.zenoh_sub:
        return zenoh_subscriber(args.zenoh_sub[0], args.zenoh_sub[1], int(args.zenoh_sub[2]))
    if args.readers:
        port, n, warm, secs = args.readers
        return readers(int(port), int(n), float(warm), float(secs))
    ladder = [int(x) for x in args.clients.split(",")]
    b = Bench()
    try:
        b.uma("agent", "--realm", b.realm, "--id", "bench", "--listen", b.ep,
              wait_for="listening on")
        anchor = measure_anchor(b, args.samples)
        out = measure_out(b, args.samples)
        inn = measure_in(b, args.samples)
        rows = measure_clients(b, ladder, args.seconds)
    finally:
        b.close()
    figures: dict[str, object] = {"cpu": cpu_model()}
    for name, xs in (("anchor_zenoh", anchor), ("vrpn_out", out), ("vrpn_in", inn)):
        figures.update({f"{name}_{k}": v for k, v in
                        median_p99([x / 1e3 for x in xs], "us").items()})
    for name in ("vrpn_out", "vrpn_in"):
        figures[f"{name}_over_anchor_median_ratio"] = (figures[f"{name}_median_us"]
                                                       / figures["anchor_zenoh_median_us"])
        figures[f"{name}_added_median_us"] = (figures[f"{name}_median_us"]
                                              - figures["anchor_zenoh_median_us"])
    served = [r["clients"] for r in rows if r["worst_client_share"] >= SERVED_SHARE
              and r["vrpn_out_cpu_core"] < SERVED_SHARE]
    for r in rows:
        n = r["clients"]
        figures[f"clients_{n}_worst_share"] = r["worst_client_share"]
        figures[f"clients_{n}_vrpn_out_cpu_core"] = r["vrpn_out_cpu_core"]
        figures[f"clients_{n}_source_hz"] = r["source_hz"]
    figures["clients_served_at_300hz"] = max(served, default=0)
    figures.update(per_client_cost([r for r in rows if r["worst_client_share"] >= SERVED_SHARE]))
    figures["load_average_1min"] = os.getloadavg()[0]
    report(figures, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
