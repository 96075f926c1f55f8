"""The pydantic contracts: what they accept, what they refuse and why, and schema drift."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from schemas import export
from schemas.expr import ExprError
from schemas.models import (
    ATTRIBUTE_NAMES,
    MEASUREMENT_TYPES,
    MODELS,
    Ability,
    AgentInfo,
    Attributes,
    Need,
    PoseResultMessage,
    ServiceDescriptor,
    frame_matches,
)

SCHEMA_DIR = Path(export.__file__).parent


def _ability(**kw: Any) -> dict[str, Any]:
    return {"name": "pose", "type": "pose6d", "edge": ["ivy/world", "alice/head"], **kw}


def _need(**kw: Any) -> dict[str, Any]:
    return {"name": "head", "type": "pose6d", "edge": ["ivy/world", "*/head"], **kw}


def _error(model: type, data: dict[str, Any]) -> str:
    with pytest.raises(ValidationError) as err:
        model.model_validate(data)
    return str(err.value)


def test_constants_match_design() -> None:
    assert ATTRIBUTE_NAMES == ("latency_s", "frequency_hz", "confidence", "pos_std_m",
                               "rot_std_rad", "ttl_s", "cost", "static")
    assert MEASUREMENT_TYPES == ("pose6d", "position3d", "rotation3d", "points3d", "markers2d",
                                 "accel_raw", "image", "event")
    assert set(MODELS) >= {"Attributes", "Ability", "Need", "ServiceDescriptor", "AgentInfo",
                           "PoseResult"}


def test_attributes_numeric_and_extras() -> None:
    a = Attributes(frequency_hz=60, latency_s=0.005, static=True, ground_truth=True,
                   mounts=[[0.1, 0.0, 0.0], [0.0, 0.1, 0.0]], label="nw", gain=2)
    assert a.numeric() == {"frequency_hz": 60.0, "latency_s": 0.005, "static": 1.0,
                           "ground_truth": 1.0, "gain": 2.0}
    assert Attributes().numeric() == {"static": 0.0}
    assert Attributes(covariance=[0.0] * 21).covariance == [0.0] * 21


@pytest.mark.parametrize(("attributes", "fragment"), [
    ({"latency_s": -1}, "greater than or equal to 0"),
    ({"frequency_hz": 0}, "greater than 0"),
    ({"confidence": 1.5}, "less than or equal to 1"),
    ({"pos_std_m": -0.1}, "greater than or equal to 0"),
    ({"rot_std_rad": float("nan")}, "finite number"),
    ({"ttl_s": 0}, "greater than 0"),
    ({"cost": float("inf")}, "finite number"),
    ({"static": "maybe"}, "valid boolean"),
    ({"covariance": [0.0] * 20}, "at least 21"),
    ({"covariance": [-1.0] + [0.0] * 20}, "negative variance"),
    ({"covariance": [float("nan")] + [0.0] * 20}, "finite number"),
    ({"bad name": 1}, "not an identifier"),
    ({"x": float("nan")}, "non-finite value"),
    ({"x": {"nested": 1}}, "dict not allowed"),
    ({"x": [1, "two"]}, "str not allowed"),
    ({"x": None}, "NoneType not allowed"),
])
def test_attributes_refused(attributes: dict[str, Any], fragment: str) -> None:
    assert fragment in _error(Ability, _ability(attributes=attributes))


@pytest.mark.parametrize(("pattern", "frame", "expected"), [
    ("ivy/world", "ivy/world", True),
    ("ivy/world", "ivy/worlds", False),
    ("*/head", "alice/head", True),
    ("*/head", "alice/hand", False),
    ("*/head", "a/b/head", False),
    ("*", "alice/head", False),
    ("*/*", "alice/head", True),
    ("ivy/cam_*", "ivy/cam_nw", True),
    ("ivy/cam_*", "ivy/light", False),
    ("*head", "alice/head", False),
    ("al*/he*d", "alice/head", True),
])
def test_frame_matches(pattern: str, frame: str, expected: bool) -> None:
    assert frame_matches(pattern, frame) is expected


def test_ability_valid_forms() -> None:
    a = Ability.model_validate(_ability(attributes={"frequency_hz": 60}))
    assert a.edge == ("ivy/world", "alice/head")
    assert a.attributes.frequency_hz == 60
    k = Ability(name="accel", type="accel_raw", key="marvin/rig")
    assert k.edge is None and k.key == "marvin/rig"
    assert Ability(name="dots", type="points3d", edge=("ivy/cam_nw", "ivy/dots")).key is None


@pytest.mark.parametrize(("data", "fragment"), [
    (_ability(key="x"), "exactly one of edge and key"),
    ({"name": "pose", "type": "pose6d"}, "exactly one of edge and key"),
    ({"name": "pose", "type": "rotation3d", "key": "x"}, "needs an edge"),
    (_ability(edge=["a/b", "a/b"]), "to itself"),
    (_ability(name="has space"), "name 'has space' is not valid"),
    (_ability(name=""), "is not valid"),
    (_ability(type="pose7d"), "Input should be 'pose6d'"),
    (_ability(edge=["ivy/world"]), "edge.1\n  Field required"),
    (_ability(edge=["ivy/*", "alice/head"]), "frame id 'ivy/*' is not valid"),
    (_ability(edge=["ivy//world", "alice/head"]), "is not valid"),
    (_ability(edge=["/world", "alice/head"]), "is not valid"),
    (_ability(edge=["ivy/world$", "alice/head"]), "is not valid"),
    (_ability(edge=["ivy/w" + "o" * 300, "alice/head"]), "longer than"),
    (_ability(colour="red"), "Extra inputs are not permitted"),
    ({"name": "clicks", "type": "event", "key": "a b"}, "key 'a b' is not valid"),
])
def test_ability_refused(data: dict[str, Any], fragment: str) -> None:
    assert fragment in _error(Ability, data)


def test_need_expressions_are_compiled() -> None:
    n = Need.model_validate(_need(where="frequency_hz >= 30 and not static",
                                  prefer="latency_s + 0.1 * pos_std_m", min_count=0,
                                  max_count=3))
    ok = Attributes(frequency_hz=60, latency_s=0.01, pos_std_m=0.1).numeric()
    slow = Attributes(frequency_hz=10, latency_s=0.01, pos_std_m=0.1).numeric()
    assert n.where_expr is not None and n.prefer_expr is not None
    assert n.where_expr.evaluate(ok) is True
    assert n.where_expr.evaluate(slow) is False
    assert n.prefer_expr.evaluate(ok) == pytest.approx(0.02)
    # unknown names are accepted when declared and reported when evaluated
    with pytest.raises(ExprError, match="no value for 'pos_std_m'"):
        n.prefer_expr.evaluate({"latency_s": 0.01})
    assert n.matches_edge("ivy/world", "bob/head")
    assert not n.matches_edge("ivy/world", "bob/hand")
    assert not n.matches_edge("lab/world", "bob/head")
    bare = Need.model_validate(_need())
    assert bare.where_expr is None and bare.prefer_expr is None
    assert (bare.min_count, bare.max_count) == (1, 1)


@pytest.mark.parametrize(("data", "fragment"), [
    (_need(where="frequency_hz >="), "where"),
    (_need(where="frequency_hz >="), "got end of expression at 15"),
    (_need(where="latency_s"), "is not a predicate"),
    (_need(prefer="latency_s < 1"), "is a predicate"),
    (_need(prefer="latency_s +* 2"), "prefer"),
    (_need(where="x" * 1001), "at most 1000 characters"),
    (_need(min_count=2), "max_count 1 < min_count 2"),
    (_need(min_count=-1), "greater than or equal to 0"),
    (_need(max_count=0), "greater than or equal to 1"),
    (_need(edge=["ivy/world", "*/he$d"]), "frame pattern"),
    (_need(edge=["ivy/world", "*/head", "x"]), "at most 2 items"),
])
def test_need_refused(data: dict[str, Any], fragment: str) -> None:
    assert fragment in _error(Need, data)


def test_service_descriptor_round_trip_and_uniqueness() -> None:
    d = ServiceDescriptor(service_id="cam-nw", agent_id="host.lab",
                          needs=[Need.model_validate(_need(where="frequency_hz >= 30"))],
                          abilities=[Ability.model_validate(_ability(
                              attributes={"frequency_hz": 60, "ground_truth": True}))],
                          attributes={"model": "sim", "cams": [1, 2], "opts": {"a": None}})
    wire = json.loads(json.dumps(d.model_dump(mode="json")))
    back = ServiceDescriptor.model_validate(wire)
    assert back == d
    assert back.v == 1
    assert back.needs[0].where_expr is not None
    assert back.abilities[0].attributes.numeric()["ground_truth"] == 1.0

    two = [_ability(), _ability(edge=["ivy/world", "bob/head"])]
    base = {"service_id": "s", "agent_id": "a"}
    assert "two ability entries named 'pose'" in _error(ServiceDescriptor,
                                                        {**base, "abilities": two})
    assert "two need entries named 'head'" in _error(ServiceDescriptor,
                                                     {**base, "needs": [_need(), _need()]})
    assert "Input should be 1" in _error(ServiceDescriptor, {**base, "v": 2})
    assert "is not valid" in _error(ServiceDescriptor, {"service_id": "a/b", "agent_id": "a"})
    assert "non-finite" in _error(ServiceDescriptor, {**base, "attributes": {"x": math.inf}})
    assert "set not allowed" in _error(ServiceDescriptor, {**base, "attributes": {"x": {1}}})


def test_agent_info() -> None:
    info = AgentInfo(agent_id="hostA", realm="lab", version="0.1.0", started_ns=1,
                     endpoints=["tcp/127.0.0.1:7447"], services=["cam-nw"])
    assert AgentInfo.model_validate(info.model_dump(mode="json")) == info
    assert "greater than or equal to 0" in _error(
        AgentInfo, {**info.model_dump(), "started_ns": -1})
    assert "is not valid" in _error(AgentInfo, {**info.model_dump(), "realm": "a b"})


def _pose(**kw: Any) -> dict[str, Any]:
    return {"source": "ivy/world", "target": "alice/head", "t_ns": 5,
            "position": [1, 2, 3], "quaternion": [0, 0, 0, 1], **kw}


def test_pose_result() -> None:
    r = PoseResultMessage.model_validate(_pose(
        quaternion=[0, 0, 0, 1.0005], covariance=[0.0] * 36,
        path=["ivy/world", "alice/head"], extrapolated_s=0.01,
        edges=[{"parent": "ivy/world", "child": "alice/head", "inverted": False,
                "owner": "hostA", "t_ns": 5}]))
    assert r.quaternion == pytest.approx((0, 0, 0, 1), abs=1e-12)  # normalised
    assert r.edges[0].owner == "hostA"
    assert PoseResultMessage.model_validate(r.model_dump(mode="json")) == r
    assert "not 1" in _error(PoseResultMessage, _pose(quaternion=[0, 0, 0, 1.1]))
    assert "finite number" in _error(PoseResultMessage, _pose(position=[0, math.nan, 0]))
    assert "at least 36" in _error(PoseResultMessage, _pose(covariance=[0.0] * 21))
    assert "greater than or equal to 0" in _error(PoseResultMessage, _pose(extrapolated_s=-1))
    assert "Field required" in _error(PoseResultMessage, _pose(edges=[{"parent": "a/b"}]))


def test_exported_schemas_match_the_models() -> None:
    """Fails when a model changed without re-running ``uma schemas export schemas``."""
    committed = {p.name for p in SCHEMA_DIR.glob("*.schema.json")}
    assert committed == {f"{name}.schema.json" for name in MODELS}
    for name in MODELS:
        text = (SCHEMA_DIR / f"{name}.schema.json").read_text(encoding="utf-8")
        assert text == export.render(name), (
            f"{name}.schema.json is out of date: run 'uma schemas export schemas'")


def test_export_writes_parseable_schemas(tmp_path: Path) -> None:
    written = export.export(tmp_path / "out")
    assert sorted(p.name for p in written) == sorted(f"{n}.schema.json" for n in MODELS)
    need = json.loads((tmp_path / "out" / "Need.schema.json").read_text())
    assert need["additionalProperties"] is False
    assert {"name", "type", "edge"} <= set(need["required"])
    assert need["properties"]["edge"]["prefixItems"][0]["pattern"]


@pytest.mark.parametrize("bad", ["host:1", "a/b", "a b", "*", "@x", "x" * 65, ""])
def test_one_id_rule_for_keys_models_and_the_agent(bad: str) -> None:
    """An id refused by one layer is refused by all: `uma agent --id host:1` used to pass
    the agent's check and then have its snapshot rejected by the model."""
    from agent.daemon.settings import AgentSettings
    from agent.errors import UmaError
    from agent.protocol import keys
    from schemas.ids import check_id

    with pytest.raises(ValueError):
        check_id("agent id", bad)
    with pytest.raises(UmaError, match="agent id"):
        keys.check_name("agent id", bad)
    with pytest.raises(UmaError, match="agent id"):
        AgentSettings(realm="lab", agent_id=bad).check()
    with pytest.raises(ValidationError):
        AgentInfo(agent_id=bad, realm="lab", version="1", started_ns=0)


def test_uma_agent_refuses_an_id_the_models_would_refuse() -> None:
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "agent.cli", "agent", "--realm", "lab", "--id",
                        "host:1"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "agent id 'host:1' is not valid" in r.stderr
    assert "Traceback" not in r.stderr
