"""What a uma recording holds: its channels, their metadata, the file's own metadata.

=========================  ==========  =======================================================
channel topic              encoding    messages
=========================  ==========  =======================================================
``uma/R/data/A/S/N``       msgpack     the samples of ability N, the exact bytes on the wire;
                                       log time = receive time, publish time = the sample's
                                       own ``t``; metadata: ``uma.kind`` = ``data``,
                                       ``uma.ability`` (the Ability descriptor as JSON),
                                       ``uma.schema`` = ``Ability`` (its JSON Schema, ``uma
                                       schemas export``), ``uma.service_attributes`` (JSON)
``uma/R/agent/A/services`` msgpack     agent A's snapshot of its services, needs, abilities and
                                       matches, at the start and at every change
``uma/R/agent/A/supernode`` msgpack    agent A's SRG summary (its frames)
``uma/R/agent/A/static``   msgpack     agent A's static edges and clock offset, looked up by
                                       the recorder (``agent.record.statics``)
``/tf``, ``/tf_static``    cdr         poses as ``tf2_msgs/msg/TFMessage`` (``ros2msg``
                                       schema), frame ids are uma's frame names
=========================  ==========  =======================================================

The msgpack channels have no schema record (schema id 0): msgpack describes itself, and the
``rosbags`` reader refuses a whole file holding a schema encoding it does not know.  The
file's metadata record ``uma.recording`` names the realm and the key patterns; the record
``uma.recording.end`` (written when the recording stops) counts what could not be written.
"""

from __future__ import annotations

import json
from typing import Any

from schemas.models import Ability

MSGPACK = "msgpack"
DATA = "data"
SNAPSHOT = "snapshot"
SUPERNODE = "supernode"
STATIC = "static"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
META_START = "uma.recording"
META_END = "uma.recording.end"
#: the JSON Schema (``uma schemas export``) of the descriptor in ``uma.ability``
ABILITY_SCHEMA = "Ability"


def data_metadata(ability: Ability | None, service_attributes: dict[str, Any]) -> dict[str, str]:
    """Metadata of a data channel; ``ability`` None when the recorder never learnt it."""
    meta = {"uma.kind": DATA, "uma.schema": ABILITY_SCHEMA,
            "uma.service_attributes": json.dumps(service_attributes, sort_keys=True)}
    if ability is not None:
        meta["uma.ability"] = ability.model_dump_json(exclude_none=True)
    return meta


def realm_metadata(kind: str) -> dict[str, str]:
    """Metadata of an agent's snapshot or summary channel."""
    return {"uma.kind": kind}


def kind_of_topic(topic: str) -> str | None:
    """``snapshot``, ``supernode`` or ``static`` for an agent's topic, else None (data)."""
    if "/data/" in topic:
        return None
    for suffix, kind in (("/services", SNAPSHOT), ("/supernode", SUPERNODE),
                         ("/static", STATIC)):
        if topic.endswith(suffix):
            return kind
    return None


def ability_of(metadata: dict[str, str]) -> Ability | None:
    """The Ability a data channel's metadata carries (None: not recorded, or unreadable)."""
    text = metadata.get("uma.ability")
    if text is None:
        return None
    try:
        return Ability.model_validate_json(text)
    except ValueError:
        return None


def service_attributes_of(metadata: dict[str, str]) -> dict[str, Any]:
    try:
        value = json.loads(metadata.get("uma.service_attributes", "{}"))
    except ValueError:
        return {}
    return value if isinstance(value, dict) else {}
