"""``uma deploy certs`` and ``uma deploy config``: a secured site's certificates and the
Zenoh configuration of each of its roles (:mod:`agent.deploy`; threat model in
``docs/SECURITY.md``)."""

from __future__ import annotations

import argparse

from agent.deploy.certs import SiteSpec, create_site, load_site
from agent.deploy.zenoh_config import write_configs
from agent.errors import UmaError


def main(args: argparse.Namespace) -> int:
    """Handler of ``uma deploy``."""
    if args.deploy_command == "certs":
        return _certs(args)
    return _config(args)


def _certs(args: argparse.Namespace) -> int:
    spec = SiteSpec(site=args.site, router=args.router, hosts=_names(args.hosts, "--hosts"),
                    clients=_names(args.clients, "--clients") if args.clients else [],
                    addresses=_addresses(args.address)).check()
    root = create_site(args.dir, spec, days=args.days)
    print(f"site {spec.site}: CA in {root / 'ca'} (keep ca.key off the hosts); one directory "
          f"per host in {root / 'hosts'}: {', '.join(spec.members)}")
    router = (spec.addresses.get(spec.router) or [spec.router])[0]
    print(f"next: uma deploy config {args.dir} --realm REALM --router-endpoint "
          f"tls/{router}:7447")
    return 0


def _config(args: argparse.Namespace) -> int:
    spec = load_site(args.dir)
    listen = args.listen or args.router_endpoint
    written = write_configs(args.dir, spec, args.realm, listen, args.router_endpoint,
                            args.install_dir)
    for path in written:
        print(path)
    print(f"copy {args.dir}/hosts/NAME to {args.install_dir or 'the same place'} on host NAME; "
          "run each process with --zenoh-config NAME/ROLE.json5 and --connect "
          f"{args.router_endpoint[0]}")
    return 0


def _names(text: str, option: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise UmaError(f"{option}: give a comma-separated list of host names, e.g. a,b,c")
    return names


def _addresses(pairs: list[str]) -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for pair in pairs:
        name, sep, address = pair.partition("=")
        if not sep or not name or not address:
            raise UmaError(f"--address {pair!r}: expected NAME=ADDRESS, e.g. "
                           "router=10.0.0.1")
        found.setdefault(name, []).append(address)
    return found
