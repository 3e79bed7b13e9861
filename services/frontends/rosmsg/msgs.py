"""The ROS 2 messages we bridge, as frozen dataclasses, with CDR encode and bounded decode.

Nested geometry is flattened into tuples: a Vector3 or Point is `(x, y, z)`, a Quaternion
`(x, y, z, w)` (ROS order, w last). `encode(msg)` gives the bytes an rmw publishes (with the
encapsulation header); `decode(cls, data)` refuses anything malformed, over its bounds, or
(for the geometry) not finite, with a `CdrError` that says why. The field order of each
encoder is the order of its description in `defs`; the golden tests check both against an
independent library.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar, cast

from services.frontends.rosmsg import defs
from services.frontends.rosmsg.cdr import CdrError, Reader, Writer, finite
from services.geometry import V3

QuatXyzw = tuple[float, float, float, float]
"""A ROS quaternion (x, y, z, w), w last; `services.geometry.Quat` is scalar first."""

MAX_FRAME_ID = 256
"""Characters in a frame id or another short name."""
MAX_JOINTS = 64
MAX_TRANSFORMS = 256
MAX_TEXT = 1 << 20
"""A std_msgs/String (a URDF is ~10 kB)."""
MAX_IMAGE_BYTES = 64 << 20
MAX_SMALL_MESSAGE = 4096
"""Bytes of any message without a sequence of images or text in it."""


@dataclass(frozen=True, slots=True)
class Header:
    """std_msgs/Header: stamp (sec, nanosec) and frame_id."""

    sec: int
    nanosec: int
    frame_id: str

    @classmethod
    def at(cls, t_ns: int, frame_id: str) -> Header:
        """The header of a message stamped `t_ns` (ns since the epoch)."""
        sec, nanosec = divmod(t_ns, 1_000_000_000)
        return cls(sec, nanosec, frame_id)

    @property
    def t_ns(self) -> int:
        return self.sec * 1_000_000_000 + self.nanosec


@dataclass(frozen=True, slots=True)
class JointState:
    TYPE: ClassVar[defs.TypeDef] = defs.JOINT_STATE
    header: Header
    name: tuple[str, ...]
    position: tuple[float, ...]
    velocity: tuple[float, ...] = ()
    effort: tuple[float, ...] = ()


@dataclass(frozen=True, slots=True)
class WrenchStamped:
    TYPE: ClassVar[defs.TypeDef] = defs.WRENCH_STAMPED
    header: Header
    force: V3
    torque: V3


@dataclass(frozen=True, slots=True)
class TransformStamped:
    TYPE: ClassVar[defs.TypeDef] = defs.TRANSFORM_STAMPED
    header: Header
    child_frame_id: str
    translation: V3
    rotation: QuatXyzw


@dataclass(frozen=True, slots=True)
class TFMessage:
    TYPE: ClassVar[defs.TypeDef] = defs.TF_MESSAGE
    transforms: tuple[TransformStamped, ...]


@dataclass(frozen=True, slots=True)
class String:
    TYPE: ClassVar[defs.TypeDef] = defs.STRING_MSG
    data: str


@dataclass(frozen=True, slots=True)
class CompressedImage:
    TYPE: ClassVar[defs.TypeDef] = defs.COMPRESSED_IMAGE
    header: Header
    format: str
    data: bytes = field(repr=False)


@dataclass(frozen=True, slots=True)
class RegionOfInterest:
    x_offset: int = 0
    y_offset: int = 0
    height: int = 0
    width: int = 0
    do_rectify: bool = False


@dataclass(frozen=True, slots=True)
class CameraInfo:
    TYPE: ClassVar[defs.TypeDef] = defs.CAMERA_INFO
    header: Header
    height: int
    width: int
    distortion_model: str
    d: tuple[float, ...]
    k: tuple[float, ...]
    r: tuple[float, ...]
    p: tuple[float, ...]
    binning_x: int = 0
    binning_y: int = 0
    roi: RegionOfInterest = RegionOfInterest()


@dataclass(frozen=True, slots=True)
class PoseStamped:
    TYPE: ClassVar[defs.TypeDef] = defs.POSE_STAMPED
    header: Header
    position: V3
    orientation: QuatXyzw


# --- encoding -------------------------------------------------------------------------
def _header(w: Writer, h: Header) -> None:
    w.time(h.sec, h.nanosec)
    w.string(h.frame_id)


def _vec(w: Writer, v: tuple[float, ...]) -> None:
    w.f64s(v)


def _joint_state(w: Writer, m: JointState) -> None:
    _header(w, m.header)
    w.string_seq(m.name)
    w.f64_seq(m.position)
    w.f64_seq(m.velocity)
    w.f64_seq(m.effort)


def _wrench(w: Writer, m: WrenchStamped) -> None:
    _header(w, m.header)
    _vec(w, m.force)
    _vec(w, m.torque)


def _transform(w: Writer, t: TransformStamped) -> None:
    _header(w, t.header)
    w.string(t.child_frame_id)
    _vec(w, t.translation)
    _vec(w, t.rotation)


def _tf(w: Writer, m: TFMessage) -> None:
    w.u32(len(m.transforms))
    for t in m.transforms:
        _transform(w, t)


def _string(w: Writer, m: String) -> None:
    w.string(m.data)


def _compressed(w: Writer, m: CompressedImage) -> None:
    _header(w, m.header)
    w.string(m.format)
    w.octets(m.data)


def _camera_info(w: Writer, m: CameraInfo) -> None:
    _header(w, m.header)
    w.u32(m.height)
    w.u32(m.width)
    w.string(m.distortion_model)
    w.f64_seq(m.d)
    w.f64s(m.k)
    w.f64s(m.r)
    w.f64s(m.p)
    w.u32(m.binning_x)
    w.u32(m.binning_y)
    w.u32(m.roi.x_offset)
    w.u32(m.roi.y_offset)
    w.u32(m.roi.height)
    w.u32(m.roi.width)
    w.boolean(m.roi.do_rectify)


def _pose(w: Writer, m: PoseStamped) -> None:
    _header(w, m.header)
    _vec(w, m.position)
    _vec(w, m.orientation)


_ENCODERS: dict[type, Callable[[Writer, Any], None]] = {
    JointState: _joint_state,
    WrenchStamped: _wrench,
    TransformStamped: _transform,
    TFMessage: _tf,
    String: _string,
    CompressedImage: _compressed,
    CameraInfo: _camera_info,
    PoseStamped: _pose,
}


def encode(msg: Any) -> bytes:
    """The CDR bytes (encapsulation header first) of one of the messages above."""
    w = Writer()
    _ENCODERS[type(msg)](w, msg)
    return w.bytes()


# --- decoding -------------------------------------------------------------------------
def _r_header(r: Reader) -> Header:
    sec, nanosec = r.time()
    return Header(sec, nanosec, r.string(MAX_FRAME_ID, "header.frame_id"))


def _r_finite(r: Reader, n: int, name: str) -> tuple[float, ...]:
    v = r.f64s(n)
    finite(name, *v)
    return v


def _r_vec3(r: Reader, name: str) -> V3:
    return cast(V3, _r_finite(r, 3, name))


def _r_quat(r: Reader, name: str) -> QuatXyzw:
    return cast(QuatXyzw, _r_finite(r, 4, name))


def _r_joint_state(r: Reader) -> JointState:
    h = _r_header(r)
    names = r.string_seq(MAX_JOINTS, MAX_FRAME_ID, "name")
    return JointState(
        h,
        names,
        r.f64_seq(MAX_JOINTS, "position"),
        r.f64_seq(MAX_JOINTS, "velocity"),
        r.f64_seq(MAX_JOINTS, "effort"),
    )


def _r_wrench(r: Reader) -> WrenchStamped:
    return WrenchStamped(_r_header(r), _r_vec3(r, "force"), _r_vec3(r, "torque"))


def _r_transform(r: Reader) -> TransformStamped:
    h = _r_header(r)
    child = r.string(MAX_FRAME_ID, "child_frame_id")
    return TransformStamped(h, child, _r_vec3(r, "translation"), _r_quat(r, "rotation"))


def _r_tf(r: Reader) -> TFMessage:
    n = r.count(MAX_TRANSFORMS, "transforms")
    return TFMessage(tuple(_r_transform(r) for _ in range(n)))


def _r_string(r: Reader) -> String:
    return String(r.string(MAX_TEXT, "data"))


def _r_compressed(r: Reader) -> CompressedImage:
    h = _r_header(r)
    fmt = r.string(MAX_FRAME_ID, "format")
    return CompressedImage(h, fmt, r.octets(MAX_IMAGE_BYTES, "data"))


def _r_camera_info(r: Reader) -> CameraInfo:
    h = _r_header(r)
    height, width = r.u32(), r.u32()
    model = r.string(MAX_FRAME_ID, "distortion_model")
    d = r.f64_seq(64, "d")
    k, rr, p = r.f64s(9), r.f64s(9), r.f64s(12)
    bx, by = r.u32(), r.u32()
    roi = RegionOfInterest(r.u32(), r.u32(), r.u32(), r.u32(), r.boolean())
    return CameraInfo(h, height, width, model, d, k, rr, p, bx, by, roi)


def _r_pose(r: Reader) -> PoseStamped:
    return PoseStamped(_r_header(r), _r_vec3(r, "position"), _r_quat(r, "orientation"))


_DECODERS: dict[type, tuple[Callable[[Reader], Any], int]] = {
    JointState: (_r_joint_state, 64 * 1024),
    WrenchStamped: (_r_wrench, MAX_SMALL_MESSAGE),
    TransformStamped: (_r_transform, MAX_SMALL_MESSAGE),
    TFMessage: (_r_tf, MAX_TRANSFORMS * 1024),
    String: (_r_string, MAX_TEXT + 64),
    CompressedImage: (_r_compressed, MAX_IMAGE_BYTES + 1024),
    CameraInfo: (_r_camera_info, MAX_SMALL_MESSAGE),
    PoseStamped: (_r_pose, MAX_SMALL_MESSAGE),
}

M = TypeVar("M")


def decode(cls: type[M], data: bytes | bytearray | memoryview) -> M:
    """Decode `data` as `cls`; CdrError if it is malformed, too large, or not finite."""
    read, max_bytes = _DECODERS[cls]
    r = Reader(data, max_bytes)
    msg: M = read(r)
    r.end()
    return msg


__all__ = [
    "CameraInfo",
    "CdrError",
    "CompressedImage",
    "Header",
    "JointState",
    "PoseStamped",
    "RegionOfInterest",
    "String",
    "TFMessage",
    "TransformStamped",
    "WrenchStamped",
    "decode",
    "encode",
]
