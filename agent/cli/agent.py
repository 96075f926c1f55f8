"""``uma agent``: run this host's agent until Ctrl-C / SIGTERM.

Settings come from an optional TOML file (``--config``, examples in ``deploy/``) and the
command line; a command-line option given explicitly wins over the file for single values
(``--realm``, ``--id``, ``--mode``), and adds to its lists (``--listen``, ``--connect``,
``--service``).

TOML keys (all optional)::

    realm = "lab"
    id = "hostA"                    # agent id (default: host name)
    mode = "peer"                   # or "client" (behind a Zenoh router)
    listen = ["tcp/127.0.0.1:7450"]
    connect = ["tcp/127.0.0.1:7447"]
    services = ["sim"]              # hosted service plug-ins

    [matching]
    grace_s = 0.5                   # how long a measured rate/latency may fail a predicate
    rate_window_s = 0.5             # sliding window of the rate measurement

    [zenoh]
    lease_ms = 1000                 # failure detection of a frozen process / lost host

    [[static]]                      # static edges (calibrations) for the SRG
    parent = "ivy/world"
    child = "ivy/cam_nw"
    position = [0.0, 0.0, 2.4]
    quaternion = [0.0, 0.0, 0.0, 1.0]   # x, y, z, w
    pos_std_m = 0.001               # optional
    rot_std_rad = 0.001             # optional
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import tomllib
from pathlib import Path
from typing import Any

from agent.daemon.agent import Agent
from agent.daemon.settings import AgentSettings
from agent.errors import UmaError
from agent.runtime.processes import stop_on_signals
from agent.runtime.ready import notify
from agent.sdk.client import Client

_TOP = {"realm", "id", "mode", "listen", "connect", "services", "matching", "zenoh", "static"}
_MATCHING = {"grace_s", "rate_window_s"}
_ZENOH = {"lease_ms"}


def load_config(path: str) -> dict[str, Any]:
    """Read and check the shape of a TOML config; ``UmaError`` names the file and the key."""
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UmaError(f"config file {path!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UmaError(f"cannot read config file {path!r}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise UmaError(f"config file {path!r} is not valid TOML: {exc}") from None
    _only(data, _TOP, path)
    for table, allowed in (("matching", _MATCHING), ("zenoh", _ZENOH)):
        if table in data:
            if not isinstance(data[table], dict):
                raise UmaError(f"{path}: [{table}] must be a table")
            _only(data[table], allowed, f"{path} [{table}]")
    for name in ("listen", "connect", "services"):
        if name in data and not (isinstance(data[name], list)
                                 and all(isinstance(x, str) for x in data[name])):
            raise UmaError(f"{path}: {name} must be a list of strings")
    for name in ("realm", "id", "mode"):
        if name in data and not isinstance(data[name], str):
            raise UmaError(f"{path}: {name} must be a string")
    if "static" in data and not isinstance(data["static"], list):
        raise UmaError(f"{path}: static edges are written as [[static]] tables")
    return data


def _only(d: dict[str, Any], allowed: set[str], where: str) -> None:
    unknown = set(d) - allowed
    if unknown:
        raise UmaError(f"{where}: unknown setting(s) {', '.join(sorted(unknown))} "
                       f"(known: {', '.join(sorted(allowed))})")


def settings_from(args: argparse.Namespace) -> AgentSettings:
    """Merge the config file (if any) and the command line into checked settings."""
    cfg = load_config(args.config) if args.config else {}
    s = AgentSettings()
    s.realm = cfg.get("realm", s.realm)
    s.agent_id = cfg.get("id", s.agent_id)
    s.mode = cfg.get("mode", s.mode)
    listen = list(cfg.get("listen", [])) + list(args.listen)
    s.listen = listen or None
    s.connect = list(cfg.get("connect", [])) + list(args.connect)
    s.services = list(cfg.get("services", [])) + list(args.service)
    s.static_edges = list(cfg.get("static", []))
    for k, v in cfg.get("matching", {}).items():
        setattr(s, k, v)
    if "lease_ms" in cfg.get("zenoh", {}):
        lease = cfg["zenoh"]["lease_ms"]
        if isinstance(lease, bool) or not isinstance(lease, int) or not 50 <= lease <= 600_000:
            raise UmaError(f"[zenoh] lease_ms must be an integer in 50..600000, got {lease!r}")
        s.lease_ms = lease
    if args.realm != "default" or "realm" not in cfg:
        s.realm = args.realm
    if args.id is not None:
        s.agent_id = args.id
    if getattr(args, "mode", None) is not None:
        s.mode = args.mode
    s.insecure = bool(getattr(args, "insecure", False))
    return s.check()


#: Zenoh's runtimes (rx, acc, net, app) all hand their work over to the tx runtime: an
#: agent answers small queries and forwards small samples, and on a loaded host each hop
#: between runtime threads costs a context switch: handing everything to tx saves most of
#: an agent's context switches per query (``bench/bench_query_remote.py`` measures the
#: query against a bare get).  A ZENOH_RUNTIME set by the user wins.
AGENT_ZENOH_RUNTIME = "(rx: (handover: tx), acc: (handover: tx), net: (handover: tx), " \
                      "app: (handover: tx))"


#: An agent starts in well under a second; one that has not within this many seconds is
#: stuck inside Zenoh (see ``_start_or_exit``).
START_LIMIT_S = 15.0
#: What a stalled start prints; supervisors (and the test harness) restart on it.
STALLED_START = "the Zenoh session stalled while the agent was starting"
#: What a session that stalls later prints (the same deadlock, after the start)
STALLED_RUNNING = "the Zenoh session stalled while the agent was running"
#: A worker call blocked this long means a stalled session (its calls take milliseconds;
#: the longest, a full re-match of 10,000 abilities x 1,000 needs, 2.8 s cold in
#: bench/bench_scale.py on a loaded 2-core host)
STALL_LIMIT_S = 30.0


def main(args: argparse.Namespace) -> int:
    """Handler of ``uma agent``."""
    os.environ.setdefault("ZENOH_RUNTIME", AGENT_ZENOH_RUNTIME)  # before any session opens
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    settings = settings_from(args)
    stop = stop_on_signals()
    agent = Agent(settings, client=Client)
    _start_or_exit(agent)
    try:
        status = (f"uma agent {settings.agent_id} (realm {settings.realm}) listening on "
                  f"{' '.join(agent.endpoints) or 'nothing'}")
        print(status, flush=True)
        notify(READY="1", STATUS=status)
        while not stop.wait(0.2):
            if not agent.alive():
                print("uma agent: error: the agent's worker stopped; see the log above",
                      file=sys.stderr)
                return 1
            _exit_if_stalled(agent)
    finally:
        notify(STOPPING="1")
        agent.close()
    return 0


def _exit_if_stalled(agent: Agent) -> None:
    """Exit 1 with a message if the agent's Zenoh session stalled while it runs.

    Such an agent stays alive but its peers and services lose it for good (its links lapse
    and are never re-made); exiting lets its supervisor (``Restart=on-failure`` in
    ``deploy/systemd``) start it again, and its services, which keep their connections
    meanwhile, register again.  ``os._exit``: the stalled threads are in native code, a
    clean close would block on them too."""
    stalled = agent.stalled(STALL_LIMIT_S)
    if stalled is not None:
        print(f"uma agent: error: {STALLED_RUNNING} ({stalled}; a known Zenoh deadlock "
              "under peer churn); start it again", file=sys.stderr, flush=True)
        os._exit(1)


def _start_or_exit(agent: Agent) -> None:
    """``agent.start()``, or exit 1 with a clear message if it never returns.

    A Zenoh session that opens while its peers reconnect to it (an agent restarted on its
    old port) can deadlock: about 1 restart in 120 in the multi-process tests, stuck in the
    first ``session.get``, as described in eclipse-zenoh/zenoh#2581 (fixed upstream by
    #2779; eclipse-zenoh 1.10.2, the newest release here, still shows it).  The daemon
    would hang silently; it exits instead, so that whoever runs it starts it again.
    """
    def stalled() -> None:
        print(f"uma agent: error: {STALLED_START} (no progress in {START_LIMIT_S:g} s; a "
              "known Zenoh deadlock when peers reconnect during start-up); start it again",
              file=sys.stderr, flush=True)
        os._exit(1)  # the main thread is blocked in native code: no clean unwinding

    watchdog = threading.Timer(START_LIMIT_S, stalled)
    watchdog.daemon = True
    watchdog.start()
    try:
        agent.start()
    finally:
        watchdog.cancel()
