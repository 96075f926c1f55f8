"""Opening Zenoh sessions the way every uma process needs them.

One place builds the Zenoh configuration so agents, services, clients and the router all
behave alike:

- **multicast scouting off**: it finds nobody on plain loopback and fails in many
  containers; peers meet through explicit ``connect`` endpoints and gossip.
- **every peer listens** (default ``tcp/127.0.0.1:0``): peers do not relay for each other,
  so a peer that only connects is invisible to the other peers of its agent.
- **lease 1000 ms** (``transport/link/tx/lease``, keep-alive every lease/4 = 250 ms): the
  lease that counts is the one of the process that *dies*; 1 s makes a frozen process or
  a vanished host detected within about a second, while a killed process is seen at once
  anyway (the kernel closes its sockets).  Override with ``UMA_LEASE_MS`` or ``lease_ms=``.
- **scouting/delay 0**: otherwise ``open()`` of a router waits 0.5 s.
- **connect retry 250 ms doubling to 1 s**: a service whose agent restarts is linked again
  within ~1 s (Zenoh's default back-off reaches 4 s).
- **client mode** for every service and client that names its agent (``connect``): the
  host's agent, a listening peer, routes for the processes of its host, so a realm holds
  one Zenoh link per process plus the agents' mesh, instead of a link between every pair of
  peers (``docs/ARCHITECTURE.md``, "Topology").  A router or agent that cannot be reached
  is an error at open (:class:`UnreachableEndpointError`), as it is for ``require_connection=True``
  peers.
- **one session per process and configuration**: :func:`acquire_session` hands every
  ``Service`` and ``Client`` of a process that asks for the same settings the same session
  (and its Zenoh runtime threads), and :func:`release_session` closes it when the last one
  leaves.  ``shared=False`` opts out.
- **a Zenoh configuration file** (``zenoh_config=``, ``--zenoh-config FILE``, or
  ``UMA_ZENOH_CONFIG`` for every process of a host) is the base that these settings are
  applied on top of: how a secured site adds TLS, certificates and access control
  (``uma deploy config``, ``docs/SECURITY.md``).
- **receive limit 33 MiB** (``transport/link/rx/max_message_size``, Zenoh's default 1 GiB):
  the largest message uma accepts is an image of 32 MiB (``schemas.codec.MAX_IMAGE_BYTES``,
  every other message 1 MiB), so a peer cannot make Zenoh reassemble more than that per
  message for us to copy and refuse.  A base configuration may set it lower.
- **admin space off** (``adminspace/enabled``): it let any peer read every session's
  configuration, links and locators under ``@/**``.  Only a base configuration
  (``uma router --config``) can turn it on.  The real port of a ``:0`` listener is
  therefore chosen before opening (:func:`listening_endpoints`).
- **the process ends after Zenoh's callback threads**: zenoh-python runs each Python
  callback in a thread of its own, a daemon when the callback was declared from a daemon or
  Zenoh thread, which Python does not wait for.  One still ending when the interpreter
  finalizes cannot take the GIL and aborts the process ("FATAL: exception not rethrown"),
  so at exit uma closes the sessions it opened and waits for those threads
  (:func:`_end_callback_threads`, at most ``EXIT_WAIT_S``).
- **closing never raises**: a session that cannot close in time (a starved host) is logged
  and left to the process's exit, so a ``with`` block or a command's result is never lost
  to a close error.

Bad endpoints (wrong syntax, port out of range, unknown host, nothing listening when a
connection is required) become an :class:`agent.errors.UmaError` naming the endpoint.
"""

from __future__ import annotations

import atexit
import ipaddress
import json
import logging
import os
import re
import socket
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import zenoh

from agent.errors import UmaError
from agent.protocol import keys
from agent.runtime.callbacks import guarded
from agent.runtime.logs import RateLimitedLog
from schemas.codec import MAX_IMAGE_BYTES, MAX_MESSAGE_BYTES

log = logging.getLogger("uma.session")
_log = RateLimitedLog(log)

MODES = ("peer", "client", "router")
#: environment variable: the Zenoh mode of services and clients that are not told one
SDK_MODE_ENV = "UMA_SDK_MODE"
#: environment variable: the Zenoh configuration file of processes that are not given one
ZENOH_CONFIG_ENV = "UMA_ZENOH_CONFIG"
DEFAULT_LEASE_MS = 1000
DEFAULT_PEER_LISTEN = "tcp/127.0.0.1:0"
DEFAULT_ROUTER_LISTEN = "tcp/127.0.0.1:7447"
#: back-off of re-dialling a lost connect endpoint (Zenoh's defaults: 1000 / 4000 ms)
RETRY_INIT_MS, RETRY_MAX_MS = 250, 1000
#: how long a ``require_connection`` open waits for its connect endpoints
CONNECT_TIMEOUT_MS = 2000
#: the largest message Zenoh reassembles for a uma process: uma's largest (an image) + 1 MiB
MAX_RECEIVE_BYTES = MAX_IMAGE_BYTES + MAX_MESSAGE_BYTES
#: a ``:0`` listener whose chosen port was taken meanwhile is opened again this often
LISTEN_ATTEMPTS = 3

_PROTOCOLS_WITH_PORT = {"tcp", "udp", "tls", "quic", "ws"}
_ENDPOINT = re.compile(r"^(?P<proto>[a-z][a-z0-9-]*)/(?P<addr>[^?#]+)(?P<rest>[?#].*)?$")
_HOST_PORT = re.compile(r"^(?P<host>\[[0-9a-fA-F:.]+\]|[^:\[\]]+):(?P<port>\d+)$")


def check_endpoint(ep: str) -> str:
    """Return ``ep`` if it is a usable Zenoh endpoint, else raise ``UmaError`` saying why.

    Zenoh itself accepts ``tcp/127.0.0.1:99999`` or an unresolvable host and then silently
    never connects; catching these here turns a hang into a message.
    """
    if not isinstance(ep, str) or not ep.strip():
        raise UmaError(f"empty Zenoh endpoint {ep!r} (expected e.g. tcp/127.0.0.1:7447)")
    m = _ENDPOINT.match(ep.strip())
    if not m:
        raise UmaError(f"invalid Zenoh endpoint {ep!r}: expected <protocol>/<address>, "
                       "e.g. tcp/127.0.0.1:7447")
    if m["proto"] not in _PROTOCOLS_WITH_PORT:
        return ep.strip()
    hp = _HOST_PORT.match(m["addr"])
    if not hp:
        raise UmaError(f"invalid Zenoh endpoint {ep!r}: expected {m['proto']}/HOST:PORT")
    port = int(hp["port"])
    if not 0 <= port <= 65535:
        raise UmaError(f"invalid Zenoh endpoint {ep!r}: port {port} is not in 0..65535")
    host = hp["host"].strip("[]")
    try:
        ipaddress.ip_address(host)
    except ValueError:
        try:
            socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except (socket.gaierror, UnicodeError) as exc:
            raise UmaError(f"invalid Zenoh endpoint {ep!r}: unknown host {host!r} "
                           f"({exc})") from None
    return ep.strip()


def lease_ms_default() -> int:
    """The lease in ms: ``UMA_LEASE_MS`` if set (validated), else 1000."""
    raw = os.environ.get("UMA_LEASE_MS")
    if raw is None:
        return DEFAULT_LEASE_MS
    try:
        value = int(raw)
    except ValueError:
        raise UmaError(f"UMA_LEASE_MS={raw!r} is not an integer number of ms") from None
    if not 50 <= value <= 600_000:
        raise UmaError(f"UMA_LEASE_MS={value} is outside 50..600000 ms")
    return value


def build_config(mode: str = "peer", listen: Sequence[str] | None = None,
                 connect: Iterable[str] = (), *, lease_ms: int | None = None,
                 require_connection: bool = False,
                 base_file: str | None = None) -> zenoh.Config:
    """The Zenoh configuration of a uma process (see the module docstring for each choice).

    ``listen=None`` means the mode's default (peers: an ephemeral loopback port, routers:
    7447, clients: none) unless ``base_file`` (a Zenoh JSON5 configuration that uma's
    settings are applied on top of) names listen endpoints; ``listen=[]``: no listener.
    """
    if mode not in MODES:
        raise UmaError(f"unknown Zenoh mode {mode!r} (expected one of {', '.join(MODES)})")
    connect = [check_endpoint(ep) for ep in connect]
    base_file = zenoh_config_file(base_file)
    c = _base_config(base_file)
    if listen is None and base_file is not None:
        listen = _configured_listen(c, mode)
    if listen is None:
        listen = {"peer": [DEFAULT_PEER_LISTEN], "router": [DEFAULT_ROUTER_LISTEN],
                  "client": []}[mode]
    listen = [check_endpoint(ep) for ep in listen]
    if mode == "client" and not connect:
        raise UmaError("client mode needs at least one --connect endpoint (a Zenoh router)")
    lease = lease_ms_default() if lease_ms is None else int(lease_ms)
    _insert(c, "mode", mode)
    _insert(c, "scouting/multicast/enabled", False)
    _insert(c, "scouting/delay", 0)
    _insert(c, "transport/link/tx/lease", lease)
    _insert(c, "listen/endpoints", listen)
    _insert(c, "connect/endpoints", connect)
    # re-dial a lost endpoint (agent restarted) within 1 s rather than Zenoh's 4 s
    _insert(c, "connect/retry", {"period_init_ms": RETRY_INIT_MS, "period_max_ms": RETRY_MAX_MS,
                                 "period_increase_factor": 2})
    _insert(c, "transport/link/rx/max_message_size",
            min(MAX_RECEIVE_BYTES, _configured_int(c, "transport/link/rx/max_message_size")))
    if base_file is None:  # a base configuration decides on its admin space; we do not
        _insert(c, "adminspace/enabled", False)
    if require_connection and connect and mode == "peer":
        _insert(c, "connect/exit_on_failure", True)
        _insert(c, "connect/timeout_ms", CONNECT_TIMEOUT_MS)
    return c


#: listen protocols whose links are encrypted and authenticated (Zenoh's TLS; QUIC is TLS)
SECURE_PROTOCOLS = frozenset({"tls", "quic"})


def exposed_endpoints(listen: Iterable[str]) -> list[str]:
    """The listen endpoints another host could reach without TLS: a network protocol other
    than ``SECURE_PROTOCOLS`` on an address that is not loopback (a host name counts as
    loopback only if every address it resolves to is)."""
    found = []
    for ep in listen:
        m = _ENDPOINT.match(str(ep).strip())
        if m is None or m["proto"] in SECURE_PROTOCOLS or m["proto"] not in _PROTOCOLS_WITH_PORT:
            continue
        hp = _HOST_PORT.match(m["addr"])
        if hp is None or not _loopback(hp["host"].strip("[]")):
            found.append(str(ep))
    return found


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        addresses = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except (socket.gaierror, UnicodeError):
        return False
    return bool(addresses) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback
                                   for a in addresses)


def refuse_exposure(config: zenoh.Config, who: str, insecure: bool) -> None:
    """Safe by default: ``UmaError`` if ``who`` (``uma agent``, ``uma router``) would
    listen where another host reaches it without TLS, unless ``insecure`` (then a
    warning).  Whoever reaches a plain listener can read and write the whole realm."""
    listen = json.loads(config.get_json("listen/endpoints") or "[]")
    exposed = exposed_endpoints(listen if isinstance(listen, list) else [])
    if not exposed:
        return
    what = (f"{who} would listen on {', '.join(exposed)} without TLS: any process that "
            "reaches this address can read the realm, publish into it and re-register "
            "its services")
    if insecure:
        log.warning("%s (--insecure: accepted on purpose)", what)
        return
    raise UmaError(f"{what}. Secure the site (TLS and access control: 'uma deploy certs' "
                   "and 'uma deploy config', README \"Deploying a site\"), listen on "
                   "loopback only (tcp/127.0.0.1:PORT), or pass --insecure to run it "
                   "unprotected on purpose")


def zenoh_config_file(path: str | None) -> str | None:
    """The Zenoh configuration file to start from: ``path``, else ``UMA_ZENOH_CONFIG``;
    ``UmaError`` if the file named does not exist (Zenoh's own message only says "No such
    file")."""
    source = ""
    if not path:
        path, source = os.environ.get(ZENOH_CONFIG_ENV) or None, f" (from {ZENOH_CONFIG_ENV})"
    if path is not None and not os.path.isfile(path):
        raise UmaError(f"cannot use Zenoh configuration {path!r}{source}: the file does "
                       "not exist")
    return path


def _base_config(path: str | None) -> zenoh.Config:
    if path is None:
        return zenoh.Config()
    try:
        return zenoh.Config.from_file(path)
    except zenoh.ZError as exc:
        raise UmaError(f"cannot use Zenoh configuration {path!r}: {_short(exc)}") from None


def _configured_listen(c: zenoh.Config, mode: str) -> list[str] | None:
    """The listen endpoints a base configuration names (a list, or a per-mode map)."""
    found = json.loads(c.get_json("listen/endpoints") or "null")
    if isinstance(found, dict):
        found = found.get(mode)
    return [str(x) for x in found] if isinstance(found, list) and found else None


def _configured_int(c: zenoh.Config, key: str) -> int:
    """An integer setting of a configuration (Zenoh's default when it is not set)."""
    value = json.loads(c.get_json(key) or "null")
    return int(value) if isinstance(value, int) else MAX_RECEIVE_BYTES


def _insert(c: zenoh.Config, key: str, value: object) -> None:
    try:
        c.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise UmaError(f"invalid Zenoh setting {key}={value!r}: {_short(exc)}") from None


def _short(exc: BaseException) -> str:
    """Zenoh's error text without its Rust source location."""
    text = str(exc)
    return re.sub(r"\s*at /\S+\.rs:\d+\.?", "", text).strip()


def open_session(mode: str = "peer", listen: Sequence[str] | None = None,
                 connect: Iterable[str] = (), realm: str | None = None, *,
                 lease_ms: int | None = None, require_connection: bool = False,
                 base_file: str | None = None, exposed_as: str | None = None,
                 insecure: bool = False) -> zenoh.Session:
    """Open a Zenoh session configured for uma; ``UmaError`` if it cannot be opened.

    ``realm`` is only validated here (uma keys carry it; see :mod:`agent.protocol.keys`), so a bad
    realm fails before any network activity.  ``require_connection`` makes a peer fail
    when none of its ``connect`` endpoints answers within 2 s (a client always does).
    A ``tcp/HOST:0`` listener gets a free port chosen here (the admin space that would tell
    Zenoh's choice is off), opened again with another if it was taken meanwhile.
    ``exposed_as`` (``"uma agent"``, ``"uma router"``) refuses listeners other hosts reach
    without TLS unless ``insecure`` (:func:`refuse_exposure`).
    """
    if realm is not None:
        keys.check_name("realm", realm)
    connect = list(connect)
    base_file = zenoh_config_file(base_file)
    config = build_config(mode, listen, connect, lease_ms=lease_ms,
                          require_connection=require_connection, base_file=base_file)
    if exposed_as is not None:
        refuse_exposure(config, exposed_as, insecure)
    wanted = json.loads(config.get_json("listen/endpoints") or "[]")
    attempts = 0
    while True:  # bounded: LISTEN_ATTEMPTS
        attempts += 1
        chosen = [_free_port(str(ep)) for ep in wanted] if isinstance(wanted, list) else []
        if chosen != wanted:
            _insert(config, "listen/endpoints", chosen)
        try:
            session = zenoh.open(config)
        except zenoh.ZError as exc:
            error = _open_error(exc, mode, connect, base_file)
            if chosen == wanted or attempts >= LISTEN_ATTEMPTS or not isinstance(
                    error, _ListenError):
                raise error from None
            continue
        _remember_endpoints(session, chosen)
        return session


class _ListenError(UmaError):
    """A listener could not be created (its port may have been taken meanwhile)."""


def _open_error(exc: zenoh.ZError, mode: str, connect: Sequence[str],
                base_file: str | None) -> UmaError:
    text = _short(exc)
    if "Unable to connect" in text:
        return UnreachableEndpointError(
            f"cannot reach {', '.join(connect)} ({mode} mode): nothing answers there; "
            f"is the agent/router running?{_tls_hint(connect, base_file)}")
    if "Can not create a new" in text or "listen" in text.lower():
        return _ListenError(f"cannot listen: {text}")
    return UmaError(f"cannot open Zenoh session: {text}")


def _free_port(ep: str) -> str:
    """``ep`` with a free port in place of ``:0`` (TCP only; others are returned as they
    are): the kernel picks it for a socket bound and closed at once."""
    m = _ENDPOINT.match(ep)
    hp = _HOST_PORT.match(m["addr"]) if m and m["proto"] == "tcp" else None
    if hp is None or hp["port"] != "0":
        return ep
    host = hp["host"].strip("[]")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        port = sock.getsockname()[1]
    return f"tcp/{hp['host']}:{port}{m['rest'] or ''}"


#: the endpoints each open session listens on, by Zenoh id (see ``listening_endpoints``)
_listening: dict[str, tuple[zenoh.Session, list[str]]] = {}
#: sessions whose endpoints are remembered at most (the oldest are forgotten first)
_LISTENING_KEPT = 256
_listening_lock = threading.Lock()  # not _shared_lock: _acquire opens sessions under it


def _remember_endpoints(session: zenoh.Session, endpoints: list[str]) -> None:
    with _listening_lock:
        _listening[str(session.zid())] = (session, list(endpoints))
        while len(_listening) > _LISTENING_KEPT:
            del _listening[next(iter(_listening))]


def _tls_hint(connect: Sequence[str], base_file: str | None) -> str:
    """What else a failed ``tls/`` connection may mean: Zenoh reports a refused TLS
    handshake (no certificate, one of another site, a name the router's certificate does not
    carry) only as "Unable to connect"."""
    if not any(ep.startswith("tls/") for ep in connect):
        return ""
    if base_file is None:
        return (" A tls/ endpoint needs this host's certificates: --zenoh-config FILE "
                "(written by 'uma deploy config').")
    return (f" Or the TLS handshake was refused: check that {base_file} holds this site's "
            "certificates and that the router's certificate names the address dialled.")


class UnreachableEndpointError(UmaError):
    """Nothing answers at the endpoints a client-mode session (or a peer that requires a
    connection) was told to connect to."""


@dataclass
class _Shared:
    session: zenoh.Session
    users: int


_shared: dict[tuple[object, ...], _Shared] = {}
_shared_lock = threading.Lock()


def sdk_mode(mode: str | None, connect: Sequence[str]) -> str:
    """The Zenoh mode of a service or client: given explicitly (or by ``UMA_SDK_MODE``,
    so a whole host can keep the all-peers topology without changing code), else a client
    of the endpoint it names (its host's agent), else a listening peer."""
    if mode is None:
        mode = os.environ.get(SDK_MODE_ENV) or ("client" if connect else "peer")
    if mode not in ("peer", "client"):
        raise UmaError(f"mode {mode!r}: a service or client runs as 'client' (of its "
                       f"host's agent) or 'peer' (from {SDK_MODE_ENV} or mode=)")
    return mode


def acquire_session(mode: str, listen: Sequence[str] | None, connect: Sequence[str],
                    realm: str | None = None, *, shared: bool = True,
                    wait_s: float = 0.0, base_file: str | None = None) -> zenoh.Session:
    """This process's session for these settings, opened on first use.

    A client whose agent does not answer yet is tried again every 0.1 s for ``wait_s``
    seconds (an agent started together with its clients listens a moment later), then
    :class:`UnreachableEndpointError`.  Every ``acquire_session`` must be paired with one
    :func:`release_session`.  ``base_file``: the Zenoh configuration file to start from
    (:func:`zenoh_config_file`).
    """
    deadline = time.monotonic() + wait_s
    base_file = zenoh_config_file(base_file)
    while True:  # bounded by wait_s
        try:
            return _acquire(mode, listen, connect, realm, shared, base_file)
        except UnreachableEndpointError:
            if time.monotonic() >= deadline:
                raise
        time.sleep(0.1)


def _acquire(mode: str, listen: Sequence[str] | None, connect: Sequence[str],
             realm: str | None, shared: bool, base_file: str | None) -> zenoh.Session:
    if not shared:
        return open_session(mode, listen, connect, realm, base_file=base_file)
    if realm is not None:
        keys.check_name("realm", realm)
    key = (mode, None if listen is None else tuple(listen), tuple(connect),
           lease_ms_default(), base_file)
    with _shared_lock:
        entry = _shared.get(key)
        if entry is None:
            entry = _shared[key] = _Shared(open_session(mode, listen, connect,
                                                        base_file=base_file), 0)
        entry.users += 1
        return entry.session


def release_session(session: zenoh.Session) -> None:
    """Give back a session from :func:`acquire_session`; the last user closes it.  A
    session opened with ``shared=False`` is closed at once."""
    with _shared_lock:
        for key, entry in _shared.items():
            if entry.session is session:
                entry.users -= 1
                if entry.users > 0:
                    return
                del _shared[key]
                break
    close_session(session)


#: how long a process's exit waits for the callback threads of its closed Zenoh sessions
EXIT_WAIT_S = 2.0
#: the name zenoh-python gives the thread that runs a Python callback
_CALLBACK_THREAD = "(pyo3-closure)"


@atexit.register
def _end_callback_threads() -> None:
    """Close the sessions still open and wait for their callback threads before Python
    finalizes: a daemon thread that wakes during finalization aborts the whole process.
    atexit runs after Python joined its non-daemon threads and before it finalizes."""
    with _listening_lock:
        still_open = [session for session, _ in _listening.values()]
    for session in still_open:
        if not session.is_closed():
            close_session(session)
    deadline = time.monotonic() + EXIT_WAIT_S
    for thread in threading.enumerate():
        if thread.daemon and thread.name.endswith(_CALLBACK_THREAD):
            thread.join(max(0.0, deadline - time.monotonic()))
    left = sum(t.daemon and t.name.endswith(_CALLBACK_THREAD) and t.is_alive()
               for t in threading.enumerate())
    if left:
        log.warning("%d Zenoh callback thread(s) still running at exit (a session uma did "
                    "not open?); the process may abort while finalizing", left)


def close_session(session: zenoh.Session) -> None:
    """Close ``session``, never raising.

    Zenoh's close times out on a CPU-starved host ("close operation timed out!"); what the
    caller did with the session is done by then, so the failure is logged, not raised.
    """
    with _listening_lock:
        for zid, (known, _) in list(_listening.items()):
            if known is session:
                del _listening[zid]
    try:
        session.close()
    except zenoh.ZError as exc:
        log.warning("the Zenoh session did not close cleanly (%s); it ends with the process",
                    _short(exc))


def query(session: zenoh.Session, selector: str, timeout: float, *,
          liveliness: bool = False, **options: object) -> list[zenoh.Reply]:
    """The replies of a ``get`` (or a liveliness ``get``), waiting at most ``timeout`` s.

    Iterating a ``get``'s handler blocks until Zenoh finishes the query, and a query routed
    through a router has been seen never to finish; this bounds the wait on our side.
    """
    replies: list[zenoh.Reply] = []
    done = threading.Event()
    handler = zenoh.handlers.Callback(replies.append, done.set)
    if liveliness:
        session.liveliness().get(selector, handler, timeout=timeout)
    else:
        session.get(selector, handler, timeout=timeout, **options)
    done.wait(timeout + 0.25)
    return list(replies)


def ask_all(session: zenoh.Session, selector: str, timeout: float,
            done: Callable[[list[bytes]], None], *, every_reply: bool = False,
            admit: Callable[[int], bool] | None = None) -> None:
    """Ask ``selector`` without waiting: ``done(payloads)`` with the payloads of every
    successful reply once the query ends (in Zenoh's thread: hand over, do not block).
    ``every_reply``: keep the replies of two processes answering on one key.  ``admit``
    (a reply's size): whether to keep it; one refused is never copied out of Zenoh."""
    answers: list[bytes] = []

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is not None and (admit is None or admit(len(reply.ok.payload))):
            answers.append(reply.ok.payload.to_bytes())
    extra = {"consolidation": zenoh.ConsolidationMode.NONE} if every_reply else {}
    session.get(selector, zenoh.handlers.Callback(
        guarded(on_reply, f"replies on {selector}", _log),
        lambda: guarded(done, f"replies on {selector}", _log)(answers)),
        timeout=timeout, **extra)


def listening_endpoints(session: zenoh.Session, timeout: float = 1.0) -> list[str]:
    """The endpoints this session really listens on (``:0`` resolved to the real port).

    Those :func:`open_session` chose; for a session opened otherwise, what its own admin
    space says (empty when the admin space is off).
    """
    zid = str(session.zid())
    with _listening_lock:
        known = _listening.get(zid)
    if known is not None:
        return list(known[1])
    found: list[str] = []
    for reply in query(session, f"@/{zid}/**", timeout):
        if reply.ok is None:
            continue
        try:
            info = json.loads(reply.ok.payload.to_bytes())
        except ValueError:
            continue
        if isinstance(info, dict) and isinstance(info.get("locators"), list):
            found.extend(str(x) for x in info["locators"])
    return found
