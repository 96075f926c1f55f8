"""Every program in examples/ runs against real agents on loopback and does what its
docstring says."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from agent_helpers.harness import agent, spawn
from conftest import endpoint, free_port

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def run(name: str, *args: str, timeout: float = 90.0) -> str:
    """Run ``examples/NAME`` to its end; its stdout (a failure shows its stderr)."""
    out = subprocess.run([sys.executable, str(EXAMPLES / name), *args], capture_output=True,
                         text=True, timeout=timeout, cwd=EXAMPLES.parent)
    assert out.returncode == 0, f"{name} exited {out.returncode}:\n{out.stderr[-2000:]}"
    return out.stdout


def test_offline_srg() -> None:
    text = run("offline_srg.py")
    assert "path: cam/nw -> ivy/world -> alice/head" in text
    assert "[1.2   0.695 0.4  ]" in text  # the head between its samples at 0.505 s


def test_tracker_consumer_query_and_subscription_across_two_agents(processes, realm,
                                                                   tmp_path) -> None:
    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    agent(processes, realm, "hostA", ep_a)
    config = tmp_path / "hostB.toml"
    config.write_text('[[static]]\nparent = "ivy/world"\nchild = "cam/nw"\n'
                      "position = [1.2, 1.2, 1.2]\nquaternion = [0.0, 0.0, 1.0, 0.0]\n")
    agent(processes, realm, "hostB", ep_b, connect=(ep_a,), extra=("--config", str(config)))
    tracker = spawn(processes, [str(EXAMPLES / "tracker_service.py"), "--realm", realm,
                                "--agent", "hostA", "--connect", ep_a, "--seconds", "120"])
    tracker.wait_line("publishing ivy/world -> alice/head")

    on_b = ("--realm", realm, "--connect", ep_b)
    samples = run("consumer.py", "--agent", "hostB", *on_b, "--count", "3").splitlines()
    assert len(samples) == 3
    assert all(s.startswith("sample from tracker: ivy/world -> alice/head") for s in samples)

    answer = run("cross_agent_query.py", "cam/nw", "alice/head", *on_b)
    assert "path cam/nw -> ivy/world -> alice/head" in answer
    assert "agents hostB, hostA" in answer  # the camera is B's, the head is A's

    poses = run("subscription.py", "ivy/world", "alice/head", *on_b, "--count", "3")
    assert len(poses.splitlines()) == 3 and poses.startswith("pose at ")
