"""rmw_zenoh conventions against the examples of its docs/design.md and Zenoh's serializer."""

from __future__ import annotations

import pytest
import zenoh
from zenoh.ext import Int64, UInt8, z_deserialize, z_serialize

from services.frontends.ros2 import rmw
from services.frontends.rosmsg import defs

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_data_keys_of_the_design_examples() -> None:
    """design.md: `chatter`, and `chatter` under the namespace /robot1."""
    t = defs.STRING_MSG
    assert (
        rmw.topic_key(0, "/chatter", t) == f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    fqn = rmw.fully_qualified("/robot1", "chatter")
    assert fqn == "/robot1/chatter"
    assert (
        rmw.topic_key(0, fqn, t) == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )


def test_tokens_of_the_design_examples() -> None:
    """design.md "Graph Cache": the talker's node... and its publisher with depth 7, the
    listener's subscription with depth 10 (default reliability, durability, history)."""
    zid = "8b20917502ee955ac4476e0266340d5c"
    assert rmw.node_token(2, zid, 0, "/", "talker") == f"@ros2_lv/2/{zid}/0/0/NN/%/%/talker"
    pub = rmw.endpoint_token(
        "MP", 2, zid, 0, 10, "/", "talker", "/chatter", defs.STRING_MSG, rmw.Qos(depth=7)
    )
    assert pub == (
        f"@ros2_lv/2/{zid}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,"
    )
    lzid = "aac3178e146ba6f1fc6e6a4085e77f21"
    sub = rmw.endpoint_token(
        "MS", 2, lzid, 0, 10, "/", "listener", "/chatter", defs.STRING_MSG, rmw.Qos(depth=10)
    )
    assert sub.endswith(
        f"/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,"
    )


def test_qos_text() -> None:
    assert rmw.Qos(depth=42).keyexpr() == "::,:,:,:,,"
    assert rmw.LATCHED.keyexpr() == ":1:,1:,:,:,,"
    assert rmw.SENSOR_DATA.keyexpr() == "2::,5:,:,:,,"


def test_namespaced_tokens_mangle_the_namespace_and_topic() -> None:
    tok = rmw.endpoint_token(
        "MP", 0, "ab", 0, 3, "/cell2", "telerobot", "/cell2/tf", defs.TF_MESSAGE, rmw.Qos(depth=100)
    )
    assert "/MP/%/%cell2/telerobot/%cell2%tf/tf2_msgs::msg::dds_::TFMessage_/" in tok
    zenoh.KeyExpr(tok)  # a valid key expression


@pytest.mark.parametrize("bad", ["a//b", "1abc", "a b", "a/-"])
def test_bad_names_are_refused(bad: str) -> None:
    with pytest.raises(ValueError):
        rmw.fully_qualified("/", bad)


def test_attachment_is_zenohs_serialization_of_seq_stamp_gid() -> None:
    gid = bytes(range(16))
    raw = rmw.attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(raw) == 33
    ours = z_serialize((Int64(7), Int64(1_700_000_000_123_456_789), [UInt8(b) for b in gid]))
    assert raw == ours.to_bytes()
    seq, t_ns, g = z_deserialize(tuple[Int64, Int64, list[UInt8]], zenoh.ZBytes(raw))
    assert (seq, t_ns, bytes(g)) == (7, 1_700_000_000_123_456_789, gid)
    assert rmw.parse_attachment(raw) == rmw.Attachment(7, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError):
        rmw.parse_attachment(raw[:-1])


def test_gids_differ_per_endpoint() -> None:
    a = rmw.gid_of("@ros2_lv/0/x/0/1/MP/%/%/n/%a/T/H/::,10:,:,:,,")
    b = rmw.gid_of("@ros2_lv/0/x/0/2/MP/%/%/n/%a/T/H/::,10:,:,:,,")
    assert len(a) == 16 and a != b
