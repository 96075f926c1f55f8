"""One realm of ``bench_scale.py``: N real ``uma agent`` processes on loopback, each with F
frames, and what a client, a subscriber and a new service see of it.

Agent ``h{i}`` listens on a free port (all join ``h0``; multicast scouting is off in every
uma session) and holds, from its ``--config`` file, the static edges ``scale/world ->
h{i}/world`` and ``h{i}/world -> h{i}/f{k}``; one process of ``SERVICES`` services (or as
many as the row asks for)
(``tests/agent_helpers/many_services.py``) adds the measured edges ``h{i}/world ->
h{i}/s{j}`` at ``RATE_HZ`` each.  ``scale/world`` is the one frame every agent shares, so
a query from ``h0/s0`` to ``h{N-1}/s0`` crosses two agents.  Every process is stopped by
its PID when the realm closes.
"""

from __future__ import annotations

import os
import re
import tempfile
import time
import uuid
from contextlib import suppress
from pathlib import Path
from typing import Any

import msgpack
from bench_host_load import Child, cpu_percent, free_endpoint, new_need, rss_mb
from summary import median_p99

from agent.errors import UmaError
from agent.protocol import keys
from agent.protocol.query import decode_summary, parse_summary, spelt_out
from agent.runtime.processes import stop_processes
from agent.runtime.session import close_session, open_session, query
from schemas.codec import decode_message

SHARED = "scale/world"
SERVICES, RATE_HZ = 2, 100.0
#: default bound on forming a realm: 20 agents, or agents of 1,000 frames whose summaries
#: take minutes to compute, on 2 shared cores
FORM_S = 600.0
#: how long a subscription is asked for again: on a saturated host an agent that missed one
#: answer counts as gone until the client's probe (every 2 s) finds it
SUBSCRIBE_S = 30.0


def config_text(agent_id: str, frames: int, services: int = SERVICES) -> str:
    """The agent's TOML: static edges giving it ``frames`` frames with its services'."""
    statics = [(SHARED, f"{agent_id}/world")]
    statics += [(f"{agent_id}/world", f"{agent_id}/f{k}")
                for k in range(max(0, frames - 2 - services))]
    tables = [f'[[static]]\nparent = "{p}"\nchild = "{c}"\nposition = [{k}.0, 0.0, 1.0]\n'
              f"quaternion = [0.0, 0.0, 0.0, 1.0]\npos_std_m = {0.001 * (1 + k % 7)}\n"
              for k, (p, c) in enumerate(statics)]
    return "\n".join(tables)


class Realm:
    """The running realm (module docstring); use as a context manager."""

    def __init__(self, agents: int, frames: int, form_s: float = FORM_S,
                 services: int = SERVICES) -> None:
        self.n, self.frames, self.form_s = agents, frames, form_s
        self.services_per_agent = services
        self.realm = f"scale{uuid.uuid4().hex[:8]}"
        self.eps = [free_endpoint() for _ in range(agents)]
        self.agents: list[Child] = []
        #: agents started again because they exited before listening (see ``_listening``)
        self.restarts = 0
        self.services: list[Child] = []
        self._dir = tempfile.TemporaryDirectory(prefix="uma-scale-")

    def __enter__(self) -> Realm:
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _start(self) -> None:
        deadline = time.monotonic() + self.form_s
        self.agents = [Child(*self._agent_args(i)) for i in range(self.n)]
        for i in range(self.n):
            self._listening(i, deadline)
        count = str(self.services_per_agent)
        self.services = [Child("-m", "tests.agent_helpers.many_services", "--realm", self.realm,
                               "--agent", f"h{i}", "--connect", ep, "--count", count,
                               "--rate", str(RATE_HZ)) for i, ep in enumerate(self.eps)]
        for c in self.services:
            c.wait_for("started", deadline)

    def _agent_args(self, i: int) -> list[str]:
        path = Path(self._dir.name) / f"h{i}.toml"
        path.write_text(config_text(f"h{i}", self.frames, self.services_per_agent))
        return ["-m", "agent.cli", "agent", "--realm", self.realm, "--id", f"h{i}", "--config",
                str(path), "--listen", self.eps[i], *(["--connect", self.eps[0]] if i else [])]

    def _listening(self, i: int, deadline: float) -> None:
        """Agent ``i`` says it listens.  One that exited first is started once more, as its
        supervisor would: an agent whose Zenoh session stalls at start (20 agents starting
        at once on a loaded host) exits 1 for that (``agent.cli.agent.STALLED_START``)."""
        try:
            self.agents[i].wait_for("listening on", deadline)
        except RuntimeError:
            if self.agents[i].proc.poll() is None:
                raise
            self.restarts += 1
            self.agents[i] = Child(*self._agent_args(i))
            self.agents[i].wait_for("listening on", deadline)

    def close(self) -> None:
        stop_processes(c.proc for c in self.services + self.agents)
        self._dir.cleanup()

    @property
    def source(self) -> str:
        return "h0/s0"

    @property
    def target(self) -> str:
        return f"h{self.n - 1}/s0"


def wait_formed(client: Any, realm: Realm) -> float:
    """Seconds until the cross-agent query first succeeds (bounded by ``realm.form_s``)."""
    start = time.monotonic()
    while True:  # bounded: realm.form_s
        try:
            client.pose(realm.source, realm.target)
            return time.monotonic() - start
        except (LookupError, ValueError, UmaError) as exc:
            if time.monotonic() - start > realm.form_s:
                raise RuntimeError(f"realm of {realm.n} agents x {realm.frames} frames not "
                                   f"formed within {realm.form_s:g} s: {exc}") from None
            time.sleep(0.2)


def query_ms(client: Any, realm: Realm, count: int) -> dict[str, float]:
    """``Client.pose`` across two agents, ``count`` times (failures are not timed)."""
    ms = []
    for _ in range(count):
        t = time.perf_counter()
        with suppress(LookupError, ValueError, UmaError):
            client.pose(realm.source, realm.target)
            ms.append((time.perf_counter() - t) * 1e3)
    return {f"query_{k}": v for k, v in median_p99(ms, "ms").items()} | {
        "query_failed": count - len(ms)}


def busy_fraction() -> tuple[int, int]:
    """(busy, total) jiffies of the whole machine so far (``/proc/stat``)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]
    return sum(fields) - idle, sum(fields)


#: the names Zenoh gives its runtime threads (tx-0, rx-1, ...): an agent's CPU in them is
#: Zenoh's own work (links, routing), the rest is uma's Python
ZENOH_THREAD = re.compile(r"(tx|rx|net|acc|app)-\d+")


def threads_cpu_s(pid: int, only: re.Pattern[str] | None = None) -> float:
    """CPU seconds of ``pid``'s live threads so far (``only``: those whose name matches),
    in nanoseconds (``/proc/PID/task/*/schedstat``): a 5 s window read in 10 ms jiffies is
    +-0.2 % of a core, about 1 % of the per-1,000-samples figure at 200 samples/s.  An agent's
    threads live as long as it does."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        with suppress(OSError, ValueError):
            if only is None or only.fullmatch((task / "comm").read_text().strip()):
                total += int((task / "schedstat").read_text().split()[0])
    return total / 1e9


def stream_figures(client: Any, realm: Realm, seconds: float) -> dict[str, Any]:
    """Over ``seconds``: a subscription's latency (sample time to ``on_pose``, on the
    agent's clock), the agents' CPU per 1,000 samples/s they receive and the part of it in
    Zenoh's own threads, the realm's CPU, how busy the machine was, and the agents' RSS."""
    latency_ms: list[float] = []
    owner = f"h{realm.n - 1}"

    def on_pose(r: Any) -> None:
        latency_ms.append((time.time_ns() - client.clock.to_remote(owner, r.t_ns)) / 1e6)
    sub, refused = subscribe(client, realm.target, on_pose)
    try:
        busy0 = busy_fraction()
        agents0 = [(threads_cpu_s(c.pid), threads_cpu_s(c.pid, ZENOH_THREAD))
                   for c in realm.agents]
        t0 = time.monotonic()
        cpu = cpu_percent(realm.agents + realm.services, seconds)
        t1 = time.monotonic()
        agents1 = [(threads_cpu_s(c.pid), threads_cpu_s(c.pid, ZENOH_THREAD))
                   for c in realm.agents]
        busy1 = busy_fraction()
    finally:
        sub.close()
    agents_cpu = [100 * (a[0] - b[0]) / (t1 - t0) for a, b in zip(agents1, agents0, strict=True)]
    zenoh_pct = 100 * sum(a[1] - b[1] for a, b in zip(agents1, agents0, strict=True)) / (t1 - t0)
    per_agent_rate = realm.services_per_agent * RATE_HZ
    rss = [rss_mb(c.pid) for c in realm.agents]
    out: dict[str, Any] = {}
    if latency_ms:
        out |= {f"subscription_{k}": v for k, v in median_p99(latency_ms, "ms").items()}
    return out | {
        "subscription_poses": len(latency_ms), "subscription_refused": refused,
        "agent_cpu_pct_per_1k_samples_s": sum(agents_cpu) / realm.n / (per_agent_rate / 1e3),
        "agent_zenoh_cpu_pct_per_1k_samples_s": zenoh_pct / realm.n / (per_agent_rate / 1e3),
        "agents_cpu_pct_total": sum(agents_cpu), "realm_cpu_pct": sum(cpu),
        "machine_busy_pct": 100.0 * (busy1[0] - busy0[0]) / max(1, busy1[1] - busy0[1]),
        "agent_rss_mb_median": sorted(rss)[len(rss) // 2], "agent_rss_mb_max": max(rss)}


def subscribe(client: Any, target: str, on_pose: Any) -> tuple[Any, int]:
    """A subscription from the shared frame to ``target`` and how many times it was refused
    first (asked again for up to ``SUBSCRIBE_S``)."""
    deadline = time.monotonic() + SUBSCRIBE_S
    refused = 0
    while True:  # bounded: SUBSCRIBE_S
        try:
            return client.subscribe(SHARED, target, on_pose=on_pose, error="hops"), refused
        except (LookupError, UmaError):
            refused += 1
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def summary_bytes(realm: Realm) -> dict[str, Any]:
    """Every agent's summary as it travels (compact) and spelt out (``summarize``'s form,
    the verbose form): the largest of each, in bytes."""
    session = open_session("client", None, [realm.eps[0]], realm.realm,
                           require_connection=True)
    try:
        replies = query(session, keys.all_agent_supernodes(realm.realm), 5.0)
    finally:
        close_session(session)
    compact, spelt = [], []
    for reply in replies:
        if reply.ok is None:
            continue
        data = reply.ok.payload.to_bytes()
        msg = decode_message(data)
        if decode_summary(data) != parse_summary(spelt_out(msg)):
            raise RuntimeError("a compact summary reads differently spelt out")
        compact.append(len(data))
        spelt.append(len(msgpack.packb(dict(spelt_out(msg)))))  # may exceed a message's limit
    return {"summaries": len(compact), "summary_bytes_max": max(compact, default=0),
            "summary_bytes_spelt_out_max": max(spelt, default=0)}


def measure(agents: int, frames: int, queries: int, seconds: float,
            form_s: float = FORM_S, services: int = SERVICES) -> dict[str, Any]:
    """One realm's row (module docstring); forming it may take ``form_s`` at most."""
    from agent import Client

    row: dict[str, Any] = {"agents": agents, "frames_per_agent": frames,
                           "samples_per_agent_s": services * RATE_HZ,
                           "load_1min": os.getloadavg()[0]}
    started = time.monotonic()
    with Realm(agents, frames, form_s, services) as realm, Client(realm=realm.realm,
                                                connect=[realm.eps[0]]) as client:
        row["processes_started_s"] = time.monotonic() - started
        row["formed_s"] = wait_formed(client, realm) + row["processes_started_s"]
        row |= query_ms(client, realm, queries)
        row |= stream_figures(client, realm, seconds)
        row |= summary_bytes(realm)
        row["agent_restarts"] = realm.restarts
        need = new_need(realm.realm, realm.eps[0], 0.0,
                        edge=(f"{realm.target.split('/')[0]}/world", realm.target))
        row["new_need_connected_ms"] = need["new_need_first_sample_ms"]
    return row
