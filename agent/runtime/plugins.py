"""Service and evaluation plug-ins, found by name through package entry points.

A tracker service is a module exposing ``PLUGIN = ServicePlugin(...)`` and registered in
``pyproject.toml`` under ``[project.entry-points."uma.services"]``; an accuracy evaluation
likewise under ``"uma.evals"``.  The CLI (``uma service run NAME``, ``uma eval NAME``) and
the agent (``uma agent --service NAME``) look them up here, so the agent never imports a
service by hand and a third-party package can add its own.
"""

from __future__ import annotations

import argparse
import threading
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any

from agent.errors import UmaError

SERVICE_GROUP = "uma.services"
EVAL_GROUP = "uma.evals"


@dataclass(frozen=True)
class ServicePlugin:
    """A runnable service.

    ``run(args, stop)`` runs until ``stop`` is set (or the service ends by itself) and
    returns an exit code.  ``args`` always carries ``realm``, ``agent``, ``connect`` and
    ``listen`` besides the options that ``add_arguments`` declared.
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace, threading.Event], int]


@dataclass(frozen=True)
class EvalPlugin:
    """An accuracy evaluation against simulated ground truth.

    ``run(args)`` returns the figures as a JSON-serialisable dict; ``args`` carries
    ``seconds``, ``seed`` and ``json`` besides the plug-in's own options.
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], dict[str, Any]]


def names(group: str) -> list[str]:
    """Registered plug-in names of a group, sorted, without importing them."""
    return sorted(ep.name for ep in entry_points(group=group))


def load(group: str, name: str) -> Any:
    """Import and return the plug-in ``name`` of ``group``; ``UmaError`` if there is none."""
    found = [ep for ep in entry_points(group=group) if ep.name == name]
    if not found:
        known = ", ".join(names(group)) or "none"
        raise UmaError(f"no {group.split('.')[-1][:-1]} named {name!r} (known: {known})")
    try:
        return found[0].load()
    except (ImportError, AttributeError) as exc:
        raise UmaError(f"{name!r} is registered but not built yet ({exc})") from None


def add_service_arguments(parser: argparse.ArgumentParser, service: ServicePlugin) -> None:
    """The options every service takes, then the service's own."""
    parser.add_argument("--realm", default="default",
                        help="deployment namespace; only agents of the same realm meet")
    parser.add_argument("--agent", default=None,
                        help="id of the local agent to register with (default: host name)")
    parser.add_argument("--connect", action="append", default=[], metavar="EP",
                        help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    parser.add_argument("--listen", action="append", default=[], metavar="EP",
                        help="Zenoh endpoint to listen on (default: tcp/127.0.0.1:0)")
    service.add_arguments(parser)
