"""A secured site on real hosts (network namespaces): Zenoh's TLS with mutual
authentication and the router's access control, as written by ``uma deploy certs`` and
``uma deploy config`` (:mod:`agent.deploy`, ``docs/SECURITY.md``).

One site serves the module: h0 the router, h1 and h2 agent hosts, h3 a client host.
"""

from __future__ import annotations

import json
import os
import signal
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from agent_helpers.harness import poll
from agent_helpers.secure import SPARE, SecuredSite
from agent_helpers.site import Site, unavailable

from agent.deploy.certs import SiteSpec, create_site
from agent.deploy.zenoh_config import write_configs
from agent.runtime.processes import stop_processes

MARKER_NS = 123_456_789  # the sample time an intruder stamps its poses with


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SecuredSite]:
    reason = unavailable()
    if reason:
        pytest.skip(reason)
    site = Site(4)
    try:
        site.build()
        s = SecuredSite(site, tmp_path_factory.mktemp("site"), f"t{uuid.uuid4().hex[:10]}")
        s.start_router()
        s.start_agents()
        yield s
    finally:
        site.close()


@pytest.fixture(autouse=True)
def own_processes(secured: SecuredSite) -> Iterator[None]:
    """What a test starts on the module's site stops when the test ends: a camera left
    streaming at 50 Hz to a service that reports every sample, or an extra agent, would
    load the machine for the rest of the module."""
    first = len(secured.site.procs)
    yield
    stop_processes(secured.site.procs[first:])


def agents_seen(s: SecuredSite, realm: str | None = None) -> list[str]:
    code, out = s.services(s.client_host, s.env(s.client_host, "client"), realm)
    assert code == 0, out
    return [a["agent_id"] for a in json.loads(out.splitlines()[-1])["agents"]]


def test_the_sites_hosts_connect_and_see_the_realm(secured: SecuredSite) -> None:
    assert poll(lambda: agents_seen(secured) == ["h1", "h2"], 60, "both agents seen")


def test_a_process_without_a_site_certificate_cannot_connect(
        secured: SecuredSite, tmp_path: Path) -> None:
    code, out = secured.services(secured.client_host, None)
    assert code == 1 and "cannot reach" in out and "--zenoh-config" in out, out

    # a certificate of another site (its own CA) with the same host name
    other = SiteSpec(site="other", router="h0", hosts=["h1"], clients=["h3"],
                     addresses={"h0": [secured.router_host.addr]})
    create_site(tmp_path, other, days=1)
    write_configs(tmp_path, other, secured.realm, [secured.router_ep], [secured.router_ep])
    code, out = secured.services(secured.client_host,
                                 {"UMA_ZENOH_CONFIG": str(tmp_path / "hosts/h3/client.json5")})
    assert code == 1 and "TLS handshake was refused" in out, out

    # plain TCP to the router's port: the router speaks TLS only
    plain = secured.site.run(secured.client_host, [
        "-m", "agent.cli", "services", "--realm", secured.realm, "--connect",
        f"tcp/{secured.router_host.addr}:7447", "--json"], 90)
    assert plain.returncode == 1 and "cannot reach" in plain.stderr, plain.stderr


def test_a_host_with_the_wrong_role_cannot_publish_into_another_services_stream(
        secured: SecuredSite) -> None:
    s = secured
    h1, h2, h3 = s.agent_hosts[0], s.agent_hosts[1], s.client_host
    common = ["-m", "tests.agent_helpers.svc", "--realm", s.realm, "--connect", s.router_ep]
    # the camera on h1 publishes once an hour until told otherwise: what arrives is spoofed
    cam = s.site.spawn(h1, [*common, "--id", "cam", "--agent", "h1", "--ability", "pose",
                            "--rate", "0.0003"], s.env(h1, "service"))
    app = s.site.spawn(h2, [*common, "--id", "app", "--agent", "h2", "--need", "head",
                            "--each-sample"], s.env(h2, "service"))
    app.wait_for(lambda ev: ev.get("event") == "match" and ev["keys"], 60)
    stream = f"uma/{s.realm}/data/h1/cam/pose"
    for host, role in ((h2, "service"), (h3, "client")):  # valid certificates, wrong role
        intruder = s.site.spawn(host, ["-m", "tests.agent_helpers.intruder", "--connect",
                                       s.router_ep, "--key", stream, "--count", "100",
                                       "--t-ns", str(MARKER_NS)], s.env(host, role))
        intruder.wait_for(lambda ev: ev.get("event") == "sent", 60)
    mark = app.mark
    cam.send("rate 50")  # the real camera: its samples do arrive
    app.wait_for(lambda ev: ev.get("event") == "sample" and ev["t_ns"] != MARKER_NS, 30, mark)
    spoofed = [ev for ev in app.events if ev.get("event") == "sample"
               and ev["t_ns"] == MARKER_NS]
    assert spoofed == []


def test_only_an_agents_own_host_reaches_its_registration_queryable(
        secured: SecuredSite) -> None:
    """A registration is a write: another agent host and the read-only client host asking
    ``agent/h1/register`` (directly or through a wildcard) get no answer at all, so they
    cannot re-register h1's services; h1's own services register."""
    s = secured
    h1, h2, h3 = s.agent_hosts[0], s.agent_hosts[1], s.client_host
    victim = s.site.spawn(h1, ["-m", "tests.agent_helpers.svc", "--realm", s.realm,
                               "--connect", s.router_ep, "--id", "victim", "--agent", "h1",
                               "--ability", "pose"], s.env(h1, "service"))
    assert victim.wait_for(lambda ev: ev.get("event") == "started", 60)["registered"]
    root = f"uma/{s.realm}"
    selectors = [f"{root}/agent/h1/register", f"{root}/agent/*/register",
                 f"{root}/agent/h1/**", f"{root}/**"]
    for host, role in ((h2, "agent"), (h3, "client")):
        asker = s.site.spawn(host, ["-m", "tests.agent_helpers.intruder", "--connect",
                                    s.router_ep, "--agent", "h1", "--service", "victim",
                                    *[a for sel in selectors for a in ("--ask", sel)]],
                             s.env(host, role))
        answers = asker.wait_for(lambda ev: ev.get("event") == "asked", 60)["answers"]
        assert answers == dict.fromkeys(selectors, 0), (host.name, answers)


def test_a_spoofed_agent_id_is_refused(secured: SecuredSite) -> None:
    s = secured
    h2 = s.agent_hosts[1]
    # h2's certificate, another site member's agent id: the token never leaves the router
    spoof = s.site.spawn(h2, s.agent_args(SPARE), s.env(h2, "agent"))
    spoof.wait_line("listening on", 60)
    token = s.site.spawn(h2, ["-m", "tests.agent_helpers.intruder", "--connect", s.router_ep,
                              "--key", f"uma/{s.realm}/agent/h1/services", "--count", "1",
                              "--t-ns", "1", "--token", f"uma/{s.realm}/agent/{SPARE}"],
                         s.env(h2, "agent"))
    token.wait_for(lambda ev: ev.get("event") == "sent", 60)
    for _ in range(3):  # the real agents stay visible, the spoofed one never appears
        assert agents_seen(s) == ["h1", "h2"]


def test_realms_stay_isolated(secured: SecuredSite) -> None:
    s = secured
    h1 = s.agent_hosts[0]
    other = f"o{uuid.uuid4().hex[:10]}"
    stray = s.site.spawn(h1, s.agent_args("h1", realm=other), s.env(h1, "agent"))
    stray.wait_line("listening on", 60)
    assert agents_seen(s, other) == []  # the router carries nothing of another realm
    assert agents_seen(s) == ["h1", "h2"]


def test_the_secured_site_heals_after_its_router_is_killed(secured: SecuredSite) -> None:
    """Last in this module: it replaces the router the other tests share."""
    s = secured
    router = next(p for p in s.site.procs if "router" in p.args)
    os.kill(router.pid, signal.SIGKILL)
    router.wait(10)
    time.sleep(3.0)
    s.start_router()  # same address, same certificate: the agents re-attach over TLS
    assert poll(lambda: agents_seen(s) == ["h1", "h2"], 60, "both agents back")
