"""schemas.codec.decode_pose (the compiled twin schemas/_pose.c where it was built) against
decode_measurement: the same values for every message it accepts, the same DecodeError for
every other; and Graph.add_decoded against add_measurement."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from agent.srg import Graph
from schemas import codec
from schemas.codec import DecodeError, decode_measurement, decode_pose, encode_pose


def _reference(data: bytes):
    """What decode_measurement says of ``data``: its values, or its error message."""
    try:
        m = decode_measurement(data, expected_type="pose6d")
    except DecodeError as exc:
        return str(exc)
    return (m.t_ns, m.seq, tuple(m.position.tolist()), tuple(m.quaternion.tolist()),
            None if m.covariance is None else m.covariance.tolist())


def _fast(data: bytes):
    try:
        t, seq, p, q, cov = decode_pose(data)
    except DecodeError as exc:
        return str(exc)
    return t, seq, p, q, None if cov is None else cov.tolist()


def _random_cov(rng: np.random.Generator, dominant: bool) -> np.ndarray:
    a = rng.normal(size=(6, 6)) * 1e-3
    c = a @ a.T
    if dominant:
        c += np.eye(6) * np.abs(c).sum(axis=1).max()
    return c


def _messages(rng: np.random.Generator) -> list[bytes]:
    """Well-formed poses (with and without a sequence number and a covariance, quaternions
    off unit norm inside and outside the tolerance) and hand-made near misses."""
    out = []
    for k in range(300):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= 1 + rng.choice([0.0, 1e-6, 5e-4, -9e-4, 2e-3])
        cov = None if k % 3 == 0 else _random_cov(rng, dominant=k % 3 == 1)
        t = int(rng.integers(0, 2**62))
        seq = None if k % 4 == 0 else int(rng.integers(0, 2**40))
        msg = {"v": 1, "k": "pose6d", "t": t, "p": rng.normal(size=3).tolist(),
               "q": q.tolist(), "c": None if cov is None else codec.pack_covariance(cov)}
        if seq is not None:
            msg["s"] = seq
        out.append(msgpack.packb(msg))
        out.append(msgpack.packb(msg, use_single_float=True))  # float32 values
        out.append(msgpack.packb(dict(reversed(list(msg.items())))))  # any field order
    base = {"v": 1, "k": "pose6d", "t": 5, "s": 7, "p": [1.0, 2.0, 3.0],
            "q": [0.0, 0.0, 0.0, 1.0], "c": None}
    variants = [
        {}, {"p": [1, 2, 3]}, {"q": [0, 0, 0, 1]}, {"x": {"a": 1}}, {"v": 2}, {"v": True},
        {"k": "pose6"}, {"k": "position3d"}, {"t": -1}, {"t": 2**63}, {"t": 2**64 - 1},
        {"t": 1.5}, {"t": True}, {"s": -3}, {"p": [1.0, 2.0]}, {"p": [1.0, math.nan, 3.0]},
        {"p": [1.0, math.inf, 3.0]}, {"q": [0.0, 0.0, 0.0, 2.0]}, {"p": [True, 2.0, 3.0]},
        {"c": [0.1] * 21}, {"c": [0.0] * 20}, {"c": [-1.0] + [0.0] * 20}, {"z": 1},
        {"c": "no"}, {"p": "abc"}, {"p": None}, {"q": [0.0, 0.0, 0.0, 1.0, 0.0]},
    ]
    for change in variants:
        out.append(msgpack.packb({**base, **change}))
    for missing in ("v", "k", "t", "p", "q", "s", "c"):
        out.append(msgpack.packb({k: v for k, v in base.items() if k != missing}))
    good = msgpack.packb(base)
    out += [good + b"\x00", good[:-1], b"", b"\x80", b"\xc0", msgpack.packb([1, 2]),
            b"\x81\xa1v\x01\xa1v\x01", b"\x82\xa1v\x01\xa1v\x01",
            msgpack.packb({**base, "c": codec.pack_covariance(np.eye(6))}) * 2]
    return out


def test_decode_pose_accepts_and_refuses_what_decode_measurement_does() -> None:
    rng = np.random.default_rng(7)
    messages = _messages(rng)
    for data in messages:
        assert _fast(data) == _reference(data), data
    # and every truncation and one-byte change of well-formed ones
    for data in messages[:60:3]:
        for i in range(len(data)):
            cut = data[:i]
            assert _fast(cut) == _reference(cut)
            changed = bytearray(data)
            changed[i] = int(rng.integers(0, 256))
            assert _fast(bytes(changed)) == _reference(bytes(changed))


def test_the_compiled_decoder_takes_the_common_messages() -> None:
    if codec._NATIVE_POSE is None:
        pytest.skip("the compiled pose decoder was not built (schemas/_pose.c)")
    data = encode_pose(123, [1.0, 2.0, 3.0], [0.0, 0.0, 0.6, 0.8], np.eye(6) * 1e-4, seq=4)
    got = codec._NATIVE_POSE(data)
    assert got is not None and got[0] == 123 and got[1] == 4
    assert codec._NATIVE_POSE(encode_pose(1, [1, 2, 3], [0, 0, 0, 1])) is not None


def test_add_decoded_fills_the_buffer_as_add_measurement_does() -> None:
    rng = np.random.default_rng(3)
    a, b = Graph(), Graph()
    for k in range(50):
        q = rng.normal(size=4)
        q *= (1 + 4e-4) / np.linalg.norm(q)
        cov = None if k % 2 else _random_cov(rng, dominant=True)
        data = encode_pose(1_000 + 10 * k, rng.normal(size=3), q, cov, seq=k)
        m = decode_measurement(data, expected_type="pose6d")
        a.add_measurement("w", "x", m.t_ns, m.position, m.quaternion, m.covariance, source="s")
        t, _, p, qd, c = decode_pose(data)
        b.add_decoded("w", "x", t, p, qd, c, source="s")
    ea, eb = a._edges[("w", "x", "s")].buffer, b._edges[("w", "x", "s")].buffer
    assert ea.times == eb.times and ea.values == eb.values
    assert all((x is None and y is None) or np.array_equal(x, y)
               for x, y in zip(ea.covs, eb.covs, strict=True))
    b.add_static("w", "y", [0, 0, 0], [0, 0, 0, 1], source="cal")
    with pytest.raises(ValueError, match="static"):
        b.add_decoded("w", "y", 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), source="cal")


def _encoded(encode, *args):
    try:
        return encode(*args)
    except ValueError as exc:
        return f"{type(exc).__name__}: {exc}"


def test_encode_pose_makes_the_bytes_and_refusals_of_the_python_encoder() -> None:
    rng = np.random.default_rng(11)
    times = [0, 5, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**62, 2**63 - 1,
             -1, 2**63, True, np.int64(5), 1.0]
    positions = [[0.0, -0.0, 1e300], [1, 2, 3], (0.5, 2.0, -3.25), np.array([1.0, 2.0, 3.0]),
                 np.array([1.0, 2.0, 3.0], dtype=np.float32), np.arange(6.0)[::2],
                 [[1.0, 2.0, 3.0]], [1.0, 2.0], [1.0, math.nan, 3.0], [math.inf, 0.0, 0.0],
                 ["a", 2.0, 3.0], [True, 2.0, 3.0], [2**70, 1.0, 2.0],
                 [np.float64(1.5), 2.0, 3.0], [np.float64(math.nan), 2.0, 3.0],
                 [np.float32(1.5), 2.0, 3.0]]
    quaternions = [[0.0, 0.0, 0.0, 1.0], [0, 0, 0, 1], (0.0, 0.0, 0.6, 0.8),
                   np.array([0.0, 0.0, 0.0, 1.0004]), [0.0, 0.0, 0.0, 1.002], [0.0] * 4,
                   [0.0, 0.0, 0.0], [0.0, math.nan, 0.0, 1.0], [0.1, 0.2, 0.3]]
    seqs = [None, 0, 1, 300, 2**40, -1, True, 2**63]
    for _ in range(100):
        q = rng.normal(size=4)
        quaternions.append((q * (1 + rng.uniform(-2e-3, 2e-3)) / np.linalg.norm(q)).tolist())
        positions.append(rng.normal(size=3) * 10.0 ** rng.integers(-5, 5))
    native = codec._NATIVE_ENCODE or codec._encode_pose
    cases = 0
    for k, t in enumerate(times):
        for p in positions:
            q = quaternions[(k + cases) % len(quaternions)]
            seq = seqs[cases % len(seqs)]
            cases += 1
            want = _encoded(codec._encode_pose, t, p, q, None, seq)
            assert _encoded(encode_pose, t, p, q, None, seq) == want
            got = _encoded(native, t, p, q, seq) if native is not codec._encode_pose else want
            assert got is None or got == want, (t, p, q, seq)
    for q in quaternions:
        want = _encoded(codec._encode_pose, 7, [1.0, 2.0, 3.0], q, None, 9)
        assert _encoded(encode_pose, 7, [1.0, 2.0, 3.0], q, None, 9) == want
    if codec._NATIVE_ENCODE is not None:  # the common case is the compiled one's
        assert codec._NATIVE_ENCODE(1, [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], 3) is not None
        assert codec._NATIVE_ENCODE(1, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), None)
        # numpy's float64 scalars in a list (a tracker's arithmetic) stay compiled
        assert codec._NATIVE_ENCODE(1, [np.float64(0.5), 2.0, 3.0], [0, 0, 0, 1], 3) is not None
