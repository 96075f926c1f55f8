"""The registration protocol: how services join their agent and agents learn each other's
services (what one agent then knows of its realm is :mod:`agent.daemon.realm_view`).

Registration protocol (all messages are msgpack maps with ``"v": 1``, built and checked by
the functions below; ``R`` = realm, ``A`` = agent id, ``S`` = service id)
===========================================================================================

**Service -> its local agent**

1. The service opens its session, declares its control subscriber ``uma/R/ctl/A/S``, its
   descriptor queryable ``uma/R/svc/A/S`` and its publishers, then watches the liveliness
   token ``uma/R/agent/A`` (history on).  While that token is absent the service waits: it
   is started, publishes, and registers as soon as the agent appears.
2. Register: ``get uma/R/agent/A/register`` with ``{op: "register", instance, revision,
   descriptor, connected}`` where ``descriptor`` is ``schemas.codec.encode_descriptor``
   bytes, ``instance`` a random id of this process, ``revision`` a counter bumped by every
   attribute change, ``connected`` the data keys each need is subscribed to right now.
3. The agent validates the descriptor (``agent_id`` must be A) and replies ``{ok: true,
   epoch, key}``, or ``reply_err {ok: false, error}``.  ``key`` (random, per service
   instance, kept by the agent for its lifetime) signs the agent's control messages to the
   service; a query reply reaches only the querier, so no other peer learns it.  A
   re-registration of an instance the agent holds must prove that instance's key without
   sending it: every answer to a registration carries a ``challenge`` (opaque, good for
   ``CHALLENGE_TTL_S``), and the next request carries it back with ``proof`` = HMAC of the
   challenge and the request's content with the key (:func:`register_request`); a proof
   that does not verify, or a stale challenge, is refused with ``retry`` and a fresh
   challenge.  A process that merely copies another's instance id is refused, and one
   that overhears a request learns no key.  An instance
   the agent holds without a key (it restarted and re-adopted the service, step 4) is
   refused with ``renew: true``: the service takes a new ``instance`` and registers again,
   which is a second process for the duplicate check below, answered by itself.  A second
   process registering a service id that is already registered (different ``instance``)
   is refused with "duplicate service id" *if the first one still answers* on
   ``uma/R/svc/A/S`` (anything answering there with another instance than the
   newcomer's); if it does not (it died and its lease has not expired yet) the newcomer
   replaces it.  A refusal with
   ``retry: true`` is temporary: a check for that id is in progress, or the instance is
   held but its token has not come, so the agent's answer with the key may have reached
   the service after it stopped waiting (the held registration expires after
   ``PENDING_TIMEOUT_S`` and the retry is then accepted as new).
4. On the first acceptance the service declares its liveliness token ``uma/R/svc/A/S``
   (only then, so a refused duplicate never merges with the original's token).  The agent
   advertises a local service's abilities once it has seen that token.  A token's DELETE
   (undeclared, process killed: ~2 ms; frozen process: the lease, 1 s) is *checked*
   before anything is torn down: the agent asks ``uma/R/svc/A/S``; a service that still
   answers with the same ``instance`` is kept (a DELETE can be spurious: a transport whose
   lease expired between starved processes, re-established at once, gives DELETE then PUT,
   and the two can reach the agent out of order with the service's own re-registration).
   A killed or unreachable service has no queryable left, so that get ends at once and
   failover stays fast.  If a local service's token comes back after the agent dropped
   it, the agent **re-adopts** it from its answer on ``uma/R/svc/A/S`` (descriptor,
   instance, revision, connected: :func:`parse_descriptor_answer`), with no action by the
   service.  Every ``RESEND_S`` the agent compares the live service tokens with what it
   believes and checks or re-adopts the differences.
   A registration whose token never shows up is dropped after ``PENDING_TIMEOUT_S``.
5. Attribute changes (``ability.update(...)``) are re-registrations with a higher revision.
   If the agent restarts (its token goes and comes back) the service registers again; its
   data subscriptions stay declared meanwhile (a client-mode service's samples flow again
   as soon as its agent, which routes them, is back; a peer-mode one's never stop), and the
   new agent learns them from ``connected``, so nothing is torn down needlessly.

**Agent -> its local services** (``uma/R/ctl/A/S``, put, congestion control BLOCK)

``{op: "signed", body, mac}`` with ``body`` = ``{op: "connect", epoch, seq, need, matches:
[match...], satisfied, standby: [match...]}``: the complete set of abilities the need must
be subscribed to now (``match`` = ``{key, agent_id, service_id, ability, type, edge,
attributes}``, at most ``MAX_CONTROL_MATCHES``) and its standby (the next best, subscribed
as well, their samples delivered while a chosen one is silent; absent: none), and ``mac`` =
HMAC-SHA256 of ``body`` with the service's key (first 16 bytes).  The service applies only a
message that verifies, whose ``epoch`` is the one its agent replied with, and whose ``seq``
is newer than the last applied but not further ahead than the milliseconds passed since then
plus ``SEQ_WINDOW`` of the service: an agent's ``seq`` is the milliseconds since it started
(:func:`next_seq`; one more when two messages of a need fall in one millisecond), so a
forged jump, were the key ever known, holds the agent's real messages back for
``SEQ_WINDOW`` ms at most.  One that does not verify makes the service register again (its
key may be one the agent has not given it yet).  Set semantics make messages idempotent, and
the agent re-sends every need's set every ``RESEND_S`` with the next ``seq`` (anti-entropy,
in case a put was lost).

**Agent <-> agents**

- Every agent declares its token ``uma/R/agent/A`` and watches ``uma/R/agent/*`` (history on).
- ``uma/R/agent/A/services`` is a queryable *and* a publication: the snapshot ``{agent
  (AgentInfo), epoch, revision, services: [{descriptor, instance, matches, satisfied,
  excluded}]}`` of A's live local services with their current matches and measured
  rates.  A publishes it whenever it changes; a newcomer fetches it when A's token
  appears.  Snapshots older than the last applied one (``(epoch, revision)``) are ignored;
  ``revision`` is A's milliseconds since it started (:func:`next_seq`), so one further
  ahead than the time passed since the last one applied (plus a slack) is confirmed by
  asking A before it is applied.
- Every agent also watches all service tokens ``uma/R/svc/*/*``: a killed remote service is
  dropped on its own token's DELETE, without waiting for its agent's next snapshot.  A
  remote ability is offered to matching only while its descriptor is known (snapshot) *and*
  its service token is alive; when an agent's token goes, all its services go with it,
  once the agent does not answer on ``uma/R/agent/A/services`` either (a lease can lapse on
  a starved host while the agent and its services' data are up).

**Measuring** (the consuming side): the agent of the consuming service subscribes itself
to every data key its local needs are connected to, measures rate and latency over a
sliding window, and judges them against the need's predicate (``agent.daemon.monitor``).  The SDK
only receives; it reports nothing.

Bad input anywhere (undecodable bytes, invalid descriptors, unknown types, invalid
predicates, a key of the wrong shape) is dropped with one rate-limited log line naming the
key or service and the reason; nothing else is affected.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from agent.protocol import keys
from schemas.codec import DecodeError, decode_descriptor, decode_message, encode_message
from schemas.models import Ability, ServiceDescriptor

#: seconds a registered service may take to declare its liveliness token
PENDING_TIMEOUT_S = 5.0
#: seconds between re-sends of every need's match set (anti-entropy)
RESEND_S = 5.0
#: length of the key an agent signs its control messages to one service instance with
CONTROL_KEY_BYTES = 16
#: length of the challenge an agent gives with every answer to a registration (the next
#: re-registration signs it), and how long one stays good
CHALLENGE_BYTES = 16
CHALLENGE_TTL_S = 60.0
#: most matches one control message may name (a need's max_count is far lower)
MAX_CONTROL_MATCHES = 64
#: largest register request an agent reads (a service with a hundred abilities and their
#: attributes needs tens of KiB; a request is refused before it is decoded)
MAX_REGISTRATION_BYTES = 128 * 1024


# --------------------------------------------------------------------------- matches


@dataclass(frozen=True)
class Match:
    """An ability a need is connected to, as the service sees it."""

    key: str
    agent_id: str
    service_id: str
    ability: str
    type: str
    edge: tuple[str, str] | None
    attributes: dict[str, Any]

    @classmethod
    def of(cls, key: str, agent_id: str, service_id: str, a: Ability) -> Match:
        """The match of the ability ``a`` published on ``key``."""
        return cls(key, agent_id, service_id, a.name, a.type,
                   None if a.edge is None else (a.edge[0], a.edge[1]),
                   a.attributes.model_dump(mode="json", exclude_none=True))

    @classmethod
    def unknown(cls, key: str, type_: str, realm: str) -> Match:
        """A data key a service reports being subscribed to that this agent does not know
        (yet): what the key itself says."""
        parts = keys.parse_data(key, realm) or ("?", "?", "?")
        return cls(key, parts[0], parts[1], parts[2], type_, None, {})

    def to_wire(self) -> dict[str, Any]:
        return {"key": self.key, "agent_id": self.agent_id, "service_id": self.service_id,
                "ability": self.ability, "type": self.type,
                "edge": None if self.edge is None else list(self.edge),
                "attributes": self.attributes}

    @classmethod
    def from_wire(cls, d: Any, realm: str) -> Match:
        """Check a wire match; ``DecodeError`` names the field that is wrong."""
        if not isinstance(d, dict):
            raise DecodeError(f"match: expected a map, got {type(d).__name__}")
        key = d.get("key")
        parts = keys.parse_data(key, realm) if isinstance(key, str) else None
        if parts is None:
            raise DecodeError(f"match: {key!r} is not a data key of realm {realm!r}")
        edge = d.get("edge")
        if edge is not None and not (isinstance(edge, list) and len(edge) == 2
                                     and all(isinstance(x, str) for x in edge)):
            raise DecodeError(f"match {key}: edge must be two frame ids or nil")
        attributes = d.get("attributes")
        if not isinstance(attributes, dict):
            raise DecodeError(f"match {key}: attributes must be a map")
        typ = d.get("type")
        if not isinstance(typ, str):
            raise DecodeError(f"match {key}: type must be a string")
        return cls(key, parts[0], parts[1], parts[2], typ,
                   None if edge is None else (edge[0], edge[1]), attributes)


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class Proof:
    """A registration's proof that its sender holds the instance's key, without sending
    it: ``mac`` = HMAC-SHA256 (first 16 bytes) with the key over ``signed``, the agent's
    ``challenge`` and the request's content (:func:`register_request`)."""

    challenge: bytes
    mac: bytes
    #: what ``mac`` must sign, rebuilt by the receiver from the request it got
    signed: bytes

    def verifies(self, key: bytes) -> bool:
        return hmac.compare_digest(self.mac, _mac(key, self.signed))


@dataclass(frozen=True)
class Registration:
    """A decoded register request."""

    descriptor: ServiceDescriptor
    instance: str
    revision: int
    connected: dict[str, list[str]]
    #: proof of the key this agent gave the instance before (None: it claims none)
    proof: Proof | None = None


def register_request(desc_bytes: bytes, instance: str, revision: int,
                     connected: Mapping[str, Iterable[str]], key: bytes | None = None,
                     challenge: bytes | None = None) -> bytes:
    """A register request; with the ``key`` the agent gave this instance and the last
    ``challenge`` it sent, signed to prove the key (the key itself never travels)."""
    wire = {k: list(v) for k, v in connected.items()}
    msg: dict[str, Any] = {"op": "register", "instance": instance, "revision": revision,
                           "descriptor": desc_bytes, "connected": wire}
    if key is not None and challenge is not None:
        msg["challenge"] = challenge
        msg["proof"] = _mac(key, _signed(challenge, instance, revision, desc_bytes, wire))
    return encode_message(msg)


def _signed(challenge: bytes, instance: str, revision: int, desc_bytes: bytes,
            connected: Mapping[str, list[str]]) -> bytes:
    """What a registration's proof signs: the challenge and everything the request says."""
    return encode_message({"challenge": challenge, "instance": instance,
                           "revision": revision,
                           "descriptor": hashlib.sha256(desc_bytes).digest(),
                           "connected": sorted([k, v] for k, v in connected.items())})


def _proof(msg: dict[str, Any]) -> Proof | None:
    """The proof of a decoded request (``DecodeError`` if malformed, None if absent)."""
    challenge, mac = msg.get("challenge"), msg.get("proof")
    if challenge is None and mac is None:
        return None
    if not (isinstance(challenge, bytes) and len(challenge) == CHALLENGE_BYTES
            and isinstance(mac, bytes) and len(mac) == CONTROL_KEY_BYTES):
        raise DecodeError(f"proof: expected a {CHALLENGE_BYTES}-byte challenge and a "
                          f"{CONTROL_KEY_BYTES}-byte proof")
    connected = msg.get("connected") or {}
    if not isinstance(connected, dict) or not isinstance(msg["descriptor"], bytes):
        raise DecodeError("connected: expected a map")
    return Proof(challenge, mac, _signed(challenge, msg["instance"], msg["revision"],
                                         msg["descriptor"], connected))


class RegisterClaim(NamedTuple):
    """Who a register request says it is, read without validating the descriptor."""

    service_id: str
    instance: str
    proof: Proof | None


def peek_register(data: bytes) -> RegisterClaim | None:
    """The service id, instance and proof a register request claims (cheap: no descriptor
    validation), None if unreadable; what the agent rates registrations by."""
    try:
        msg = decode_message(data, required=("instance", "revision", "descriptor"))
        desc = msg["descriptor"]
        sid = decode_message(desc).get("service_id") if isinstance(desc, bytes) else None
        instance = msg["instance"]
        if not (isinstance(sid, str) and isinstance(instance, str)):
            return None
        return RegisterClaim(sid[:64], instance[:64], _proof(msg))
    except (DecodeError, TypeError):
        return None


def parse_register_request(data: bytes, agent_id: str) -> Registration:
    """Decode and validate a registration for agent ``agent_id``; ``DecodeError`` says why."""
    msg = decode_message(data, required=("op", "instance", "revision", "descriptor"))
    if msg["op"] != "register":
        raise DecodeError(f"unknown op {msg['op']!r} (expected 'register')")
    reg = _registration(msg, agent_id)
    return Registration(reg.descriptor, reg.instance, reg.revision, reg.connected,
                        _proof(msg))


def parse_descriptor_answer(data: bytes, agent_id: str) -> Registration:
    """A service's answer on ``uma/R/svc/A/S`` (:func:`descriptor_reply`) as the
    registration it stands for: how an agent re-adopts a local service whose token came
    back after the agent had dropped it, without any action by the service."""
    return _registration(decode_message(data, required=("instance", "revision", "descriptor")),
                         agent_id)


def _registration(msg: dict[str, Any], agent_id: str) -> Registration:
    """Check the fields a register request and a descriptor answer share."""
    instance, revision = msg["instance"], msg["revision"]
    if not isinstance(instance, str) or not 0 < len(instance) <= 64:
        raise DecodeError("instance: expected a short string")
    if type(revision) is not int or revision < 0:
        raise DecodeError("revision: expected a non-negative integer")
    if not isinstance(msg["descriptor"], bytes):
        raise DecodeError("descriptor: expected encoded descriptor bytes")
    try:
        desc = decode_descriptor(msg["descriptor"])
    except DecodeError as exc:
        raise DecodeError(f"service {_peek_service_id(msg['descriptor'])!r}: {exc}") from None
    if desc.agent_id != agent_id:
        raise DecodeError(f"service {desc.service_id!r} names agent {desc.agent_id!r}, but "
                          f"registered with agent {agent_id!r}")
    connected = msg.get("connected") or {}
    if not isinstance(connected, dict) or not all(
            isinstance(k, str) and isinstance(v, list) and all(isinstance(x, str) for x in v)
            for k, v in connected.items()):
        raise DecodeError("connected: expected a map of need name -> list of data keys")
    return Registration(desc, instance, revision, connected)


def _peek_service_id(desc_bytes: bytes) -> str:
    """The service id an invalid descriptor claims, to name it in the refusal."""
    try:
        sid = decode_message(desc_bytes).get("service_id")
    except DecodeError:
        return "?"
    return sid[:64] if isinstance(sid, str) else "?"


def reply_ok(epoch: int, control_key: bytes, challenge: bytes | None = None) -> bytes:
    """An accepted registration: the agent's epoch, the key its control messages to this
    service are signed with (a query reply reaches only the querier) and the challenge
    the next re-registration signs."""
    msg: dict[str, Any] = {"ok": True, "epoch": epoch, "key": control_key}
    if challenge is not None:
        msg["challenge"] = challenge
    return encode_message(msg)


def reply_error(error: str, retry: bool = False, renew: bool = False,
                challenge: bytes | None = None) -> bytes:
    """A refusal; ``retry`` says it is temporary (try again shortly), ``renew`` that the
    agent holds this instance without a key it gave (it restarted and re-adopted it): the
    service registers again as a new instance; ``challenge``: a fresh one to sign."""
    msg: dict[str, Any] = {"ok": False, "error": error, "retry": retry, "renew": renew}
    if challenge is not None:
        msg["challenge"] = challenge
    return encode_message(msg)


class RegisterReply(NamedTuple):
    """A register reply: accepted (with the agent's epoch and control key) or refused."""

    ok: bool
    error: str = ""
    retry: bool = False
    epoch: int | None = None
    key: bytes | None = None
    renew: bool = False
    challenge: bytes | None = None


def parse_reply(data: bytes) -> RegisterReply:
    """A register reply (a reply_err payload included); ``DecodeError`` if an acceptance
    lacks the epoch or the control key."""
    msg = decode_message(data, required=("ok",))
    challenge = msg.get("challenge")
    if challenge is not None and not (isinstance(challenge, bytes)
                                      and len(challenge) == CHALLENGE_BYTES):
        raise DecodeError(f"challenge: expected {CHALLENGE_BYTES} bytes")
    if not msg["ok"]:
        return RegisterReply(False, str(msg.get("error", ""))[:500],
                             bool(msg.get("retry", False)), renew=bool(msg.get("renew", False)),
                             challenge=challenge)
    epoch, key = msg.get("epoch"), msg.get("key")
    if type(epoch) is not int or not (isinstance(key, bytes) and len(key) == CONTROL_KEY_BYTES):
        raise DecodeError("accepted registration without an integer epoch and a "
                          f"{CONTROL_KEY_BYTES}-byte control key")
    return RegisterReply(True, epoch=epoch, key=key, challenge=challenge)


def next_seq(last: int, since_start_s: float) -> int:
    """The ``seq`` of an agent's next control message of one need: the milliseconds since
    the agent started, and always more than the ``last`` one."""
    return max(last + 1, int(since_start_s * 1000))


class UnverifiedControlError(DecodeError):
    """A control message whose signature does not verify with the key this service holds
    (forged, or signed with a key it was not given yet)."""


def _mac(key: bytes, body: bytes) -> bytes:
    return hmac.new(key, body, hashlib.sha256).digest()[:16]


def control_message(key: bytes | None, epoch: int, seq: int, need: str,
                    matches: Iterable[Match], satisfied: bool,
                    standby: Iterable[Match] = ()) -> bytes:
    """A need's match set, signed with the service's control ``key`` (HMAC-SHA256, RFC
    2104); ``key`` None (the service never registered with this agent) sends it unsigned:
    the service refuses it and registers, which gives it a key."""
    body = encode_message({"op": "connect", "epoch": epoch, "seq": seq, "need": need,
                           "matches": [m.to_wire() for m in matches],
                           "satisfied": satisfied,
                           "standby": [m.to_wire() for m in standby]})
    return encode_message({"op": "signed", "body": body,
                           "mac": b"" if key is None else _mac(key, body)})


@dataclass(frozen=True)
class Control:
    epoch: int
    seq: int
    need: str
    matches: tuple[Match, ...]
    satisfied: bool
    standby: tuple[Match, ...] = ()


def control_need(data: bytes) -> str | None:
    """The need a control message names, unverified (to keep the newest unverified message
    of each of the service's own needs until its key arrives); None if unreadable."""
    try:
        body = decode_message(decode_message(data, required=("body",))["body"])
    except (DecodeError, TypeError):
        return None
    need = body.get("need")
    return need if isinstance(need, str) else None


def parse_control(data: bytes, realm: str, key: bytes | None) -> Control:
    """A control message verified with ``key``: ``UnverifiedControlError`` if its signature does
    not match (or there is no key yet), ``DecodeError`` if it is malformed."""
    env = decode_message(data, required=("op", "body", "mac"))
    body, mac = env["body"], env["mac"]
    if env["op"] != "signed" or not isinstance(body, bytes) or not isinstance(mac, bytes):
        raise DecodeError("expected a signed envelope {op: 'signed', body, mac}")
    if key is None or not hmac.compare_digest(mac, _mac(key, body)):
        raise UnverifiedControlError("signature does not verify with this service's control key"
                                if key is not None else "no control key yet (not registered)")
    msg = decode_message(body, required=("op", "epoch", "seq", "need", "matches"))
    if msg["op"] != "connect":
        raise DecodeError(f"unknown op {msg['op']!r} (expected 'connect')")
    if type(msg["epoch"]) is not int or type(msg["seq"]) is not int:
        raise DecodeError("epoch and seq must be integers")
    standby = msg.get("standby", [])
    if not isinstance(msg["need"], str) or not isinstance(msg["matches"], list) or (
            not isinstance(standby, list)):
        raise DecodeError("need must be a string, matches and standby lists")
    if len(msg["matches"]) + len(standby) > MAX_CONTROL_MATCHES:
        raise DecodeError(f"{len(msg['matches'])} matches and {len(standby)} standby, more "
                          f"than {MAX_CONTROL_MATCHES}")
    return Control(msg["epoch"], msg["seq"], msg["need"],
                   tuple(Match.from_wire(m, realm) for m in msg["matches"]),
                   bool(msg.get("satisfied", True)),
                   tuple(Match.from_wire(m, realm) for m in standby))


def descriptor_reply(desc_bytes: bytes, instance: str, revision: int,
                     connected: Mapping[str, Iterable[str]]) -> bytes:
    """What a service answers on ``uma/R/svc/A/S`` (used for duplicate checks)."""
    return encode_message({"instance": instance, "revision": revision,
                           "descriptor": desc_bytes,
                           "connected": {k: list(v) for k, v in connected.items()}})


def parse_descriptor_reply(data: bytes) -> str:
    """The ``instance`` of a service's descriptor reply."""
    msg = decode_message(data, required=("instance",))
    if not isinstance(msg["instance"], str):
        raise DecodeError("instance: expected a string")
    return msg["instance"]


@dataclass
class Snapshot:
    """A decoded agent snapshot; ``errors`` lists the services that were dropped and why."""

    agent_id: str
    epoch: int
    revision: int
    info: dict[str, Any]
    services: dict[str, ServiceDescriptor]
    status: dict[str, dict[str, Any]]
    errors: list[str] = field(default_factory=list)
    #: bytes on the wire (what holding it is bounded by)
    size: int = 0

    @property
    def version(self) -> tuple[int, int]:
        return (self.epoch, self.revision)


def snapshot_message(info: Mapping[str, Any], epoch: int, revision: int,
                     services: Iterable[Mapping[str, Any]]) -> bytes:
    return encode_message({"agent": dict(info), "epoch": epoch, "revision": revision,
                           "services": list(services)})


def parse_snapshot(data: bytes, agent_id: str | None = None) -> Snapshot:
    """Decode a snapshot; a bad service entry is dropped (and listed in ``errors``), a bad
    envelope raises ``DecodeError``."""
    msg = decode_message(data, required=("agent", "epoch", "revision", "services"))
    info = msg["agent"]
    if not isinstance(info, dict) or not isinstance(info.get("agent_id"), str):
        raise DecodeError("agent: expected a map with agent_id")
    if agent_id is not None and info["agent_id"] != agent_id:
        raise DecodeError(f"snapshot of agent {info['agent_id']!r} published as {agent_id!r}")
    if type(msg["epoch"]) is not int or type(msg["revision"]) is not int:
        raise DecodeError("epoch and revision must be integers")
    if not isinstance(msg["services"], list):
        raise DecodeError("services: expected a list")
    snap = Snapshot(info["agent_id"], msg["epoch"], msg["revision"], info, {}, {},
                    size=len(data))
    for i, entry in enumerate(msg["services"]):
        try:
            if not isinstance(entry, dict) or not isinstance(entry.get("descriptor"), bytes):
                raise DecodeError("expected a map with descriptor bytes")
            desc = decode_descriptor(entry["descriptor"])
            if desc.agent_id != snap.agent_id:
                raise DecodeError(f"service {desc.service_id!r} names agent {desc.agent_id!r}")
        except DecodeError as exc:
            snap.errors.append(f"service #{i}: {exc}")
            continue
        snap.services[desc.service_id] = desc
        snap.status[desc.service_id] = {k: v for k, v in entry.items() if k != "descriptor"}
    return snap
