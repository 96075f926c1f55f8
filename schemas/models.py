"""The pydantic models of uma's contracts: what services declare and what queries answer.

These validate everything that crosses a process boundary except measurements on the hot
path (those go through ``schemas.codec``): service descriptors, agent information, pose
query results (:class:`PoseResultMessage`).  Their JSON Schemas are exported by ``uma
schemas export`` and committed beside this file.

Identifiers:

* **Frame ids** are ``site/object`` strings (``ivy/world``, ``alice/head``): one or more
  non-empty segments of ``[A-Za-z0-9_.-]`` separated by ``/``.  They end up inside Zenoh key
  expressions, so ``* $ # ? @`` and spaces are refused.
* **Edge patterns** of needs may use ``*`` as a whole segment or inside one; ``*`` never
  crosses a ``/`` (``*/head`` matches ``alice/head``, not ``a/b/head``).  See ``frame_matches``.
* **Names** of needs and abilities are ``[A-Za-z0-9_-]+``; agent, service and realm ids also
  allow ``.`` (host names).

Expressions (``Need.where``, ``Need.prefer``) are parsed with ``schemas.expr`` when the model
is validated, so syntax and type errors are reported to whoever declares the need.  Any
identifier is accepted as a name at that point — abilities may carry extra attributes the
declaring service cannot know — and a name that an ability lacks is reported when the
matcher evaluates it (``ExprError``), i.e. that ability does not satisfy the need.  The names
the matcher provides are ``ATTRIBUTE_NAMES``, the ability's extra numeric attributes, and
``MEASURED_NAMES`` (rates and latencies the agent measures on the stream).

Klinker, Bauer 2005: Klinker, Bauer (eds.), *Ubiquitous Tracking for Augmented Reality*,
JASS 2005.
"""

from __future__ import annotations

import math
import re
from fnmatch import fnmatchcase
from functools import lru_cache
from typing import Annotated, Any, Literal, get_args

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    field_validator,
    model_validator,
)

from schemas import expr, ids
from schemas.quaternion import unit_norm

ATTRIBUTE_NAMES = ("latency_s", "frequency_hz", "confidence", "pos_std_m", "rot_std_rad",
                   "ttl_s", "cost", "static")
MEASURED_NAMES = ("measured_frequency_hz", "measured_latency_s")
#: Types whose abilities must name an edge (they are spatial relationships).
EDGE_TYPES = ("pose6d", "position3d", "rotation3d")
MeasurementType = Literal["pose6d", "position3d", "rotation3d", "points3d", "markers2d",
                          "accel_raw", "image", "event"]
#: the measurement types of samples and abilities (``schemas.codec`` encodes each)
MEASUREMENT_TYPES: tuple[str, ...] = get_args(MeasurementType)

FRAME_PATTERN = r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$"
EDGE_PATTERN = r"^[A-Za-z0-9_.\-*]+(/[A-Za-z0-9_.\-*]+)*$"
ATTRIBUTE_NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*$"
_FRAME_RE = re.compile(FRAME_PATTERN)
_EDGE_RE = re.compile(EDGE_PATTERN)
_ATTRIBUTE_NAME_RE = re.compile(ATTRIBUTE_NAME_PATTERN)

MAX_FRAME_LENGTH = 200
MAX_NAME_LENGTH = ids.MAX_LENGTH
#: Bounds on free-form attribute values (lists of numbers such as rig geometry, nesting).
MAX_LIST_LENGTH = 1024
MAX_PLAIN_DEPTH = 4
#: Most next-best abilities a need may keep subscribed besides its chosen ones.
MAX_STANDBY = 8
#: Offsets of the diagonal in the 21 upper-triangular entries (row by row) of a 6x6 matrix.
_TRIU6_DIAGONAL = (0, 6, 11, 15, 18, 20)


# --------------------------------------------------------------------------- identifiers


def _checker(regex: re.Pattern[str], what: str, rule: str, max_length: int):
    def check(value: str) -> str:
        if len(value) > max_length:
            raise ValueError(f"{what} {value[:40]!r}... longer than {max_length} characters")
        if not regex.match(value):
            raise ValueError(f"{what} {value!r} is not valid: {rule}")
        return value
    return check


_check_frame = _checker(_FRAME_RE, "frame id", "non-empty segments of letters, digits, "
                        "'_', '.', '-' separated by '/', e.g. 'ivy/world'", MAX_FRAME_LENGTH)
_check_pattern = _checker(_EDGE_RE, "frame pattern", "like a frame id, '*' allowed inside "
                          "segments, e.g. '*/head'", MAX_FRAME_LENGTH)
_check_key = _checker(_FRAME_RE, "key", "non-empty segments of letters, digits, '_', '.', "
                      "'-' separated by '/', e.g. 'marvin/rig'", MAX_FRAME_LENGTH)


def _check_name(value: str) -> str:
    return ids.check_name("name", value)


def _check_id(value: str) -> str:
    return ids.check_id("id", value)


FrameId = Annotated[str, AfterValidator(_check_frame),
                    Field(json_schema_extra={"pattern": FRAME_PATTERN,
                                             "maxLength": MAX_FRAME_LENGTH})]
FramePattern = Annotated[str, AfterValidator(_check_pattern),
                         Field(json_schema_extra={"pattern": EDGE_PATTERN,
                                                  "maxLength": MAX_FRAME_LENGTH})]
StreamKey = Annotated[str, AfterValidator(_check_key),
                      Field(json_schema_extra={"pattern": FRAME_PATTERN,
                                               "maxLength": MAX_FRAME_LENGTH})]
Name = Annotated[str, AfterValidator(_check_name),
                 Field(json_schema_extra={"pattern": ids.NAME_PATTERN,
                                          "maxLength": MAX_NAME_LENGTH})]
Id = Annotated[str, AfterValidator(_check_id),
               Field(json_schema_extra={"pattern": ids.ID_PATTERN, "maxLength": MAX_NAME_LENGTH})]


def frame_matches(pattern: str, frame: str) -> bool:
    """Whether ``frame`` matches the need's edge ``pattern`` (``*`` within one segment)."""
    if "*" not in pattern:
        return pattern == frame
    parts = pattern.split("/")
    segments = frame.split("/")
    return len(parts) == len(segments) and all(
        fnmatchcase(s, p) for p, s in zip(parts, segments, strict=True))


# --------------------------------------------------------------------------- plain values


def check_plain(value: Any, where: str, depth: int = 0, numbers_only: bool = False) -> None:
    """Refuse anything but finite numbers, bools, strings, None, and bounded lists/dicts."""
    if depth > MAX_PLAIN_DEPTH:
        raise ValueError(f"{where}: nested deeper than {MAX_PLAIN_DEPTH} levels")
    if isinstance(value, bool):
        return
    if isinstance(value, int | float):
        if not math.isfinite(value):
            raise ValueError(f"{where}: non-finite value {value!r}")
        return
    if isinstance(value, list | tuple):
        if len(value) > MAX_LIST_LENGTH:
            raise ValueError(f"{where}: list longer than {MAX_LIST_LENGTH}")
        for i, item in enumerate(value):
            check_plain(item, f"{where}[{i}]", depth + 1, numbers_only)
        return
    if not numbers_only and (value is None or isinstance(value, str)):
        return
    if not numbers_only and isinstance(value, dict):
        if len(value) > MAX_LIST_LENGTH:
            raise ValueError(f"{where}: more than {MAX_LIST_LENGTH} entries")
        for k, item in value.items():
            if not isinstance(k, str):
                raise ValueError(f"{where}: key {k!r} is not a string")
            check_plain(item, f"{where}.{k}", depth + 1)
        return
    allowed = "numbers or lists of numbers" if numbers_only else "plain JSON values"
    raise ValueError(f"{where}: {type(value).__name__} not allowed ({allowed})")


def _plain_dict(value: dict[str, Any]) -> dict[str, Any]:
    check_plain(value, "attributes")
    return value


PlainDict = Annotated[dict[str, Any], AfterValidator(_plain_dict)]


# --------------------------------------------------------------------------- models


class Attributes(BaseModel):
    """Quality-of-service attributes of an ability (Klinker, Bauer 2005, §1.3.2).

    Besides the named ones, any extra attribute is allowed (``ground_truth=True``, a rig's
    geometry as lists of numbers); its name must be an identifier so expressions can use it,
    its value a finite number, a bool, a string, or (nested) lists of finite numbers.
    """

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)

    latency_s: float | None = Field(None, ge=0, description="delay from measurement to publication")
    frequency_hz: float | None = Field(None, gt=0, description="nominal sample rate")
    confidence: float | None = Field(None, ge=0, le=1, description="probability the data is right")
    pos_std_m: float | None = Field(None, ge=0, description="position standard deviation")
    rot_std_rad: float | None = Field(None, ge=0, description="rotation standard deviation")
    ttl_s: float | None = Field(None, gt=0, description="how long a sample stays valid")
    cost: float | None = Field(None, ge=0, description="abstract cost of using this ability")
    static: bool = Field(False, description="one value valid at all times (a calibration)")
    covariance: list[float] | None = Field(
        None, min_length=21, max_length=21,
        description="21 upper-triangular entries (row by row) of the 6x6 pose covariance over "
                    "the parent-frame perturbation [translation m, rotation rad]")

    @field_validator("covariance")
    @classmethod
    def _diagonal_non_negative(cls, v: list[float] | None) -> list[float] | None:
        if v is not None:
            bad = [i for i in _TRIU6_DIAGONAL if v[i] < 0]
            if bad:
                raise ValueError(f"covariance: negative variance {v[bad[0]]!r} on the diagonal")
        return v

    @model_validator(mode="after")
    def _check_extras(self) -> Attributes:
        for name, value in (self.__pydantic_extra__ or {}).items():
            if not _ATTRIBUTE_NAME_RE.match(name):
                raise ValueError(f"attribute name {name!r} is not an identifier "
                                 "(letters, digits, '_'; no leading digit)")
            if not isinstance(value, str):
                check_plain(value, f"attribute {name}", numbers_only=True)
        return self

    def numeric(self) -> dict[str, float]:
        """The scalar attributes as floats (bools as 0/1), for expression evaluation."""
        out: dict[str, float] = {}
        for name in ATTRIBUTE_NAMES:
            value = getattr(self, name)
            if value is not None:
                out[name] = float(value)
        for name, value in (self.__pydantic_extra__ or {}).items():
            if isinstance(value, bool | int | float):
                out[name] = float(value)
        return out


class Ability(BaseModel):
    """What a service publishes: a typed stream of one edge (A -> B) or under a key."""

    model_config = ConfigDict(extra="forbid")

    name: Name
    type: MeasurementType
    edge: tuple[FrameId, FrameId] | None = Field(
        None, description="(parent, child): the stream carries the pose of child in parent")
    key: StreamKey | None = Field(None, description="stream id for data that is not an edge")
    attributes: Attributes = Field(default_factory=Attributes)

    @model_validator(mode="after")
    def _edge_or_key(self) -> Ability:
        if (self.edge is None) == (self.key is None):
            raise ValueError(f"ability {self.name!r}: set exactly one of edge and key")
        if self.type in EDGE_TYPES and self.edge is None:
            raise ValueError(f"ability {self.name!r}: type {self.type} needs an edge")
        if self.edge is not None and self.edge[0] == self.edge[1]:
            raise ValueError(f"ability {self.name!r}: edge from {self.edge[0]!r} to itself")
        return self


@lru_cache(maxsize=1024)
def _parse_expression(text: str | None, what: str, predicate: bool) -> expr.Expr | None:
    """Parse and type-check once per distinct text (descriptors are re-validated often)."""
    if text is None:
        return None
    e = expr.parse(text)
    if predicate and not e.is_predicate:
        raise ValueError(f"{what} {text!r} is not a predicate (a comparison, and/or/not, "
                         "true/false); write e.g. 'static == true'")
    if not predicate and e.is_predicate:
        raise ValueError(f"{what} {text!r} is a predicate; a preference is a number to "
                         "minimise, e.g. 'latency_s' or 'pos_std_m + 0.1 * latency_s'")
    return e


class Need(BaseModel):
    """What a service wants: abilities of a type on matching edges, filtered and ranked.

    ``where`` is a predicate over the ability's attributes; ``prefer`` an expression to
    minimise.  Both are checked for syntax and types here; see the module docstring for
    which names they may use.  ``standby``: how many of the next-best abilities the service
    subscribes to as well, so that a chosen one falling silent (a camera that lost its tag)
    is stood in for at the next sample, before the agent has heard of it and matched anew.
    """

    model_config = ConfigDict(extra="forbid")

    name: Name
    type: MeasurementType
    edge: tuple[FramePattern, FramePattern] = Field(
        description="(parent, child) patterns; '*' matches within one segment")
    where: str | None = Field(None, max_length=expr.MAX_LENGTH,
                              description="predicate, e.g. 'frequency_hz >= 30'")
    prefer: str | None = Field(None, max_length=expr.MAX_LENGTH,
                               description="expression to minimise, e.g. 'latency_s'")
    min_count: int = Field(1, ge=0, description="fewest abilities to connect")
    max_count: int = Field(1, ge=1, description="most abilities to connect")
    standby: int = Field(0, ge=0, le=MAX_STANDBY, description=(
        "next-best abilities kept subscribed as well; their samples are delivered while a "
        "connected one sends nothing"))

    _where: expr.Expr | None = PrivateAttr(None)
    _prefer: expr.Expr | None = PrivateAttr(None)

    @field_validator("where")
    @classmethod
    def _where_is_predicate(cls, text: str | None) -> str | None:
        _parse_expression(text, "where", predicate=True)
        return text

    @field_validator("prefer")
    @classmethod
    def _prefer_is_number(cls, text: str | None) -> str | None:
        _parse_expression(text, "prefer", predicate=False)
        return text

    @model_validator(mode="after")
    def _check(self) -> Need:
        if self.max_count < self.min_count:
            raise ValueError(f"need {self.name!r}: max_count {self.max_count} < "
                             f"min_count {self.min_count}")
        self._where = _parse_expression(self.where, "where", predicate=True)
        self._prefer = _parse_expression(self.prefer, "prefer", predicate=False)
        return self

    @property
    def where_expr(self) -> expr.Expr | None:
        """The compiled predicate (``None``: every ability of the type qualifies)."""
        return self._where

    @property
    def prefer_expr(self) -> expr.Expr | None:
        """The compiled preference (``None``: no preference)."""
        return self._prefer

    def matches_edge(self, parent: str, child: str) -> bool:
        """Whether an ability's edge fits this need's edge patterns."""
        return frame_matches(self.edge[0], parent) and frame_matches(self.edge[1], child)


class ServiceDescriptor(BaseModel):
    """Everything an agent advertises about one of its services."""

    model_config = ConfigDict(extra="forbid")

    v: Literal[1] = Field(1, description="schema version")
    service_id: Id
    agent_id: Id
    needs: list[Need] = Field(default_factory=list)
    abilities: list[Ability] = Field(default_factory=list)
    attributes: PlainDict = Field(default_factory=dict)

    @model_validator(mode="after")
    def _unique_names(self) -> ServiceDescriptor:
        for what, items in (("need", self.needs), ("ability", self.abilities)):
            seen: set[str] = set()
            for item in items:
                if item.name in seen:
                    raise ValueError(f"service {self.service_id!r}: two {what} entries named "
                                     f"{item.name!r}")
                seen.add(item.name)
        return self


class AgentInfo(BaseModel):
    """An agent as the realm sees it."""

    model_config = ConfigDict(extra="forbid")

    agent_id: Id
    realm: Id
    version: str = Field(max_length=64)
    started_ns: int = Field(ge=0, description="start time, ns since the Unix epoch")
    endpoints: list[str] = Field(default_factory=list, description="Zenoh endpoints it listens on")
    services: list[Id] = Field(default_factory=list, description="ids of its local services")


class EdgeUse(BaseModel):
    """One edge a pose result was composed from."""

    model_config = ConfigDict(extra="forbid")

    parent: FrameId
    child: FrameId
    inverted: bool = Field(description="walked child -> parent, i.e. the edge was inverted")
    owner: Id = Field(description="agent that holds the edge")
    t_ns: int = Field(description="timestamp of the sample(s) used")


# The wire form of a pose query's answer; in a process it is an ``agent.PoseResult``, and its
# JSON Schema keeps that name (PoseResult.schema.json, its docstring the description).
class PoseResultMessage(BaseModel):
    """The answer to a pose query: the pose of ``target`` in ``source``'s frame at ``t_ns``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, title="PoseResult")

    source: FrameId
    target: FrameId
    t_ns: int
    position: tuple[float, float, float]
    quaternion: tuple[float, float, float, float] = Field(description="x, y, z, w; unit norm")
    covariance: list[float] | None = Field(
        None, min_length=36, max_length=36, description="6x6 row-major, or null if unknown")
    path: list[FrameId] = Field(default_factory=list, description="frames from source to target")
    edges: list[EdgeUse] = Field(default_factory=list)
    attributes: PlainDict = Field(default_factory=dict)
    extrapolated_s: float = Field(0.0, ge=0, description="how far any edge was extrapolated")

    @field_validator("quaternion")
    @classmethod
    def _unit(cls, q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        n = unit_norm(*q)
        return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


MODELS: dict[str, type[BaseModel]] = {
    m.model_config.get("title") or m.__name__: m
    for m in (Attributes, Ability, Need, ServiceDescriptor, AgentInfo, EdgeUse,
              PoseResultMessage)
}
