"""The codec's round trip and every rejection rule of the wire contract (PROTOCOL.md §3).

Each rejection must be a ProtocolError whose `field` names what is wrong, so an operator
reading the `rejected` event knows which sender to fix. The hypothesis properties are the
safety net: whatever arrives on a key, the codec either returns a valid message or raises
ProtocolError, never anything else (a stray TypeError in a subscriber would be a crash).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import fields
from typing import Any, Literal, TypeVar

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
    ArmDescription,
    ArmTarget,
    Event,
    ForceSample,
    Joints,
    MasterFeedback,
    MasterState,
    Message,
    OperatorCommand,
    PassivityState,
    RobotState,
    Rot,
    StereoFrame,
    Unit,
    Vec3,
    VisionStats,
    mat3,
    vec,
)

M = TypeVar("M", bound=Message)

RZ90 = [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
REFLECTED = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0]
SCALED = [1.001, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
SHEARED = [1.0, 1e-3, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]

# One valid wire map per message, as a peer would send it (lists, every optional present).
VALID: dict[type[Message], dict[str, Any]] = {
    OperatorCommand: {
        "seq": 1,
        "t_ns": 10,
        "master": "m1",
        "engage": 1,
        "active": True,
        "frame": "tool",
        "dp": [0.1, 0.2, 0.3],
        "dR": RZ90,
        "grip": 0.5,
    },
    ArmTarget: {
        "seq": 1,
        "t_ns": 10,
        "origin_t_ns": 7,
        "master": "decision",
        "engage": 1,
        "p": [0.5, 0.0, 0.6],
        "R": RZ90,
        "grip": 0.5,
        "hold": True,
    },
    RobotState: {
        "seq": 1,
        "t_ns": 10,
        "status": "ready",
        "q": [0.0, 1.0, -1.0, 0.0, 0.5, 0.0],
        "tool_p": [0.5, 0.0, 0.8],
        "tool_R": list(IDENTITY_R),
        "flange_p": [0.5, 0.0, 1.0],
        "flange_R": RZ90,
        "engage": 1,
        "cmd_seq": 4,
        "grip": 0.0,
        "manipulability": 0.02,
        "cmd_rx_ns": 11,
        "setpoint_ns": 12,
        "cmd_origin_t_ns": 8,
        "tool_p_cmd": [0.5, 0.0, 0.3],
    },
    ArmDescription: {
        "seq": 1,
        "t_ns": 10,
        "model": "two-link",
        "n": 2,
        "joints": [
            {"name": "j1", "lo": -1.0, "hi": 1.0, "max_speed": 2.0, "max_accel": 5.0},
            {"name": "j2", "lo": -2.0, "hi": 2.0, "max_speed": 3.0, "max_accel": 6.0},
        ],
        "base_frame": "world",
        "flange_frame": "flange",
        "urdf": "<robot name='two-link'/>",
        "eMt": {"p": [0.0, 0.0, 0.1], "R": list(IDENTITY_R)},
        "analytic_ik": False,
        "grip": False,
        "named": {"home": [0.0, 0.5]},
        "reach_m": 0.8,
        "max_target_step_m": 0.05,
        "max_target_step_rad": 0.35,
        "workspace": {"min": [0.0, -0.5, 0.0], "max": [0.8, 0.5, 0.8]},
        "max_tool_speed_m_s": 0.5,
        "max_tool_rot_speed_rad_s": 1.5,
        "packages": {"two_link_description": "/opt/two_link"},
    },
    ForceSample: {
        "seq": 1,
        "t_ns": 10,
        "f": [1.0, 2.0, 3.0],
        "c": [0.1, 0.2, 0.3],
        "raw": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
        "estimate": True,
    },
    Event: {
        "seq": 1,
        "t_ns": 10,
        "source": "arm",
        "kind": "status",
        "message": "ready",
        "data": {"a": 1},
    },
    StereoFrame: {
        "seq": 1,
        "t_ns": 10,
        "eye": "l",
        "width": 2,
        "height": 2,
        "encoding": "bgr8",
        "data": bytes(12),
        "fx": 1.0,
        "fy": 1.0,
        "cx": 1.0,
        "cy": 1.0,
        "baseline": 0.06,
    },
    MasterState: {
        "seq": 1,
        "t_ns": 10,
        "master": "m1",
        "engage": 0,
        "active": False,
        "frame": "world",
        "scale_t": 0.5,
        "scale_r": 1.0,
        "hand_p": [0.0, 0.0, 0.0],
        "hand_R": list(IDENTITY_R),
        "device": "spacemouse",
    },
    VisionStats: {
        "seq": 1,
        "t_ns": 10,
        "fps": 30.0,
        "encode_ms": 3.0,
        "dropped": 0,
        "skew_ms": 0.1,
        "width": 640,
        "height": 480,
        "encoding": "jpeg",
        "data": {"q": 80},
    },
    MasterFeedback: {
        "seq": 1,
        "t_ns": 10,
        "master": "m1",
        "f": [1.0, -2.0, 0.5],
        "c": [0.0, 0.1, 0.0],
        "saturated": False,
        "stale": False,
    },
    PassivityState: {
        "seq": 1,
        "t_ns": 10,
        "master": "m1",
        "engage": 2,
        "side": "master",
        "enabled": True,
        "e_in": 0.5,
        "e_out": 0.25,
        "dissipated_j": 0.125,
        "gain": 3.0,
        "active_steps": 4,
        "asked_n": 8.5,
        "shown_n": 7.25,
        "repaid_j": 0.0625,
        "forgiven_j": 0.03125,
        "rot_e_in": 0.015625,
        "rot_e_out": 0.0078125,
        "rot_dissipated_j": 0.00390625,
        "echo_t_ns": 7,
        "echo_age_ns": 2_000_000,
        "rtt_ms": 201.5,
    },
}

OPTIONAL: dict[type[Message], set[str]] = {
    OperatorCommand: {"grip"},
    ArmTarget: {"grip", "hold"},
    RobotState: {
        "grip",
        "manipulability",
        "cmd_rx_ns",
        "setpoint_ns",
        "cmd_origin_t_ns",
        "tool_p_cmd",
    },
    ArmDescription: {
        "grip",
        "named",
        "reach_m",
        "max_target_step_m",
        "max_target_step_rad",
        "workspace",
        "max_tool_speed_m_s",
        "max_tool_rot_speed_rad_s",
        "packages",
    },
    ForceSample: {"raw", "estimate"},
    Event: {"data"},
    StereoFrame: {"fx", "fy", "cx", "cy", "baseline"},
    MasterState: set(),
    VisionStats: {"data"},
    MasterFeedback: set(),
    PassivityState: {
        "asked_n",
        "shown_n",
        "repaid_j",
        "forgiven_j",
        "rot_e_in",
        "rot_e_out",
        "rot_dissipated_j",
        "echo_t_ns",
        "echo_age_ns",
        "rtt_ms",
    },
}


def _decode_with(cls: type[M], **changes: Any) -> M:
    data = {**VALID[cls], **changes}
    return codec.decode(cls, msgpack.packb(data, use_bin_type=True))


def _rejects(cls: type[Message], field_name: str, **changes: Any) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        _decode_with(cls, **changes)
    assert info.value.field == field_name, str(info.value)
    assert str(info.value).startswith(f"{field_name}: ")
    return info.value


# --- round trip --------------------------------------------------------------------


def test_valid_maps_cover_every_message_and_field() -> None:
    assert set(VALID) == set(ALL_MESSAGES)
    for cls in ALL_MESSAGES:
        assert set(VALID[cls]) == {f.name for f in fields(cls)}, cls.name


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.name)
def test_round_trip_every_message(cls: type[Message]) -> None:
    msg = codec.decode(cls, msgpack.packb(VALID[cls], use_bin_type=True))
    assert codec.decode(cls, codec.encode(msg)) == msg
    assert codec.to_fields(msg) == VALID[cls]


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.name)
def test_round_trip_without_optionals(cls: type[Message]) -> None:
    data = {k: v for k, v in VALID[cls].items() if k not in OPTIONAL[cls]}
    msg = codec.decode(cls, msgpack.packb(data, use_bin_type=True))
    assert all(getattr(msg, k) is None for k in OPTIONAL[cls])
    assert msgpack.unpackb(codec.encode(msg), raw=False) == data


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
vec3 = st.tuples(finite, finite, finite)


@st.composite
def rotations(draw: st.DrawFn) -> tuple[float, ...]:
    """A proper rotation from a random unit quaternion."""
    q = np.array(draw(st.tuples(*[st.floats(-1.0, 1.0)] * 4)))
    n = float(np.linalg.norm(q))
    if n < 1e-3:
        return IDENTITY_R
    w, x, y, z = q / n
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    return vec(R)


@given(
    seq=st.integers(0, 2**63 - 1),
    t_ns=st.integers(0, 2**63 - 1),
    master=st.text(max_size=128),
    engage=st.integers(0, 2**63 - 1),
    active=st.booleans(),
    frame=st.sampled_from(["world", "tool"]),
    dp=vec3,
    dR=rotations(),
    grip=st.none() | st.floats(0.0, 1.0),
)
@settings(max_examples=150, deadline=None)
def test_operator_command_round_trips(
    seq: int,
    t_ns: int,
    master: str,
    engage: int,
    active: bool,
    frame: Literal["world", "tool"],
    dp: tuple[float, ...],
    dR: tuple[float, ...],
    grip: float | None,
) -> None:
    cmd = OperatorCommand(seq, t_ns, master, engage, active, frame, dp, dR, grip)
    assert codec.decode(OperatorCommand, codec.encode(cmd)) == cmd


@given(
    seq=st.integers(0, 2**63 - 1),
    f=vec3,
    c=vec3,
    raw=st.none() | st.tuples(*[finite] * 6),
)
@settings(max_examples=100, deadline=None)
def test_force_sample_round_trips(
    seq: int, f: tuple[float, ...], c: tuple[float, ...], raw: tuple[float, ...] | None
) -> None:
    fs = ForceSample(seq=seq, t_ns=seq, f=f, c=c, raw=raw)
    assert codec.decode(ForceSample, codec.encode(fs)) == fs


def test_numpy_values_encode_as_plain_numbers() -> None:
    assert msgpack.unpackb(codec.pack({"a": np.arange(3.0), "b": np.float32(0.5)})) == {
        "a": [0.0, 1.0, 2.0],
        "b": 0.5,
    }
    assert mat3(RZ90).shape == (3, 3) and vec(mat3(RZ90)) == tuple(RZ90)


# --- rejection: missing, nil, type, size, range, literal -------------------------


REQUIRED = [(cls, name) for cls in ALL_MESSAGES for name in VALID[cls] if name not in OPTIONAL[cls]]


@pytest.mark.parametrize(("cls", "name"), REQUIRED, ids=[f"{c.name}.{n}" for c, n in REQUIRED])
def test_missing_required_field_is_named(cls: type[Message], name: str) -> None:
    data = {k: v for k, v in VALID[cls].items() if k != name}
    with pytest.raises(ProtocolError) as info:
        codec.decode(cls, msgpack.packb(data, use_bin_type=True))
    assert info.value.field == name and info.value.reason == "missing"


@pytest.mark.parametrize(("cls", "name"), REQUIRED, ids=[f"{c.name}.{n}" for c, n in REQUIRED])
def test_nil_required_field_is_named(cls: type[Message], name: str) -> None:
    err = _rejects(cls, name, **{name: None})
    assert err.reason == "is nil"


NAN, INF = float("nan"), float("inf")

# (message, field changed, bad value, the field the error must name)
BAD: list[tuple[type[Message], str, Any, str]] = [
    # wrong type
    (OperatorCommand, "seq", "1", "seq"),
    (OperatorCommand, "seq", True, "seq"),
    (OperatorCommand, "seq", 1.0, "seq"),
    (OperatorCommand, "engage", 2.5, "engage"),
    (OperatorCommand, "master", ["m1"], "master"),
    (OperatorCommand, "master", 7, "master"),
    (OperatorCommand, "master", b"m1", "master"),
    (OperatorCommand, "active", 1, "active"),
    (OperatorCommand, "active", "true", "active"),
    (OperatorCommand, "dp", "0.1,0.2,0.3", "dp"),
    (OperatorCommand, "dp", {"x": 1.0}, "dp"),
    (OperatorCommand, "dp", [0.0, "x", 0.0], "dp[1]"),
    (OperatorCommand, "dp", [0.0, 0.0, True], "dp[2]"),
    (OperatorCommand, "dp", [0.0, None, 0.0], "dp[1]"),
    (OperatorCommand, "dp", [[0.0], 0.0, 0.0], "dp[0]"),
    (OperatorCommand, "grip", "closed", "grip"),
    (OperatorCommand, "grip", True, "grip"),
    (ForceSample, "f", "1 2 3", "f"),
    (ForceSample, "raw", {"a": 1}, "raw"),
    (Event, "kind", 5, "kind"),
    (Event, "message", ["x"], "message"),
    (Event, "data", [1, 2], "data"),
    (Event, "data", "a=1", "data"),
    (StereoFrame, "data", "pixels", "data"),
    (StereoFrame, "data", [1, 2, 3], "data"),
    (StereoFrame, "width", 2.0, "width"),
    (StereoFrame, "fx", "500", "fx"),
    (MasterState, "scale_t", "0.5", "scale_t"),
    (MasterState, "active", 0, "active"),
    (MasterState, "device", None, "device"),
    (VisionStats, "width", 1.5, "width"),
    (VisionStats, "fps", False, "fps"),
    (MasterFeedback, "saturated", 1, "saturated"),
    (MasterFeedback, "stale", None, "stale"),
    # wrong size
    (OperatorCommand, "dp", [0.0, 0.0], "dp"),
    (OperatorCommand, "dp", [0.0, 0.0, 0.0, 0.0], "dp"),
    (OperatorCommand, "dp", [], "dp"),
    (OperatorCommand, "dR", RZ90[:8], "dR"),
    (OperatorCommand, "dR", [*RZ90, 0.0], "dR"),
    (RobotState, "q", [], "q"),
    (RobotState, "q", [0.0] * 33, "q"),
    (RobotState, "tool_R", [1.0, 0.0, 0.0, 1.0], "tool_R"),
    (ForceSample, "raw", [0.0] * 5, "raw"),
    (MasterState, "hand_p", [0.0] * 2, "hand_p"),
    # not finite, in vectors and scalars
    (OperatorCommand, "dp", [NAN, 0.0, 0.0], "dp[0]"),
    (OperatorCommand, "dp", [0.0, INF, 0.0], "dp[1]"),
    (OperatorCommand, "dp", [0.0, 0.0, -INF], "dp[2]"),
    (OperatorCommand, "dR", [NAN, *RZ90[1:]], "dR[0]"),
    (OperatorCommand, "grip", NAN, "grip"),
    (RobotState, "q", [0.0, 0.0, 0.0, 0.0, 0.0, NAN], "q[5]"),
    (RobotState, "tool_p", [INF, 0.0, 0.0], "tool_p[0]"),
    (RobotState, "flange_R", [*RZ90[:4], INF, *RZ90[5:]], "flange_R[4]"),
    (RobotState, "manipulability", NAN, "manipulability"),
    (RobotState, "manipulability", -INF, "manipulability"),
    (ForceSample, "f", [0.0, NAN, 0.0], "f[1]"),
    (ForceSample, "c", [0.0, 0.0, INF], "c[2]"),
    (ForceSample, "raw", [0.0, 0.0, 0.0, 0.0, NAN, 0.0], "raw[4]"),
    (StereoFrame, "fx", NAN, "fx"),
    (StereoFrame, "baseline", INF, "baseline"),
    (MasterState, "scale_t", INF, "scale_t"),
    (MasterState, "scale_r", NAN, "scale_r"),
    (MasterState, "hand_p", [0.0, -INF, 0.0], "hand_p[1]"),
    (VisionStats, "fps", NAN, "fps"),
    (VisionStats, "skew_ms", INF, "skew_ms"),
    (MasterFeedback, "f", [0.0, 0.0, NAN], "f[2]"),
    (MasterFeedback, "c", [INF, 0.0, 0.0], "c[0]"),
    (MasterFeedback, "f", [0.0, 0.0], "f"),
    # not a rotation
    (OperatorCommand, "dR", SCALED, "dR"),
    (OperatorCommand, "dR", SHEARED, "dR"),
    (OperatorCommand, "dR", [0.0] * 9, "dR"),
    (OperatorCommand, "dR", REFLECTED, "dR"),
    (OperatorCommand, "dR", [-x for x in IDENTITY_R], "dR"),
    (RobotState, "tool_R", REFLECTED, "tool_R"),
    (RobotState, "flange_R", SCALED, "flange_R"),
    (MasterState, "hand_R", REFLECTED, "hand_R"),
    # bad Literal
    (OperatorCommand, "frame", "base", "frame"),
    (OperatorCommand, "frame", "World", "frame"),
    (OperatorCommand, "frame", 0, "frame"),
    (RobotState, "status", "flying", "status"),
    (StereoFrame, "eye", "c", "eye"),
    (StereoFrame, "encoding", "png", "encoding"),
    (MasterState, "frame", "wrist", "frame"),
    (VisionStats, "encoding", "h264", "encoding"),
    # out of range
    (OperatorCommand, "grip", 1.5, "grip"),
    (OperatorCommand, "grip", -0.01, "grip"),
    (OperatorCommand, "seq", -1, "seq"),
    (OperatorCommand, "t_ns", -5, "t_ns"),
    (OperatorCommand, "engage", -1, "engage"),
    (OperatorCommand, "seq", 2**64 - 1, "seq"),
    (RobotState, "cmd_seq", -1, "cmd_seq"),
    (RobotState, "grip", 2.0, "grip"),
    (StereoFrame, "width", 0, "width"),
    (StereoFrame, "height", 16385, "height"),
    (VisionStats, "dropped", -1, "dropped"),
    # oversized strings
    (OperatorCommand, "master", "m" * 129, "master"),
    (Event, "source", "s" * 129, "source"),
    (Event, "kind", "k" * 129, "kind"),
    (Event, "message", "x" * 4097, "message"),
    (MasterState, "device", "d" * 129, "device"),
]


@pytest.mark.parametrize(
    ("cls", "name", "value", "named"),
    BAD,
    ids=[f"{c.name}.{n}={v!r:.24}" for c, n, v, _ in BAD],
)
def test_bad_value_is_rejected_naming_the_field(
    cls: type[Message], name: str, value: Any, named: str
) -> None:
    _rejects(cls, named, **{name: value})


def test_rejection_messages_say_what_is_wrong() -> None:
    assert "expected 3 numbers, got 2" in str(_rejects(OperatorCommand, "dp", dp=[0.0, 0.0]))
    assert "not finite" in str(_rejects(ForceSample, "f[0]", f=[NAN, 0.0, 0.0]))
    assert "‖RᵀR − I‖" in str(_rejects(OperatorCommand, "dR", dR=SCALED))
    assert "det R < 0" in str(_rejects(OperatorCommand, "dR", dR=REFLECTED))
    assert "'base'" in str(_rejects(OperatorCommand, "frame", frame="base"))
    assert "out of range" in str(_rejects(OperatorCommand, "grip", grip=1.5))
    assert "expected an integer, got bool" in str(_rejects(OperatorCommand, "seq", seq=True))
    assert "longer than 128" in str(_rejects(OperatorCommand, "master", master="m" * 129))


def test_boundaries_are_accepted() -> None:
    assert _decode_with(OperatorCommand, grip=0.0, seq=0, t_ns=0).seq == 0
    assert _decode_with(OperatorCommand, grip=1, seq=2**63 - 1).grip == 1.0
    assert _decode_with(OperatorCommand, master="m" * 128).master == "m" * 128
    assert len(_decode_with(Event, message="x" * 4096).message) == 4096
    assert _decode_with(StereoFrame, width=16384, height=1).width == 16384


def test_rotation_tolerance_is_1e_6() -> None:
    """‖RᵀR − I‖ ≤ 1e-6 passes (floats that went through a computation), more does not."""
    ok = [1.0 + 2e-7, *IDENTITY_R[1:]]  # ‖RᵀR − I‖ ≈ 4e-7
    bad = [1.0 + 2e-6, *IDENTITY_R[1:]]  # ≈ 4e-6
    assert _decode_with(OperatorCommand, dR=ok).dR[0] == ok[0]
    _rejects(OperatorCommand, "dR", dR=bad)
    codec.check_rotation("R", tuple(RZ90))
    with pytest.raises(ProtocolError):
        codec.check_rotation("R", tuple(bad))
    codec.check_rotation("R", tuple(bad), tol=1e-5)


def test_event_data_with_non_string_keys_is_rejected() -> None:
    with pytest.raises(ProtocolError) as info:
        codec.from_fields(Event, {**VALID[Event], "data": {1: "x"}})
    assert info.value.field == "data"
    # On the wire the unpacker already refuses such a map (strict_map_key).
    payload = msgpack.packb({**VALID[Event], "data": {1: "x"}}, use_bin_type=True)
    with pytest.raises(ProtocolError) as info:
        codec.decode(Event, payload)
    assert info.value.field == "payload"


# --- rejection: the payload itself ---------------------------------------------------


@pytest.mark.parametrize(
    "obj", [[1, 2, 3], 5, "robot", None, True, 1.5, b"\x00"], ids=lambda o: type(o).__name__
)
def test_non_map_payload_is_rejected(obj: Any) -> None:
    with pytest.raises(ProtocolError) as info:
        codec.decode(ForceSample, msgpack.packb(obj, use_bin_type=True))
    assert info.value.field == "payload" and "expected a msgpack map" in info.value.reason


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"\xc1",  # the one byte msgpack never uses
        b"hello world",  # a fixint followed by extra data
        b'{"seq": 1}',  # JSON is not msgpack
        b"\x81\xa3seq",  # a map with a key and no value
        b"\xa5ab",  # a str that claims 5 bytes and has 2
        b"\x81\xa1\xff\x01",  # invalid UTF-8 in a key
        msgpack.packb({1: 2}),  # non-string map key
        b"\x91" * 5000 + b"\xc0",  # nested 5000 deep
    ],
    ids=["empty", "c1", "text", "json", "no-value", "short-str", "bad-utf8", "int-key", "deep"],
)
def test_garbage_bytes_are_rejected_as_payload(payload: bytes) -> None:
    with pytest.raises(ProtocolError) as info:
        codec.decode(OperatorCommand, payload)
    assert info.value.field == "payload"


def test_every_truncation_of_a_message_is_rejected() -> None:
    full = msgpack.packb(VALID[RobotState], use_bin_type=True)
    for n in range(len(full)):
        with pytest.raises(ProtocolError) as info:
            codec.decode(RobotState, full[:n])
        assert info.value.field == "payload", n
    with pytest.raises(ProtocolError):
        codec.decode(RobotState, full + b"\x00")  # trailing bytes are not one message either


def test_encode_validates_too() -> None:
    """Nothing that breaks the contract leaves a process of ours."""
    bad = ForceSample(seq=1, t_ns=1, f=(NAN, 0.0, 0.0), c=(0.0, 0.0, 0.0))
    with pytest.raises(ProtocolError) as info:
        codec.encode(bad)
    assert info.value.field == "f[0]"
    # Dataclasses do not validate on construction; the codec does, on the way out.
    cmd = OperatorCommand(1, 1, "m", 1, True, "base", (0.0, 0.0, 0.0), IDENTITY_R)  # type: ignore[arg-type]
    with pytest.raises(ProtocolError) as info:
        codec.encode(cmd)
    assert info.value.field == "frame"
    with pytest.raises(ProtocolError) as info:
        codec.encode(OperatorCommand(1, 1, "m", 1, True, "tool", (0.0, 0.0, 0.0), tuple(REFLECTED)))
    assert info.value.field == "dR"


# --- properties: nothing but ProtocolError, whatever arrives ---------------------------

msgpack_scalars = (
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats(width=64)
    | st.text(max_size=20)
    | st.binary(max_size=20)
)
msgpack_values = st.recursive(
    msgpack_scalars,
    lambda inner: (
        st.lists(inner, max_size=10) | st.dictionaries(st.text(max_size=8), inner, max_size=8)
    ),
    max_leaves=40,
)


@given(st.binary(max_size=200))
@settings(max_examples=300, deadline=None)
def test_random_bytes_raise_only_protocol_error(payload: bytes) -> None:
    for cls in ALL_MESSAGES:
        with contextlib.suppress(ProtocolError):
            codec.decode(cls, payload)


@given(msgpack_values)
@settings(max_examples=300, deadline=None)
def test_random_msgpack_structures_raise_only_protocol_error(obj: Any) -> None:
    payload = msgpack.packb(obj, use_bin_type=True)
    for cls in ALL_MESSAGES:
        with contextlib.suppress(ProtocolError):
            codec.decode(cls, payload)


@given(
    cls=st.sampled_from(ALL_MESSAGES),
    data=st.data(),
    value=msgpack_values,
)
@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_one_field_replaced_by_anything_decodes_validly_or_names_it(
    cls: type[Message], data: st.DataObject, value: Any
) -> None:
    """A valid message with one field swapped for any msgpack value: either it still
    meets the contract (and re-encodes to the same map) or the error names that field."""
    name = data.draw(st.sampled_from(sorted(VALID[cls])))
    payload = msgpack.packb({**VALID[cls], name: value}, use_bin_type=True)
    try:
        msg = codec.decode(cls, payload)
    except ProtocolError as e:
        head = e.field.split(".")[0].split("[")[0]
        # an ArmDescription's cross-field rules (n joints, n-joint named configurations)
        # name the field they read the mismatch in
        crossed = cls is ArmDescription and {head, name} <= {"n", "joints", "named"}
        assert head == name or crossed, (e.field, name)
        return
    # Compared as bytes: free-form `data` maps may carry NaN, which is never == itself.
    wire = codec.encode(msg)
    assert codec.encode(codec.decode(cls, wire)) == wire


@given(
    index=st.integers(0, 2),
    bad=st.sampled_from([NAN, INF, -INF]),
    good=vec3,
    name=st.sampled_from(["f", "c"]),
)
@settings(max_examples=100, deadline=None)
def test_any_non_finite_force_is_rejected(
    index: int, bad: float, good: tuple[float, ...], name: str
) -> None:
    """Safety: a force with a NaN or inf anywhere never reaches a supervisor."""
    v = list(good)
    v[index] = bad
    with pytest.raises(ProtocolError) as info:
        _decode_with(ForceSample, **{name: v})
    assert info.value.field == f"{name}[{index}]"


@given(
    R=rotations(),
    index=st.integers(0, 8),
    eps=st.floats(1e-5, 10.0) | st.floats(-10.0, -1e-5),
)
@settings(max_examples=200, deadline=None)
def test_proper_rotations_pass_and_perturbed_or_reflected_ones_do_not(
    R: tuple[float, ...], index: int, eps: float
) -> None:
    """Safety: only proper rotations command the arm (‖RᵀR − I‖ ≤ 1e-6, det R > 0)."""
    assert _decode_with(OperatorCommand, dR=list(R)).dR == R
    _rejects(OperatorCommand, "dR", dR=[-x for x in R])
    bent = list(R)
    bent[index] += eps
    _rejects(OperatorCommand, "dR", dR=bent)


@given(dp=st.lists(finite, min_size=0, max_size=8).filter(lambda v: len(v) != 3))
@settings(max_examples=50, deadline=None)
def test_any_wrong_length_dp_is_rejected(dp: list[float]) -> None:
    err = _rejects(OperatorCommand, "dp", dp=dp)
    assert f"got {len(dp)}" in err.reason


# --- method arguments: codec.arg ----------------------------------------------------


def test_arg_validates_with_the_same_rules() -> None:
    args = {
        "q": [0, 1, 2, 3, 4, 5],
        "p": [0.5, 0, 1],
        "R": RZ90,
        "speed": 1,
        "frame": "wrist",
        "name": "demo",
    }
    assert codec.arg(args, "q", Joints) == (0.0, 1.0, 2.0, 3.0, 4.0, 5.0)
    assert codec.arg(args, "p", Vec3) == (0.5, 0.0, 1.0)
    assert codec.arg(args, "R", Rot) == tuple(RZ90)
    assert codec.arg(args, "speed", Unit) == 1.0
    assert codec.arg(args, "frame", Literal["world", "wrist", "tool"]) == "wrist"
    assert codec.arg(args, "name", str) == "demo"
    assert codec.arg(args, "R", Rot | None) == tuple(RZ90)


def test_arg_missing_uses_default_or_names_it() -> None:
    assert codec.arg({}, "speed", Unit, 0.5) == 0.5
    assert codec.arg({"speed": None}, "speed", Unit, 0.25) == 0.25
    assert codec.arg({}, "config", str | None, None) is None
    with pytest.raises(ProtocolError) as info:
        codec.arg({}, "q", Joints)
    assert info.value.field == "q" and info.value.reason == "missing"


@pytest.mark.parametrize(
    ("name", "value", "annotation", "named"),
    [
        ("q", [], Joints, "q"),
        ("q", [0.0, 0.0, NAN, 0.0, 0.0, 0.0], Joints, "q[2]"),
        ("p", "here", Vec3, "p"),
        ("R", REFLECTED, Rot, "R"),
        ("R", SCALED, Rot, "R"),
        ("speed", 1.5, Unit, "speed"),
        ("speed", True, Unit, "speed"),
        ("frame", "base", Literal["world", "wrist", "tool"], "frame"),
        ("count", 1.0, int, "count"),
        ("wait", "yes", bool, "wait"),
        ("name", ["a"], str, "name"),
        ("name", "n" * 5000, str, "name"),
        ("period_ms", INF, float, "period_ms"),
    ],
)
def test_arg_rejects_naming_the_argument(
    name: str, value: Any, annotation: Any, named: str
) -> None:
    with pytest.raises(ProtocolError) as info:
        codec.arg({name: value}, name, annotation)
    assert info.value.field == named


# --- people's view ------------------------------------------------------------------


def test_jsonable_summarizes_bytes_and_non_finite() -> None:
    frame = codec.decode(StereoFrame, msgpack.packb(VALID[StereoFrame], use_bin_type=True))
    view = codec.jsonable(frame)
    assert view["data"] == "<12 bytes>" and view["width"] == 2 and view["eye"] == "l"
    assert codec.jsonable({"x": [math.inf, 1.0], "b": b"abc"}) == {
        "x": ["inf", 1.0],
        "b": "<3 bytes>",
    }
