"""Each stream's reliability on the link (keys.Delivery, issue 41): latest-wins streams that
a later sample supersedes are best-effort, so over QUIC with `mixed_rel` (or UDP) they ride
datagrams and never wait behind a retransmission; what must arrive whole is reliable."""

from __future__ import annotations

import zenoh

from services.bus import keys
from services.bus.keys import Delivery
from services.bus.streams import Publisher, publisher_qos

BEST_EFFORT = {
    "robot/cmd",
    "robot/arm/target",
    "robot/state",
    "robot/force",
    "master/state",
    "master/feedback",
    "robot/passivity/master",
    "robot/passivity/slave",
    "vision/stereo/l",
    "vision/stereo/r",
}


def test_every_key_declares_the_reliability_the_issue_gives_it() -> None:
    declared = {t.key for t in keys.TOPICS if t.delivery is Delivery.BEST_EFFORT}
    assert declared == BEST_EFFORT
    for t in keys.TOPICS:
        if t.delivery is Delivery.BEST_EFFORT:
            assert t.latest_wins, f"{t.key}: only a latest-wins stream may lose a sample"
    assert keys.EVENTS.delivery is Delivery.RELIABLE
    assert keys.ARM_DESCRIPTION.delivery is Delivery.RELIABLE


def test_publishers_are_declared_with_it() -> None:
    assert publisher_qos(keys.FORCE)["reliability"] == zenoh.Reliability.BEST_EFFORT
    assert publisher_qos(keys.EVENTS)["reliability"] == zenoh.Reliability.RELIABLE
    # the priority and congestion control of the class stay as they were
    assert publisher_qos(keys.FORCE)["priority"] == zenoh.Priority.REAL_TIME
    assert publisher_qos(keys.STEREO_L)["congestion_control"] == zenoh.CongestionControl.DROP
    cfg = zenoh.Config()
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", "[]")
    with zenoh.open(cfg) as session:
        for topic, want in ((keys.CMD, "BEST_EFFORT"), (keys.EVENTS, "RELIABLE")):
            pub = Publisher(session, topic)
            assert pub._pub.reliability == getattr(zenoh.Reliability, want), topic.key
            pub.undeclare()
