"""Running under a supervisor (``deploy/systemd/``): the router and the agent tell systemd
they are ready over ``$NOTIFY_SOCKET`` (``agent/runtime/ready.py``), an agent that cannot
start exits 1 with a message, and the units' command lines are ones ``uma`` accepts."""

from __future__ import annotations

import argparse
import re
import shlex
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from agent_helpers.harness import ROOT, START_WAIT_S, spawn
from conftest import endpoint, free_port

from agent.cli.main import build_parser
from agent.runtime import plugins
from agent.runtime.ready import notify

UNITS = Path(ROOT) / "deploy" / "systemd"


def notify_socket(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(str(path))
    s.settimeout(START_WAIT_S)
    return s


def fields(datagram: bytes) -> dict[str, str]:
    return dict(line.split("=", 1) for line in datagram.decode().splitlines())


def test_router_and_agent_notify_ready_and_stopping(tmp_path: Path, processes, realm: str
                                                     ) -> None:
    sock = notify_socket(tmp_path / "notify")
    env = {"NOTIFY_SOCKET": str(tmp_path / "notify")}
    router_ep = endpoint(free_port())
    router = spawn(processes, ["-m", "agent.cli", "router", "--listen", router_ep], env)
    got = fields(sock.recv(4096))
    assert got["READY"] == "1" and f"listening on {router_ep}" in got["STATUS"]
    agent = spawn(processes, ["-m", "agent.cli", "agent", "--realm", realm, "--id", "A",
                              "--listen", endpoint(free_port()), "--connect", router_ep], env)
    got = fields(sock.recv(4096))
    assert got["READY"] == "1" and got["STATUS"].startswith(f"uma agent A (realm {realm})")
    for proc in (agent, router):
        proc.popen.send_signal(signal.SIGTERM)
        assert fields(sock.recv(4096)) == {"STOPPING": "1"}
        assert proc.popen.wait(30) == 0


def test_notify_reaches_an_abstract_socket_and_is_silent_without_one(monkeypatch) -> None:
    name = f"uma-test-{free_port()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.bind("\0" + name)
        s.settimeout(5)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert notify(READY="1", STATUS="up")
        assert s.recv(100) == b"READY=1\nSTATUS=up"
    monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)  # nobody listens any more: logged
    assert not notify(READY="1")
    monkeypatch.delenv("NOTIFY_SOCKET")
    assert not notify(READY="1")


def test_an_agent_whose_router_is_unreachable_exits_1_saying_so(realm: str) -> None:
    ep = endpoint(free_port())
    out = subprocess.run([sys.executable, "-m", "agent.cli", "agent", "--realm", realm,
                          "--id", "A", "--connect", ep, "--mode", "client"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    assert f"uma agent: error: cannot reach {ep}" in out.stderr
    assert "Traceback" not in out.stderr


def exec_start(unit: Path, env: dict[str, str], instance: str) -> list[str]:
    """A unit's ExecStart as argv, with its ${VARS}, $VARS and %i filled in."""
    text = unit.read_text().replace("\\\n", " ")
    line = next(x for x in text.splitlines() if x.startswith("ExecStart="))
    line = line.removeprefix("ExecStart=").replace("%i", instance)
    line = re.sub(r"\$\{(\w+)\}|\$(\w+)", lambda m: env.get(m[1] or m[2], ""), line)
    return shlex.split(line)


@pytest.mark.parametrize("unit", ["uma-router.service", "uma-agent.service",
                                  "uma-service@.service"])
def test_each_unit_runs_a_command_uma_accepts(unit: str) -> None:
    env = dict(line.split("=", 1) for line in (UNITS / "site.env.example").read_text()
               .splitlines() if line and not line.startswith("#"))
    text = (UNITS / unit).read_text()
    assert "Restart=on-failure" in text and "SyslogIdentifier=" in text
    argv = exec_start(UNITS / unit, env, "sim")
    assert argv[0] == "/opt/uma/bin/uma"
    args = build_parser().parse_args(argv[1:])
    if args.command == "service":
        service = plugins.load(plugins.SERVICE_GROUP, args.name)
        parser = argparse.ArgumentParser()
        plugins.add_service_arguments(parser, service)
        args = parser.parse_args(args.rest)
        assert args.zenoh_config == f"/etc/uma/{env['UMA_HOST']}/service.json5"
    assert ("Type=notify" in text) == (unit != "uma-service@.service")
