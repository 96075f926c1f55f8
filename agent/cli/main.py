"""The ``uma`` command line: argument parsing and dispatch.

Each command's work lives in its own module, imported only when the command runs, so
``uma --help`` stays fast and one command's dependencies never slow another.
Exit codes: 0 success, 1 failure (a clear message on stderr), 2 bad arguments.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import sys
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version
from typing import Any, NoReturn

from agent.cli import seeds
from agent.errors import UmaError
from agent.runtime import plugins
from agent.runtime.processes import stop_on_signals

# command -> "module:function"; the function takes the parsed arguments, returns an exit code
HANDLERS = {
    "agent": "agent.cli.agent:main",
    "router": "agent.cli.router:main",
    "services": "agent.cli.services:main",
    "query": "agent.cli.query:main",
    "schemas": "schemas.export:main",
    "deploy": "agent.cli.deploy:main",
}
#: what --insecure of ``uma agent`` and ``uma router`` says
INSECURE_HELP = ("listen without TLS on addresses other hosts reach (refused by default: "
                 "anyone who reaches it can read and write the realm; secure the site with "
                 "'uma deploy' instead)")


def _version() -> str:
    try:
        return version("uma-tracking")
    except PackageNotFoundError:
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    """The whole command-line grammar."""
    top = argparse.ArgumentParser(
        prog="uma",
        description="uma: peer-to-peer middleware for ubiquitous tracking. One agent per host "
                    "matches tracker services' needs and abilities over Zenoh and answers pose "
                    "queries across hosts.",
        epilog="Start here: 'uma demo' runs an agent, simulated trackers and a query in one "
               "process. 'uma COMMAND --help' explains each command.")
    top.add_argument("--version", action="version", version=f"uma {_version()}")
    sub = top.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("agent", help="run the agent daemon of this host",
                       description="Run the per-host agent: advertises local services, matches "
                                   "their needs to abilities in the realm, keeps the host's "
                                   "spatial relationship graph and answers pose queries. "
                                   "Stops cleanly on Ctrl-C / SIGTERM.")
    plugins.add_network_arguments(p)
    p.add_argument("--id", default=None, help="agent id (default: this host's name)")
    p.add_argument("--mode", choices=("peer", "client"), default=None,
                   help="peer (the default: listens and meets the other agents directly) or "
                        "client (behind a Zenoh router: larger and secured sites)")
    p.add_argument("--service", action="append", default=[], metavar="NAME",
                   help="host a service inside the agent process (repeatable; see "
                        "'uma service run --help' for names)")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="TOML file with the same settings and static edges (examples in deploy/)")
    p.add_argument("--insecure", action="store_true", help=INSECURE_HELP)

    p = sub.add_parser("router", help="run a Zenoh router for client-mode agents",
                       description="Run a Zenoh router in this process so agents and clients in "
                                   "client mode can meet through it (larger sites).")
    p.add_argument("--listen", action="append", default=[], metavar="EP",
                   help="endpoint to listen on (repeatable; default: the --config file's, "
                        "else tcp/127.0.0.1:7447)")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="Zenoh JSON5 configuration to start from (default: $ZENOH_CONFIG if "
                        "set; example in deploy/router.json5); uma's settings (mode, lease, "
                        "no multicast scouting) are applied on top")
    p.add_argument("--insecure", action="store_true", help=INSECURE_HELP)

    p = sub.add_parser("service", help="run one tracker service on its own",
                       description="Run a tracker service as its own process; it registers with "
                                   "the local agent.")
    ssub = p.add_subparsers(dest="service_command", metavar="ACTION", required=True)
    names = plugins.names(plugins.SERVICE_GROUP)
    sp = ssub.add_parser("run", help="run the service NAME",
                         description="Run the service NAME. Known services: "
                                     f"{', '.join(names) or 'none installed'}. "
                                     "'uma service run NAME --help' lists its options.",
                         add_help=False)
    sp.add_argument("-h", "--help", dest="show_help", action="store_true")
    sp.add_argument("name", metavar="NAME", nargs="?", help="service name")
    sp.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    for command in plugins.load_all(plugins.SERVICE_COMMAND_GROUP):
        _add_command(ssub, command)

    p = sub.add_parser("services", help="list agents, services, needs, abilities and matches",
                       description="Ask every agent of the realm for its services and print "
                                   "each agent, service, need, ability and current match.")
    plugins.add_network_arguments(p, listen=False)
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for answers")
    p.add_argument("--json", action="store_true", help="print one JSON object")

    p = sub.add_parser("query", help="query the pose of TARGET in SOURCE's frame",
                       description="Compute the pose of frame TARGET in frame SOURCE over the "
                                   "spatial relationship graphs of all agents in the realm.")
    p.add_argument("source", metavar="SOURCE", help="frame id, e.g. ivy/world")
    p.add_argument("target", metavar="TARGET", help="frame id, e.g. alice/head")
    p.add_argument("--at", default=None, metavar="T",
                   help="time: integer ns since the epoch, or 'now' (default: latest common time)")
    p.add_argument("--error", default="hops", metavar="E",
                   help="error function to minimise: hops, latency, accuracy, confidence, cost, "
                        "or an expression over attributes (default: hops)")
    plugins.add_network_arguments(p, listen=False)
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for the answer")
    p.add_argument("--json", action="store_true", help="print one JSON object")

    _add_deploy(sub)

    evals = plugins.names(plugins.EVAL_GROUP)
    p = sub.add_parser("eval", help="measure a tracker's accuracy against simulated ground truth",
                       description="Run a tracker on the simulator and print its accuracy against "
                                   f"ground truth. Known: {', '.join(evals) or 'none'}. "
                                   "'uma eval NAME --help' lists its options.",
                       add_help=False)
    p.add_argument("-h", "--help", dest="show_help", action="store_true")
    p.add_argument("name", metavar="NAME", nargs="?", help="what to evaluate")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)

    p = sub.add_parser("schemas", help="export the JSON Schemas of uma's models",
                       description="Export the JSON Schemas of uma's descriptors and results.")
    xsub = p.add_subparsers(dest="schemas_command", metavar="ACTION", required=True)
    xp = xsub.add_parser("export", help="write one JSON Schema file per model into DIR",
                         description="Write <Model>.schema.json for each of uma's models "
                                     "(service descriptors, needs, abilities, attributes, pose "
                                     "results) into DIR, for validating messages in other "
                                     "languages.")
    xp.add_argument("dir", metavar="DIR", help="output directory (created if missing)")

    for command in plugins.load_all(plugins.COMMAND_GROUP):
        _add_command(sub, command)
    return top


def _add_deploy(sub: Any) -> None:
    """``uma deploy certs`` and ``uma deploy config``: a secured site (docs/SECURITY.md)."""
    p = sub.add_parser("deploy", help="certificates and Zenoh configurations of a secured site",
                       description="Secure a site with Zenoh's TLS, mutual authentication and "
                                   "access control: 'certs' makes a site CA and one "
                                   "certificate per host, 'config' writes each role's Zenoh "
                                   "configuration (see docs/SECURITY.md).")
    dsub = p.add_subparsers(dest="deploy_command", metavar="ACTION", required=True)
    cp = dsub.add_parser("certs", help="create a site CA and one certificate per host",
                         description="Create DIR/ca (the site CA; keep its key off the hosts) "
                                     "and DIR/hosts/NAME (CA certificate, certificate and key "
                                     "of host NAME, whose common name is NAME) for the router, "
                                     "every agent host and every client host.",
                         epilog="example: uma deploy certs site/ --site lab --hosts a,b,c "
                                "--router r --address r=10.0.0.1")
    cp.add_argument("dir", metavar="DIR", help="output directory (must not hold a site yet)")
    cp.add_argument("--site", required=True, help="site name (in the CA's name)")
    cp.add_argument("--hosts", required=True, metavar="A,B,C",
                    help="agent hosts: each runs an agent (its id = the host name) and services")
    cp.add_argument("--router", default="router", metavar="NAME",
                    help="name of the router host (default: router)")
    cp.add_argument("--clients", default=None, metavar="X,Y",
                    help="client-only hosts: they may query and subscribe, never publish")
    cp.add_argument("--address", action="append", default=[], metavar="NAME=ADDR",
                    help="an IP address or DNS name NAME is reached at, added to its "
                         "certificate (repeatable; needed for the router's address)")
    cp.add_argument("--days", type=int, default=825,
                    help="validity of host certificates in days (default 825; the CA: 4x)")
    fp = dsub.add_parser("config", help="write the Zenoh configuration of every role",
                         description="Write DIR/hosts/NAME/ROLE.json5 (router; agent, service "
                                     "and client) with TLS only, mutual authentication and "
                                     "the router's access control for REALM.",
                         epilog="example: uma deploy config site/ --realm lab "
                                "--router-endpoint tls/10.0.0.1:7447")
    fp.add_argument("dir", metavar="DIR", help="the directory 'uma deploy certs' wrote")
    fp.add_argument("--realm", required=True, help="the one realm the site's hosts may use")
    fp.add_argument("--router-endpoint", action="append", required=True, metavar="EP",
                    help="tls/HOST:PORT the hosts dial to reach the router (repeatable)")
    fp.add_argument("--listen", action="append", default=[], metavar="EP",
                    help="tls/ADDR:PORT the router listens on (default: --router-endpoint)")
    fp.add_argument("--install-dir", default=None, metavar="PATH",
                    help="where each host's directory will live on that host, e.g. /etc/uma "
                         "(default: where it is now)")


def _add_command(sub: Any, command: plugins.CommandPlugin) -> None:
    """A plug-in's command: its parser, and what runs it (``args.plugin_run``)."""
    p = sub.add_parser(command.name, help=command.help, description=command.description)
    command.add_arguments(p)
    p.set_defaults(plugin_run=command.run)


def _call(target: str, args: argparse.Namespace) -> int:
    try:
        fn = plugins.runner(target)
    except UmaError:
        raise UmaError(f"'uma {args.command}' is not built yet") from None
    return int(fn(args) or 0)


def _plugin_args(args: argparse.Namespace) -> list[str]:
    """The plug-in's own arguments; a ``--help`` that argparse took for us goes back to it."""
    return ["--help", *args.rest] if args.show_help else list(args.rest)


def _run_service(args: argparse.Namespace) -> int:
    names = plugins.names(plugins.SERVICE_GROUP)
    if args.name is None:
        print("usage: uma service run NAME [options]\n\nRun one tracker service as its own "
              f"process.\nKnown services: {', '.join(names)}\n"
              "'uma service run NAME --help' lists the options of NAME.",
              file=sys.stdout if args.show_help else sys.stderr)
        return 0 if args.show_help else 2
    plugin: plugins.ServicePlugin = plugins.load(plugins.SERVICE_GROUP, args.name)
    parser = argparse.ArgumentParser(prog=f"uma service run {plugin.name}",
                                     description=plugin.help)
    plugins.add_service_arguments(parser, plugin)
    sargs = parser.parse_args(_plugin_args(args))
    plugins.use_zenoh_config(sargs)
    # a service is a daemon like the agent: its status and refusals go to stderr
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    return plugins.runner(plugin.run)(sargs, stop_on_signals())


def _run_eval(args: argparse.Namespace) -> int:
    names = plugins.names(plugins.EVAL_GROUP)
    if args.name is None:
        print("usage: uma eval NAME [--seconds S] [--seed N | --seeds 1-10] [--json] "
              "[options]\n\n"
              "Measure a tracker's accuracy against simulated ground truth.\n"
              f"Known: {', '.join(names)}\n'uma eval NAME --help' lists the options of NAME.",
              file=sys.stdout if args.show_help else sys.stderr)
        return 0 if args.show_help else 2
    plugin: plugins.EvalPlugin = plugins.load(plugins.EVAL_GROUP, args.name)
    parser = argparse.ArgumentParser(prog=f"uma eval {plugin.name}", description=plugin.help)
    parser.add_argument("--seconds", type=float, default=60.0,
                        help="simulated seconds (default 60)")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--seed", type=int, default=1, help="simulation seed (default 1)")
    which.add_argument("--seeds", type=seeds.parse_seeds, metavar="LIST",
                       help="run once per seed (e.g. 1-10 or 1,3,5-7) and report every "
                            "figure per seed with its median and worst")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    plugin.add_arguments(parser)
    eargs = parser.parse_args(_plugin_args(args))
    if not (math.isfinite(eargs.seconds) and eargs.seconds > 0):
        parser.error(f"--seconds must be a positive number, got {eargs.seconds!r}")
    run = plugins.runner(plugin.run)
    if eargs.seeds is None:
        figures = run(eargs)
        print(json.dumps(figures) if eargs.json else format_figures(figures))
        return 0
    per_seed = {}
    for i, s in enumerate(eargs.seeds):
        per_seed[s] = run(argparse.Namespace(**{**vars(eargs), "seed": s}))
        print(f"uma eval {plugin.name}: seed {s} done ({i + 1} of {len(eargs.seeds)})",
              file=sys.stderr, flush=True)
    table = seeds.spread(per_seed, plugin.higher_is_better)
    if eargs.json:
        print(json.dumps({"seeds": eargs.seeds, "spread": table,
                          "per_seed": {str(s): f for s, f in per_seed.items()}}))
    else:
        print(seeds.format_spread(eargs.seeds, table))
    return 0


def format_figures(figures: Any, indent: int = 0) -> str:
    """Nested figures as indented ``name: value`` lines for people."""
    pad = "  " * indent
    lines = []
    for key, value in figures.items():
        if isinstance(value, dict):
            lines.append(f"{pad}{key}:")
            lines.append(format_figures(value, indent + 1))
        elif isinstance(value, float):
            lines.append(f"{pad}{key}: {value:.6g}")
        else:
            lines.append(f"{pad}{key}: {value}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``uma`` console script."""
    args = build_parser().parse_args(argv)
    try:
        plugins.use_zenoh_config(args)
        if getattr(args, "plugin_run", None):
            return _call(args.plugin_run, args)
        if args.command == "service":
            return _run_service(args)
        if args.command == "eval":
            return _run_eval(args)
        return _call(HANDLERS[args.command], args)
    except KeyboardInterrupt:
        return 130
    except (UmaError, ValueError, LookupError, OSError, TimeoutError) as exc:
        print(f"uma {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # last resort: a message, never a traceback (UMA_DEBUG=1 shows it)
        if os.environ.get("UMA_DEBUG"):
            raise
        print(f"uma {args.command}: internal error: {type(exc).__name__}: {exc} "
              "(set UMA_DEBUG=1 for the traceback)", file=sys.stderr)
        return 1


def status(argv: Sequence[str] | None = None) -> int:
    """:func:`main`'s exit status, argparse's exits (``--help``, a bad option) included:
    what the ``uma`` executable exits with."""
    try:
        return main(argv)
    except SystemExit as stop:
        if stop.code is not None and not isinstance(stop.code, int):
            print(stop.code, file=sys.stderr)
        return stop.code if isinstance(stop.code, int) else int(stop.code is not None)


def run() -> NoReturn:
    """The ``uma`` executable: :func:`status`, then the process ends without Python's
    finalization.  Zenoh's native threads may still deliver a callback after ``main``
    returns (a session that could not close in time ends with the process); one that
    meets a finalizing interpreter aborts the whole process ("FATAL: exception not
    rethrown") and turns a clean exit into SIGABRT."""
    code = status()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed pipe: nothing left to say
            stream.flush()
    os._exit(code)

