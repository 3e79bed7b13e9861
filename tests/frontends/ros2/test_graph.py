"""The ROS node on a Zenoh session: tokens appear and vanish, matching follows subscribers."""

from __future__ import annotations

import pytest
import zenoh

from services.bus.config import NodeConfig
from services.frontends.ros2 import rmw
from services.frontends.ros2.graph import RosNode
from services.frontends.rosmsg import defs, msgs
from tests.conftest import Net, wait_until


def _tokens(s: zenoh.Session) -> set[str]:
    return {str(r.ok.key_expr) for r in s.liveliness().get("@ros2_lv/**") if r.ok}


def test_matching_tokens_and_attachments(net: Net) -> None:
    a = zenoh.open(net.config(listen=True).to_zenoh())
    b = zenoh.open(NodeConfig(connect=(net.endpoint,)).to_zenoh())
    try:
        got: list[zenoh.Sample] = []
        topic_key = rmw.topic_key(7, "/ns1/wrench", defs.WRENCH_STAMPED)
        early = b.declare_subscriber(topic_key, got.append)  # before the publisher exists
        node = RosNode(a, 7, "/ns1", "bridge")
        pub = node.publisher("wrench", defs.WRENCH_STAMPED, rmw.Qos(depth=10))
        seen: list[bool] = []
        pub.on_matching(seen.append)
        assert wait_until(lambda: pub.matching, 10.0)
        m = msgs.WrenchStamped(msgs.Header(1, 2, "tool"), (1.0, 2.0, 3.0), (4.0, 5.0, 6.0))
        pub.put(msgs.encode(m))
        pub.put(msgs.encode(m))
        assert wait_until(lambda: len(got) == 2, 10.0)
        atts = [rmw.parse_attachment(s.attachment.to_bytes()) for s in got if s.attachment]
        assert [x.seq for x in atts] == [1, 2] and {x.gid for x in atts} == {pub.gid}
        assert msgs.decode(msgs.WrenchStamped, got[0].payload.to_bytes()) == m
        assert wait_until(lambda: set(node.tokens()) <= _tokens(b), 10.0)
        early.undeclare()
        assert wait_until(lambda: not pub.matching, 10.0)
        assert seen[-1] is False
        node.close()
        assert wait_until(lambda: not (set(node.tokens()) & _tokens(b)), 10.0)
    finally:
        b.close()
        a.close()


@pytest.mark.parametrize(("ns", "name"), [("/a b", "n"), ("/", "a/b"), ("/", "")])
def test_the_node_refuses_bad_names(net: Net, ns: str, name: str) -> None:
    s = zenoh.open(net.config(listen=True).to_zenoh())
    try:
        with pytest.raises(ValueError):
            RosNode(s, 0, ns, name)
    finally:
        s.close()
