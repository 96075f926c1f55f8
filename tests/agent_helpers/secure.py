"""A secured site on the network-namespace harness (:mod:`agent_helpers.site`): certificates
and role configurations made by :mod:`agent.deploy`, a TLS router with access control on
the first host, agents in client mode behind it.

Roles on a site of N hosts: ``h0`` the router, ``h1 .. h(N-2)`` agent hosts, the last host
a client host; ``spare`` names one more agent host that holds a certificate but never runs
an agent (an identity to spoof).
"""

from __future__ import annotations

from pathlib import Path

from agent.deploy.certs import SiteSpec, create_site
from agent.deploy.zenoh_config import write_configs
from agent_helpers.harness import START_WAIT_S, Proc
from agent_helpers.site import Host, Site

SPARE = "spare"


class SecuredSite:
    """Certificates, configurations, the router and the agents of a secured site."""

    def __init__(self, site: Site, directory: Path, realm: str) -> None:
        self.site = site
        self.dir = directory
        self.realm = realm
        self.router_host = site.hosts[0]
        self.agent_hosts = site.hosts[1:-1]
        self.client_host = site.hosts[-1]
        self.router_ep = f"tls/{self.router_host.addr}:7447"
        self.spec = SiteSpec(site="test", router=self.router_host.name,
                             hosts=[h.name for h in self.agent_hosts] + [SPARE],
                             clients=[self.client_host.name],
                             addresses={self.router_host.name: [self.router_host.addr]})
        create_site(directory, self.spec, days=1)
        write_configs(directory, self.spec, realm, [self.router_ep], [self.router_ep])

    def config(self, name: str, role: str) -> str:
        """The Zenoh configuration file of ``role`` on host ``name``."""
        return str(self.dir / "hosts" / name / f"{role}.json5")

    def env(self, host: Host | str, role: str) -> dict[str, str]:
        """The environment that gives a process the certificate of ``host`` in ``role``."""
        name = host if isinstance(host, str) else host.name
        return {"UMA_ZENOH_CONFIG": self.config(name, role)}

    def start_router(self) -> Proc:
        router = self.site.spawn(self.router_host, [
            "-m", "agent.cli", "router", "--config", self.config(self.router_host.name,
                                                                 "router")])
        router.wait_line("listening on", START_WAIT_S)
        return router

    def agent_args(self, agent_id: str, realm: str | None = None) -> list[str]:
        """``uma agent`` in client mode behind the router (its certificate from the env)."""
        return ["-m", "agent.cli", "agent", "--realm", realm or self.realm, "--id", agent_id,
                "--connect", self.router_ep, "--mode", "client"]

    def start_agents(self) -> list[Proc]:
        procs = [self.site.spawn(h, self.agent_args(h.name), self.env(h, "agent"))
                 for h in self.agent_hosts]
        for p in procs:
            p.wait_line("listening on", START_WAIT_S)
        return procs

    def services(self, host: Host, env: dict[str, str] | None, realm: str | None = None,
                 timeout: float = 2.0) -> tuple[int, str]:
        """``uma services --json`` run on ``host``: its exit code and output (stdout, else
        stderr)."""
        args = ["-m", "agent.cli", "services", "--realm", realm or self.realm, "--connect",
                self.router_ep, "--json", "--timeout", str(timeout)]
        if env:
            args += ["--zenoh-config", env["UMA_ZENOH_CONFIG"]]
        out = self.site.run(host, args, 90)
        return out.returncode, (out.stdout.strip() or out.stderr.strip())
