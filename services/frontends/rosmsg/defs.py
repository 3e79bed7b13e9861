"""The type descriptions (REP-2016 `TypeDescription`) of every ROS 2 type we speak.

One place per field list: the hash (`typehash`) is computed from these tables, and the
golden tests check them against the published hashes and an independent message library.
Field type ids are those of type_description_interfaces/msg/FieldType.msg, as listed in
rosidl_generator_type_description (FIELD_TYPE_NAME_TO_ID). Default values are not part of a
description's hash (REP-2016, "Hash Requirements"), so they are not written here.
"""

from __future__ import annotations

from dataclasses import dataclass

# FieldType ids (type_description_interfaces/msg/FieldType.msg)
NESTED = 1
UINT8 = 3
INT32 = 6
UINT32 = 7
DOUBLE = 11
BOOLEAN = 15
STRING = 17
ARRAY_OFFSET = 48
"""A fixed-size array of T has id T + 48 (e.g. FIELD_TYPE_DOUBLE_ARRAY = 59)."""
SEQUENCE_OFFSET = 144
"""An unbounded sequence of T has id T + 144 (e.g. FIELD_TYPE_STRING_UNBOUNDED_SEQUENCE = 161)."""


@dataclass(frozen=True, slots=True)
class Field:
    """One field: name, FieldType id, array size (fixed arrays), nested type name."""

    name: str
    type_id: int
    capacity: int = 0
    string_capacity: int = 0
    nested_type_name: str = ""


@dataclass(frozen=True, slots=True)
class TypeDef:
    """One message type: `pkg/msg/Name` and its fields in declaration order."""

    name: str
    fields: tuple[Field, ...]

    @property
    def dds_name(self) -> str:
        """The DDS type name rmw implementations use (`pkg::msg::dds_::Name_`)."""
        pkg, kind, short = self.name.split("/")
        return f"{pkg}::{kind}::dds_::{short}_"


def _f64(name: str) -> Field:
    return Field(name, DOUBLE)


def _u32(name: str) -> Field:
    return Field(name, UINT32)


def _nested(name: str, type_name: str, sequence: bool = False) -> Field:
    return Field(name, NESTED + (SEQUENCE_OFFSET if sequence else 0), nested_type_name=type_name)


def _seq(name: str, element_id: int) -> Field:
    return Field(name, element_id + SEQUENCE_OFFSET)


TIME = TypeDef("builtin_interfaces/msg/Time", (Field("sec", INT32), _u32("nanosec")))
HEADER = TypeDef("std_msgs/msg/Header", (_nested("stamp", TIME.name), Field("frame_id", STRING)))
STRING_MSG = TypeDef("std_msgs/msg/String", (Field("data", STRING),))
VECTOR3 = TypeDef("geometry_msgs/msg/Vector3", (_f64("x"), _f64("y"), _f64("z")))
POINT = TypeDef("geometry_msgs/msg/Point", (_f64("x"), _f64("y"), _f64("z")))
QUATERNION = TypeDef("geometry_msgs/msg/Quaternion", (_f64("x"), _f64("y"), _f64("z"), _f64("w")))
POSE = TypeDef(
    "geometry_msgs/msg/Pose",
    (_nested("position", POINT.name), _nested("orientation", QUATERNION.name)),
)
POSE_STAMPED = TypeDef(
    "geometry_msgs/msg/PoseStamped", (_nested("header", HEADER.name), _nested("pose", POSE.name))
)
WRENCH = TypeDef(
    "geometry_msgs/msg/Wrench",
    (_nested("force", VECTOR3.name), _nested("torque", VECTOR3.name)),
)
WRENCH_STAMPED = TypeDef(
    "geometry_msgs/msg/WrenchStamped",
    (_nested("header", HEADER.name), _nested("wrench", WRENCH.name)),
)
TRANSFORM = TypeDef(
    "geometry_msgs/msg/Transform",
    (_nested("translation", VECTOR3.name), _nested("rotation", QUATERNION.name)),
)
TRANSFORM_STAMPED = TypeDef(
    "geometry_msgs/msg/TransformStamped",
    (
        _nested("header", HEADER.name),
        Field("child_frame_id", STRING),
        _nested("transform", TRANSFORM.name),
    ),
)
TF_MESSAGE = TypeDef(
    "tf2_msgs/msg/TFMessage", (_nested("transforms", TRANSFORM_STAMPED.name, sequence=True),)
)
JOINT_STATE = TypeDef(
    "sensor_msgs/msg/JointState",
    (
        _nested("header", HEADER.name),
        _seq("name", STRING),
        _seq("position", DOUBLE),
        _seq("velocity", DOUBLE),
        _seq("effort", DOUBLE),
    ),
)
COMPRESSED_IMAGE = TypeDef(
    "sensor_msgs/msg/CompressedImage",
    (_nested("header", HEADER.name), Field("format", STRING), _seq("data", UINT8)),
)
REGION_OF_INTEREST = TypeDef(
    "sensor_msgs/msg/RegionOfInterest",
    (
        _u32("x_offset"),
        _u32("y_offset"),
        _u32("height"),
        _u32("width"),
        Field("do_rectify", BOOLEAN),
    ),
)
CAMERA_INFO = TypeDef(
    "sensor_msgs/msg/CameraInfo",
    (
        _nested("header", HEADER.name),
        _u32("height"),
        _u32("width"),
        Field("distortion_model", STRING),
        _seq("d", DOUBLE),
        Field("k", DOUBLE + ARRAY_OFFSET, capacity=9),
        Field("r", DOUBLE + ARRAY_OFFSET, capacity=9),
        Field("p", DOUBLE + ARRAY_OFFSET, capacity=12),
        _u32("binning_x"),
        _u32("binning_y"),
        _nested("roi", REGION_OF_INTEREST.name),
    ),
)

ALL: tuple[TypeDef, ...] = (
    TIME,
    HEADER,
    STRING_MSG,
    VECTOR3,
    POINT,
    QUATERNION,
    POSE,
    POSE_STAMPED,
    WRENCH,
    WRENCH_STAMPED,
    TRANSFORM,
    TRANSFORM_STAMPED,
    TF_MESSAGE,
    JOINT_STATE,
    COMPRESSED_IMAGE,
    REGION_OF_INTEREST,
    CAMERA_INFO,
)
BY_NAME: dict[str, TypeDef] = {t.name: t for t in ALL}
