"""The README's Python examples run as written (with this test's port and realm)."""

from __future__ import annotations

import subprocess
import sys
import time

from agent_helpers.harness import agent
from agent_helpers.readme import readme_block as _block
from agent_helpers.readme import run_python as _run
from conftest import endpoint, free_port


def test_graph_example_runs() -> None:
    done = _run(_block("Graph(buffer_s"))
    assert done.returncode == 0, done.stderr
    assert "cam/nw" in done.stdout and "alice/head" in done.stdout


def test_public_modules_example_runs() -> None:
    done = _run(_block("ServicePlugin("))
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[:2] == ["[1. 1. 0.]", "my-tracker"]


def test_inventory_example_lists_the_agent(processes, realm) -> None:
    ep = endpoint(free_port())
    agent(processes, realm, "hostA", ep)
    code = _block("collect_realm(").replace("tcp/127.0.0.1:7447", ep).replace('"lab"',
                                                                             f'"{realm}"')
    done = _run(code)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "['hostA'] []"


def test_service_and_client_examples_run_against_an_agent(processes, realm) -> None:
    ep = endpoint(free_port())

    def adapt(code: str) -> str:
        return code.replace("tcp/127.0.0.1:7447", ep).replace('realm="lab"', f'realm="{realm}"')

    agent(processes, realm, "hostA", ep)  # up before its services start
    svc = subprocess.Popen([sys.executable, "-c", adapt(_block("Service("))],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20.0
        last = None
        while time.monotonic() < deadline and svc.poll() is None:
            last = _run(adapt(_block("c.pose(")))
            if last.returncode == 0:
                break
            time.sleep(0.2)
        assert last is not None and last.returncode == 0, (last.stderr if last else
                                                           svc.stderr.read())
        assert "alice/head" in last.stdout
        assert svc.wait(timeout=20) == 0, svc.stderr.read()
    finally:
        if svc.poll() is None:
            svc.kill()
            svc.wait()
        svc.stdout.close()
        svc.stderr.close()
