"""Our CDR bytes against rosbags (an independent, pure-Python ROS 2 CDR implementation).

For random messages of every type: rosbags decodes our bytes to the same values, rosbags'
own serialization is byte-identical to ours, and our decoder reads rosbags' bytes back.
Then the decoder's refusals: truncation, lying lengths, bad header, NaN, oversize.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore

from services.frontends.rosmsg import msgs
from services.frontends.rosmsg.cdr import CdrError

STORE = get_typestore(Stores.ROS2_KILTED)
T = STORE.types

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
names = st.text(alphabet=st.characters(codec="utf-8", exclude_characters="\x00"), max_size=12)
u32 = st.integers(0, 2**32 - 1)
headers = st.builds(
    msgs.Header,
    st.integers(-(2**31), 2**31 - 1),
    st.integers(0, 999_999_999),
    names,
)
vec3 = st.tuples(finite, finite, finite)
quat = st.tuples(finite, finite, finite, finite)
floats = st.lists(finite, max_size=7).map(tuple)


def _rb_header(h: msgs.Header) -> Any:
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=h.sec, nanosec=h.nanosec), frame_id=h.frame_id
    )


def _v3(v: tuple[float, ...]) -> Any:
    return T["geometry_msgs/msg/Vector3"](x=v[0], y=v[1], z=v[2])


def _q(q: tuple[float, ...]) -> Any:
    return T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])


def _f64(v: tuple[float, ...]) -> Any:
    return np.array(v, dtype=np.float64)


def _transform(t: msgs.TransformStamped) -> Any:
    return T["geometry_msgs/msg/TransformStamped"](
        header=_rb_header(t.header),
        child_frame_id=t.child_frame_id,
        transform=T["geometry_msgs/msg/Transform"](
            translation=_v3(t.translation), rotation=_q(t.rotation)
        ),
    )


def to_rosbags(m: Any) -> Any:
    """The same message as a rosbags object."""
    if isinstance(m, msgs.JointState):
        return T["sensor_msgs/msg/JointState"](
            header=_rb_header(m.header),
            name=list(m.name),
            position=_f64(m.position),
            velocity=_f64(m.velocity),
            effort=_f64(m.effort),
        )
    if isinstance(m, msgs.WrenchStamped):
        return T["geometry_msgs/msg/WrenchStamped"](
            header=_rb_header(m.header),
            wrench=T["geometry_msgs/msg/Wrench"](force=_v3(m.force), torque=_v3(m.torque)),
        )
    if isinstance(m, msgs.TFMessage):
        return T["tf2_msgs/msg/TFMessage"](transforms=[_transform(t) for t in m.transforms])
    if isinstance(m, msgs.String):
        return T["std_msgs/msg/String"](data=m.data)
    if isinstance(m, msgs.CompressedImage):
        return T["sensor_msgs/msg/CompressedImage"](
            header=_rb_header(m.header),
            format=m.format,
            data=np.frombuffer(m.data, dtype=np.uint8),
        )
    if isinstance(m, msgs.CameraInfo):
        roi = m.roi
        return T["sensor_msgs/msg/CameraInfo"](
            header=_rb_header(m.header),
            height=m.height,
            width=m.width,
            distortion_model=m.distortion_model,
            d=_f64(m.d),
            k=_f64(m.k),
            r=_f64(m.r),
            p=_f64(m.p),
            binning_x=m.binning_x,
            binning_y=m.binning_y,
            roi=T["sensor_msgs/msg/RegionOfInterest"](
                x_offset=roi.x_offset,
                y_offset=roi.y_offset,
                height=roi.height,
                width=roi.width,
                do_rectify=roi.do_rectify,
            ),
        )
    if isinstance(m, msgs.PoseStamped):
        p = m.position
        return T["geometry_msgs/msg/PoseStamped"](
            header=_rb_header(m.header),
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                orientation=_q(m.orientation),
            ),
        )
    raise TypeError(type(m))


transforms = st.builds(msgs.TransformStamped, headers, names, vec3, quat)
messages = st.one_of(
    st.builds(
        msgs.JointState, headers, st.lists(names, max_size=6).map(tuple), floats, floats, floats
    ),
    st.builds(msgs.WrenchStamped, headers, vec3, vec3),
    st.builds(msgs.TFMessage, st.lists(transforms, max_size=4).map(tuple)),
    st.builds(
        msgs.String, st.text(alphabet=st.characters(codec="utf-8", exclude_characters="\x00"))
    ),
    st.builds(msgs.CompressedImage, headers, names, st.binary(max_size=300)),
    st.builds(
        msgs.CameraInfo,
        headers,
        u32,
        u32,
        names,
        floats,
        st.tuples(*[finite] * 9),
        st.tuples(*[finite] * 9),
        st.tuples(*[finite] * 12),
        u32,
        u32,
        st.builds(msgs.RegionOfInterest, u32, u32, u32, u32, st.booleans()),
    ),
    st.builds(msgs.PoseStamped, headers, vec3, quat),
)


@settings(max_examples=300, deadline=None)
@given(messages)
def test_bytes_equal_rosbags_and_round_trip(m: Any) -> None:
    ours = msgs.encode(m)
    theirs = STORE.serialize_cdr(to_rosbags(m), m.TYPE.name)
    assert ours == theirs
    assert msgs.decode(type(m), theirs) == m
    back = STORE.deserialize_cdr(ours, m.TYPE.name)
    assert STORE.serialize_cdr(back, m.TYPE.name) == ours


def test_golden_bytes_of_a_wrench() -> None:
    """Pinned bytes: header, stamp, frame id with its NUL and padding to 8, six doubles."""
    m = msgs.WrenchStamped(msgs.Header(1, 2, "tool"), (1.0, 2.0, 3.0), (0.5, 0.25, 0.125))
    expected = (
        b"\x00\x01\x00\x00"
        + struct.pack("<iI", 1, 2)
        + struct.pack("<I", 5)
        + b"tool\x00"
        + b"\x00" * 7
        + struct.pack("<6d", 1.0, 2.0, 3.0, 0.5, 0.25, 0.125)
    )
    assert msgs.encode(m) == expected


def _pose_bytes(**kw: Any) -> bytes:
    m = msgs.PoseStamped(msgs.Header(0, 0, "world"), (0.5, 0.0, 0.6), (0.0, 0.0, 0.0, 1.0))
    return msgs.encode(msgs.PoseStamped(**{**{f: getattr(m, f) for f in m.__slots__}, **kw}))


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (b"", "shorter than the encapsulation header"),
        (b"\x00\x00\x00\x00" + _pose_bytes()[4:], "not plain CDR little-endian"),
        (_pose_bytes()[:-1], "truncated"),
        (_pose_bytes() + b"\x00" * 8, "trailing"),
        (_pose_bytes(position=(math.nan, 0.0, 0.0)), "not finite"),
        (_pose_bytes(orientation=(0.0, 0.0, math.inf, 1.0)), "not finite"),
        (_pose_bytes(header=msgs.Header(0, 0, "w" * 300)), "exceed the bound"),
        (b"\x00\x01\x00\x00" + struct.pack("<iII", 0, 0, 0xFFFFFFFF), "exceed the bound"),
        (b"\x00\x01\x00\x00" + b"\x00" * 8000, "exceeds the"),
        (b"\x00\x01\x00\x00" + struct.pack("<iII", 0, 2_000_000_000, 1), "nanosec"),
    ],
)
def test_decoder_refuses(data: bytes, why: str) -> None:
    with pytest.raises(CdrError, match=why):
        msgs.decode(msgs.PoseStamped, data)


def test_decoder_refuses_lying_counts_and_bad_text() -> None:
    h = msgs.Header(0, 0, "x")
    js = bytearray(msgs.encode(msgs.JointState(h, ("a",), (1.0,))))
    js[20:24] = struct.pack("<I", 1_000_000)  # the name count, after the 2-char frame id
    with pytest.raises(CdrError, match="exceed the bound"):
        msgs.decode(msgs.JointState, bytes(js))
    bad = bytearray(msgs.encode(msgs.String("abc")))
    bad[8] = 0xFF
    with pytest.raises(CdrError, match="UTF-8"):
        msgs.decode(msgs.String, bytes(bad))
    unterminated = bytearray(msgs.encode(msgs.String("abc")))
    unterminated[11] = ord("d")
    with pytest.raises(CdrError, match="NUL"):
        msgs.decode(msgs.String, bytes(unterminated))


def test_a_character_utf8_cannot_carry_is_written_as_a_question_mark() -> None:
    """A lone surrogate (what `os.fsdecode` makes of undecodable bytes) in a string: the
    writer sends `?` in its place rather than failing (found by hypothesis in CI, 2026-11-26)."""
    data = msgs.encode(msgs.String("a\ud800b"))
    assert data == msgs.encode(msgs.String("a?b"))
    assert msgs.decode(msgs.String, data) == msgs.String("a?b")
