"""Service and evaluation plug-ins, found by name through package entry points.

A tracker service is a :class:`ServicePlugin` declared in a light module (its options and
the ``"module:function"`` that runs it) and registered in ``pyproject.toml`` under
``[project.entry-points."uma.services"]``; an accuracy evaluation
likewise under ``"uma.evals"``; a command that a package adds to ``uma`` (``uma demo``) is a
:class:`CommandPlugin` under ``"uma.commands"``, and one under ``uma service`` (``uma
service recalibrate``) under ``"uma.service_commands"``.  The CLI (``uma service run NAME``,
``uma eval NAME``, the added commands) and the agent (``uma agent --service NAME``) look
them up here, so the agent never imports a service by hand and a third-party package can
add its own.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import EntryPoints, entry_points
from typing import Any

from agent.errors import UmaError

log = logging.getLogger("uma.plugins")

SERVICE_GROUP = "uma.services"
EVAL_GROUP = "uma.evals"
COMMAND_GROUP = "uma.commands"
SERVICE_COMMAND_GROUP = "uma.service_commands"


@dataclass(frozen=True)
class ServicePlugin:
    """A runnable service.

    The module that declares it must be light to import (``uma service run NAME --help``
    loads it): ``run`` is ``"module:function"``, imported only when the service runs, and
    ``function(args, stop)`` runs until ``stop`` is set (or the service ends by itself) and
    returns an exit code.  ``args`` always carries ``realm``, ``agent``, ``connect`` and
    ``listen`` besides the options that ``add_arguments`` declared.
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: str


@dataclass(frozen=True)
class EvalPlugin:
    """An accuracy evaluation against simulated ground truth.

    The module that declares it must be light to import (``uma eval NAME --help`` and a bad
    option load it, and an evaluation's module takes seconds): ``run`` is
    ``"module:function"``, imported only when the evaluation runs; ``function(args)``
    returns the figures as a JSON-serialisable dict; ``args`` carries
    ``seconds``, ``seed`` and ``json`` besides the plug-in's own options.  With ``--seeds``
    the CLI calls ``run`` once per seed; ``higher_is_better`` names the figures (leaf keys)
    whose worst seed is the one with the smallest value (shares, success counts).
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: str
    higher_is_better: frozenset[str] = frozenset()


@dataclass(frozen=True)
class CommandPlugin:
    """A command a package adds to ``uma``.

    ``uma --help`` builds every command's parser, so the module that defines the plug-in
    must be light to import: ``run`` is ``"module:function"``, imported only when the
    command runs, and the function takes the parsed arguments and returns an exit code.
    """

    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: str


def load_all(group: str) -> list[Any]:
    """Every plug-in of ``group`` (for commands, whose parsers are built up front); one that
    cannot be imported is skipped with a warning, so one broken package does not break
    ``uma``."""
    found = []
    for name in names(group):
        try:
            found.append(load(group, name))
        except UmaError as exc:
            log.warning("skipping %s plug-in %s: %s", group, name, exc)
    return found


@functools.cache
def _installed() -> EntryPoints:
    """Every installed package's entry points, read once per process: each reading opens
    the metadata of every installed distribution, and building ``uma``'s parser looks up a
    group some fifteen times (about 40 ms of CPU at every start of every ``uma`` process)."""
    return entry_points()


def _registered(group: str) -> EntryPoints:
    return _installed().select(group=group)


def names(group: str) -> list[str]:
    """Registered plug-in names of a group, sorted, without importing them."""
    return sorted(ep.name for ep in _registered(group))


def load(group: str, name: str) -> Any:
    """Import and return the plug-in ``name`` of ``group``; ``UmaError`` if there is none."""
    found = [ep for ep in _registered(group) if ep.name == name]
    if not found:
        known = ", ".join(names(group)) or "none"
        raise UmaError(f"no {group.split('.')[-1][:-1]} named {name!r} (known: {known})")
    try:
        return found[0].load()
    except (ImportError, AttributeError) as exc:
        raise UmaError(f"{name!r} is registered but not built yet ({exc})") from None


def runner(target: str) -> Callable[..., Any]:
    """The function a plug-in's ``run`` names (``"module:function"``), imported now; an
    ``UmaError`` says so if it cannot be."""
    module, _, func = target.partition(":")
    try:
        return getattr(importlib.import_module(module), func)
    except (ImportError, AttributeError) as exc:
        raise UmaError(f"{target!r} cannot be run: it is not built yet ({exc})") from None


def add_network_arguments(p: argparse.ArgumentParser, listen: bool = True) -> None:
    """``--realm``, ``--connect`` (and ``--listen``): every command that joins a realm."""
    p.add_argument("--realm", default="default",
                   help="deployment namespace; agents of one realm only meet each other")
    p.add_argument("--connect", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    if listen:
        p.add_argument("--listen", action="append", default=[], metavar="EP",
                       help="Zenoh endpoint to listen on (repeatable; default tcp/127.0.0.1:0)")
    p.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="Zenoh JSON5 configuration to start from, e.g. a secured site's TLS "
                        "certificates ('uma deploy config'; default: $UMA_ZENOH_CONFIG); "
                        "uma's own settings are applied on top")


def use_zenoh_config(args: argparse.Namespace) -> None:
    """Make ``--zenoh-config`` the Zenoh configuration of every session this process opens
    (the agent's, its hosted services', a command's), through ``UMA_ZENOH_CONFIG``; a file
    that does not exist is an ``UmaError`` before anything starts."""
    path = getattr(args, "zenoh_config", None)
    if path is not None:
        # here, not at the top: 'uma --help' builds every parser and must not load Zenoh
        from agent.runtime.session import ZENOH_CONFIG_ENV, zenoh_config_file

        os.environ[ZENOH_CONFIG_ENV] = os.path.abspath(zenoh_config_file(path))


def add_service_arguments(parser: argparse.ArgumentParser, service: ServicePlugin) -> None:
    """The options every service takes, then the service's own."""
    add_network_arguments(parser)
    parser.add_argument("--agent", default=None,
                        help="id of the local agent to register with (default: host name)")
    service.add_arguments(parser)
