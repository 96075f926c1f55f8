"""The Zenoh configuration of every role of a secured site: TLS only, both ends
authenticated by the site CA, and the router's access control.

The secured layout is the router layout of ``docs/ARCHITECTURE.md`` ("Topology"): every
process of every host (agent, services, clients) is a Zenoh *client* of the site router
over TLS.  Zenoh clients never route for each other, so every message crosses the router,
and the router alone enforces who may do what, by the common name of the certificate the
remote presented (``cert_common_names``; :mod:`agent.deploy.certs`).  Access control in
Zenoh 1.x is checked where a link ends, per message, on ingress and egress; with
``default_permission: "deny"`` a message no rule allows is dropped.

What the router allows (``R`` the site's realm, ``h`` the common name of the remote):

==========================  ===========  =================================================
who                         flow         messages, key expressions
==========================  ===========  =================================================
every member of the site    ingress      declare_subscriber, liveliness_query,
                                         declare_liveliness_subscriber on ``uma/R/**``
every member of the site    ingress      query on the keys that are read by asking:
                                         ``uma/R/agent/*/services``, ``.../supernode``,
                                         ``.../query``, ``uma/R/svc/**`` (``ASK_KEYS``)
every member of the site    egress       every message on ``uma/R/**`` (what it may read)
agent host ``h``            ingress      put, delete, declare_queryable,
                                         liveliness_token on ``uma/R/agent/h``,
                                         ``uma/R/agent/h/**``, ``uma/R/svc/h/**``,
                                         ``uma/R/ctl/h/**``, ``uma/R/data/h/**``;
                                         query on ``uma/R/agent/h/register`` (its
                                         services register with its agent, nobody else)
every agent host            ingress      reply on ``uma/R/**`` (see below)
client host                 —            nothing more: it queries and subscribes
anyone else, anything else  —            denied (and without a site certificate the TLS
                                         handshake fails before any message)
==========================  ===========  =================================================

Zenoh's access control matches a message's key expression by *inclusion* in a rule's: a
query on ``uma/R/agent/h/**`` or ``uma/R/**`` is included in no rule above and is denied,
so the registration queryable of agent ``h`` is reached by host ``h`` alone.

Zenoh checks a reply against the key expression of the *query* it answers, not the key the
reply carries; a host receives only the queries that meet the queryables it was allowed to
declare, so replies are allowed realm-wide.  What this leaves open (a site host answering
a wildcard query such as ``agent/*/query`` under another agent's key) is in
``docs/SECURITY.md``.

So a host can speak only as itself: its agent id is the common name of its certificate
(an agent started with another host's id declares a token the router drops), its services'
streams are ``data/h/...`` and nobody else's, and a client host publishes nothing.  Keys
outside ``uma/R/`` (another realm, the admin space ``@/**``) are denied both ways.

Names are checked on connect (``verify_name_on_connect``): the router's certificate must
name the address the hosts dial (``uma deploy certs --address``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from agent.deploy.certs import SiteSpec
from agent.errors import UmaError
from agent.protocol import keys
from agent.runtime.session import check_endpoint

READ_MESSAGES = ["declare_subscriber", "liveliness_query", "declare_liveliness_subscriber"]
#: what every member may query, under the realm's root: what agents and services answer
#: to anyone (a registration is a write: ``register_key``, for the agent's own host only)
ASK_KEYS = ("agent/*/services", "agent/*/supernode", "agent/*/query", "svc/**")
WRITE_MESSAGES = ["put", "delete", "declare_queryable", "liveliness_token"]
#: every message type Zenoh's access control knows (``DEFAULT_CONFIG.json5``, 1.x)
ALL_MESSAGES = [*WRITE_MESSAGES, "reply", "query", *READ_MESSAGES]
ROLES = ("router", "agent", "service", "client")


def host_files(host_dir: str | Path) -> dict[str, str]:
    """The absolute paths of a host's CA certificate, certificate and key."""
    base = Path(host_dir).resolve()
    return {"ca": str(base / "ca.pem"), "cert": str(base / "cert.pem"),
            "key": str(base / "key.pem")}


def router_config(spec: SiteSpec, realm: str, listen: list[str], files: dict[str, str]
                  ) -> dict[str, Any]:
    """The router's configuration: TLS listeners, mTLS and the site's access control."""
    return {
        "mode": "router",
        "listen": {"endpoints": _tls_endpoints(listen, "--listen")},
        "transport": {"link": {"protocols": ["tls"], "tls": {
            "root_ca_certificate": files["ca"],
            "listen_private_key": files["key"],
            "listen_certificate": files["cert"],
            "enable_mtls": True,
            "connect_private_key": files["key"],
            "connect_certificate": files["cert"],
            "verify_name_on_connect": True,
            "close_link_on_expiration": True}}},
        "access_control": access_control(spec, realm),
    }


def member_config(router: list[str], files: dict[str, str]) -> dict[str, Any]:
    """The configuration of an agent, service or client process: a Zenoh client of the
    router over TLS, presenting its host's certificate.  (The three roles of one host
    present the same certificate; what each may do is the router's access control.)"""
    return {
        "mode": "client",
        "connect": {"endpoints": _tls_endpoints(router, "--router-endpoint")},
        "transport": {"link": {"protocols": ["tls"], "tls": {
            "root_ca_certificate": files["ca"],
            "enable_mtls": True,  # else Zenoh's connecting side sends no certificate
            "connect_private_key": files["key"],
            "connect_certificate": files["cert"],
            "verify_name_on_connect": True,
            "close_link_on_expiration": True}}},
    }


def access_control(spec: SiteSpec, realm: str) -> dict[str, Any]:
    """The router's ``access_control`` block (table in the module docstring)."""
    root = keys.realm_root(realm)
    members = [*spec.hosts, *spec.clients]
    rules = [
        {"id": "read", "flows": ["ingress"], "permission": "allow",
         "messages": READ_MESSAGES, "key_exprs": [f"{root}/**"]},
        {"id": "ask", "flows": ["ingress"], "permission": "allow",
         "messages": ["query"], "key_exprs": [f"{root}/{k}" for k in ASK_KEYS]},
        {"id": "deliver", "flows": ["egress"], "permission": "allow",
         "messages": ALL_MESSAGES, "key_exprs": [f"{root}/**"]},
        {"id": "answer", "flows": ["ingress"], "permission": "allow",
         "messages": ["reply"], "key_exprs": [f"{root}/**"]},
    ]
    subjects = [{"id": "site", "cert_common_names": members, "link_protocols": ["tls"]},
                {"id": "agent-hosts", "cert_common_names": list(spec.hosts),
                 "link_protocols": ["tls"]}]
    policies = [{"id": "members-read", "rules": ["read", "ask", "deliver"],
                 "subjects": ["site"]},
                {"id": "agent-hosts-answer", "rules": ["answer"], "subjects": ["agent-hosts"]}]
    for host in spec.hosts:
        rules.append({"id": f"write-{host}", "flows": ["ingress"], "permission": "allow",
                      "messages": WRITE_MESSAGES, "key_exprs": own_keys(realm, host)})
        rules.append({"id": f"register-{host}", "flows": ["ingress"], "permission": "allow",
                      "messages": ["query"], "key_exprs": [keys.agent_register(realm, host)]})
        subjects.append({"id": f"host-{host}", "cert_common_names": [host],
                         "link_protocols": ["tls"]})
        policies.append({"id": f"{host}-writes", "rules": [f"write-{host}", f"register-{host}"],
                         "subjects": [f"host-{host}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def own_keys(realm: str, host: str) -> list[str]:
    """The keys agent host ``host`` may write: its agent's, its services' and their
    streams."""
    agent = keys.agent_token(realm, host)
    root = keys.realm_root(realm)
    return [agent, f"{agent}/**", f"{root}/svc/{host}/**", f"{root}/ctl/{host}/**",
            f"{root}/data/{host}/**"]


def write_configs(cert_dir: str | Path, spec: SiteSpec, realm: str, router_listen: list[str],
                  router_endpoints: list[str], install_dir: str | None = None
                  ) -> list[Path]:
    """Write ``hosts/NAME/<role>.json5`` for every member and role it plays; paths inside
    point at ``install_dir/NAME`` (where the host directory will be copied to; default: its
    place here).  Returns the files written."""
    keys.check_name("realm", realm)
    _tls_endpoints(router_endpoints, "--router-endpoint")
    _tls_endpoints(router_listen, "--listen")
    written = []
    for name in spec.members:
        host_dir = Path(cert_dir) / "hosts" / name
        if not (host_dir / "cert.pem").exists():
            raise UmaError(f"{host_dir / 'cert.pem'} is missing: run 'uma deploy certs' "
                           "first")
        files = host_files(Path(install_dir) / name if install_dir else host_dir)
        if name == spec.router:
            configs = {"router": router_config(spec, realm, router_listen, files)}
        else:
            member = member_config(router_endpoints, files)
            roles = ("agent", "service", "client") if name in spec.hosts else ("client",)
            configs = dict.fromkeys(roles, member)
        for role, config in configs.items():
            path = host_dir / f"{role}.json5"
            path.write_text(_header(name, role, realm) + json.dumps(config, indent=2) + "\n",
                            encoding="utf-8")
            written.append(path)
    return written


def _header(name: str, role: str, realm: str) -> str:
    return (f"// Zenoh configuration of the {role} on host {name}, realm {realm}, written by "
            "'uma deploy config'.\n// Use it with: uma ... --zenoh-config THIS_FILE (uma's "
            "own settings are applied on top).\n")


def _tls_endpoints(endpoints: list[str], option: str) -> list[str]:
    if not endpoints:
        raise UmaError(f"{option}: at least one tls/HOST:PORT endpoint is needed")
    for ep in endpoints:
        if not check_endpoint(ep).startswith("tls/"):
            raise UmaError(f"{option} {ep!r}: a secured site speaks TLS only "
                           "(tls/HOST:PORT)")
    return list(endpoints)
