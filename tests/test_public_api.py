"""The public API: what ``agent.__all__`` promises resolves, and importing the pure parts
pulls in no Zenoh."""

from __future__ import annotations

import subprocess
import sys

import agent


def test_every_public_name_resolves() -> None:
    for name in agent.__all__:
        assert getattr(agent, name).__name__ == name


def test_an_unknown_name_is_a_clear_attribute_error() -> None:
    try:
        agent.Agent  # noqa: B018  (the daemon is not public API)
    except AttributeError as exc:
        assert "'agent' has no attribute 'Agent'" in str(exc)
    else:
        raise AssertionError("agent.Agent resolved")


def test_the_srg_alone_imports_no_zenoh() -> None:
    code = ("import sys, agent, agent.srg\n"
            "from agent.srg import Graph\n"
            "assert 'zenoh' not in sys.modules, 'zenoh imported'\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr


def test_the_agent_never_imports_a_service() -> None:
    """Dependencies go one way (schemas -> agent -> services): the agent finds services,
    evaluations and the commands they add only through plug-in entry points."""
    import re
    from pathlib import Path

    root = Path(agent.__file__).parent
    offenders = [f"{path.relative_to(root.parent)}:{n}"
                 for path in root.rglob("*.py")
                 for n, line in enumerate(path.read_text().splitlines(), 1)
                 if re.match(r"\s*(from|import)\s+services\b", line)
                 or re.search(r"[\"']services\.[a-z_.]+:", line)]
    assert offenders == []


def test_commands_added_by_plugins_are_in_uma_help() -> None:
    from agent.cli.main import build_parser

    text = build_parser().format_help()
    assert "demo" in text
    out = subprocess.run([sys.executable, "-m", "agent.cli", "service", "recalibrate",
                          "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "--agent ID" in out.stdout
