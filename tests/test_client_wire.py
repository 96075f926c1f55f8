"""The client's light check of segment answers (``agent.protocol.query.pose_from_wire``) against the
documented contract, ``schemas.models.PoseResultMessage``: the same verdict on valid answers and on
each kind of damage, and the same values where both accept."""

from __future__ import annotations

import copy
import math
import re

import numpy as np
import pytest
from pydantic import ValidationError

from agent import geometry as geo
from agent.protocol import query
from agent.protocol.query import attributes_from_wire, pose_from_wire, result_to_wire
from agent.srg import Graph
from schemas.models import PoseResultMessage as PoseModel

S = 1_000_000_000


def answers() -> list[dict]:
    """Real answers of an agent's graph: static, measured, inverted, with and without
    covariance."""
    g = Graph()
    g.add_static("w", "cam", [1.0, 2.0, 3.0], geo.rotvec_to_quat(np.array([0.1, 0.2, 0.3])),
                 pos_std_m=0.01, rot_std_rad=0.002)
    g.add_static("cam", "rig", [0.0, 0.5, 0.0], [0.0, 0.0, 0.0, 1.0])
    for k in range(3):
        g.add_measurement("rig", "head", k * S // 10, [0.1 * k, 0.0, 0.2],
                          geo.rotvec_to_quat(np.array([0.0, 0.05 * k, 0.0])),
                          frequency_hz=10.0, latency_s=0.004)
    out = []
    for src, dst, at in (("w", "cam", None), ("cam", "rig", None), ("head", "w", S // 20),
                         ("w", "head", S // 10)):
        r = g.pose(src, dst, at=at, error="hops")
        out.append(result_to_wire(r, src, dst, "agent-1", r.t_ns if r.t_ns is not None else 7))
    return out


def model_accepts(d: dict) -> bool:
    try:
        PoseModel.model_validate(d)
    except ValidationError:
        return False
    return True


def light_accepts(d: dict) -> bool:
    try:
        pose_from_wire(d)
    except ValueError:
        return False
    return True


@pytest.mark.parametrize("i", range(4))
def test_valid_answers_give_what_the_model_gives(i):
    d = answers()[i]
    m = PoseModel.model_validate(d)
    r = pose_from_wire(d, lambda t: t - 5)
    np.testing.assert_array_equal(r.position, m.position)
    np.testing.assert_allclose(r.quaternion, m.quaternion, rtol=0, atol=1e-15)
    if m.covariance is None:
        assert r.covariance is None
    else:
        np.testing.assert_array_equal(r.covariance, np.array(m.covariance).reshape(6, 6))
    assert r.path == m.path and r.t_ns == m.t_ns - 5 and r.extrapolated_s == m.extrapolated_s
    assert [(e["parent"], e["child"], not e["forward"], e["owner"], e["t_ns"] + 5)
            for e in r.edges] == [(e.parent, e.child, e.inverted, e.owner, e.t_ns)
                                  for e in m.edges]
    for k, v in m.attributes.items():  # None on the wire stands for an infinite rate or ttl
        assert r.attributes[k] == (math.inf if v is None and k in ("frequency_hz", "ttl_s")
                                   else v)


def test_a_slightly_denormalized_quaternion_is_renormalized_like_the_model():
    d = answers()[0]
    d["quaternion"] = [x * 1.0004 for x in d["quaternion"]]
    np.testing.assert_allclose(pose_from_wire(d).quaternion,
                               PoseModel.model_validate(d).quaternion, atol=1e-15)


def _set(path, value):
    def damage(d):
        target = d
        for key in path[:-1]:
            target = target[key]
        if value is _DELETE:
            del target[path[-1]]
        else:
            target[path[-1]] = value
    return damage


_DELETE = object()
DAMAGES = {
    "nan position": _set(["position", 1], math.nan),
    "inf position": _set(["position", 0], math.inf),
    "2 position values": _set(["position"], [0.0, 1.0]),
    "string in position": _set(["position", 2], "x"),
    "nan quaternion": _set(["quaternion", 3], math.nan),
    "non-unit quaternion": _set(["quaternion"], [0.0, 0.0, 0.0, 2.0]),
    "zero quaternion": _set(["quaternion"], [0.0, 0.0, 0.0, 0.0]),
    "3 quaternion values": _set(["quaternion"], [0.0, 0.0, 1.0]),
    "35 covariance values": _set(["covariance"], [0.0] * 35),
    "nan in covariance": _set(["covariance"], [math.nan] + [0.0] * 35),
    "covariance as a map": _set(["covariance"], {"a": 1}),
    "missing position": _set(["position"], _DELETE),
    "missing t_ns": _set(["t_ns"], _DELETE),
    "float t_ns": _set(["t_ns"], 1.5),
    "string t_ns": _set(["t_ns"], "soon"),
    "unknown field": _set(["bogus"], 1),
    "bad source id": _set(["source"], "a//b"),
    "non-string target": _set(["target"], 3),
    "bad frame in path": _set(["path", 0], "has space"),
    "path not a list": _set(["path"], "w"),
    "negative extrapolation": _set(["extrapolated_s"], -1.0),
    "nan extrapolation": _set(["extrapolated_s"], math.nan),
    "nan attribute": _set(["attributes", "latency_s"], math.nan),
    "object attribute": _set(["attributes", "latency_s"], {1, 2}),
    "attributes not a map": _set(["attributes"], [1]),
    "edge missing owner": _set(["edges", 0, "owner"], _DELETE),
    "edge extra field": _set(["edges", 0, "extra"], 1),
    "edge bad owner id": _set(["edges", 0, "owner"], "a/b"),
    "edge float t_ns": _set(["edges", 0, "t_ns"], 0.5),
    "edge inverted not a bool": _set(["edges", 0, "inverted"], [1]),
    "edge not a map": _set(["edges", 0], "w->cam"),
}


@pytest.mark.parametrize("name", sorted(DAMAGES))
def test_damaged_answers_are_refused_by_both(name):
    d = copy.deepcopy(answers()[0])
    DAMAGES[name](d)
    assert not model_accepts(d), "the damage must break the contract"
    with pytest.raises(ValueError) as err:
        pose_from_wire(d)
    assert str(err.value)  # says what is wrong


def test_not_a_map_is_refused():
    for bad in (None, [1, 2], "pose"):
        assert not light_accepts(bad)


def test_remembered_ids_change_no_verdict():
    """Ids found valid are remembered: a damaged id is still refused after the same answer
    passed, and the memory stays bounded."""
    from agent.protocol.query import _IdCheck

    d = answers()[0]
    pose_from_wire(d)
    pose_from_wire(d)
    bad = copy.deepcopy(d)
    bad["path"][0] = "has space"
    for _ in range(2):
        with pytest.raises(ValueError, match=r"path\[0\]"):
            pose_from_wire(bad)
    check = _IdCheck(r"^[a-z]+$", 5, limit=2)
    for name in ("a", "b", "c", "a"):
        assert check(name, "id") == name
    assert len(check.valid) <= 2
    for wrong in ("toolong", "B", 3, ["a"]):
        with pytest.raises(ValueError, match="id"):
            check(wrong, "id")


@pytest.mark.parametrize("field", sorted(PoseModel.model_fields))
def test_every_field_of_the_model_is_checked_by_both(field):
    """Every field the model has, a new one included, is refused with the same verdict when
    its value is of the wrong kind (no field accepts a string holding a NUL)."""
    d = copy.deepcopy(answers()[3])
    d[field] = "\x00"
    assert not model_accepts(d)
    with pytest.raises(ValueError, match=field):
        pose_from_wire(d)


@pytest.mark.parametrize("field", sorted(n for n, f in PoseModel.model_fields.items()
                                         if f.is_required()))
def test_every_required_field_is_required_by_both(field):
    d = copy.deepcopy(answers()[3])
    del d[field]
    assert not model_accepts(d)
    with pytest.raises(ValueError, match=field):
        pose_from_wire(d)


def test_the_optional_fields_take_the_models_defaults():
    d = {k: v for k, v in answers()[0].items()
         if PoseModel.model_fields[k].is_required()}
    m, r = PoseModel.model_validate(d), pose_from_wire(d)
    assert (r.covariance, r.path, r.edges, r.extrapolated_s) == (
        m.covariance, m.path, m.edges, m.extrapolated_s)
    assert r.attributes == attributes_from_wire(m.attributes)


def test_a_local_result_is_sent_and_read_as_the_models_fields():
    """What an agent sends is exactly the model's fields, and the runtime class takes every
    one of them that is not the query's own (source and target)."""
    import inspect

    from agent.result import PoseResult

    for d in answers():
        assert d.keys() == PoseModel.model_fields.keys()
    taken = set(inspect.signature(PoseResult).parameters)
    assert set(PoseModel.model_fields) - {"source", "target"} <= taken


compiled = pytest.mark.skipif(
    query._NATIVE_RESULT is None,
    reason="the compiled reader (agent/protocol/_wire.c) is not in use: not built, or "
           "UMA_CODEC_PURE_PYTHON=1")


def _compiled(d: dict, to_local=None):
    """The compiled reader's own answer (None: it leaves ``d`` to Python)."""
    p, q, cov = np.empty(3), np.empty(4), np.empty((6, 6))
    return query._NATIVE_RESULT(d, query._frame_id.valid, query._agent_id.valid, to_local,
                                p, q, cov)


def _python(d: dict, to_local=query._same_time, monkeypatch=None):
    monkeypatch.setattr(query, "_NATIVE_RESULT", None)
    try:
        return pose_from_wire(d, to_local)
    finally:
        monkeypatch.undo()


def _same_result(a, b) -> None:
    for name in ("position", "quaternion", "covariance"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None and y is None) or np.array_equal(x, y), name
    assert (a.path, a.edges, a.t_ns, a.extrapolated_s, a.stamps, a.attributes) == (
        b.path, b.edges, b.t_ns, b.extrapolated_s, b.stamps, b.attributes)


@compiled
@pytest.mark.parametrize("i", range(4))
def test_the_compiled_reader_reads_answers_as_the_python_one(i, monkeypatch):
    """An agent's answer, with ids already seen: read by the compiled twin (not left to
    Python), to the same bits, times mapped by the same function."""
    d = answers()[i]
    d["quaternion"] = [x * 1.0004 for x in d["quaternion"]]  # renormalised alike
    want = _python(d, lambda t: t - 5, monkeypatch)
    assert _compiled(d, lambda t: t - 5) is not None
    _same_result(pose_from_wire(d, lambda t: t - 5), want)
    _same_result(pose_from_wire(d), _python(d, monkeypatch=monkeypatch))


@compiled
@pytest.mark.parametrize("name", sorted(DAMAGES))
def test_the_compiled_reader_leaves_every_damage_to_python(name):
    pose_from_wire(answers()[0])  # its ids are known
    d = copy.deepcopy(answers()[0])
    DAMAGES[name](d)
    assert _compiled(d) is None


LEFT_TO_PYTHON = {
    "a nested attribute": _set(["attributes", "note"], [1, {"a": 2}]),
    "integers in position": _set(["position"], [1, 2, 3]),
    "a bool extrapolation": _set(["extrapolated_s"], False),
    "no covariance": _set(["covariance"], None),
    "an id not seen before": _set(["path", 0], "fresh/frame"),
    "a default left out": _set(["extrapolated_s"], _DELETE),
}


@compiled
@pytest.mark.parametrize("name", sorted(LEFT_TO_PYTHON))
def test_answers_either_reader_may_take_are_read_alike(name, monkeypatch):
    """Valid answers off the agents' usual form: whichever reader takes them, the same
    result or the same refusal."""
    pose_from_wire(answers()[0])
    d = copy.deepcopy(answers()[0])
    LEFT_TO_PYTHON[name](d)
    try:
        want = _python(d, monkeypatch=monkeypatch)
    except ValueError as exc:
        with pytest.raises(ValueError, match=re.escape(str(exc))):
            pose_from_wire(d)
        return
    _same_result(pose_from_wire(d), want)


@compiled
def test_a_time_map_that_fails_fails_alike(monkeypatch):
    def broken(t):
        raise OverflowError("clock")
    pose_from_wire(answers()[3])
    with pytest.raises(OverflowError, match="clock"):
        pose_from_wire(answers()[3], broken)
