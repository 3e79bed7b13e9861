"""RIHS01 type hashes: ours against the published values and against rosbags' computation."""

from __future__ import annotations

import json

import pytest
from rosbags.typesys import Stores, get_typestore

from services.frontends.rosmsg import defs, typehash

# Published values: std_msgs/String is the example of rmw_zenoh docs/design.md ("Topic and
# Service name mapping"); the others are the `type_hashes` of ROS 2 Jazzy/Kilted's
# share/<pkg>/msg/<Type>.json, as `ros2 topic info --verbose` and rosbag2's metadata.yaml
# print them (e.g. "Topic type hash: RIHS01_a13ee3…" for /joint_states).
PUBLISHED = {
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",  # noqa: E501
    "std_msgs/msg/Header": "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",  # noqa: E501
    "builtin_interfaces/msg/Time": "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197",  # noqa: E501
    "sensor_msgs/msg/JointState": "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",  # noqa: E501
    "geometry_msgs/msg/WrenchStamped": "RIHS01_8dc3deaf06b2ab281f9f9a742a8961c328ca7cec16e3fd6586d3a5c83fa78f77",  # noqa: E501
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",  # noqa: E501
    "sensor_msgs/msg/CompressedImage": "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",  # noqa: E501
    "sensor_msgs/msg/CameraInfo": "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",  # noqa: E501
    "sensor_msgs/msg/RegionOfInterest": "RIHS01_ad16bcba5f9131dcdba6fbded19f726f5440e3c513b4fb586dd3027eeed8abb1",  # noqa: E501
    "geometry_msgs/msg/PoseStamped": "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",  # noqa: E501
}

STORE = get_typestore(Stores.ROS2_KILTED)


@pytest.mark.parametrize("name", sorted(PUBLISHED))
def test_hash_matches_the_published_value(name: str) -> None:
    assert typehash.rihs01(name) == PUBLISHED[name]


@pytest.mark.parametrize("name", [t.name for t in defs.ALL])
def test_hash_matches_rosbags(name: str) -> None:
    assert typehash.rihs01(name) == STORE.hash_rihs01(name)


@pytest.mark.parametrize("name", [t.name for t in defs.ALL])
def test_field_lists_match_rosbags(name: str) -> None:
    """Names and order of the fields, as the CDR encoders rely on them."""
    ours = [f.name for f in defs.BY_NAME[name].fields]
    theirs = [f[0] for f in STORE.get_msgdef(name).fields]
    assert ours == theirs


def test_the_hashed_text_is_compact_json_with_sorted_references() -> None:
    text = typehash.hashable_json(defs.TF_MESSAGE)
    assert "\n" not in text and '", "' in text and '": ' in text
    doc = json.loads(text)
    refs = [r["type_name"] for r in doc["referenced_type_descriptions"]]
    assert refs == sorted(refs)
    assert set(refs) == {
        "builtin_interfaces/msg/Time",
        "geometry_msgs/msg/Quaternion",
        "geometry_msgs/msg/Transform",
        "geometry_msgs/msg/TransformStamped",
        "geometry_msgs/msg/Vector3",
        "std_msgs/msg/Header",
    }
    assert list(doc["type_description"]["fields"][0]["type"]) == [
        "type_id",
        "capacity",
        "string_capacity",
        "nested_type_name",
    ]


def test_dds_names() -> None:
    assert defs.STRING_MSG.dds_name == "std_msgs::msg::dds_::String_"
    assert defs.TF_MESSAGE.dds_name == "tf2_msgs::msg::dds_::TFMessage_"
