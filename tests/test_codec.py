"""The msgpack wire codec: round trips per type, and one DecodeError for everything wrong."""

from __future__ import annotations

import contextlib
import math
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas import codec
from schemas.codec import (
    MAX_MESSAGE_BYTES,
    DecodeError,
    Measurement,
    decode_descriptor,
    decode_measurement,
    decode_message,
    encode_descriptor,
    encode_measurement,
    encode_message,
    encode_pose,
    peek_time,
)
from schemas.models import Ability, Need, ServiceDescriptor

RNG = np.random.default_rng(7)


def _spd(n: int) -> np.ndarray:
    A = RNG.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def _unit_quat() -> np.ndarray:
    q = RNG.normal(size=4)
    return q / np.linalg.norm(q)


def _packed(**fields: Any) -> bytes:
    base = {"v": 1, "k": "pose6d", "t": 1, "p": [1.0, 2.0, 3.0], "q": [0.0, 0.0, 0.0, 1.0],
            "c": None}
    base.update(fields)
    return msgpack.packb({k: v for k, v in base.items() if v is not _DROP})


_DROP = object()


# --------------------------------------------------------------------------- round trips


def test_pose6d_round_trip_with_covariance_and_seq() -> None:
    p, q, C = RNG.normal(size=3), _unit_quat(), _spd(6)
    m = decode_measurement(encode_pose(1_700_000_000_123_456_789, p, q, C, seq=42), "pose6d")
    assert (m.type, m.t_ns, m.seq) == ("pose6d", 1_700_000_000_123_456_789, 42)
    np.testing.assert_array_equal(m.position, p)
    np.testing.assert_allclose(m.quaternion, q, atol=1e-15)
    np.testing.assert_allclose(m.covariance, C, rtol=0, atol=0)
    assert m.points is None and m.values is None and m.extra == {}
    # the general encoder writes the same message
    via = decode_measurement(encode_measurement(Measurement("pose6d", 5, position=p,
                                                            quaternion=q)))
    assert via.covariance is None and via.seq is None
    np.testing.assert_array_equal(via.position, p)


def test_wire_layout_is_the_documented_one() -> None:
    C = _spd(6)
    raw = msgpack.unpackb(encode_pose(7, [1, 2, 3], [0, 0, 0, 1], C))
    assert raw == {"v": 1, "k": "pose6d", "t": 7, "p": [1.0, 2.0, 3.0],
                   "q": [0.0, 0.0, 0.0, 1.0], "c": C[np.triu_indices(6)].tolist()}
    # upper triangle, row by row, and back
    np.testing.assert_array_equal(codec.unpack_covariance(codec.pack_covariance(C)), C)


def test_position3d_and_rotation3d_round_trip() -> None:
    C3 = _spd(3)
    m = decode_measurement(encode_measurement(
        Measurement("position3d", 3, position=[0.5, -1, 2], covariance=C3, seq=1)))
    np.testing.assert_array_equal(m.position, [0.5, -1, 2])
    np.testing.assert_array_equal(m.covariance, C3)
    assert m.quaternion is None and m.seq == 1
    q = _unit_quat()
    r = decode_measurement(encode_measurement(Measurement("rotation3d", 4, quaternion=q)))
    np.testing.assert_allclose(r.quaternion, q, atol=1e-15)
    assert r.position is None and r.covariance is None


def test_markers2d_round_trip_and_refusals() -> None:
    uv = np.array([[10.25, 20.5], [639.0, 0.0]])
    m = decode_measurement(encode_measurement(Measurement(
        "markers2d", 7, points=uv, values=np.array([0.05, 0.1]),
        extra={"camera": "cam3", "calibration": "rig-1"})), "markers2d")
    assert np.array_equal(m.points, uv) and np.array_equal(m.values, [0.05, 0.1])
    assert m.extra == {"camera": "cam3", "calibration": "rig-1"}
    empty = decode_measurement(encode_measurement(Measurement(
        "markers2d", 7, points=np.zeros((0, 2)), values=np.zeros(0))))
    assert empty.points.shape == (0, 2)
    for fields, fragment in (({"P": b"\x00" * 15, "e": b""}, "n*16 bytes"),
                             ({"P": b"\x00" * 16, "e": b"\x00" * 4}, "expected 8 bytes"),
                             ({"P": b"\x00" * 16, "e": np.zeros(1).tobytes()}, "> 0"),
                             ({"P": np.full(2, np.nan).tobytes(), "e": np.ones(1).tobytes()},
                              "non-finite")):
        with pytest.raises(DecodeError, match=fragment):
            decode_measurement(msgpack.packb({"v": 1, "k": "markers2d", "t": 1, **fields}))


def test_points3d_round_trip() -> None:
    pts = RNG.normal(size=(25, 3))
    m = decode_measurement(encode_measurement(
        Measurement("points3d", 9, points=pts, ids=list(range(-3, 22)))))
    np.testing.assert_array_equal(m.points, pts)
    assert m.ids == list(range(-3, 22))
    empty = decode_measurement(encode_measurement(Measurement("points3d", 9,
                                                              points=np.zeros((0, 3)))))
    assert empty.points.shape == (0, 3) and empty.ids is None


def test_accel_raw_image_event_round_trip() -> None:
    a = decode_measurement(encode_measurement(Measurement("accel_raw", 1,
                                                          values=np.arange(18) * 0.5)))
    np.testing.assert_array_equal(a.values, np.arange(18) * 0.5)
    for shape in [(4, 6), (4, 6, 3)]:
        img = RNG.integers(0, 256, size=shape, dtype=np.uint8)
        m = decode_measurement(encode_measurement(Measurement("image", 2, image=img)), "image")
        np.testing.assert_array_equal(m.image, img)
    extra = {"name": "click", "n": [1, 2.5], "ok": True, "none": None, "sub": {"a": "b"}}
    e = decode_measurement(encode_measurement(Measurement("event", 3, extra=extra)))
    assert e.extra == extra and e.type == "event"


def test_nearly_unit_quaternion_is_normalised() -> None:
    m = decode_measurement(_packed(q=[0.0, 0.0, 0.0, 1.0005]))
    assert np.linalg.norm(m.quaternion) == pytest.approx(1.0, abs=1e-15)
    assert np.linalg.norm(decode_measurement(encode_pose(1, [0, 0, 0],
                                                         [0, 0, 0, 0.9995])).quaternion) == \
        pytest.approx(1.0, abs=1e-15)


# --------------------------------------------------------------------------- decode errors


@pytest.mark.parametrize(("data", "fragment"), [
    (b"", "empty message"),
    (b"\xc1", "not valid msgpack"),
    (msgpack.packb([1, 2]), "expected a map"),
    (msgpack.packb({"k": "pose6d"}), "schema version 'v'"),
    (msgpack.packb({"v": "1"}), "schema version 'v'"),
    (msgpack.packb({"v": 2, "k": "pose6d"}), "unsupported schema version v=2"),
    (msgpack.packb({1: 2}), "not valid msgpack"),  # non-string map keys
    (_packed(k="pose7d"), "unknown measurement type 'pose7d'"),
    (_packed(t=_DROP), "field 't': expected an integer, got NoneType"),
    (_packed(t=1.5), "field 't': expected an integer, got float"),
    (_packed(t=True), "field 't': expected an integer, got bool"),
    (_packed(t=-1), "outside"),
    (_packed(s="x"), "field 's'"),
    (_packed(p=[1.0, 2.0]), "field 'p': expected 3 numbers, got a list of 2"),
    (_packed(p=_DROP), "field 'p': expected 3 numbers, got NoneType"),
    (_packed(p=[1.0, "2", 3.0]), "field 'p': str is not a number"),
    (_packed(p=[1.0, True, 3.0]), "bool is not a number"),
    (_packed(p=[1.0, math.nan, 3.0]), "non-finite value nan"),
    (_packed(p=[1.0, math.inf, 3.0]), "non-finite value inf"),
    (_packed(q=[0.0, 0.0, 0.0, 1.1]), "quaternion norm 1.1 is not 1"),
    (_packed(q=[0.0, 0.0, 0.0, 0.0]), "quaternion norm 0 is not 1"),
    (_packed(q=[0.0, 0.0, math.nan, 1.0]), "non-finite"),
    (_packed(c=[0.0] * 20), "field 'c': expected 21 numbers"),
    (_packed(c=[math.nan] + [0.0] * 20), "non-finite"),
    (_packed(c=[-1.0] + [0.0] * 20), "negative variance"),
    (_packed(z=1), "unexpected field(s) z"),
    (_packed(x=[1]), "field 'x': expected a map"),
    (_packed(x={"a": math.nan}), "non-finite"),
    (_packed(k="position3d", q=_DROP, c=[0.0] * 21), "field 'c': expected 6 numbers"),
    (_packed(k="rotation3d", p=_DROP, q=[1.0, 0.0, 0.0]), "field 'q': expected 4 numbers"),
    (_packed(k="points3d", p=_DROP, q=_DROP, c=_DROP, P=b"\x00" * 23), "n*24 bytes"),
    (_packed(k="points3d", p=_DROP, q=_DROP, c=_DROP, P=[1.0, 2.0, 3.0]), "got list"),
    (_packed(k="points3d", p=_DROP, q=_DROP, c=_DROP,
             P=np.array([0.0, np.nan, 0.0]).tobytes()), "non-finite"),
    (_packed(k="points3d", p=_DROP, q=_DROP, c=_DROP, P=b"\x00" * 24, i=[1, 2]),
     "expected 1 integer labels"),
    (_packed(k="points3d", p=_DROP, q=_DROP, c=_DROP, P=b"\x00" * 24, i=[1.0]),
     "labels must be integers"),
    (_packed(k="accel_raw", p=_DROP, q=_DROP, c=_DROP, a=[]), "expected 1 to"),
    (_packed(k="accel_raw", p=_DROP, q=_DROP, c=_DROP, a=[1.0, None]), "NoneType is not a"),
    (_packed(k="image", p=_DROP, q=_DROP, c=_DROP, h=2, w=2, ch=1, d=b"\x00" * 3),
     "expected 4 bytes, got 3 bytes"),
    (_packed(k="image", p=_DROP, q=_DROP, c=_DROP, h=2, w=2, ch=2, d=b"\x00" * 8),
     "expected 1 or 3 channels"),
    (_packed(k="image", p=_DROP, q=_DROP, c=_DROP, h=0, w=2, ch=1, d=b""), "outside"),
    (_packed(k="event"), "unexpected field(s) c, p, q"),
    (_packed() + b"\x00", "not valid msgpack"),
    (msgpack.packb({"v": 1, "k": "pose6d", "t": msgpack.Timestamp(1, 0)}), "not valid"),
])
def test_decode_errors_say_why(data: bytes, fragment: str) -> None:
    with pytest.raises(DecodeError) as err:
        decode_measurement(data)
    assert fragment in str(err.value)


def test_expected_type_and_size_limits() -> None:
    data = encode_pose(1, [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(DecodeError, match="expected a position3d measurement, got pose6d"):
        decode_measurement(data, expected_type="position3d")
    big = msgpack.packb({"v": 1, "k": "event", "t": 1, "x": {"s": "a" * 60000,
                                                              "l": ["b" * 60000] * 20}})
    assert len(big) > MAX_MESSAGE_BYTES
    with pytest.raises(DecodeError, match="exceeds the limit"):
        decode_measurement(big)
    with pytest.raises(DecodeError, match="exceeds the limit"):
        decode_measurement(big, expected_type="event")
    with pytest.raises(DecodeError, match="expected bytes, got str"):
        decode_measurement("text")  # type: ignore[arg-type]
    # a large image is allowed past the general limit
    img = np.zeros((1024, 1024, 3), np.uint8)
    assert decode_measurement(encode_measurement(Measurement("image", 1, image=img)),
                              "image").image.shape == img.shape


def test_peek_time_reads_the_time_alone() -> None:
    t = 1_700_000_000_123_456_789
    assert peek_time(encode_pose(t, [1, 2, 3], [0, 0, 0, 1], _spd(6), seq=3)) == t
    img = encode_measurement(Measurement("image", t, image=np.zeros((480, 640, 3), np.uint8)))
    assert peek_time(img, "image") == t
    # the body is not looked at: the time of a sample whose pose is bad is still read
    assert peek_time(_packed(t=5, q=[0.0, 0.0, 0.0, 2.0])) == 5
    # the time comes first when we encode, but the map's order is not part of the format
    assert peek_time(msgpack.packb({"p": [1.0, 2.0, 3.0], "t": 7, "k": "pose6d", "v": 1})) == 7


@pytest.mark.parametrize(("data", "fragment"), [
    (b"", "non-empty"),
    (msgpack.packb([1, 2]), "msgpack map"),
    (_packed(v=2), "schema version"),
    (_packed(k="nope"), "unknown measurement type"),
    (_packed(t=-1), "outside"),
    (_packed(t=_DROP), "'t'"),
    (_packed(t="1"), "expected an integer"),
    (_packed()[:9], "msgpack map"),  # cut short before the time
])
def test_peek_time_errors_say_why(data: bytes, fragment: str) -> None:
    with pytest.raises(DecodeError, match=fragment):
        peek_time(data)


def test_peek_time_checks_the_expected_type() -> None:
    with pytest.raises(DecodeError, match="expected a points3d"):
        peek_time(_packed(), "points3d")


def test_every_truncation_is_a_decode_error() -> None:
    for data in (encode_pose(1, [1, 2, 3], [0, 0, 0, 1], _spd(6), seq=3),
                 encode_measurement(Measurement("points3d", 1, points=np.ones((3, 3)),
                                                ids=[1, 2, 3]))):
        for n in range(len(data)):
            with pytest.raises(DecodeError):
                decode_measurement(data[:n])


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_random_bytes_raise_only_decode_error(data: bytes) -> None:
    for decode in (decode_measurement, decode_descriptor, decode_message, peek_time):
        with contextlib.suppress(DecodeError):  # anything else fails the test
            decode(data)


_plain = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() |
    st.text(max_size=5) | st.binary(max_size=30),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(
        st.sampled_from(["v", "k", "t", "s", "x", "p", "q", "c", "P", "i", "a", "h", "w", "ch",
                         "d", "e"]), children, max_size=6),
    max_leaves=15)


@settings(max_examples=150, deadline=None)
@given(st.dictionaries(st.sampled_from(["v", "k", "t", "s", "x", "p", "q", "c", "P", "i", "a",
                                        "h", "w", "ch", "d", "e"]), _plain, max_size=8),
       st.sampled_from(codec.MEASUREMENT_TYPES))
def test_structured_garbage_raises_only_decode_error(obj: dict[str, Any], kind: str) -> None:
    obj = {"v": 1, "k": kind, "t": 1, **obj}
    data = msgpack.packb(obj)
    with contextlib.suppress(DecodeError):  # anything else fails the test
        peek_time(data)
    try:
        m = decode_measurement(data)
    except DecodeError:
        return
    assert peek_time(data, kind) == m.t_ns  # whatever decodes has the time peek_time reads
    # whatever was accepted is valid and re-encodes
    assert decode_measurement(encode_measurement(m)).type == m.type


# --------------------------------------------------------------------------- encode errors


@pytest.mark.parametrize(("call", "fragment"), [
    (lambda: encode_pose(1, [0, 0], [0, 0, 0, 1]), "position: expected 3 numbers"),
    (lambda: encode_pose(1, [0, 0, np.nan], [0, 0, 0, 1]), "position: non-finite"),
    (lambda: encode_pose(1, [0, 0, 0], [0, 0, 0, 2]), "quaternion: norm 2"),
    (lambda: encode_pose(1, [0, 0, 0], ["a", 0, 0, 1]), "quaternion: not numeric"),
    (lambda: encode_pose(1.5, [0, 0, 0], [0, 0, 0, 1]), "t_ns: expected an integer"),
    (lambda: encode_pose(-5, [0, 0, 0], [0, 0, 0, 1]), "t_ns: -5 outside"),
    (lambda: encode_pose(1, [0, 0, 0], [0, 0, 0, 1], seq=True), "seq: expected an integer"),
    (lambda: encode_pose(1, [0, 0, 0], [0, 0, 0, 1], np.eye(3)), "covariance: expected shape"),
    (lambda: encode_pose(1, [0, 0, 0], [0, 0, 0, 1], np.triu(np.ones((6, 6)))),
     "covariance: not symmetric"),
    (lambda: encode_pose(1, [0, 0, 0], [0, 0, 0, 1], -np.eye(6)), "negative variance"),
    (lambda: encode_measurement(Measurement("pose6d", 1, position=[0, 0, 0])),
     "quaternion: required for a pose6d measurement"),
    (lambda: encode_measurement(Measurement("pose9d", 1)), "type: 'pose9d' is not one of"),
    (lambda: encode_measurement(Measurement("points3d", 1, points=np.ones((2, 2)))),
     "points: expected shape (n, 3)"),
    (lambda: encode_measurement(Measurement("points3d", 1, points=np.ones((2, 3)), ids=[1])),
     "ids: 1 labels for 2 points"),
    (lambda: encode_measurement(Measurement("markers2d", 1, points=np.ones((2, 3)),
                                            values=np.ones(2))), "points: expected shape (n, 2)"),
    (lambda: encode_measurement(Measurement("markers2d", 1, points=np.ones((2, 2)),
                                            values=np.ones(3))), "values: expected 2 centroid"),
    (lambda: encode_measurement(Measurement("markers2d", 1, points=np.ones((1, 2)),
                                            values=np.zeros(1))), "stds must be > 0"),
    (lambda: encode_measurement(Measurement("accel_raw", 1, values=[])), "values: expected"),
    (lambda: encode_measurement(Measurement("image", 1, image=np.zeros((2, 2)))),
     "image: expected uint8"),
    (lambda: encode_measurement(Measurement("event", 1, extra={"a": math.inf})), "non-finite"),
    (lambda: encode_measurement(Measurement("event", 1, extra={1: 2})), "string keys"),
])
def test_encode_errors_name_the_field(call: Any, fragment: str) -> None:
    with pytest.raises(ValueError) as err:
        call()
    assert fragment in str(err.value)


# --------------------------------------------------------------------------- descriptors, messages


def _descriptor() -> ServiceDescriptor:
    return ServiceDescriptor(
        service_id="cam-nw", agent_id="hostA",
        needs=[Need(name="head", type="pose6d", edge=("ivy/world", "*/head"),
                    where="frequency_hz >= 30", prefer="latency_s")],
        abilities=[Ability(name="pose", type="pose6d", edge=("ivy/world", "alice/head"),
                           attributes={"frequency_hz": 60, "covariance": [0.0] * 21})])


def test_descriptor_round_trip() -> None:
    d = _descriptor()
    back = decode_descriptor(encode_descriptor(d))
    assert back == d
    assert back.needs[0].where_expr.evaluate({"frequency_hz": 40}) is True
    with pytest.raises(ValueError, match="expected a ServiceDescriptor"):
        encode_descriptor({"service_id": "x"})  # type: ignore[arg-type]


def test_invalid_descriptor_gives_one_line_reason() -> None:
    raw = _descriptor().model_dump(mode="json")
    raw["needs"][0]["where"] = "frequency_hz >"
    with pytest.raises(DecodeError) as err:
        decode_descriptor(msgpack.packb(raw))
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith("invalid service descriptor: needs.0.where: expected a number")
    raw = _descriptor().model_dump(mode="json")
    del raw["agent_id"]
    raw["abilities"][0]["attributes"]["confidence"] = 3
    raw["needs"][0]["min_count"] = -1
    raw["needs"][0]["type"] = 5
    with pytest.raises(DecodeError, match=r"agent_id: Field required.*\(and 1 more\)"):
        decode_descriptor(msgpack.packb(raw))
    with pytest.raises(DecodeError, match="unsupported schema version"):
        decode_descriptor(msgpack.packb({**_descriptor().model_dump(mode="json"), "v": 3}))


def test_messages() -> None:
    data = encode_message({"op": "connect", "need": "head", "n": np.int64(3),
                           "xs": np.arange(3.0)})
    d = decode_message(data, required=["op", "need"])
    assert d == {"v": 1, "op": "connect", "need": "head", "n": 3, "xs": [0.0, 1.0, 2.0]}
    with pytest.raises(DecodeError, match=r"lacks field\(s\) key"):
        decode_message(data, required=["op", "key"])
    with pytest.raises(DecodeError, match="unsupported schema version"):
        decode_message(msgpack.packb({"v": 9}))
    with pytest.raises(ValueError, match="string keys"):
        encode_message({1: "a"})  # type: ignore[dict-item]
    with pytest.raises(ValueError, match="cannot encode"):
        encode_message({"a": {1, 2}})
    with pytest.raises(ValueError, match="schema version"):
        encode_message({"v": 2})
    with pytest.raises(ValueError, match="more than"):
        encode_message({"blob": b"\x00" * (MAX_MESSAGE_BYTES + 1)})
