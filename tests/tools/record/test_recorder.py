"""The recorder on a live bus: what it subscribes to, video, namespaces, never blocking."""

from __future__ import annotations

import base64
import json
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from services.bus import codec, keys
from services.bus.messages import ArmDescription, Event, StereoFrame
from services.control.arm.model import load_model
from services.tools.record import recorder as recorder_mod
from services.tools.record.archive import Recording
from services.tools.record.recorder import Recorder, RecorderConfig
from tests.conftest import Net, wait_until
from tests.tools.record.helpers import force


def _wait_subscribed(node: object, key: str, timeout_s: float = 5.0) -> None:
    """Publish only once the recorder's subscription has reached the publisher's session."""
    probe = node.session.declare_publisher(key)  # type: ignore[attr-defined]
    try:
        assert wait_until(
            lambda: bool(getattr(probe.matching_status, "matching", False)), timeout_s
        )
    finally:
        probe.undeclare()


def _frame(eye: str, seq: int, encoding: str = "jpeg") -> StereoFrame:
    import cv2

    img = np.zeros((24, 32, 3), np.uint8)
    img[:, : 8 * seq % 32] = (0, 0, 255)
    data = cv2.imencode(".jpg", img)[1].tobytes() if encoding == "jpeg" else img.tobytes()
    return StereoFrame(
        seq=seq,
        t_ns=time.time_ns(),
        eye=eye,  # type: ignore[arg-type]
        width=32,
        height=24,
        encoding=encoding,  # type: ignore[arg-type]
        data=data,
    )


def test_records_contract_and_other_keys_with_video_as_foxglove_images(
    net: Net, tmp_path: Path
) -> None:
    rec_node = net.node("record")
    out = tmp_path / "v.mcap"
    rec = Recorder(rec_node, RecorderConfig(output=str(out)))
    pub = net.node("vision")
    _wait_subscribed(pub, "vision/stereo/l")
    left, right = pub.publisher(keys.STEREO_L), pub.publisher(keys.STEREO_R)
    sent = []
    for seq in range(1, 4):
        for p, eye in ((left, "l"), (right, "r")):
            f = _frame(eye, seq)
            p.put(f)
            sent.append(f)
    pub.session.put("lab/note", codec.pack({"t_ns": 5, "text": "not a contract key"}))
    assert wait_until(lambda: rec.stats().received >= 7)
    stats = rec.stop()
    assert stats.dropped == 0 and stats.written == 7
    with out.open("rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        images = [
            (c.topic, json.loads(m.data), s.name if s else "")
            for s, c, m in reader.iter_messages(topics=["vision/stereo/l", "vision/stereo/r"])
        ]
    assert len(images) == 6
    import cv2

    for topic, doc, schema in images:
        assert schema == "foxglove.CompressedImage" and doc["format"] == "jpeg"
        assert doc["frame_id"] == "stereo_" + topic[-1]
        pixels = cv2.imdecode(np.frombuffer(base64.b64decode(doc["data"]), np.uint8), 1)
        assert pixels is not None and pixels.shape == (24, 32, 3)
    raw = {m.key: m for m in Recording(out).raw()}
    assert set(raw) == {"vision/stereo/l", "vision/stereo/r", "lab/note"}
    assert codec.unpack(raw["lab/note"].payload)["text"] == "not a contract key"
    assert raw["lab/note"].publish_time_ns == 5


def test_no_video_and_key_filters(net: Net, tmp_path: Path) -> None:
    rec_node = net.node("record")
    a = Recorder(rec_node, RecorderConfig(output=str(tmp_path / "a.mcap"), video=False))
    b = Recorder(rec_node, RecorderConfig(output=str(tmp_path / "b.mcap"), keys=("robot/*",)))
    c = Recorder(
        rec_node,
        RecorderConfig(output=str(tmp_path / "c.mcap"), keys=("robot/**", "robot/events")),
    )
    pub = net.node("pub")
    _wait_subscribed(pub, "robot/events")
    _wait_subscribed(pub, "vision/stereo/l")
    pub.publisher(keys.STEREO_L).put(_frame("l", 1))
    pub.event("status", "hello")
    pub.session.put("robot/arm/target/extra", codec.pack({"x": 1}))
    assert wait_until(
        lambda: a.stats().received >= 2 and b.stats().received >= 1 and c.stats().received >= 2
    )
    sa, sb, sc = a.stop(), b.stop(), c.stop()
    assert set(sa.keys) == {"robot/events", "robot/arm/target/extra"}
    assert set(sb.keys) == {"robot/events"}
    # overlapping expressions: each sample once
    assert {k: v.written for k, v in sc.keys.items()} == {
        "robot/events": 1,
        "robot/arm/target/extra": 1,
    }
    assert Recording(tmp_path / "a.mcap").raw_keys() == ["robot/events", "robot/arm/target/extra"]


def test_a_namespaced_recorder_records_keys_without_the_namespace(
    make_net: Callable[..., Net], tmp_path: Path
) -> None:
    net = make_net("cell2")
    rec = Recorder(net.node("record"), RecorderConfig(output=str(tmp_path / "ns.mcap")))
    pub = net.node("arm")
    _wait_subscribed(pub, "robot/events")
    pub.event("status", "in cell2")
    assert wait_until(lambda: rec.stats().received >= 1)
    rec.stop()
    r = Recording(tmp_path / "ns.mcap")
    assert [m.key for m in r.raw()] == ["robot/events"]
    assert r.metadata["telerobot.recording"]["ns"] == "cell2"


def test_a_recorder_started_after_the_arm_gets_its_description_from_the_arm_s_cache(
    net: Net, tmp_path: Path
) -> None:
    """The arm published its description before any recorder listened: each recorder gets
    it from the publisher's cache. One that records every key records it (the exact bytes,
    once); one whose key filter leaves it out still draws the arm, and records no such key."""
    arm = net.node("arm")
    desc = ArmDescription(seq=1, t_ns=time.time_ns(), **load_model("fr3").description())
    arm.publisher(keys.ARM_DESCRIPTION, cache=1).put(desc)
    everything = Recorder(net.node("record-all"), RecorderConfig(output=str(tmp_path / "a.mcap")))
    states_only = Recorder(
        net.node("record-states"),
        RecorderConfig(output=str(tmp_path / "s.mcap"), keys=("robot/state",)),
    )
    assert wait_until(
        lambda: everything.stats().robot_models == 1 and states_only.stats().robot_models == 1,
        what="both recorders drew the arm",
    )
    sa, ss = everything.stop(), states_only.stop()
    key = keys.ARM_DESCRIPTION.key
    assert sa.keys[key].received == sa.keys[key].written == 1 and sa.arm_model == "fr3"
    assert key not in ss.keys and ss.arm_model == "fr3" and ss.written == 0
    assert [m.payload for m in Recording(tmp_path / "a.mcap").raw()] == [codec.encode(desc)]
    for name in ("a.mcap", "s.mcap"):
        with (tmp_path / name).open("rb") as fh:
            topics = [c.topic for _, c, _ in make_reader(fh).iter_messages()]
        assert topics.count("/robot_model") == topics.count("/robot_description") == 1
    assert Recording(tmp_path / "s.mcap").raw_keys() == []


def test_a_stalled_writer_never_blocks_the_stream_it_drops_and_counts(
    net: Net, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With the writer stuck on the disk, every sample still reaches the callback at once;
    those beyond the inbox bound are dropped and counted, the rest written afterwards."""
    release = threading.Event()
    stuck = threading.Event()
    real_write = recorder_mod.McapSink.write

    def slow_write(self: recorder_mod.McapSink, item: recorder_mod.Received) -> bool:
        stuck.set()
        release.wait(30.0)
        return real_write(self, item)

    monkeypatch.setattr(recorder_mod.McapSink, "write", slow_write)
    rec = Recorder(
        net.node("record"), RecorderConfig(output=str(tmp_path / "q.mcap"), queue_len=20)
    )
    pub = net.node("arm")
    _wait_subscribed(pub, "robot/events")
    pub.event("status", "first")  # the writer takes it and sticks
    assert stuck.wait(10.0)
    for i in range(200):  # events are reliable (BLOCK): all 200 reach the recorder
        pub.event("data", f"burst {i}")
    assert wait_until(lambda: rec.stats().received == 201), rec.stats().received
    during = rec.stats()
    release.set()
    final = rec.stop()
    assert during.written == 0
    assert final.dropped == 201 - 1 - 20 and final.written == 21
    assert final.keys["robot/events"].received == 201
    msgs = [codec.decode(Event, m.payload).message for m in Recording(tmp_path / "q.mcap").raw()]
    assert msgs == ["first"] + [f"burst {i}" for i in range(20)]


def test_a_duration_limit_ends_the_recording_by_itself(net: Net, tmp_path: Path) -> None:
    pub = net.node("force")
    fp = pub.publisher(keys.FORCE)
    stop = threading.Event()

    def stream() -> None:
        seq = 0
        while not stop.wait(0.002):
            seq += 1
            fp.put_bytes(force(seq))

    t = threading.Thread(target=stream, daemon=True)
    t.start()
    try:
        rec = Recorder(
            net.node("record"), RecorderConfig(output=str(tmp_path / "d.mcap"), max_duration_s=1.0)
        )
        assert rec.ended.wait(10.0)  # the stream goes on; the recording ends on its own
        n = rec.stop().written
    finally:
        stop.set()
        t.join()
    with (tmp_path / "d.mcap").open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics is not None
    assert n > 0 and summary.statistics.message_count == 2 * n


def test_a_recording_of_everything_leaves_out_the_ros_view_unless_asked(
    net: Net, tmp_path: Path
) -> None:
    """Issue 42 item 12: `record` took the ROS 2 view's copy of every stream (rmw_zenoh
    keys `<domain>/<topic>/<type>/<hash>`), doubling the data. Left out by default; `--ros`
    (ros=True) keeps them; an explicit key expression records what it names."""
    ros_key = "0/robot/state/telerobot_msgs::msg::dds_::RobotState_/RIHS01_0a1b"
    rec_node = net.node("record")
    plain = Recorder(rec_node, RecorderConfig(output=str(tmp_path / "plain.mcap")))
    ros = Recorder(rec_node, RecorderConfig(output=str(tmp_path / "ros.mcap"), ros=True))
    named = Recorder(rec_node, RecorderConfig(output=str(tmp_path / "n.mcap"), keys=("0/**",)))
    pub = net.node("pub")
    _wait_subscribed(pub, "robot/events")
    _wait_subscribed(pub, ros_key)
    pub.session.put(ros_key, b"\x00\x01cdr")
    pub.event("status", "hello")
    assert wait_until(lambda: ros.stats().received >= 2 and named.stats().received >= 1)
    assert wait_until(lambda: plain.stats().received >= 1)
    sp, sr, sn = plain.stop(), ros.stop(), named.stop()
    assert set(sp.keys) == {"robot/events"}
    assert set(sr.keys) == {"robot/events", ros_key}
    assert set(sn.keys) == {ros_key}
