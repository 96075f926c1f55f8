"""A realm at site scale: one agent per host of a :class:`Site`, each with one
process of K services (:mod:`agent_helpers.many_services`), and ``uma services`` asked from
a host of its own.  Used by ``tests/test_site_scale.py`` and ``bench/bench_site_scale.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent.cli.agent import STALLED_RUNNING
from agent_helpers.harness import Proc
from agent_helpers.site import Host, Site

#: every wait of forming the realm is bounded by this (20 agents and 20 service processes
#: start on 2 shared cores)
FORM_TIMEOUT_S = 120.0
#: ``uma services --timeout`` of the listings (seconds for the agents to answer)
ANSWER_S = 10.0


@dataclass
class ScaleRealm:
    """The running realm: agents on ``site.hosts[:n]``, the client on the last host."""

    site: Site
    realm: str
    agents: list[Proc]
    services: list[Proc] = field(default_factory=list)
    #: the agents started again after their Zenoh session stalled (``restart_stalled``)
    restarts: list[str] = field(default_factory=list)

    @property
    def client(self) -> Host:
        return self.site.hosts[-1]

    @property
    def seed(self) -> Host:
        return self.site.hosts[0]

    def services_json(self, timeout: float = 60.0, at: Host | None = None
                      ) -> tuple[dict[str, Any], float]:
        """``uma services --json`` run on the client host against the seed agent (or the
        agent on ``at``), and its wall time in seconds (process start to exit, as a person
        sees it).  Its answers may take ``ANSWER_S`` (the default 2 s left agents of a
        20-host site on a slow CI host unlisted at every try: a slow answer is a figure,
        not a failure)."""
        args = ["-m", "agent.cli", "services", "--json", "--realm", self.realm,
                "--connect", (at or self.seed).endpoint(), "--timeout", str(ANSWER_S)]
        start = time.monotonic()
        out = self.site.run(self.client, args, timeout)
        wall = time.monotonic() - start
        if out.returncode != 0:
            raise AssertionError(f"uma services exited {out.returncode}: {out.stderr[-2000:]}")
        return json.loads(out.stdout.strip().splitlines()[-1]), wall

    def wait_listed(self, services_per_agent: int, timeout: float = FORM_TIMEOUT_S
                    ) -> dict[str, Any]:
        """The first ``uma services`` answer that lists every agent with all its services."""
        deadline = time.monotonic() + timeout
        listing: dict[str, Any] = {}
        while time.monotonic() < deadline:
            self.restart_stalled()
            listing, _ = self.services_json()
            if complete(listing, len(self.agents), services_per_agent):
                return listing
        raise AssertionError(f"the realm did not form within {timeout} s; last listing: "
                             f"{summary(listing)}; the agents it lacks: "
                             f"{self.missing_agents(listing)}; what the agents and services "
                             f"said of registrations: {self.registration_log()}")

    def restart_stalled(self) -> None:
        """Start again, as its supervisor would, an agent that exited because its Zenoh
        session stalled (``agent.cli.agent.STALLED_RUNNING``: a Zenoh deadlock under peer
        churn, eclipse-zenoh/zenoh#2581, not the subject of these tests); counted in
        ``restarts``."""
        for i, (host, proc) in enumerate(zip(self.site.hosts, self.agents, strict=False)):
            if proc.popen.poll() is not None and any(STALLED_RUNNING in ln for ln in proc.log):
                self.agents[i] = self.site.start_agents(self.realm, [host], seed=self.seed)[0]
                self.restarts.append(host.name)

    def missing_agents(self, listing: dict[str, Any]) -> dict[str, Any]:
        """For each agent absent from ``listing``: whether its process runs, which agents it
        itself lists (a partition of the realm or a dead agent), and its log tail."""
        listed = {a["agent_id"] for a in listing.get("agents", [])}
        out: dict[str, Any] = {}
        for host, proc in zip(self.site.hosts, self.agents, strict=False):
            if host.name in listed:
                continue
            own = "not asked: its process exited"
            if proc.popen.poll() is None:
                try:
                    own = summary(self.services_json(at=host)[0])
                except (AssertionError, ValueError, subprocess.TimeoutExpired) as exc:
                    own = f"asking it failed: {exc}"
            out[host.name] = {"exit": proc.popen.poll(), "it lists": own,
                              "log tail": proc.log[-12:]}
        return out

    def registration_log(self, last: int = 5) -> dict[str, list[str]]:
        """Each process's last lines about registrations (refused, dropped, re-adopted):
        why a service is missing from a listing."""
        words = ("refused", "dropped", "re-adopted", "never declared", "gone")
        out = {}
        for proc in [*self.agents, *self.services]:
            lines = [ln for ln in proc.log if any(w in ln for w in words)]
            if lines:
                out[" ".join(proc.popen.args[-8:])] = lines[-last:]
        return out


def start(site: Site, realm: str) -> ScaleRealm:
    """An agent on every host but the last (the client's); returns once all listen."""
    return ScaleRealm(site, realm, site.start_agents(realm, site.hosts[:-1]))


def add_services(scale: ScaleRealm, services_per_agent: int, rate_hz: float) -> None:
    """One process of ``services_per_agent`` services per agent; returns once every process
    has started them."""
    for host in scale.site.hosts[:len(scale.agents)]:
        scale.services.append(scale.site.spawn(host, [
            "-m", "tests.agent_helpers.many_services", "--realm", scale.realm,
            "--agent", host.name, "--connect", host.endpoint(),
            "--count", str(services_per_agent), "--rate", str(rate_hz)]))
    for proc in scale.services:
        proc.wait_for(lambda ev: ev.get("event") == "started", FORM_TIMEOUT_S)


def complete(listing: dict[str, Any], agents: int, services_per_agent: int) -> bool:
    """Whether ``listing`` shows ``agents`` agents, each with all its services."""
    found = listing.get("agents", [])
    return len(found) == agents and all(len(a["services"]) == services_per_agent
                                        for a in found)


def summary(listing: dict[str, Any]) -> dict[str, Any]:
    """Services per agent and the problems of a listing (for failure messages)."""
    return {"services": {a["agent_id"]: len(a["services"]) for a in listing.get("agents", [])},
            "problems": listing.get("problems", [])}


def cpu_seconds(pid: int) -> float:
    """User + system CPU time a process has used, from ``/proc/PID/stat``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_percent(procs: list[Proc], seconds: float) -> list[float]:
    """Each process's CPU use over the next ``seconds``, in % of one core."""
    pids = [p.popen.pid for p in procs]
    before = [cpu_seconds(pid) for pid in pids]
    start = time.monotonic()
    time.sleep(seconds)
    elapsed = time.monotonic() - start
    return [100.0 * (cpu_seconds(pid) - b) / elapsed for pid, b in zip(pids, before,
                                                                        strict=True)]
