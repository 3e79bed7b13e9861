"""The codec's compiled fast path against a straightforward reference implementation.

`services.bus.codec` validates each message class with one generated function (exact-type
checks, plain-float rotation check) and falls back to its general validators whenever that
function declines, so errors are explained there. Speed must not change a single verdict:
whatever arrives, the codec and the reference below accept the same inputs, build the same
message (same values, same types) and, on a rejection, name the same field. The reference is
the contract read literally: isinstance checks, numpy for the rotation, fields in order.
"""

from __future__ import annotations

import math
import typing
from dataclasses import fields
from typing import Any, get_args, get_origin, get_type_hints

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.bus import codec
from services.bus.errors import ProtocolError
from services.bus.messages import (
    ALL_MESSAGES,
    IDENTITY_R,
    MAX_TEXT,
    ArmDescription,
    ForceSample,
    MaxLen,
    Message,
    OperatorCommand,
    Range,
    RobotState,
    Rotation,
    Size,
    StereoFrame,
)
from tests.bus.test_codec import RZ90, VALID

# --- the reference ------------------------------------------------------------------


def _meta(tp: Any) -> tuple[Any, list[Any]]:
    if get_origin(tp) is typing.Annotated:
        base, *meta = get_args(tp)
        return base, meta
    return tp, []


def _optional(tp: Any) -> tuple[Any, bool]:
    args = get_args(tp)
    if type(None) in args and len(args) == 2:
        return next(a for a in args if a is not type(None)), True
    return tp, False


def _ref_number(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ProtocolError(name, "not a number")
    try:
        f = float(v)
    except OverflowError:
        raise ProtocolError(name, "beyond the float range") from None
    if not math.isfinite(f):
        raise ProtocolError(name, "not finite")
    return f


def _ref_value(name: str, tp: Any, v: Any) -> Any:
    """One field by the contract's words (PROTOCOL.md §3)."""
    base, meta = _meta(tp)
    size_m = next((m for m in meta if isinstance(m, Size)), None)
    size = None if size_m is None else size_m.n
    most = None if size_m is None else size_m.hi
    rng = next((m for m in meta if isinstance(m, Range)), None)
    max_len = next((m.n for m in meta if isinstance(m, MaxLen)), MAX_TEXT)
    if get_origin(base) is typing.Literal:
        if not isinstance(v, str) or v not in get_args(base):
            raise ProtocolError(name, "not allowed")
        return v
    if size is not None:
        if not isinstance(v, list | tuple):
            raise ProtocolError(name, "wrong size")
        if (len(v) != size) if most is None else not size <= len(v) <= most:
            raise ProtocolError(name, "wrong size")
        out = tuple(_ref_number(f"{name}[{i}]", x) for i, x in enumerate(v))
        if any(isinstance(m, Rotation) for m in meta):
            R = np.array(out).reshape(3, 3)
            # numpy warns on subnormal entries too (det divides): the verdict is all we read
            with np.errstate(all="ignore"):
                err = np.linalg.norm(R.T @ R - np.eye(3))
                det = np.linalg.det(R)
            if not err <= 1e-6 or det < 0:
                raise ProtocolError(name, "not a rotation")
        return out
    if base is bool:
        if not isinstance(v, bool):
            raise ProtocolError(name, "not a bool")
        return v
    if base is int:
        lo, hi = (rng.lo, rng.hi) if rng else (-(2**63), 2**64 - 1)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise ProtocolError(name, "not an integer in range")
        return v
    if base is float:
        f = _ref_number(name, v)
        if rng is not None and not rng.lo <= f <= rng.hi:
            raise ProtocolError(name, "out of range")
        return f
    if base is str:
        if not isinstance(v, str) or len(v) > max_len:
            raise ProtocolError(name, "not a string that short")
        return v
    if base is bytes:
        if not isinstance(v, bytes | bytearray) or len(v) > max_len:
            raise ProtocolError(name, "not bytes that short")
        return bytes(v)
    if get_origin(base) is tuple:  # a list of maps (an ArmDescription's joints)
        if not isinstance(v, list | tuple) or len(v) > max_len:
            raise ProtocolError(name, "not a list of maps that short")
        return tuple(_ref_value(f"{name}[{i}]", dict[str, Any], x) for i, x in enumerate(v))
    assert get_origin(base) is dict, base
    if not isinstance(v, dict) or not all(isinstance(k, str) for k in v):
        raise ProtocolError(name, "not a map with string keys")
    return v


def ref_from_fields(cls: type[Message], data: dict[str, Any]) -> Message:
    hints = get_type_hints(cls, include_extras=True)
    values: dict[str, Any] = {}
    for f in fields(cls):
        tp, optional = _optional(hints[f.name])
        v = data.get(f.name)
        if v is None:
            if not optional:
                raise ProtocolError(f.name, "missing or nil")
            values[f.name] = None
        else:
            values[f.name] = _ref_value(f.name, tp, v)
    return cls(**values)


def ref_wire(msg: Message) -> dict[str, Any]:
    hints = get_type_hints(type(msg), include_extras=True)
    out: dict[str, Any] = {}
    for f in fields(msg):
        tp, optional = _optional(hints[f.name])
        v = getattr(msg, f.name)
        if v is None:
            if not optional:
                raise ProtocolError(f.name, "missing")
            continue
        v = _ref_value(f.name, tp, v)
        out[f.name] = list(v) if isinstance(v, tuple) else v
    return out


# --- comparing verdicts ---------------------------------------------------------------


def typed(x: Any) -> Any:
    """A value with its types spelled out, so 1 and 1.0 (or a list and a tuple) differ."""
    if isinstance(x, Message):
        return (type(x), [(f.name, typed(getattr(x, f.name))) for f in fields(x)])
    if isinstance(x, list | tuple):
        return (type(x), [typed(e) for e in x])
    if isinstance(x, float) and math.isnan(x):
        return (float, "nan")
    if isinstance(x, dict):
        return (dict, [(k, typed(v)) for k, v in x.items()])
    return (type(x), x)


def verdict(fn: Any, *args: Any) -> tuple[str, Any]:
    try:
        return ("ok", typed(fn(*args)))
    except ProtocolError as e:
        return ("rejected", e.field)


def near_tolerance(data: dict[str, Any], cls: type[Message]) -> bool:
    """A rotation within rounding of ‖RᵀR − I‖ = 1e-6, where numpy and plain floats may
    legitimately round to different sides."""
    hints = get_type_hints(cls, include_extras=True)
    for f in fields(cls):
        _, meta = _meta(_optional(hints[f.name])[0])
        v = data.get(f.name)
        if any(isinstance(m, Rotation) for m in meta) and isinstance(v, list | tuple):
            try:
                R = np.array([float(x) for x in v], dtype=float).reshape(3, 3)
            except (TypeError, ValueError, OverflowError):
                continue
            with np.errstate(all="ignore"):
                err = float(np.linalg.norm(R.T @ R - np.eye(3)))
            if abs(err - 1e-6) < 1e-12:
                return True
    return False


# --- adversarial values ----------------------------------------------------------------

EXTREME_FLOATS = [1e308, -1e308, 1.7976931348623157e308, 5e-324, -5e-324, 2.2250738585072014e-308]
EXTREME_FLOATS += [-0.0, math.nan, math.inf, -math.inf, 1e-6, 1.0 + 1e-7, 0.999999]
EXTREME_INTS = [2**63 - 1, 2**63, 2**64 - 1, 2**64, -(2**63), -(2**63) - 1, 2**100, -(2**100)]
EXTREME_INTS += [10**400, -(10**400), 10**5000]  # beyond every float, and beyond str()

scalars = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.sampled_from(EXTREME_INTS)
    | st.floats(width=64)
    | st.sampled_from(EXTREME_FLOATS)
    | st.floats(min_value=-1e-300, max_value=1e-300)  # subnormals and their neighbours
    | st.text(max_size=10)
    | st.sampled_from(["world", "tool", "ready", "l", "r", "jpeg", "bgr8", "x" * 129])
    | st.binary(max_size=10)
    | st.builds(bytearray, st.binary(max_size=4))
    | st.builds(np.float64, st.floats(width=64))
)


@st.composite
def rotation_like(draw: st.DrawFn) -> list[Any]:
    """Rotations, nearly-rotations and not-rotations, with extreme entries."""
    angle = draw(st.floats(-math.pi, math.pi))
    c, s = math.cos(angle), math.sin(angle)
    R: list[Any] = [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0]
    how = draw(st.sampled_from(["as is", "perturb", "scale", "reflect", "entry", "int"]))
    if how == "perturb":
        i = draw(st.integers(0, 8))
        R[i] += draw(st.floats(-1e-5, 1e-5))
    elif how == "scale":
        k = draw(st.sampled_from([1e308, 1e-308, 5e-324, 1.0 + 4e-7, 1.0 + 6e-7, 0.0, -1.0]))
        R = [x * k for x in R]
    elif how == "reflect":
        R[8] = -R[8]
    elif how == "entry":
        R[draw(st.integers(0, 8))] = draw(scalars)
    elif how == "int":
        R = [1, 0, 0, 0, 1, 0, 0, 0, 1]
    return R


vectors = (
    st.lists(st.floats(width=64) | st.sampled_from(EXTREME_FLOATS), min_size=2, max_size=10)
    | st.lists(scalars, min_size=3, max_size=9)
    | st.sampled_from([3, 6, 9]).flatmap(
        lambda n: st.lists(st.floats(-2.0, 2.0), min_size=n, max_size=n)
    )
    | rotation_like()
    | st.just([0.0] * 100_000)  # huge list
    | st.just([[0.0], 0.0, 0.0])
)
anything = (
    scalars
    | vectors
    | vectors.map(tuple)
    | st.dictionaries(st.text(max_size=4), scalars, max_size=3)
    | st.dictionaries(st.integers() | st.binary(max_size=3), scalars, min_size=1, max_size=2)
)


@st.composite
def maps(draw: st.DrawFn) -> tuple[type[Message], dict[str, Any]]:
    """A valid map of some class with some fields replaced, removed, nil or added."""
    cls = draw(st.sampled_from(ALL_MESSAGES))
    data = dict(VALID[cls])
    names = sorted(data)
    for name in draw(st.lists(st.sampled_from(names), max_size=3, unique=True)):
        action = draw(st.sampled_from(["replace", "replace", "replace", "delete", "nil"]))
        if action == "replace":
            data[name] = draw(anything)
        elif action == "delete":
            del data[name]
        else:
            data[name] = None
    if draw(st.booleans()):
        data[draw(st.text(max_size=6))] = draw(scalars)
    return cls, data


# --- properties -------------------------------------------------------------------


@given(maps())
@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_codec_and_reference_agree_on_every_map(case: tuple[type[Message], dict[str, Any]]) -> None:
    cls, data = case
    if near_tolerance(data, cls):
        return
    expected = verdict(ref_from_fields, cls, data)
    assert verdict(codec.from_fields, cls, data) == expected
    fast = codec._schema(cls).fast_from(data)
    if fast is not None:  # the fast path only ever accepts what the contract accepts
        assert ("ok", typed(fast)) == expected


@given(maps())
@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_decoding_the_bytes_agrees_with_the_reference(
    case: tuple[type[Message], dict[str, Any]],
) -> None:
    cls, data = case
    try:
        payload = msgpack.packb(data, use_bin_type=True)
        wire = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except (TypeError, ValueError, OverflowError):
        return  # not msgpack (huge ints, numpy scalars, non-string keys): cannot travel
    if near_tolerance(wire, cls):
        return
    assert verdict(codec.decode, cls, payload) == verdict(ref_from_fields, cls, wire)


@given(maps())
@settings(max_examples=800, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_encoding_agrees_with_the_reference(case: tuple[type[Message], dict[str, Any]]) -> None:
    """Dataclasses do not validate: whatever a message holds, encode accepts exactly what the
    reference accepts, and writes the reference's bytes."""
    cls, data = case
    if near_tolerance(data, cls):
        return
    try:
        msg = cls(**{f.name: data.get(f.name) for f in fields(cls)})
    except ProtocolError:
        return  # a class with cross-field rules (ArmDescription) refuses to be built so
    expected = verdict(ref_wire, msg)
    assert verdict(codec.to_fields, msg) == expected
    try:
        ref_payload = msgpack.packb(ref_wire(msg), use_bin_type=True)
    except ProtocolError:
        ref_payload = None
    except (TypeError, ValueError, OverflowError):  # valid, but msgpack cannot carry it
        with pytest.raises(ProtocolError) as info:
            codec.encode(msg)
        assert "cannot be encoded" in info.value.reason
        bad = getattr(msg, info.value.field)
        with pytest.raises((TypeError, ValueError, OverflowError)):
            msgpack.packb(bad, use_bin_type=True)
        return
    assert verdict(codec.encode, msg) == (
        expected if ref_payload is None else ("ok", typed(ref_payload))
    )


@given(R=rotation_like())
@settings(max_examples=300, deadline=None)
def test_plain_float_rotation_defect_matches_numpy(R: list[Any]) -> None:
    try:
        r = tuple(float(x) for x in R)
    except (TypeError, ValueError, OverflowError):
        return
    M = np.array(r).reshape(3, 3)
    with np.errstate(all="ignore"):
        err_np = float(np.linalg.norm(M.T @ M - np.eye(3)))
        det_np = float(np.linalg.det(M))
    err, det = codec.rotation_defect(r)
    if math.isfinite(err_np):
        assert err == pytest.approx(err_np, rel=1e-9, abs=1e-15)
        assert det == pytest.approx(det_np, rel=1e-9, abs=1e-15)
    else:  # numpy's squares overflowed; hypot may not, but it is a rejection either way
        assert not err <= 1e-6


# --- the fast path is the one ordinary traffic takes --------------------------------------


def _floats_only(data: dict[str, Any]) -> dict[str, Any]:
    """VALID with every number in a float field given as a float, as our encoders write it."""
    out = dict(data)
    for k in ("fx", "fy", "cx", "cy", "baseline", "grip", "manipulability", "scale_t", "scale_r"):
        if isinstance(out.get(k), int):
            out[k] = float(out[k])
    return out


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.name)
def test_valid_messages_take_the_fast_path_both_ways(cls: type[Message]) -> None:
    if cls is ArmDescription:
        # sent on change only, and carrying a list of maps the fast path does not compile:
        # the general path checks it (the test above compares it with the reference)
        return
    schema = codec._schema(cls)
    data = _floats_only(VALID[cls])
    msg = schema.fast_from(data)
    assert msg is not None and msg == codec.from_fields(cls, data) == ref_from_fields(cls, data)
    assert schema.fast_to(msg) is not None
    wire = msgpack.packb(data, use_bin_type=True)
    assert codec.decode(cls, wire) == msg and codec.encode(msg) == wire
    without = {k: v for k, v in data.items() if k in {f.name for f in fields(cls)}}
    without = {k: v for k, v in without.items() if k not in {"grip", "raw", "data", "fx"}}
    if cls is not StereoFrame and cls.name not in ("Event", "VisionStats"):
        assert schema.fast_from(without) is not None


def test_foreign_ints_in_float_fields_still_decode_to_floats() -> None:
    """The fast path declines (exact types only); the general path converts, as before."""
    data = {**VALID[ForceSample], "f": [1, 2, 3]}
    assert codec._schema(ForceSample).fast_from(data) is None
    fs = codec.decode(ForceSample, msgpack.packb(data, use_bin_type=True))
    assert fs.f == (1.0, 2.0, 3.0) and all(type(x) is float for x in fs.f)


def test_numpy_floats_in_a_message_encode_as_before() -> None:
    fs = ForceSample(1, 2, tuple(np.float64(x) for x in (1.0, 2.0, 3.0)), (0.0, 0.0, 0.0))
    plain = ForceSample(1, 2, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    assert codec.encode(fs) == codec.encode(plain)


# --- the error messages are the general path's, word for word -----------------------------


def _error(cls: type[Message], **changes: Any) -> str:
    with pytest.raises(ProtocolError) as info:
        codec.decode(cls, msgpack.packb({**VALID[cls], **changes}, use_bin_type=True))
    return str(info.value)


def test_error_messages_are_as_clear_as_ever() -> None:
    bad_R = [1.001, *IDENTITY_R[1:]]
    assert _error(RobotState, tool_R=bad_R) == "tool_R: not a rotation: ‖RᵀR − I‖ = 0.002 > 1e-06"
    q = [0.0, 0.0, 0.0, math.nan, 0.0, 0.0]
    assert _error(RobotState, q=q) == "q[3]: not finite (nan)"
    assert _error(RobotState, flange_R=[*RZ90[:8], -1.0]) == "flange_R: reflection: det R < 0"
    assert _error(OperatorCommand, dp=[0.0, True, 0.0]) == "dp[1]: expected a number, got bool"
    assert _error(OperatorCommand, dp=(0.0,) * 4) == "dp: expected 3 numbers, got 4"
    assert _error(OperatorCommand, master=["m"]) == "master: expected a string, got list"
    assert _error(OperatorCommand, frame="base") == (
        "frame: expected one of ['world', 'tool'], got 'base'"
    )
    assert _error(OperatorCommand, seq=-1) == "seq: -1 out of range [0, 9223372036854775807]"
    assert _error(RobotState, cmd_seq=None) == "cmd_seq: is nil"


def test_ints_beyond_every_float_or_string_are_rejected_cleanly() -> None:
    """Not msgpack (it stops at 64 bits), but from_fields and arg see Python maps."""
    data = {**VALID[ForceSample], "f": [10**400, 0.0, 0.0]}
    with pytest.raises(ProtocolError) as info:
        codec.from_fields(ForceSample, data)
    assert info.value.field == "f[0]" and "not finite" in info.value.reason
    with pytest.raises(ProtocolError) as info:
        codec.from_fields(ForceSample, {**VALID[ForceSample], "seq": 10**5000})
    assert info.value.field == "seq" and "out of range" in info.value.reason
    with pytest.raises(ProtocolError) as info:
        codec.from_fields(OperatorCommand, {**VALID[OperatorCommand], "frame": [10**5000]})
    assert info.value.field == "frame"


def test_a_subnormal_rotation_is_refused_by_both() -> None:
    """Found by hypothesis: numpy's det warned on subnormal entries in the reference."""
    from services.bus.messages import RobotState

    tiny = 5e-324
    fields = {
        "seq": 1, "t_ns": 10, "status": "ready", "q": [0.0, 1.0, -1.0, 0.0, 0.5, 0.0],
        "tool_p": [0.5, 0.0, 0.8], "tool_R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "flange_p": [0.5, 0.0, 1.0],
        "flange_R": [-0.0, -tiny, 0.0, tiny, -0.0, 0.0, 0.0, 0.0, tiny],
        "engage": 1, "cmd_seq": 0,
    }  # fmt: skip
    want = ("rejected", "flange_R")
    assert verdict(ref_from_fields, RobotState, fields) == want
    assert verdict(codec.from_fields, RobotState, fields) == want
