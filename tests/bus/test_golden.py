"""Golden bytes: one fixed sample of every message, pinned byte for byte (PROTOCOL.md §3).

A change to these bytes is a change of the wire contract: every peer in the field (other
languages, recordings, the zenoh CLI) would read it differently. If a test here fails, the
codec changed the contract; fix the codec, or version the contract on purpose.

The second half plays a peer that speaks the contract but is not ours: it builds its maps
with plain msgpack, sends ints where floats are allowed, adds fields we do not know and
leaves optional fields out or nil. Ours must decode all of it.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import msgpack
import pytest

from services.bus import codec
from services.bus.messages import (
    ALL_MESSAGES,
    IDENTITY_R,
    ArmDescription,
    ArmTarget,
    Event,
    ForceSample,
    MasterFeedback,
    MasterState,
    Message,
    OperatorCommand,
    PassivityState,
    RobotState,
    StereoFrame,
    VisionStats,
)

RZ90 = (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)

# One sample per message. Values are exact in binary (or fixed decimals) so the bytes are
# the same on every platform; the hex below is the contract's encoding of each.
GOLDEN: list[tuple[Message, str]] = [
    (
        OperatorCommand(
            seq=42,
            t_ns=1_700_000_000_123_456_789,
            master="spacemouse-1",
            engage=3,
            active=True,
            frame="tool",
            dp=(0.01, -0.02, 0.5),
            dR=RZ90,
            grip=0.25,
        ),
        "89a37365712aa4745f6e73cf17979cfe3d85cd15a66d6173746572ac73706163656d6f7573652d31a665"
        "6e6761676503a6616374697665c3a56672616d65a4746f6f6ca2647093cb3f847ae147ae147bcbbf947a"
        "e147ae147bcb3fe0000000000000a2645299cb0000000000000000cbbff0000000000000cb0000000000"
        "000000cb3ff0000000000000cb0000000000000000cb0000000000000000cb0000000000000000cb0000"
        "000000000000cb3ff0000000000000a467726970cb3fd0000000000000",
    ),
    (
        ArmTarget(
            seq=43,
            t_ns=1_700_000_000_123_457_789,
            origin_t_ns=1_700_000_000_123_456_789,
            master="decision",
            engage=5,
            p=(0.5, -0.125, 0.625),
            R=RZ90,
            grip=0.25,
        ),
        "88a37365712ba4745f6e73cf17979cfe3d85d0fdab6f726967696e5f745f6e73cf17979cfe3d85cd15a6"
        "6d6173746572a86465636973696f6ea6656e6761676505a17093cb3fe0000000000000cbbfc000000000"
        "0000cb3fe4000000000000a15299cb0000000000000000cbbff0000000000000cb0000000000000000cb"
        "3ff0000000000000cb0000000000000000cb0000000000000000cb0000000000000000cb000000000000"
        "0000cb3ff0000000000000a467726970cb3fd0000000000000",
    ),
    (
        RobotState(
            seq=7,
            t_ns=1_700_000_000_000_000_001,
            status="ready",
            q=(0.0, 1.5, -1.5, 0.0, 0.25, -0.125),
            tool_p=(0.5, 0.25, 0.75),
            tool_R=IDENTITY_R,
            flange_p=(0.5, 0.25, 0.95),
            flange_R=RZ90,
            engage=2,
            cmd_seq=41,
            grip=1.0,
            manipulability=0.0625,
        ),
        "8ca373657107a4745f6e73cf17979cfe362a0001a6737461747573a57265616479a17196cb0000000000"
        "000000cb3ff8000000000000cbbff8000000000000cb0000000000000000cb3fd0000000000000cbbfc0"
        "000000000000a6746f6f6c5f7093cb3fe0000000000000cb3fd0000000000000cb3fe8000000000000a6"
        "746f6f6c5f5299cb3ff0000000000000cb0000000000000000cb0000000000000000cb00000000000000"
        "00cb3ff0000000000000cb0000000000000000cb0000000000000000cb0000000000000000cb3ff00000"
        "00000000a8666c616e67655f7093cb3fe0000000000000cb3fd0000000000000cb3fee666666666666a8"
        "666c616e67655f5299cb0000000000000000cbbff0000000000000cb0000000000000000cb3ff0000000"
        "000000cb0000000000000000cb0000000000000000cb0000000000000000cb0000000000000000cb3ff0"
        "000000000000a6656e6761676502a7636d645f73657129a467726970cb3ff0000000000000ae6d616e69"
        "70756c6162696c697479cb3fb0000000000000",
    ),
    (
        ArmDescription(
            seq=2,
            t_ns=1_700_000_000_000_000_002,
            model="two-link",
            n=2,
            joints=(
                {"name": "j1", "lo": -1.5, "hi": 1.5, "max_speed": 2.0, "max_accel": 8.0},
                {"name": "j2", "lo": -2.5, "hi": 2.5, "max_speed": 3.0, "max_accel": 16.0},
            ),
            base_frame="world",
            flange_frame="flange",
            urdf="<robot name='two-link'/>",
            eMt={"p": [0.0, 0.0, 0.125], "R": list(IDENTITY_R)},
            analytic_ik=False,
        ),
        "8aa373657102a4745f6e73cf17979cfe362a0002a56d6f64656ca874776f2d6c696e6ba16e02a66a6f69"
        "6e74739285a46e616d65a26a31a26c6fcbbff8000000000000a26869cb3ff8000000000000a96d61785f"
        "7370656564cb4000000000000000a96d61785f616363656ccb402000000000000085a46e616d65a26a32"
        "a26c6fcbc004000000000000a26869cb4004000000000000a96d61785f7370656564cb40080000000000"
        "00a96d61785f616363656ccb4030000000000000aa626173655f6672616d65a5776f726c64ac666c616e"
        "67655f6672616d65a6666c616e6765a475726466b83c726f626f74206e616d653d2774776f2d6c696e6b"
        "272f3ea3654d7482a17093cb0000000000000000cb0000000000000000cb3fc0000000000000a15299cb"
        "3ff0000000000000cb0000000000000000cb0000000000000000cb0000000000000000cb3ff000000000"
        "0000cb0000000000000000cb0000000000000000cb0000000000000000cb3ff0000000000000ab616e61"
        "6c797469635f696bc2",
    ),
    (
        ForceSample(
            seq=1000,
            t_ns=1_700_000_000_000_001_000,
            f=(1.5, -2.25, 9.81),
            c=(0.0, 0.125, -0.5),
            raw=(1.0, 2.0, 3.0, 4.0, 5.0, 6.0),
        ),
        "85a3736571cd03e8a4745f6e73cf17979cfe362a03e8a16693cb3ff8000000000000cbc0020000000000"
        "00cb40239eb851eb851fa16393cb0000000000000000cb3fc0000000000000cbbfe0000000000000a372"
        "617796cb3ff0000000000000cb4000000000000000cb4008000000000000cb4010000000000000cb4014"
        "000000000000cb4018000000000000",
    ),
    (
        Event(
            seq=5,
            t_ns=1_700_000_000_000_000_005,
            source="arm",
            kind="status",
            message="ready → moving",
            data={"from": "ready", "to": "moving", "n": 2},
        ),
        "86a373657105a4745f6e73cf17979cfe362a0005a6736f75726365a361726da46b696e64a673746174"
        "7573a76d657373616765b0726561647920e28692206d6f76696e67a46461746183a466726f6da5726561"
        "6479a2746fa66d6f76696e67a16e02",
    ),
    (
        StereoFrame(
            seq=12,
            t_ns=1_700_000_000_000_000_012,
            eye="l",
            width=4,
            height=2,
            encoding="bgr8",
            data=bytes(range(24)),
            fx=500.0,
            fy=500.0,
            cx=2.0,
            cy=1.0,
            baseline=0.065,
        ),
        "8ca37365710ca4745f6e73cf17979cfe362a000ca3657965a16ca5776964746804a668656967687402a8"
        "656e636f64696e67a462677238a464617461c418000102030405060708090a0b0c0d0e0f101112131415"
        "1617a26678cb407f400000000000a26679cb407f400000000000a26378cb4000000000000000a26379cb"
        "3ff0000000000000a8626173656c696e65cb3fb0a3d70a3d70a4",
    ),
    (
        MasterState(
            seq=99,
            t_ns=1_700_000_000_000_000_099,
            master="arm-7",
            engage=4,
            active=False,
            frame="world",
            scale_t=0.5,
            scale_r=1.0,
            hand_p=(0.1, 0.2, 0.3),
            hand_R=RZ90,
            device="serial:/dev/ttyUSB0",
        ),
        "8ba373657163a4745f6e73cf17979cfe362a0063a66d6173746572a561726d2d37a6656e6761676504a6"
        "616374697665c2a56672616d65a5776f726c64a77363616c655f74cb3fe0000000000000a77363616c65"
        "5f72cb3ff0000000000000a668616e645f7093cb3fb999999999999acb3fc999999999999acb3fd33333"
        "33333333a668616e645f5299cb0000000000000000cbbff0000000000000cb0000000000000000cb3ff0"
        "000000000000cb0000000000000000cb0000000000000000cb0000000000000000cb0000000000000000"
        "cb3ff0000000000000a6646576696365b373657269616c3a2f6465762f74747955534230",
    ),
    (
        VisionStats(
            seq=3,
            t_ns=1_700_000_000_000_000_003,
            fps=30.0,
            encode_ms=4.5,
            dropped=1,
            skew_ms=0.25,
            width=640,
            height=480,
            encoding="jpeg",
            data={"quality": 80},
        ),
        "8aa373657103a4745f6e73cf17979cfe362a0003a3667073cb403e000000000000a9656e636f64655f6d"
        "73cb4012000000000000a764726f7070656401a7736b65775f6d73cb3fd0000000000000a57769647468"
        "cd0280a6686569676874cd01e0a8656e636f64696e67a46a706567a46461746181a77175616c69747950",
    ),
    (
        MasterFeedback(
            seq=250,
            t_ns=1_700_000_000_000_000_250,
            master="arm-7",
            f=(0.5, -1.25, 2.0),
            c=(0.0, 0.125, 0.0),
            saturated=True,
            stale=False,
        ),
        "87a3736571ccfaa4745f6e73cf17979cfe362a00faa66d6173746572a561726d2d37a16693cb3fe00000"
        "00000000cbbff4000000000000cb4000000000000000a16393cb0000000000000000cb3fc00000000000"
        "00cb0000000000000000a9736174757261746564c3a57374616c65c2",
    ),
    (
        PassivityState(
            seq=42,
            t_ns=1_700_000_000_000_000_042,
            master="arm-7",
            engage=3,
            side="slave",
            enabled=True,
            e_in=0.25,
            e_out=0.125,
            dissipated_j=0.0625,
            gain=0.5,
            active_steps=7,
        ),
        "8ba37365712aa4745f6e73cf17979cfe362a002aa66d6173746572a561726d2d37a6656e6761676503a4"
        "73696465a5736c617665a7656e61626c6564c3a4655f696ecb3fd0000000000000a5655f6f7574cb3fc0"
        "000000000000ac646973736970617465645f6acb3fb0000000000000a46761696ecb3fe0000000000000"
        "ac6163746976655f737465707307",
    ),
]

IDS = [type(m).__name__ for m, _ in GOLDEN]


def test_every_message_has_a_golden_sample() -> None:
    assert sorted(type(m).__name__ for m, _ in GOLDEN) == sorted(c.name for c in ALL_MESSAGES)


@pytest.mark.parametrize(("msg", "hex_bytes"), GOLDEN, ids=IDS)
def test_encode_gives_the_golden_bytes(msg: Message, hex_bytes: str) -> None:
    assert codec.encode(msg).hex() == hex_bytes


@pytest.mark.parametrize(("msg", "hex_bytes"), GOLDEN, ids=IDS)
def test_golden_bytes_decode_to_the_sample(msg: Message, hex_bytes: str) -> None:
    assert codec.decode(type(msg), bytes.fromhex(hex_bytes)) == msg


@pytest.mark.parametrize(("msg", "hex_bytes"), GOLDEN, ids=IDS)
def test_golden_bytes_are_plain_msgpack_maps_in_field_order(msg: Message, hex_bytes: str) -> None:
    """The bytes are what any msgpack library makes of the documented map: string keys,
    float64 for every float, bin for bytes, fields in the contract's order, None left out."""
    data = msgpack.unpackb(bytes.fromhex(hex_bytes), raw=False)
    assert isinstance(data, dict)
    assert list(data) == list(codec.to_fields(msg))
    assert msgpack.packb(data, use_bin_type=True).hex() == hex_bytes


@pytest.mark.parametrize(("msg", "hex_bytes"), GOLDEN, ids=IDS)
def test_golden_bytes_take_the_codec_fast_path(msg: Message, hex_bytes: str) -> None:
    """Our own traffic is what the compiled validators accept without the general path
    (but the arm's description, sent on change only: its list of maps is the general
    path's to check)."""
    if isinstance(msg, ArmDescription):
        assert codec.decode(ArmDescription, bytes.fromhex(hex_bytes)) == msg
        return
    schema = codec._schema(type(msg))
    assert schema.fast_from(msgpack.unpackb(bytes.fromhex(hex_bytes), raw=False)) == msg
    assert schema.fast_to(msg) is not None


def test_extension_timing_fields_follow_the_contract_fields_in_order() -> None:
    """docs/protocol-extensions.md: the optional timing fields, as any msgpack writes them."""
    tgt = GOLDEN[1][0]
    assert isinstance(tgt, ArmTarget)
    held = ArmTarget(**{**_fields(tgt), "hold": True})
    expected = {**codec.to_fields(tgt), "hold": True}
    assert codec.encode(held) == msgpack.packb(expected, use_bin_type=True)
    state = GOLDEN[2][0]
    assert isinstance(state, RobotState)
    timing = {
        "cmd_rx_ns": 2**63 - 1,
        "setpoint_ns": 0,
        "cmd_origin_t_ns": 17,
        "tool_p_cmd": (0.5, -0.25, 0.125),
    }
    timed = RobotState(**{**_fields(state), **timing})
    assert codec.encode(timed) == msgpack.packb(
        {**codec.to_fields(state), **timing}, use_bin_type=True
    )
    assert codec.decode(RobotState, codec.encode(timed)) == timed


def _fields(msg: Message) -> dict[str, Any]:
    return {f.name: getattr(msg, f.name) for f in fields(msg)}


def test_optional_none_fields_are_left_out() -> None:
    f = ForceSample(seq=1, t_ns=2, f=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0))
    assert msgpack.unpackb(codec.encode(f), raw=False) == {
        "seq": 1,
        "t_ns": 2,
        "f": [0.0, 0.0, 0.0],
        "c": [0.0, 0.0, 0.0],
    }


# --- a foreign peer: plain msgpack, ints for floats, unknown fields, absent/nil optionals ---


def _foreign(fields: dict[str, Any]) -> bytes:
    """A payload as another implementation would build it (no use of our codec)."""
    return msgpack.packb(fields, use_bin_type=True)


def test_foreign_operator_command_with_ints_extras_and_nil_grip() -> None:
    payload = _foreign(
        {
            "zz_vendor": {"firmware": "2.1", "temp_c": 31},
            "dR": [1, 0, 0, 0, 1, 0, 0, 0, 1],
            "dp": [0, 1, -2],
            "frame": "world",
            "active": False,
            "engage": 0,
            "master": "haptic-x",
            "t_ns": 123,
            "seq": 0,
            "grip": None,
            "unknown_list": [1, 2, 3],
        }
    )
    cmd = codec.decode(OperatorCommand, payload)
    assert cmd == OperatorCommand(
        seq=0,
        t_ns=123,
        master="haptic-x",
        engage=0,
        active=False,
        frame="world",
        dp=(0.0, 1.0, -2.0),
        dR=IDENTITY_R,
        grip=None,
    )
    assert all(isinstance(x, float) for x in cmd.dp + cmd.dR)


def test_foreign_robot_state_without_optionals() -> None:
    payload = _foreign(
        {
            "seq": 1,
            "t_ns": 2,
            "status": "moving",
            "q": [0, 0, 0, 0, 0, 0],
            "tool_p": [1, 2, 3],
            "tool_R": list(IDENTITY_R),
            "flange_p": [1, 2, 3.5],
            "flange_R": list(IDENTITY_R),
            "engage": 1,
            "cmd_seq": 9,
            "extra": "ignored",
        }
    )
    s = codec.decode(RobotState, payload)
    assert s.grip is None and s.manipulability is None
    assert s.q == (0.0,) * 6 and s.flange_p == (1.0, 2.0, 3.5)
    assert s.status == "moving" and s.cmd_seq == 9


def test_foreign_force_sample_with_int_scalars_and_raw() -> None:
    payload = _foreign(
        {"seq": 5, "t_ns": 6, "f": [1, 2, 3], "c": [0, 0, 1], "raw": [1, 2, 3, 4, 5, 6], "x": 1}
    )
    assert codec.decode(ForceSample, payload) == ForceSample(
        seq=5, t_ns=6, f=(1.0, 2.0, 3.0), c=(0.0, 0.0, 1.0), raw=(1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
    )


def test_foreign_event_with_new_kind_and_nil_data() -> None:
    payload = _foreign(
        {"seq": 1, "t_ns": 1, "source": "script", "kind": "calibrated", "message": "", "data": None}
    )
    ev = codec.decode(Event, payload)
    assert ev.kind == "calibrated" and ev.data is None and ev.message == ""


def test_foreign_stereo_frame_with_int_intrinsics() -> None:
    payload = _foreign(
        {
            "seq": 3,
            "t_ns": 4,
            "eye": "r",
            "width": 2,
            "height": 1,
            "encoding": "jpeg",
            "data": b"\xff\xd8\xff",
            "fx": 500,
            "cx": 1,
            "exposure_us": 800,
        }
    )
    fr = codec.decode(StereoFrame, payload)
    assert fr.fx == 500.0 and isinstance(fr.fx, float) and fr.cx == 1.0
    assert fr.fy is None and fr.cy is None and fr.baseline is None
    assert fr.data == b"\xff\xd8\xff"


def test_foreign_master_state_with_int_scales() -> None:
    payload = _foreign(
        {
            "seq": 1,
            "t_ns": 1,
            "master": "m",
            "engage": 0,
            "active": True,
            "frame": "tool",
            "scale_t": 1,
            "scale_r": 2,
            "hand_p": [0, 0, 0],
            "hand_R": [0, -1, 0, 1, 0, 0, 0, 0, 1],
            "device": "script",
            "buttons": [True, False],
        }
    )
    ms = codec.decode(MasterState, payload)
    assert ms.scale_t == 1.0 and ms.scale_r == 2.0 and ms.hand_R == RZ90


def test_foreign_vision_stats_with_int_rates() -> None:
    payload = _foreign(
        {
            "seq": 1,
            "t_ns": 1,
            "fps": 30,
            "encode_ms": 4,
            "dropped": 0,
            "skew_ms": 0,
            "width": 640,
            "height": 480,
            "encoding": "bgr8",
        }
    )
    vs = codec.decode(VisionStats, payload)
    assert vs.fps == 30.0 and vs.data is None


def test_foreign_master_feedback_with_int_wrench() -> None:
    payload = _foreign(
        {
            "seq": 1,
            "t_ns": 1,
            "master": "arm-7",
            "f": [1, 0, 0],
            "c": [0, 0, 0],
            "saturated": False,
            "stale": True,
            "gain": 0.5,
        }
    )
    fb = codec.decode(MasterFeedback, payload)
    assert fb.f == (1.0, 0.0, 0.0) and fb.stale is True and fb.saturated is False


def test_foreign_str8_and_bin_forms_decode_too() -> None:
    """A writer that uses str8 for short keys (not fixstr) and nil for an optional field is
    still speaking the contract."""
    packer = msgpack.Packer(use_bin_type=True)
    parts = [
        b"\x85",
        packer.pack("seq"),
        packer.pack(1),
        packer.pack("t_ns"),
        packer.pack(1),
        # "f" as str8 (0xd9) rather than fixstr
        b"\xd9\x01f",
        packer.pack([1.0, 2.0, 3.0]),
        packer.pack("c"),
        packer.pack([0.0, 0.0, 0.0]),
        packer.pack("raw"),
        b"\xc0",
    ]
    fs = codec.decode(ForceSample, b"".join(parts))
    assert fs.f == (1.0, 2.0, 3.0) and fs.raw is None
