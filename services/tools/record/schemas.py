"""What a recording holds: the channel layout, JSON Schemas and the JSON views of messages.

Every bus key gets two MCAP channels (docs/record.md, "File layout"):

- the view, topic = the key (`robot/state`), `json` message encoding with a `jsonschema`
  schema generated from the message dataclass (bytes as base64), or `foxglove.CompressedImage`
  / `foxglove.RawImage` for stereo frames, so Foxglove plots and shows video;
- the raw channel, topic = `/raw/` + key, `msgpack` message encoding, no schema: the exact
  payload received, which replay republishes byte for byte. A Zenoh key never starts with
  `/`, so a raw topic never collides with a view topic.

The schema of a contract message is derived from the same annotations the codec validates
against (`services/bus/messages.py`), so a field is still declared once.
"""

from __future__ import annotations

import base64
import json
import math
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any, get_args, get_origin, get_type_hints

import zenoh

from services.bus import codec, keys
from services.bus.errors import ConfigError, ProtocolError
from services.bus.messages import MaxLen, Message, Range, Rotation, Size, StereoFrame

RAW_PREFIX = "/raw/"
RAW_ENCODING = "msgpack"
VIEW_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
SCHEMA_PREFIX = "telerobot."
COMPRESSED_IMAGE = "foxglove.CompressedImage"
RAW_IMAGE = "foxglove.RawImage"
#: channel metadata `role` values
ROLE_VIEW = "view"
ROLE_RAW = "raw"

#: Foxglove's `time` (sec, nsec), shared by every schema that carries a timestamp
TIME_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}

_IMAGE_STAMP: dict[str, Any] = {
    "timestamp": {**TIME_SCHEMA, "description": "Timestamp of image"},
    "frame_id": {"type": "string", "description": "Frame of reference for the image"},
}
"""The fields every Foxglove image schema starts with."""

#: Foxglove's CompressedImage, as JSON Schema (foxglove/schemas, jsonschema/CompressedImage.json)
COMPRESSED_IMAGE_SCHEMA: dict[str, Any] = {
    "title": COMPRESSED_IMAGE,
    "description": "A compressed image",
    "type": "object",
    "properties": {
        **_IMAGE_STAMP,
        "data": {
            "type": "string",
            "contentEncoding": "base64",
            "description": "Compressed image data",
        },
        "format": {"type": "string", "description": "Image format"},
    },
}

#: Foxglove's RawImage (for `bgr8` stereo frames)
RAW_IMAGE_SCHEMA: dict[str, Any] = {
    "title": RAW_IMAGE,
    "description": "A raw image",
    "type": "object",
    "properties": {
        **_IMAGE_STAMP,
        "width": {"type": "integer", "minimum": 0},
        "height": {"type": "integer", "minimum": 0},
        "encoding": {"type": "string", "description": "Encoding of the raw image data"},
        "step": {"type": "integer", "minimum": 0, "description": "Byte length of one row"},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}


@dataclass(frozen=True, slots=True)
class View:
    """The JSON view of one payload: schema name ("" = schemaless JSON), the document, and
    the sender's `t_ns` when the payload carries one."""

    schema: str
    document: dict[str, Any]
    t_ns: int | None


def raw_topic(key: str) -> str:
    """The MCAP topic of the raw (msgpack) channel of `key`."""
    return RAW_PREFIX + key


def is_ros_copy(key: str) -> bool:
    """A key of the ROS 2 view (`telerobot ros2`, rmw_zenoh: `<domain id>/<topic>/<type>/
    <hash>`): copies of the cell's own streams, which a recording of everything leaves out
    unless asked (`--ros`)."""
    head = key.split("/", 1)[0]
    return head.isdigit() or head == "@ros2_lv"


def is_video(key: str) -> bool:
    """Stereo frames (the only streams `--no-video` leaves out)."""
    topic = keys.topic_for(key)
    return topic is not None and topic.type is StereoFrame


def schema_name(key: str, encoding: str | None = None) -> str:
    """The schema name of the view channel of a contract key ("" for others)."""
    topic = keys.topic_for(key)
    if topic is None:
        return ""
    if topic.type is StereoFrame:
        return RAW_IMAGE if encoding == "bgr8" else COMPRESSED_IMAGE
    return SCHEMA_PREFIX + topic.type.name


def json_schema(name: str) -> dict[str, Any]:
    """The JSON Schema registered under `name` (see `schema_name`)."""
    if name == COMPRESSED_IMAGE:
        return COMPRESSED_IMAGE_SCHEMA
    if name == RAW_IMAGE:
        return RAW_IMAGE_SCHEMA
    for topic in keys.TOPICS:
        if SCHEMA_PREFIX + topic.type.name == name:
            return message_schema(topic.type)
    raise KeyError(name)


def message_schema(cls: type[Message]) -> dict[str, Any]:
    """JSON Schema of a contract message, from its dataclass annotations.

    Sizes become minItems/maxItems, `Range` minimum/maximum, `MaxLen` maxLength, `Literal`
    an enum, bytes a base64 string; optional fields (`X | None`) are not `required`.
    """
    hints = get_type_hints(cls, include_extras=True)
    props: dict[str, Any] = {}
    required: list[str] = []
    for f in fields(cls):
        tp, optional = _unwrap_optional(hints[f.name])
        props[f.name] = _annotation_schema(tp)
        if not optional:
            required.append(f.name)
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": SCHEMA_PREFIX + cls.name,
        "description": " ".join((cls.__doc__ or cls.name).split()),
        "type": "object",
        "properties": props,
        "required": required,
    }


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    if get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def _annotation_schema(tp: Any) -> dict[str, Any]:
    meta: tuple[Any, ...] = ()
    if get_origin(tp) is typing.Annotated:
        tp, *rest = get_args(tp)
        meta = tuple(rest)
    out: dict[str, Any]
    if get_origin(tp) is typing.Literal:
        return {"type": "string", "enum": list(get_args(tp))}
    size = next((m for m in meta if isinstance(m, Size)), None)
    if size is not None:
        top = size.n if size.hi is None else size.hi
        out = {"type": "array", "items": {"type": "number"}, "minItems": size.n, "maxItems": top}
        if any(isinstance(m, Rotation) for m in meta):
            out["description"] = "3×3 rotation, row-major"
        return out
    if tp is bool:
        return {"type": "boolean"}
    if tp is int or tp is float:
        out = {"type": "integer" if tp is int else "number"}
        rng = next((m for m in meta if isinstance(m, Range)), None)
        if rng is not None:
            out["minimum"], out["maximum"] = rng.lo, rng.hi
        return out
    max_len = next((m.n for m in meta if isinstance(m, MaxLen)), None)
    if tp is str:
        return {"type": "string", **({"maxLength": max_len} if max_len else {})}
    if tp is bytes:
        return {"type": "string", "contentEncoding": "base64"}
    if get_origin(tp) is dict:
        return {"type": "object"}
    if get_origin(tp) is tuple:
        return {
            "type": "array",
            "items": {"type": "object"},
            **({"maxItems": max_len} if max_len else {}),
        }
    raise TypeError(f"no JSON Schema for annotation {tp!r}")


def view(key: str, payload: bytes) -> View | None:
    """The JSON view of a payload received on `key`, or None when it has none.

    A contract key's payload must pass the codec's validation (a rejected one is kept only
    in the raw channel); any other key's msgpack map is shown schemaless, a non-map value as
    `{"value": …}`; a payload that is not msgpack has no view.
    """
    topic = keys.topic_for(key)
    try:
        if topic is not None:
            msg = codec.decode(topic.type, payload)
            if isinstance(msg, StereoFrame):
                return _image_view(msg)
            wire = codec.to_fields(msg)
            return View(schema_name(key), jsonify(wire), int(wire["t_ns"]))
        data = codec.unpack(payload)
    except ProtocolError:
        return None
    if not isinstance(data, dict):
        return View("", {"value": jsonify(data)}, None)
    t_ns = data.get("t_ns")
    return View("", jsonify(data), t_ns if type(t_ns) is int and t_ns >= 0 else None)


def stamp(payload: bytes) -> int | None:
    """The `t_ns` of a msgpack map payload, or None (not msgpack, not a map, no valid t_ns)."""
    try:
        data = codec.unpack(payload)
    except ProtocolError:
        return None
    t_ns = data.get("t_ns") if isinstance(data, dict) else None
    return t_ns if type(t_ns) is int and t_ns >= 0 else None


def _image_view(msg: StereoFrame) -> View:
    time_ = {"sec": msg.t_ns // 1_000_000_000, "nsec": msg.t_ns % 1_000_000_000}
    data = base64.b64encode(msg.data).decode("ascii")
    frame_id = f"stereo_{msg.eye}"
    if msg.encoding == "bgr8":
        doc = {
            "timestamp": time_,
            "frame_id": frame_id,
            "width": msg.width,
            "height": msg.height,
            "encoding": "bgr8",
            "step": msg.width * 3,
            "data": data,
        }
        return View(RAW_IMAGE, doc, msg.t_ns)
    return View(
        COMPRESSED_IMAGE,
        {"timestamp": time_, "frame_id": frame_id, "data": data, "format": msg.encoding},
        msg.t_ns,
    )


def jsonify(obj: Any) -> Any:
    """A JSON-encodable copy: bytes as base64 strings, non-finite floats as strings."""
    if isinstance(obj, dict):
        return {str(k): jsonify(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonify(v) for v in obj]
    if isinstance(obj, bytes | bytearray):
        return base64.b64encode(bytes(obj)).decode("ascii")
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    return str(obj)


def dumps(doc: dict[str, Any]) -> bytes:
    """Compact UTF-8 JSON of a view document."""
    return json.dumps(doc, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode()


def key_matcher(
    patterns: Sequence[str], video: bool = True, ros: bool = True
) -> Callable[[str], bool]:
    """A predicate on keys: inside one of the Zenoh key expressions `patterns` (all keys when
    empty, but the ROS 2 view's copies unless `ros`), and not a stereo stream unless
    `video`. Raises ConfigError on a bad pattern."""
    try:
        exprs = [zenoh.KeyExpr(p) for p in patterns]
    except zenoh.ZError as e:
        raise ConfigError("keys", str(e).split(" at /")[0]) from None

    def match(key: str) -> bool:
        if not video and is_video(key):
            return False
        if not exprs:
            return ros or not is_ros_copy(key)
        try:
            k = zenoh.KeyExpr(key)
        except zenoh.ZError:
            return False
        return any(e.includes(k) for e in exprs)

    return match
