"""The README's Python examples run as written (with this test's port and realm)."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

from agent_helpers.harness import agent
from conftest import endpoint, free_port

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def _block(marker: str) -> str:
    found = [b for b in _blocks() if marker in b]
    assert len(found) == 1, f"README has no single python example containing {marker!r}"
    return found[0]


def _run(code: str, timeout: float = 30.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=timeout)


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
