"""The uma key space (``docs/ARCHITECTURE.md``, "Key space"), in one place.

Every key lives under ``uma/<realm>/``; realms, agent ids, service ids and ability names are
single key chunks, so they are checked here (no ``/``, no Zenoh wildcard or reserved
characters, no spaces) before they reach Zenoh.  Builders return ``str`` key expressions;
``parse_*`` functions take a received key and return its parts, or ``None`` when the key does
not have the expected shape (the caller logs and drops it).

=============================================  ===================  ==========================
key                                             primitive            meaning
=============================================  ===================  ==========================
``uma/R/agent/A``                               liveliness token     agent A is alive
``uma/R/agent/A/services``                      queryable + put      A's local services
``uma/R/agent/A/register``                      queryable            a service registers with A
``uma/R/agent/A/supernode``                     queryable + put      A's SRG summary
``uma/R/agent/A/query``                         queryable            pose queries, segments
``uma/R/svc/A/S``                               liveliness token     service S (on A) is alive
``uma/R/svc/A/S``                               queryable            S's descriptor (dup check)
``uma/R/ctl/A/S``                               put / subscriber     A -> S: connect needs
``uma/R/data/A/S/N``                            publisher            ability N's stream
=============================================  ===================  ==========================
"""

from __future__ import annotations

import re
import socket

from agent.errors import UmaError
from schemas import ids

ROOT = "uma"


def check_name(kind: str, value: object) -> str:
    """``value`` if it can be one key chunk, else ``UmaError`` naming ``kind`` and the reason.

    ``kind`` says which rule of :mod:`schemas.ids` applies: an ability or need name
    (``kind`` ends in "name") or an id (realms, agents, services).
    """
    check = ids.check_name if kind.endswith("name") else ids.check_id
    try:
        return check(kind, value)
    except ValueError as exc:
        raise UmaError(str(exc)) from None


def default_agent_id() -> str:
    """This host's name, made a valid agent id (the default of agents and services)."""
    name = re.sub(r"[^A-Za-z0-9_.\-]", "-", socket.gethostname()).strip(".-") or "localhost"
    return name[:64]


def realm_root(realm: str) -> str:
    return f"{ROOT}/{check_name('realm', realm)}"


def agent_token(realm: str, agent_id: str) -> str:
    """Liveliness token: the agent is alive."""
    return f"{realm_root(realm)}/agent/{check_name('agent id', agent_id)}"


def all_agent_tokens(realm: str) -> str:
    """Liveliness selector of every agent of the realm."""
    return f"{realm_root(realm)}/agent/*"


def agent_services(realm: str, agent_id: str) -> str:
    """Queryable (and publication on change) of the agent's local services."""
    return f"{agent_token(realm, agent_id)}/services"


def all_agent_services(realm: str) -> str:
    """Selector of every agent's services queryable / change publication."""
    return f"{realm_root(realm)}/agent/*/services"


def agent_register(realm: str, agent_id: str) -> str:
    """Queryable where a local service registers (and re-registers) its descriptor."""
    return f"{agent_token(realm, agent_id)}/register"


def agent_supernode(realm: str, agent_id: str) -> str:
    """Queryable + publication on change: the agent's SRG summary."""
    return f"{agent_token(realm, agent_id)}/supernode"


def all_agent_supernodes(realm: str) -> str:
    return f"{realm_root(realm)}/agent/*/supernode"


def agent_query(realm: str, agent_id: str) -> str:
    """Queryable: pose queries and segment requests."""
    return f"{agent_token(realm, agent_id)}/query"


def agent_digest(realm: str, agent_id: str) -> str:
    """Publication: the newest sample of each of the agent's pose streams
    (:mod:`agent.protocol.digest`), while someone listens."""
    return f"{agent_token(realm, agent_id)}/digest"


def all_agent_queries(realm: str) -> str:
    """Selector of every agent's query queryable (a client asks all in one get)."""
    return f"{realm_root(realm)}/agent/*/query"


def service_token(realm: str, agent_id: str, service_id: str) -> str:
    """Liveliness token (and descriptor queryable) of a service."""
    return (f"{realm_root(realm)}/svc/{check_name('agent id', agent_id)}/"
            f"{check_name('service id', service_id)}")


def service_tokens(realm: str, agent_id: str = "*") -> str:
    """Liveliness selector of the services of one agent (``*``: of every agent)."""
    if agent_id != "*":
        check_name("agent id", agent_id)
    return f"{realm_root(realm)}/svc/{agent_id}/*"


def control(realm: str, agent_id: str, service_id: str) -> str:
    """Agent -> service control messages (which data keys each need subscribes)."""
    return (f"{realm_root(realm)}/ctl/{check_name('agent id', agent_id)}/"
            f"{check_name('service id', service_id)}")


def data(realm: str, agent_id: str, service_id: str, ability: str) -> str:
    """The stream of one ability."""
    return (f"{realm_root(realm)}/data/{check_name('agent id', agent_id)}/"
            f"{check_name('service id', service_id)}/{check_name('ability name', ability)}")


def all_data(realm: str, agent_id: str = "*") -> str:
    """Selector of every stream of one agent's services (``*``: of the realm)."""
    if agent_id != "*":
        check_name("agent id", agent_id)
    return f"{realm_root(realm)}/data/{agent_id}/*/*"


def _parts(key: str, realm: str, kind: str, n: int) -> list[str] | None:
    prefix = f"{realm_root(realm)}/{kind}/"
    if not str(key).startswith(prefix):
        return None
    rest = str(key)[len(prefix):].split("/")
    if len(rest) != n or not all(map(ids.is_id, rest)):
        return None
    return rest


def parse_agent_token(key: str, realm: str) -> str | None:
    """Agent id of ``uma/R/agent/A`` (None if ``key`` has another shape)."""
    parts = _parts(key, realm, "agent", 1)
    return parts[0] if parts else None


def parse_agent_services(key: str, realm: str) -> str | None:
    """Agent id of ``uma/R/agent/A/services``."""
    parts = _parts(key, realm, "agent", 2)
    return parts[0] if parts and parts[1] == "services" else None


def parse_agent_supernode(key: str, realm: str) -> str | None:
    """Agent id of ``uma/R/agent/A/supernode``."""
    parts = _parts(key, realm, "agent", 2)
    return parts[0] if parts and parts[1] == "supernode" else None


def parse_agent_query(key: str, realm: str) -> str | None:
    """Agent id of ``uma/R/agent/A/query``."""
    parts = _parts(key, realm, "agent", 2)
    return parts[0] if parts and parts[1] == "query" else None


def parse_service_token(key: str, realm: str) -> tuple[str, str] | None:
    """``(agent_id, service_id)`` of ``uma/R/svc/A/S``."""
    parts = _parts(key, realm, "svc", 2)
    return (parts[0], parts[1]) if parts else None


def parse_data(key: str, realm: str) -> tuple[str, str, str] | None:
    """``(agent_id, service_id, ability)`` of ``uma/R/data/A/S/N``."""
    parts = _parts(key, realm, "data", 3)
    return (parts[0], parts[1], parts[2]) if parts else None
