"""The file layout's pure parts: JSON Schemas from the dataclasses, JSON views, key selection."""

from __future__ import annotations

import base64
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.bus import codec, keys
from services.bus.errors import ConfigError
from services.bus.messages import (
    ALL_MESSAGES,
    ArmDescription,
    ArmTarget,
    ForceSample,
    OperatorCommand,
    RobotState,
    StereoFrame,
    vec,
)
from services.geometry import rotation_about
from services.tools.record import schemas
from tests.bus.test_golden import GOLDEN
from tests.tools.record.helpers import conforms


def test_every_contract_message_has_a_schema_generated_from_its_annotations() -> None:
    for cls in ALL_MESSAGES:
        s = schemas.message_schema(cls)
        assert s["title"] == f"telerobot.{cls.name}"
        assert s["type"] == "object"
        assert "seq" in s["required"] and "t_ns" in s["required"]
    s = schemas.message_schema(RobotState)
    assert s["properties"]["q"] == {
        "type": "array",
        "items": {"type": "number"},
        "minItems": 1,
        "maxItems": 32,
    }
    assert s["properties"]["status"]["enum"] == [
        "disconnected",
        "connected",
        "initializing",
        "ready",
        "moving",
        "error",
    ]
    assert "grip" not in s["required"] and "manipulability" not in s["required"]
    assert s["properties"]["grip"] == {"type": "number", "minimum": 0.0, "maximum": 1.0}
    frame = schemas.message_schema(StereoFrame)["properties"]["data"]
    assert frame == {"type": "string", "contentEncoding": "base64"}
    json.dumps(s)  # the schema itself is JSON


def test_the_arm_s_new_messages_have_the_wire_s_schemas() -> None:
    """ArmTarget (robot/arm/target) and ArmDescription (robot/arm/description, with the
    URDF): the channel schema follows the annotations, and a real arm's description (the
    FR3's, 7 joints) is a view that conforms to it."""
    from services.control.arm.model import load_model

    s = schemas.message_schema(ArmTarget)
    assert s["properties"]["p"]["minItems"] == s["properties"]["p"]["maxItems"] == 3
    assert s["properties"]["R"]["maxItems"] == 9
    assert {"origin_t_ns", "master", "engage", "p", "R"} <= set(s["required"])
    assert keys.topic_for(keys.ARM_TARGET.key) is keys.ARM_TARGET
    s = schemas.message_schema(ArmDescription)
    assert s["properties"]["n"] == {"type": "integer", "minimum": 1, "maximum": 32}
    assert s["properties"]["joints"]["items"] == {"type": "object"}
    assert s["properties"]["urdf"]["type"] == "string"
    fr3 = load_model("fr3")
    payload = codec.encode(ArmDescription(seq=1, t_ns=5, **fr3.description()))
    v = schemas.view(keys.ARM_DESCRIPTION.key, payload)
    assert v is not None and v.schema == "telerobot.ArmDescription" and v.t_ns == 5
    assert conforms(schemas.json_schema(v.schema), v.document) == []
    assert v.document["urdf"] == fr3.urdf and len(v.document["joints"]) == 7


@pytest.mark.parametrize("msg", [m for m, _ in GOLDEN], ids=lambda m: type(m).name)
def test_the_view_of_every_golden_message_conforms_to_its_channel_schema(msg: object) -> None:
    key = next(t.key for t in keys.TOPICS if t.type is type(msg))
    v = schemas.view(key, codec.encode(msg))  # type: ignore[arg-type]
    assert v is not None
    assert v.t_ns == msg.t_ns  # type: ignore[attr-defined]
    assert conforms(schemas.json_schema(v.schema), v.document) == []
    json.loads(schemas.dumps(v.document))


def test_a_stereo_frame_is_a_foxglove_compressed_image_and_bgr8_a_raw_image() -> None:
    jpeg = bytes(range(256)) * 3
    f = StereoFrame(
        seq=5,
        t_ns=1_700_000_001_250_000_000,
        eye="r",
        width=4,
        height=2,
        encoding="jpeg",
        data=jpeg,
    )
    v = schemas.view("vision/stereo/r", codec.encode(f))
    assert v is not None and v.schema == "foxglove.CompressedImage"
    assert v.document["timestamp"] == {"sec": 1_700_000_001, "nsec": 250_000_000}
    assert v.document["frame_id"] == "stereo_r" and v.document["format"] == "jpeg"
    assert base64.b64decode(v.document["data"]) == jpeg
    assert conforms(schemas.COMPRESSED_IMAGE_SCHEMA, v.document) == []
    raw = StereoFrame(seq=5, t_ns=1, eye="l", width=2, height=1, encoding="bgr8", data=bytes(6))
    v = schemas.view("vision/stereo/l", codec.encode(raw))
    assert v is not None and v.schema == "foxglove.RawImage"
    assert v.document["step"] == 6 and v.document["encoding"] == "bgr8"
    assert conforms(schemas.RAW_IMAGE_SCHEMA, v.document) == []


def test_bad_and_foreign_payloads() -> None:
    # A contract key whose payload breaks the contract has no view (kept raw only).
    assert schemas.view("robot/force", codec.pack({"seq": 1})) is None
    assert schemas.view("robot/force", b"\xc1garbage") is None
    # Another key's msgpack map is shown schemaless, with bytes as base64.
    v = schemas.view("lab/note", codec.pack({"t_ns": 12, "blob": b"\x00\x01", "x": math.inf}))
    assert v is not None and v.schema == "" and v.t_ns == 12
    assert v.document == {"t_ns": 12, "blob": "AAE=", "x": "inf"}
    v = schemas.view("lab/count", codec.pack(7))
    assert v is not None and v.document == {"value": 7} and v.t_ns is None
    assert schemas.view("lab/text", b"\xc1") is None
    assert schemas.stamp(codec.pack({"t_ns": 5})) == 5
    assert schemas.stamp(codec.pack({"t_ns": -5})) is None
    assert schemas.stamp(b"\xc1") is None


def test_key_selection_uses_zenoh_key_expressions() -> None:
    sel = schemas.key_matcher(("robot/*",))
    assert sel("robot/cmd") and sel("robot/force")
    assert not sel("robot/arm/target") and not sel("master/state")
    sel = schemas.key_matcher(("robot/**", "vision/**"), video=False)
    assert sel("robot/arm/target") and sel("vision/stats")
    assert not sel("vision/stereo/l") and not sel("vision/stereo/r")
    assert schemas.key_matcher(())("anything/at/all")
    with pytest.raises(ConfigError) as err:
        schemas.key_matcher(("robot//cmd",))
    assert err.value.key == "keys"
    assert schemas.raw_topic("robot/state") == "/raw/robot/state"


finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite)


def _rotation(axis: tuple[float, float, float], angle: float) -> tuple[float, ...]:
    a = axis if float(np.linalg.norm(axis)) > 1e-6 else (0.0, 0.0, 1.0)
    return vec(rotation_about(a, angle))


commands = st.builds(
    OperatorCommand,
    seq=st.integers(0, 2**63 - 1),
    t_ns=st.integers(0, 2**63 - 1),
    master=st.text(max_size=128),
    engage=st.integers(0, 2**63 - 1),
    active=st.booleans(),
    frame=st.sampled_from(["world", "tool"]),
    dp=vec3,
    dR=st.builds(_rotation, st.tuples(finite, finite, finite), st.floats(-3.14, 3.14)),
    grip=st.none() | st.floats(0.0, 1.0),
)
targets = st.builds(
    ArmTarget,
    seq=st.integers(0, 2**63 - 1),
    t_ns=st.integers(0, 2**63 - 1),
    origin_t_ns=st.integers(0, 2**63 - 1),
    master=st.text(max_size=128),
    engage=st.integers(0, 2**63 - 1),
    p=vec3,
    R=st.builds(_rotation, st.tuples(finite, finite, finite), st.floats(-3.14, 3.14)),
    grip=st.none() | st.floats(0.0, 1.0),
    hold=st.none() | st.just(True),
)
forces = st.builds(
    ForceSample,
    seq=st.integers(0, 2**63 - 1),
    t_ns=st.integers(0, 2**63 - 1),
    f=vec3,
    c=vec3,
    raw=st.none() | st.tuples(finite, finite, finite, finite, finite, finite),
)


@settings(max_examples=150, deadline=None)
@given(
    st.one_of(
        commands.map(lambda m: ("robot/cmd", m)),
        targets.map(lambda m: ("robot/arm/target", m)),
        forces.map(lambda m: ("robot/force", m)),
    )
)
def test_views_conform_and_decode_back_to_the_same_message(case: tuple[str, object]) -> None:
    """What Foxglove shows is the message, nothing lost: the JSON view matches its schema
    and the codec reads it back to an equal message."""
    key, msg = case
    v = schemas.view(key, codec.encode(msg))  # type: ignore[arg-type]
    assert v is not None
    assert conforms(schemas.json_schema(v.schema), v.document) == []
    doc = json.loads(schemas.dumps(v.document))
    assert codec.from_fields(type(msg), doc) == msg  # type: ignore[type-var]
