"""Safe by default: ``uma agent`` and ``uma router`` refuse to listen without TLS where other
hosts reach them, and say how to go on (secure the site, or ``--insecure`` on purpose).
The refusal comes before anything listens; the ``--insecure`` path is what the plain
network-namespace sites run (``agent_helpers.site``, ``test_site_faults``)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from agent_helpers.harness import ROOT
from conftest import free_port

from agent.runtime.session import exposed_endpoints


def test_only_plain_listeners_other_hosts_reach_are_exposed() -> None:
    """Endpoint strings only: nothing listens or connects."""
    assert exposed_endpoints([
        "tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tcp/localhost:7447", "tls/0.0.0.0:7447",
        "quic/10.0.0.1:7447", "unixsock-stream//tmp/uma.sock", "tcp/0.0.0.0:7447",
        "udp/10.0.0.1:7447", "tcp/[::]:7447"]) == [
        "tcp/0.0.0.0:7447", "udp/10.0.0.1:7447", "tcp/[::]:7447"]


def _isolated() -> list[str]:
    """A fresh network namespace holding only its own loopback: were the refusal ever to
    fail, the agent's 'every interface' would still reach nothing beyond this test."""
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("a network namespace of its own needs root and unshare(1)")
    return ["unshare", "--net"]


def uma(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*_isolated(), sys.executable, "-m", "agent.cli", *args], cwd=ROOT,
                          text=True, capture_output=True, timeout=20, env=env)


@pytest.mark.parametrize("command", [
    ["agent", "--realm", "lab", "--id", "hostA"],
    ["router"],
])
def test_a_plain_listener_on_every_interface_is_refused(command: list[str]) -> None:
    ep = f"tcp/0.0.0.0:{free_port()}"
    out = uma(*command, "--listen", ep)
    assert out.returncode == 1, out.stdout
    assert f"would listen on {ep} without TLS" in out.stderr
    assert "--insecure" in out.stderr and "Deploying a site" in out.stderr
    assert "Traceback" not in out.stderr


def test_a_plain_listener_from_a_zenoh_configuration_is_refused(tmp_path: Path) -> None:
    cfg = tmp_path / "agent.json5"
    ep = f"tcp/0.0.0.0:{free_port()}"
    cfg.write_text(json.dumps({"listen": {"endpoints": [ep]}}))
    out = uma("agent", "--realm", "lab", "--id", "hostA", "--zenoh-config", str(cfg))
    assert out.returncode == 1 and f"would listen on {ep} without TLS" in out.stderr, (
        out.stderr)
