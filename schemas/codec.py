"""The msgpack wire codec: measurements on the hot path, descriptors and control messages.

Every message is one msgpack map with the schema version ``"v": 1``.  Measurements are
decoded by hand (no pydantic: a pose costs a few microseconds each way); descriptors go
through ``schemas.models``.  Everything that is wrong with incoming bytes raises one
``DecodeError`` (a ``ValueError``) whose message says what and where; encoding refuses bad
values with a ``ValueError`` naming the field, so a bug shows up at the sender.

Measurement wire format (``k`` is the type; keys absent from a type are refused):

======================  ==================================================================
every type              ``v``: 1, ``k``: type, ``t``: int ns since the epoch (0 <= t < 2**63),
                        ``s``: sequence number (optional), ``x``: map of extra plain values
                        (optional: str keys; numbers, bools, strings, nil, lists, maps)
``pose6d``              ``p``: [x, y, z] m, ``q``: [x, y, z, w] unit quaternion,
                        ``c``: 21 floats (upper triangle of the 6x6 covariance over the
                        parent-frame perturbation [translation, rotation], row by row) or nil;
                        optionally ``x[SYSTEMATIC_COVARIANCE]``: 21 floats, the part of ``c``
                        that persists from sample to sample (a filter must not average it)
``position3d``          ``p``, ``c``: 6 floats (upper triangle of the 3x3 covariance) or nil
``rotation3d``          ``q``, ``c``: 6 floats (3x3 rotation covariance, rad^2) or nil
``points3d``            ``P``: bin, n*3 little-endian float64 (x, y, z per point),
                        ``i``: n int labels or nil; laser dots optionally ``x[DOT_STD]`` and
                        ``x[DOT_SYSTEMATIC_STD]``: n floats each, per point
``markers2d``           ``P``: bin, n*2 little-endian float64 (u, v: distorted pixels of
                        marker images, pixel centres at integers), ``e``: bin, n float64
                        (each centroid's std, px, > 0); ``x[MARKERS_CAMERA]`` and
                        ``x[MARKERS_CALIBRATION]`` name the camera and its calibration
``accel_raw``           ``a``: N floats (one reading per accelerometer axis, m/s^2)
``image``               ``h``, ``w``, ``ch`` (1 or 3): ints, ``d``: bin, h*w*ch uint8, row-major
``event``               only the common fields; the payload is ``x``
======================  ==================================================================

Quaternions within ``QUAT_NORM_TOL`` of unit norm are normalised; farther off is an error,
not a repair.  Covariances must be symmetric with a non-negative diagonal, and a received
one positive semi-definite (checked once, at decode: one 6x6 Cholesky).  Messages are
limited to ``MAX_MESSAGE_BYTES`` (images: ``MAX_IMAGE_BYTES``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from operator import itemgetter
from typing import Any

import msgpack
import numpy as np
from pydantic import ValidationError

from schemas.errors import UmaError
from schemas.models import MEASUREMENT_TYPES, ServiceDescriptor, check_plain
from schemas.native import compiled_twin
from schemas.quaternion import QUAT_NORM_TOL, unit_norm

WIRE_VERSION = 1
MAX_MESSAGE_BYTES = 1 << 20
MAX_IMAGE_BYTES = 32 << 20
MAX_POINTS = 40_000
MAX_VALUES = 4096
MAX_MAP_LEN = 1024
MAX_STR_LEN = 1 << 16

_COMMON = frozenset({"v", "k", "t", "s", "x"})
_FIELDS = {
    "pose6d": _COMMON | {"p", "q", "c"},
    "position3d": _COMMON | {"p", "c"},
    "rotation3d": _COMMON | {"q", "c"},
    "points3d": _COMMON | {"P", "i"},
    "markers2d": _COMMON | {"P", "e"},
    "accel_raw": _COMMON | {"a"},
    "image": _COMMON | {"h", "w", "ch", "d"},
    "event": _COMMON,
}
_TRIU = {6: np.triu_indices(6), 3: np.triu_indices(3)}


def _full_index(dim: int) -> np.ndarray:
    """For each entry of a symmetric matrix, its position among the packed upper triangle."""
    index = np.zeros((dim, dim), dtype=np.intp)
    index[_TRIU[dim]] = np.arange(dim * (dim + 1) // 2)
    return np.maximum(index, index.T)


_FULL = {6: _full_index(6), 3: _full_index(3)}
#: Positions of the diagonal among the packed upper triangle.
_DIAG = {dim: tuple(int(_FULL[dim][i, i]) for i in range(dim)) for dim in (6, 3)}
_T_MAX = 1 << 63
#: a covariance may have eigenvalues down to -PSD_TOL x its largest entry (rounding)
PSD_TOL = 1e-9
_EYE = {6: np.eye(6), 3: np.eye(3)}
#: per row of a packed covariance: the position of its variance, a getter of its covariances
_ROWS = {dim: [(int(_FULL[dim][i, i]),
                itemgetter(*(int(_FULL[dim][i, j]) for j in range(dim) if j != i)))
               for i in range(dim)] for dim in (6, 3)}


class DecodeError(UmaError, ValueError):
    """Bytes that are not a valid uma message; the message says why."""


@dataclass(slots=True, eq=False)
class Measurement:
    """One sample of an ability's stream.

    Which fields are set depends on ``type`` (see the module docstring).  ``edge``,
    ``source`` and ``attributes`` are context the receiving SDK fills in from the match;
    ``time_error_ns`` is the bound it gives on the error of ``t_ns`` once moved onto the
    receiving host's clock (0: stamped on that clock).  None of them is on the wire.
    """

    type: str
    t_ns: int
    position: np.ndarray | None = None
    quaternion: np.ndarray | None = None
    covariance: np.ndarray | None = None
    points: np.ndarray | None = None
    values: np.ndarray | None = None
    ids: list[int] | None = None
    seq: int | None = None
    image: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    edge: tuple[str, str] | None = None
    source: str | None = None
    attributes: Any = None
    time_error_ns: int | None = None


# --------------------------------------------------------------------------- covariance packing


def pack_covariance(C: Any, dim: int = 6, name: str = "covariance") -> list[float]:
    """The upper triangle (row by row) of a symmetric ``dim x dim`` covariance.

    ``ValueError`` if it is not finite, not symmetric or has a negative variance.
    """
    a = np.asarray(C, dtype=float)
    if a.shape != (dim, dim):
        raise ValueError(f"{name}: expected shape ({dim}, {dim}), got {a.shape}")
    packed = a[_TRIU[dim]].tolist()
    if not all(map(math.isfinite, packed)):
        raise ValueError(f"{name}: non-finite value")
    scale = max(1.0, max(map(abs, packed)))
    if np.abs(a - a.T).max() > 1e-9 * scale:  # also refuses a non-finite lower triangle
        raise ValueError(f"{name}: not symmetric")
    if min(packed[i] for i in _DIAG[dim]) < 0:
        raise ValueError(f"{name}: negative variance on the diagonal")
    return packed


def unpack_covariance(values: Any, dim: int = 6, name: str = "covariance") -> np.ndarray:
    """Rebuild the symmetric ``dim x dim`` matrix from its upper triangle."""
    v = np.asarray(values, dtype=float)
    n = dim * (dim + 1) // 2
    if v.shape != (n,):
        raise ValueError(f"{name}: expected {n} upper-triangular values, got shape {v.shape}")
    return v[_FULL[dim]]


# --------------------------------------------------------------------------- encoding


def _floats_out(x: Any, n: int, name: str) -> list[float]:
    try:
        values = np.asarray(x, dtype=float).ravel().tolist()
    except (TypeError, ValueError):
        raise ValueError(f"{name}: not numeric") from None
    if len(values) != n:
        raise ValueError(f"{name}: expected {n} numbers, got {len(values)}")
    if not all(map(math.isfinite, values)):
        raise ValueError(f"{name}: non-finite value in {values}")
    return values


def _quat_out(q: Any) -> list[float]:
    v = _floats_out(q, 4, "quaternion")
    n = unit_norm(*v)
    return [v[0] / n, v[1] / n, v[2] / n, v[3] / n]


def _int_out(x: Any, name: str, low: int = 0, high: int = _T_MAX) -> int:
    if isinstance(x, bool) or not isinstance(x, int | np.integer):
        raise ValueError(f"{name}: expected an integer, got {type(x).__name__}")
    x = int(x)
    if not low <= x < high:
        raise ValueError(f"{name}: {x} outside [{low}, {high})")
    return x


def _pack(obj: dict[str, Any]) -> bytes:
    try:
        return msgpack.packb(obj, use_bin_type=True, default=_plain_default)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"cannot encode: {exc}") from None


def _plain_default(obj: Any) -> Any:
    """numpy scalars and arrays become plain msgpack values; anything else is refused."""
    if isinstance(obj, np.generic | np.ndarray):
        return obj.tolist()
    raise TypeError(f"cannot encode a {type(obj).__name__}")


#: ``extra`` key of a pose's systematic covariance: the part of ``c`` that persists from
#: sample to sample (an installation's imperfections), packed as ``c`` is.  Optional:
#: receivers that do not know it ignore it, and its absence means "not known"
SYSTEMATIC_COVARIANCE = "c_sys"


def systematic_covariance(m: Any) -> np.ndarray | None:
    """A received pose's systematic covariance (``SYSTEMATIC_COVARIANCE`` in its extra
    map), None if its tracker sends none; ``DecodeError`` names a malformed or non-finite
    one.  Read by the consumers that hold it apart (the fusion, the alignment), not at
    decode: the decoder checks a pose's own ``c`` only, and leaves ``x`` to its readers."""
    packed = (getattr(m, "extra", None) or {}).get(SYSTEMATIC_COVARIANCE)
    if packed is None:
        return None
    name = f"pose extra {SYSTEMATIC_COVARIANCE!r}"
    try:
        cov = unpack_covariance(packed, 6, name)
    except (TypeError, ValueError) as exc:
        raise DecodeError(f"{name}: expected 21 numbers ({exc})") from None
    if not np.all(np.isfinite(cov)):
        raise DecodeError(f"{name}: non-finite value")
    return cov


#: ``extra`` keys of a ``points3d`` of laser dots: per point, the per-axis in-plane standard
#: deviation (m) of its noise, new in every sample, and of its installation error, which
#: persists.  Optional: a receiver that needs them refuses points without them
DOT_STD = "std_m"
DOT_SYSTEMATIC_STD = "std_sys_m"
#: ``extra`` keys of a ``markers2d``: the camera's id and its calibration's version (a
#: consumer matches the images to the calibration it holds, and refuses others)
MARKERS_CAMERA = "camera"
MARKERS_CALIBRATION = "calibration"


def encode_pose(t_ns: int, position: Any, quaternion: Any, covariance: Any = None,
                seq: int | None = None) -> bytes:
    """A ``pose6d`` message (the hot path: validates, but builds no ``Measurement``).
    Without a covariance, plain floats (lists, tuples, float64 arrays) are encoded by the
    compiled twin ``schemas/_pose.c`` where it was built, to the same bytes."""
    if covariance is None and _NATIVE_ENCODE is not None:
        data = _NATIVE_ENCODE(t_ns, position, quaternion, seq)
        if data is not None:
            return data
    return _encode_pose(t_ns, position, quaternion, covariance, seq)


def _encode_pose(t_ns: int, position: Any, quaternion: Any, covariance: Any,
                 seq: int | None) -> bytes:
    """:func:`encode_pose` in Python: every input it takes, and every refusal's words."""
    msg = {"v": WIRE_VERSION, "k": "pose6d", "t": _int_out(t_ns, "t_ns"),
           "p": _floats_out(position, 3, "position"), "q": _quat_out(quaternion),
           "c": None if covariance is None else pack_covariance(covariance, 6)}
    if seq is not None:
        msg["s"] = _int_out(seq, "seq")
    return _pack(msg)


def encode_measurement(m: Measurement) -> bytes:
    """Any measurement type; ``ValueError`` names the field that is missing or wrong."""
    if m.type not in _FIELDS:
        raise ValueError(f"type: {m.type!r} is not one of {', '.join(MEASUREMENT_TYPES)}")
    msg: dict[str, Any] = {"v": WIRE_VERSION, "k": m.type, "t": _int_out(m.t_ns, "t_ns")}
    if m.seq is not None:
        msg["s"] = _int_out(m.seq, "seq")
    if m.extra:
        if not isinstance(m.extra, dict) or not all(isinstance(k, str) for k in m.extra):
            raise ValueError("extra: expected a dict with string keys")
        check_plain(m.extra, "extra")
        msg["x"] = m.extra
    _ENCODERS[m.type](m, msg)
    return _pack(msg)


def _required(m: Measurement, name: str) -> Any:
    value = getattr(m, name)
    if value is None:
        raise ValueError(f"{name}: required for a {m.type} measurement")
    return value


def _enc_pose6d(m: Measurement, msg: dict[str, Any]) -> None:
    msg["p"] = _floats_out(_required(m, "position"), 3, "position")
    msg["q"] = _quat_out(_required(m, "quaternion"))
    msg["c"] = None if m.covariance is None else pack_covariance(m.covariance, 6)


def _enc_position3d(m: Measurement, msg: dict[str, Any]) -> None:
    msg["p"] = _floats_out(_required(m, "position"), 3, "position")
    msg["c"] = None if m.covariance is None else pack_covariance(m.covariance, 3)


def _enc_rotation3d(m: Measurement, msg: dict[str, Any]) -> None:
    msg["q"] = _quat_out(_required(m, "quaternion"))
    msg["c"] = None if m.covariance is None else pack_covariance(m.covariance, 3)


def _enc_points3d(m: Measurement, msg: dict[str, Any]) -> None:
    pts = np.asarray(_required(m, "points"), dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected shape (n, 3), got {pts.shape}")
    if len(pts) > MAX_POINTS:
        raise ValueError(f"points: {len(pts)} points, more than {MAX_POINTS}")
    if not np.isfinite(pts).all():
        raise ValueError("points: non-finite value")
    msg["P"] = pts.astype("<f8").tobytes()
    if m.ids is None:
        msg["i"] = None
    else:
        if len(m.ids) != len(pts):
            raise ValueError(f"ids: {len(m.ids)} labels for {len(pts)} points")
        msg["i"] = [_int_out(i, "ids", -_T_MAX, _T_MAX) for i in m.ids]


def _enc_markers2d(m: Measurement, msg: dict[str, Any]) -> None:
    uv = np.asarray(_required(m, "points"), dtype=float)
    std = np.asarray(_required(m, "values"), dtype=float)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"points: expected shape (n, 2) of pixels, got {uv.shape}")
    if len(uv) > MAX_POINTS:
        raise ValueError(f"points: {len(uv)} marker images, more than {MAX_POINTS}")
    if std.shape != (len(uv),):
        raise ValueError(f"values: expected {len(uv)} centroid stds, got shape {std.shape}")
    if not (np.isfinite(uv).all() and np.isfinite(std).all()):
        raise ValueError("points: non-finite value")
    if len(std) and std.min() <= 0:
        raise ValueError("values: centroid stds must be > 0")
    msg["P"] = uv.astype("<f8").tobytes()
    msg["e"] = std.astype("<f8").tobytes()


def _enc_accel_raw(m: Measurement, msg: dict[str, Any]) -> None:
    values = np.asarray(_required(m, "values"), dtype=float)
    if values.ndim != 1 or not 0 < len(values) <= MAX_VALUES:
        raise ValueError(f"values: expected 1 to {MAX_VALUES} numbers, got shape {values.shape}")
    msg["a"] = _floats_out(values, len(values), "values")


def _enc_image(m: Measurement, msg: dict[str, Any]) -> None:
    img = np.asarray(_required(m, "image"))
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ValueError(f"image: expected uint8 (h, w) or (h, w, 3), got {img.dtype} "
                         f"{img.shape}")
    if img.nbytes > MAX_IMAGE_BYTES - 1024:
        raise ValueError(f"image: {img.nbytes} bytes, more than {MAX_IMAGE_BYTES - 1024}")
    msg["h"], msg["w"] = int(img.shape[0]), int(img.shape[1])
    msg["ch"] = 1 if img.ndim == 2 else 3
    msg["d"] = np.ascontiguousarray(img).tobytes()


def _enc_event(m: Measurement, msg: dict[str, Any]) -> None:
    """An event is its common fields and ``extra``."""


_ENCODERS = {"pose6d": _enc_pose6d, "position3d": _enc_position3d,
             "rotation3d": _enc_rotation3d, "points3d": _enc_points3d,
             "markers2d": _enc_markers2d, "accel_raw": _enc_accel_raw, "image": _enc_image,
             "event": _enc_event}


# --------------------------------------------------------------------------- decoding


def _unpack(data: Any, max_bytes: int) -> Any:
    if not isinstance(data, bytes | bytearray | memoryview):
        raise DecodeError(f"expected bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise DecodeError(f"message of {len(data)} bytes exceeds the limit of {max_bytes}")
    if not data:
        raise DecodeError("empty message")
    try:
        return msgpack.unpackb(
            data, raw=False, strict_map_key=True, use_list=True,
            max_str_len=MAX_STR_LEN, max_bin_len=max_bytes, max_array_len=3 * MAX_POINTS,
            max_map_len=MAX_MAP_LEN, max_ext_len=0)
    except Exception as exc:  # msgpack raises many types (ValueError, FormatError, ...)
        reason = str(exc) or type(exc).__name__
        raise DecodeError(f"not valid msgpack: {reason}") from None


def _root(obj: Any) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise DecodeError(f"expected a map at the top level, got {type(obj).__name__}")
    v = obj.get("v")
    if type(v) is not int:
        raise DecodeError("missing or non-integer schema version 'v'")
    if v != WIRE_VERSION:
        raise DecodeError(f"unsupported schema version v={v} (this side speaks "
                          f"v={WIRE_VERSION})")
    return obj


def _floats_in(obj: dict[str, Any], key: str, n: int, kind: str) -> list[float]:
    x = obj.get(key)
    if type(x) is not list or len(x) != n:
        got = f"a list of {len(x)}" if type(x) is list else type(x).__name__
        raise DecodeError(f"{kind} field {key!r}: expected {n} numbers, got {got}")
    for value in x:
        t = type(value)
        if t is float:
            if value - value != 0.0:  # inf - inf and nan - nan are nan
                raise DecodeError(f"{kind} field {key!r}: non-finite value {value!r}")
        elif t is not int:
            raise DecodeError(f"{kind} field {key!r}: {t.__name__} is not a number")
    return x


def _int_in(obj: dict[str, Any], key: str, kind: str, low: int = 0,
            high: int = _T_MAX) -> int:
    x = obj.get(key)
    if type(x) is not int:
        raise DecodeError(f"{kind} field {key!r}: expected an integer, got {type(x).__name__}")
    if not low <= x < high:
        raise DecodeError(f"{kind} field {key!r}: {x} outside [{low}, {high})")
    return x


def _quat_in(obj: dict[str, Any], kind: str) -> np.ndarray:
    x, y, z, w = _floats_in(obj, "q", 4, kind)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(n - 1.0) > QUAT_NORM_TOL:
        raise DecodeError(f"{kind} field 'q': quaternion norm {n:.6g} is not 1 "
                          f"(tolerance {QUAT_NORM_TOL:g})")
    return np.array((x / n, y / n, z / n, w / n))


def _cov_in(obj: dict[str, Any], dim: int, kind: str) -> np.ndarray | None:
    if obj.get("c") is None:
        return None
    values = _floats_in(obj, "c", dim * (dim + 1) // 2, kind)
    if min(values[i] for i in _DIAG[dim]) < 0:
        raise DecodeError(f"{kind} field 'c': negative variance on the diagonal")
    cov = np.array(values, dtype=float)[_FULL[dim]]
    _check_psd(values, cov, kind)
    return cov


def _check_psd(values: list[float], cov: np.ndarray, kind: str) -> None:
    """Refuse a covariance that is not positive semi-definite (within ``PSD_TOL`` of its
    largest entry, the tolerance of ``agent.geometry.check_covariance``).

    Cheap first: a diagonally dominant matrix (each variance at least the sum of its row's
    absolute covariances) is positive semi-definite by Gershgorin's theorem, checked in
    plain Python on the packed values; only others pay one Cholesky factorisation of
    ``cov + tol I`` (LAPACK's ``dpotrf`` called directly: a third of the cost of
    ``numpy.linalg.cholesky`` on a 6x6), which exists exactly when the smallest eigenvalue
    is above ``-tol``; the eigenvalues are computed only to say why one is refused.
    """
    tol = PSD_TOL * max(1.0, max(values), -min(values))
    if all(values[d] + tol >= sum(map(abs, off(values))) for d, off in _ROWS[len(cov)]):
        return
    from scipy.linalg.lapack import dpotrf  # here: most processes never get this far

    if dpotrf(cov + tol * _EYE[len(cov)], overwrite_a=True)[1] != 0:
        smallest = float(np.linalg.eigvalsh(cov)[0])
        raise DecodeError(f"{kind} field 'c': covariance not positive semi-definite "
                          f"(smallest eigenvalue {smallest:.3g})")


def _dec_pose6d(obj: dict[str, Any], m: Measurement) -> None:
    m.position = np.array(_floats_in(obj, "p", 3, "pose6d"), dtype=float)
    m.quaternion = _quat_in(obj, "pose6d")
    m.covariance = _cov_in(obj, 6, "pose6d")


def _dec_position3d(obj: dict[str, Any], m: Measurement) -> None:
    m.position = np.array(_floats_in(obj, "p", 3, "position3d"), dtype=float)
    m.covariance = _cov_in(obj, 3, "position3d")


def _dec_rotation3d(obj: dict[str, Any], m: Measurement) -> None:
    m.quaternion = _quat_in(obj, "rotation3d")
    m.covariance = _cov_in(obj, 3, "rotation3d")


def _dec_points3d(obj: dict[str, Any], m: Measurement) -> None:
    raw = obj.get("P")
    if type(raw) is not bytes or len(raw) % 24:
        got = f"{len(raw)} bytes" if type(raw) is bytes else type(raw).__name__
        raise DecodeError(f"points3d field 'P': expected n*24 bytes of float64, got {got}")
    pts = np.frombuffer(raw, dtype="<f8").reshape(-1, 3).astype(float)
    if len(pts) > MAX_POINTS:
        raise DecodeError(f"points3d field 'P': {len(pts)} points, more than {MAX_POINTS}")
    if not np.isfinite(pts).all():
        raise DecodeError("points3d field 'P': non-finite value")
    m.points = pts
    ids = obj.get("i")
    if ids is not None:
        if type(ids) is not list or len(ids) != len(pts):
            raise DecodeError(f"points3d field 'i': expected {len(pts)} integer labels")
        if any(type(i) is not int for i in ids):
            raise DecodeError("points3d field 'i': labels must be integers")
        m.ids = ids


def _dec_markers2d(obj: dict[str, Any], m: Measurement) -> None:
    raw, err = obj.get("P"), obj.get("e")
    if type(raw) is not bytes or len(raw) % 16:
        got = f"{len(raw)} bytes" if type(raw) is bytes else type(raw).__name__
        raise DecodeError(f"markers2d field 'P': expected n*16 bytes of float64, got {got}")
    uv = np.frombuffer(raw, dtype="<f8").reshape(-1, 2).astype(float)
    if len(uv) > MAX_POINTS:
        raise DecodeError(f"markers2d field 'P': {len(uv)} marker images, more than "
                          f"{MAX_POINTS}")
    if type(err) is not bytes or len(err) != 8 * len(uv):
        got = f"{len(err)} bytes" if type(err) is bytes else type(err).__name__
        raise DecodeError(f"markers2d field 'e': expected {8 * len(uv)} bytes of float64, "
                          f"got {got}")
    std = np.frombuffer(err, dtype="<f8").astype(float)
    if not (np.isfinite(uv).all() and np.isfinite(std).all()):
        raise DecodeError("markers2d: non-finite value")
    if len(std) and std.min() <= 0:
        raise DecodeError("markers2d field 'e': centroid stds must be > 0")
    m.points, m.values = uv, std


def _dec_accel_raw(obj: dict[str, Any], m: Measurement) -> None:
    a = obj.get("a")
    n = len(a) if type(a) is list else -1
    if not 0 < n <= MAX_VALUES:
        raise DecodeError(f"accel_raw field 'a': expected 1 to {MAX_VALUES} numbers")
    m.values = np.array(_floats_in(obj, "a", n, "accel_raw"), dtype=float)


def _dec_image(obj: dict[str, Any], m: Measurement) -> None:
    h = _int_in(obj, "h", "image", 1, 1 << 16)
    w = _int_in(obj, "w", "image", 1, 1 << 16)
    ch = _int_in(obj, "ch", "image", 1, 4)
    if ch == 2:
        raise DecodeError("image field 'ch': expected 1 or 3 channels, got 2")
    d = obj.get("d")
    if type(d) is not bytes or len(d) != h * w * ch:
        got = f"{len(d)} bytes" if type(d) is bytes else type(d).__name__
        raise DecodeError(f"image field 'd': expected {h * w * ch} bytes, got {got}")
    img = np.frombuffer(d, dtype=np.uint8)
    m.image = img.reshape(h, w) if ch == 1 else img.reshape(h, w, 3)


def _dec_event(obj: dict[str, Any], m: Measurement) -> None:
    """Nothing beyond the common fields."""


_DECODERS = {"pose6d": _dec_pose6d, "position3d": _dec_position3d,
             "rotation3d": _dec_rotation3d, "points3d": _dec_points3d,
             "markers2d": _dec_markers2d, "accel_raw": _dec_accel_raw, "image": _dec_image,
             "event": _dec_event}


def decode_measurement(data: bytes, expected_type: str | None = None) -> Measurement:
    """Decode and validate one measurement; ``DecodeError`` says what was wrong."""
    limit = MAX_MESSAGE_BYTES if expected_type not in (None, "image") else MAX_IMAGE_BYTES
    obj = _root(_unpack(data, limit))
    kind = obj.get("k")
    if type(kind) is not str or kind not in _FIELDS:
        raise DecodeError(f"field 'k': unknown measurement type {kind!r} (known: "
                          f"{', '.join(MEASUREMENT_TYPES)})")
    if expected_type is not None and kind != expected_type:
        raise DecodeError(f"expected a {expected_type} measurement, got {kind}")
    if kind != "image" and len(data) > MAX_MESSAGE_BYTES:
        raise DecodeError(f"message of {len(data)} bytes exceeds the limit of "
                          f"{MAX_MESSAGE_BYTES}")
    unknown = obj.keys() - _FIELDS[kind]
    if unknown:
        raise DecodeError(f"{kind}: unexpected field(s) {', '.join(sorted(map(str, unknown)))}")
    m = Measurement(kind, _int_in(obj, "t", kind))
    if "s" in obj:
        m.seq = _int_in(obj, "s", kind)
    if "x" in obj:
        m.extra = _extra_in(obj["x"], kind)
    _DECODERS[kind](obj, m)
    return m


#: a decoded ``pose6d``: time (ns), sequence number (None: not sent), position, unit
#: quaternion (x, y, z, w: renormalised as decode_measurement does) and covariance (or None)
PoseSample = tuple[int, int | None, tuple[float, float, float],
                   tuple[float, float, float, float], np.ndarray | None]


def _native_pose() -> Any:
    """The compiled twin of a common ``pose6d``'s decoding and encoding
    (``schemas/_pose.c``), or None (not built, built from older source, or
    ``UMA_CODEC_PURE_PYTHON=1``)."""
    _pose = compiled_twin("schemas._pose", "UMA_CODEC_PURE_PYTHON")
    if _pose is None:
        return None
    _pose.configure(MAX_MESSAGE_BYTES, QUAT_NORM_TOL, PSD_TOL)
    return _pose


_NATIVE: Any = _native_pose()
_NATIVE_POSE: Callable[[bytes], Any] | None = None if _NATIVE is None else _NATIVE.decode
_NATIVE_ENCODE: Callable[..., bytes | None] | None = None if _NATIVE is None else _NATIVE.encode


def decode_pose(data: bytes) -> PoseSample:
    """A ``pose6d`` message as plain values: for whoever puts samples straight into an SRG
    (no ``Measurement``, no arrays but the covariance).  It accepts and refuses exactly
    what ``decode_measurement(data, "pose6d")`` does, with its ``DecodeError``: the common
    message (floats, no extra field, a covariance its Gershgorin test passes) is decoded by
    the compiled twin ``schemas/_pose.c`` where it was built; every other by
    :func:`decode_measurement`, which also words every refusal."""
    if _NATIVE_POSE is not None:
        got = _NATIVE_POSE(data)
        if got is not None:
            t, seq, p, q, c = got
            return t, seq, p, q, None if c is None else np.array(c, dtype=float)[_FULL[6]]
    m = decode_measurement(data, expected_type="pose6d")
    assert m.position is not None and m.quaternion is not None
    return (m.t_ns, m.seq, tuple(m.position.tolist()), tuple(m.quaternion.tolist()),
            m.covariance)


def peek_time(data: bytes, expected_type: str | None = None) -> int:
    """The sample time ``t`` (ns) of an encoded measurement (:func:`peek_time_seq`)."""
    return peek_time_seq(data, expected_type)[0]


def peek_time_seq(data: bytes, expected_type: str | None = None) -> tuple[int, int | None]:
    """The sample time ``t`` (ns) and sequence number ``s`` (None if the publisher sent
    none) of an encoded measurement, without decoding the rest.

    For whoever needs only the time of every sample (the agent measuring a stream's
    latency): the other values are skipped unread, so an image or a point cloud costs
    about what a pose does.  Checks the envelope (``v``, ``k``, ``t``) as
    :func:`decode_measurement` does, not the body; ``DecodeError`` says what was wrong.
    """
    if not isinstance(data, bytes | bytearray | memoryview) or not data:
        raise DecodeError("expected a non-empty message")
    if len(data) > MAX_IMAGE_BYTES:
        raise DecodeError(f"message of {len(data)} bytes exceeds the limit of "
                          f"{MAX_IMAGE_BYTES}")
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=True, max_buffer_size=len(data),
                                max_ext_len=0)
    unpacker.feed(data)
    head: dict[str, Any] = {}
    try:
        for _ in range(unpacker.read_map_header()):
            key = unpacker.unpack()
            if key in ("v", "k", "t", "s"):
                head[key] = unpacker.unpack()
            else:
                unpacker.skip()
    except Exception as exc:  # msgpack raises many types (ValueError, StackError, ...)
        raise DecodeError(f"not a valid msgpack map: {str(exc) or type(exc).__name__}") from None
    _root(head)
    kind = head.get("k")
    if type(kind) is not str or kind not in _FIELDS:
        raise DecodeError(f"field 'k': unknown measurement type {kind!r}")
    if expected_type is not None and kind != expected_type:
        raise DecodeError(f"expected a {expected_type} measurement, got {kind}")
    if kind != "image" and len(data) > MAX_MESSAGE_BYTES:
        raise DecodeError(f"message of {len(data)} bytes exceeds the limit of "
                          f"{MAX_MESSAGE_BYTES}")
    return _int_in(head, "t", kind), _int_in(head, "s", kind) if "s" in head else None


def _extra_in(x: Any, kind: str) -> dict[str, Any]:
    if not isinstance(x, dict):
        raise DecodeError(f"{kind} field 'x': expected a map, got {type(x).__name__}")
    try:
        check_plain(x, "x")
    except ValueError as exc:
        raise DecodeError(f"{kind} field {exc}") from None
    return x


# --------------------------------------------------------------------------- descriptors, messages


def encode_descriptor(desc: ServiceDescriptor) -> bytes:
    """A ``ServiceDescriptor`` as msgpack (its JSON form, so the schema describes it)."""
    if not isinstance(desc, ServiceDescriptor):
        raise ValueError(f"expected a ServiceDescriptor, got {type(desc).__name__}")
    return _pack(desc.model_dump(mode="json"))


def decode_descriptor(data: bytes) -> ServiceDescriptor:
    """Decode and validate a ``ServiceDescriptor``; ``DecodeError`` with a one-line reason."""
    obj = _root(_unpack(data, MAX_MESSAGE_BYTES))
    try:
        return ServiceDescriptor.model_validate(obj)
    except ValidationError as exc:
        raise DecodeError(f"invalid service descriptor: {validation_summary(exc)}") from None


def validation_summary(exc: ValidationError, limit: int = 3) -> str:
    """A pydantic ``ValidationError`` as one line: ``loc: reason; loc: reason``."""
    parts = []
    for err in exc.errors()[:limit]:
        loc = ".".join(str(p) for p in err["loc"]) or "(root)"
        msg = str(err["msg"]).removeprefix("Value error, ").splitlines()[0]
        parts.append(f"{loc}: {msg}")
    more = exc.error_count() - limit
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")


def encode_message(d: dict[str, Any]) -> bytes:
    """A control or query message: a map with string keys; adds ``"v": 1`` if absent."""
    if not isinstance(d, dict) or not all(isinstance(k, str) for k in d):
        raise ValueError("message: expected a dict with string keys")
    out = {"v": WIRE_VERSION, **d}
    if out["v"] != WIRE_VERSION:
        raise ValueError(f"message: schema version v={out['v']!r}, this side speaks "
                         f"v={WIRE_VERSION}")
    data = _pack(out)
    if len(data) > MAX_MESSAGE_BYTES:
        raise ValueError(f"message: {len(data)} bytes, more than {MAX_MESSAGE_BYTES}")
    return data


def decode_message(data: bytes, required: Iterable[str] = ()) -> dict[str, Any]:
    """Decode a control or query message and check that the ``required`` keys are present."""
    obj = _root(_unpack(data, MAX_MESSAGE_BYTES))
    missing = [k for k in required if k not in obj]
    if missing:
        raise DecodeError(f"message lacks field(s) {', '.join(missing)}")
    return obj
