"""A site of real hosts on one machine: Linux network namespaces joined by veth pairs to one
bridge, for what loopback cannot show (a link that drops, hosts that reach each other only
through a network, an address per host).

A site tagged ``T`` (unique per run) with N hosts::

    namespace T-br   bridge br0 with ports p0 .. pN-1 (one end of each host's veth pair)
    namespace T-h0   eth0 (the other end), 10.77.X.1/24, lo up
    ...
    namespace T-hN-1 eth0, 10.77.X.N/24, lo up

Nothing is added to the machine's own namespace: each veth pair is created inside the
bridge's namespace with its other end moved straight into its host's.  ``X`` differs per
site so two sites' logs never show the same address (the namespaces keep them apart anyway).
Processes run inside a host with ``ip netns exec``; the site stops them by PID, then deletes
its namespaces (and with them the veths and the bridge), also when the test failed.  A site
left behind by a run that was killed is removed by the next one (its tag names the PID).

Needs root and ``ip`` (iproute2): :func:`unavailable` says why a test must skip.
"""

from __future__ import annotations

import contextlib
import os
import random
import re
import shutil
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import count
from pathlib import Path

from agent.runtime.processes import stop_processes
from agent_helpers.harness import ROOT, Proc, agent_command, spawn, start_agents

#: namespaces of test sites are named PREFIX<pid>x<n>-...; deploy/netns_site.sh uses "umasite"
PREFIX = "umat"
AGENT_PORT = 7447
NETNS_DIR = Path("/run/netns")
_STALE = re.compile(rf"^{PREFIX}(\d+)x\d+-")
_serial = count()


def unavailable() -> str | None:
    """Why no site can be built here (the reason a test skips with), or None."""
    if os.geteuid() != 0:
        return "the site harness needs root (it creates network namespaces)"
    if shutil.which("ip") is None:
        return "the site harness needs the `ip` command (iproute2)"
    return None


def ip(*args: str) -> None:
    """Run ``ip ARGS``; a failure raises naming the command and ip's own message."""
    out = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if out.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)} failed: {out.stderr.strip()}")


@dataclass(frozen=True)
class Host:
    """One host of the site: its namespace, its address and its port on the bridge."""

    name: str
    netns: str
    addr: str
    bridge_port: str

    def endpoint(self, port: int = AGENT_PORT) -> str:
        """A Zenoh TCP endpoint on this host's address."""
        return f"tcp/{self.addr}:{port}"

    @property
    def prefix(self) -> list[str]:
        """The command prefix that runs a program inside this host."""
        return ["ip", "netns", "exec", self.netns]


class Site:
    """N hosts on one bridge; build with :meth:`build`, always end with :meth:`close`."""

    def __init__(self, hosts: int, subnet: int | None = None) -> None:
        if not 1 <= hosts <= 250:
            raise ValueError(f"a site has 1..250 hosts, not {hosts}")
        self.tag = f"{PREFIX}{os.getpid()}x{next(_serial)}"
        self.subnet = random.randrange(1, 255) if subnet is None else subnet
        self.bridge_ns = f"{self.tag}-br"
        self.hosts = [Host(f"h{i}", f"{self.tag}-h{i}", f"10.77.{self.subnet}.{i + 1}",
                           f"p{i}") for i in range(hosts)]
        #: every process started in the site (the registry ``harness.spawn`` appends to)
        self.procs: list[subprocess.Popen] = []
        self._namespaces: list[str] = []

    def build(self) -> Site:
        """Create the bridge and the hosts (a failure part-way is cleaned up by close)."""
        remove_stale()
        self._add_netns(self.bridge_ns)
        ip("-n", self.bridge_ns, "link", "add", "br0", "type", "bridge")
        ip("-n", self.bridge_ns, "link", "set", "br0", "up")
        for host in self.hosts:
            self._add_netns(host.netns)
            ip("-n", self.bridge_ns, "link", "add", host.bridge_port, "type", "veth",
               "peer", "name", "eth0", "netns", host.netns)
            ip("-n", self.bridge_ns, "link", "set", host.bridge_port, "master", "br0", "up")
            ip("-n", host.netns, "addr", "add", f"{host.addr}/24", "dev", "eth0")
            ip("-n", host.netns, "link", "set", "eth0", "up")
        return self

    def _add_netns(self, name: str) -> None:
        ip("netns", "add", name)
        self._namespaces.append(name)
        ip("-n", name, "link", "set", "lo", "up")

    def spawn(self, host: Host, args: list[str], env: dict[str, str] | None = None) -> Proc:
        """``python ARGS`` inside ``host`` (see ``harness.spawn``)."""
        return spawn(self, args, env, host.prefix)

    def start_agents(self, realm: str, hosts: Sequence[Host] | None = None,
                     seed: Host | None = None, extra: Sequence[str] = ()) -> list[Proc]:
        """One ``uma agent`` per host (default: all), id = the host's name, listening on the
        host's address and connecting to ``seed``'s (default: the first host); the seed
        starts first so that the others find it, then the others all at once."""
        hosts = list(self.hosts if hosts is None else hosts)
        seed = hosts[0] if seed is None else seed

        def command(host: Host) -> tuple[list[str], list[str]]:
            connect = () if host == seed else (seed.endpoint(),)
            return (agent_command(realm, host.name, host.endpoint(), connect,
                                  [*extra, "--insecure"]), host.prefix)

        procs = {}
        if seed in hosts:
            procs[seed] = start_agents(self, [command(seed)])[0]
        others = [h for h in hosts if h != seed]
        procs.update(zip(others, start_agents(self, [command(h) for h in others]), strict=True))
        return [procs[h] for h in hosts]

    def run(self, host: Host, args: Sequence[str], timeout: float
            ) -> subprocess.CompletedProcess:
        """``python ARGS`` inside ``host`` to completion (output captured)."""
        return subprocess.run([*host.prefix, sys.executable, *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=timeout)

    def cut(self, host: Host) -> None:
        """Take ``host``'s link down (at the bridge: the host keeps its address and sees
        its carrier go, as when a cable is pulled)."""
        ip("-n", self.bridge_ns, "link", "set", host.bridge_port, "down")

    def heal(self, host: Host) -> None:
        """Bring ``host``'s link back up."""
        ip("-n", self.bridge_ns, "link", "set", host.bridge_port, "up")

    def close(self) -> None:
        """Stop every process started here (by PID), then delete the namespaces."""
        stop_processes(self.procs)
        for p in self.procs:
            for stream in (p.stdin, p.stdout, p.stderr):
                if stream:
                    with contextlib.suppress(OSError):
                        stream.close()
        for name in reversed(self._namespaces):
            with contextlib.suppress(RuntimeError):
                ip("netns", "del", name)
        self._namespaces.clear()


def remove_stale() -> None:
    """Delete the namespaces of test sites whose run has ended without cleaning up (its
    process was killed): the PID in their name no longer exists."""
    if not NETNS_DIR.is_dir():
        return
    for entry in NETNS_DIR.iterdir():
        m = _STALE.match(entry.name)
        if m and not _alive(int(m[1])):
            with contextlib.suppress(RuntimeError):
                ip("netns", "del", entry.name)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
