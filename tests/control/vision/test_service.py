"""The vision service over Zenoh: synchronized pairs that decode, stats, following the arm."""

from __future__ import annotations

import threading
from typing import Any

import cv2
import numpy as np
import pytest

from services.bus import codec, keys
from services.bus.messages import ArmDescription, StereoFrame
from services.control.arm.model import load_model
from services.control.vision.config import VisionConfig
from services.control.vision.service import VisionService
from services.control.vision.sim_camera import SimStereoCamera
from tests.conftest import ready_state, wait_until

STEREO = (keys.STEREO_L, keys.STEREO_R)


def test_pairs_are_synchronized_decode_and_stats_flow(net) -> None:
    vision_node = net.node("vision")
    viewer = net.node("viewer")
    pairs: dict[int, dict[str, StereoFrame]] = {}
    lock = threading.Lock()
    done = threading.Event()

    def on_frame(f: StereoFrame) -> None:
        with lock:
            pairs.setdefault(f.seq, {})[f.eye] = f
            if sum(len(p) == 2 for p in pairs.values()) >= 5:
                done.set()

    viewer.subscribe(keys.STEREO_L, on_frame)
    viewer.subscribe(keys.STEREO_R, on_frame)
    stats = viewer.subscribe(keys.VISION_STATS)
    svc = VisionService(vision_node, VisionConfig(width=160, height=120, fps=20.0))
    try:
        assert done.wait(20.0), "fewer than 5 complete pairs arrived"
        assert stats.wait_count(1, 10.0)
        assert viewer.call("vision", "status", {}, timeout_s=5.0)["camera"]
    finally:
        svc.close()
    with lock:
        complete = [p for p in pairs.values() if len(p) == 2]
    for p in complete:
        left, right = p["l"], p["r"]
        assert left.t_ns == right.t_ns
        assert (left.width, left.height) == (160, 120)
        assert left.baseline == right.baseline and left.baseline is not None
        img = cv2.imdecode(np.frombuffer(left.data, np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape == (120, 160, 3)
    latest = stats.latest
    assert latest is not None and latest.width == 160 and latest.encoding == "jpeg"


def test_sim_camera_draws_the_newest_robot_state_once_watched(net) -> None:
    """While nobody watches, robot/state is only stored; the first viewer's first pair
    shows the arm where the newest state puts it."""
    vision_node = net.node("vision")
    arm = net.node("arm")
    viewer = net.node("viewer")
    svc = VisionService(vision_node, VisionConfig(width=160, height=120, fps=20.0))
    model = load_model("fr3")
    kin = model.kinematics()
    q = model.home
    oMt = kin.fk_tool(q)
    oMe = kin.fk_flange(q)
    # the arm it draws is the one described (with a cache: it came before the subscriber)
    described = arm.publisher(keys.ARM_DESCRIPTION, cache=1)
    described.put(ArmDescription(seq=1, t_ns=1, **model.description()))
    pub = arm.publisher(keys.STATE)
    camera = svc.camera
    assert isinstance(camera, SimStereoCamera)
    try:
        for seq in range(1, 4):
            pub.put(ready_state(seq, seq, q, oMt, oMe))
        assert wait_until(
            lambda: svc._robot is not None and svc._robot.seq == 3, what="robot/state"
        )
        assert camera._robot is None, "the arm was drawn while nobody watched"
        frames = viewer.subscribe(keys.STEREO_L)
        assert wait_until(
            lambda: camera._robot is not None, what="the arm drawn for the first viewer"
        )
        assert frames.wait_count(1, 10.0)
        robot = camera._robot
        assert robot is not None
        assert np.allclose(robot.tool_p, oMt.translation)
        assert np.allclose(robot.link_points, kin.link_origins(q))  # the FR3's skeleton
        assert np.allclose(robot.link_points[0], [0.30, 0.0, 0.0])  # where it is mounted
    finally:
        svc.close()


def test_vision_renders_only_while_someone_subscribes(net) -> None:
    """Nobody on vision/stereo/*: nothing rendered, stats flow and say idle. A subscriber:
    pairs flow. It leaves: rendering stops (the frame counter stays put across two stats
    periods) while the stats keep flowing."""
    vision_node = net.node("vision")
    viewer = net.node("viewer")
    stats = viewer.subscribe(keys.VISION_STATS)
    svc = VisionService(vision_node, VisionConfig(width=160, height=120, fps=20.0))
    got: dict[str, int] = {"l": 0, "r": 0}
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        f = codec.decode(StereoFrame, sample.payload.to_bytes())
        with lock:
            got[f.eye] += 1

    def count(eye: str) -> int:
        with lock:
            return got[eye]

    try:
        assert wait_until(lambda: svc.pipeline.stats()["idle_waits"] == 1, what="vision asleep")
        assert stats.wait_for(lambda s: s.data is not None and s.data["idle"], 10.0)
        assert svc.pipeline.stats()["captured"] == 0

        subs = [viewer.session.declare_subscriber(k.key, on_sample) for k in STEREO]
        assert wait_until(
            lambda: count("l") >= 5 and count("r") >= 5, what="5 pairs", timeout_s=20.0
        )
        assert stats.wait_for(lambda s: s.data is not None and not s.data["idle"], 10.0)

        for sub in subs:
            sub.undeclare()
        assert wait_until(
            lambda: svc.pipeline.stats()["idle_waits"] == 2, what="vision asleep again"
        )
        captured = svc.pipeline.stats()["captured"]
        n = stats.received
        assert stats.wait_count(n + 2, 10.0), "vision/stats stopped flowing"
        assert svc.pipeline.stats()["captured"] == captured, "rendering went on unwatched"
        last = stats.latest
        assert last is not None and last.data is not None and last.data["idle"] is True
    finally:
        svc.close()


@pytest.mark.parametrize("ns", ["", "cell2"])
def test_a_first_subscriber_gets_a_pair_at_once(make_net, ns: str) -> None:
    # One frame per 50 s: a pair within the wait's deadline can only come from the
    # subscription waking the capture thread (also under a namespace).
    net = make_net(ns)
    vision_node = net.node("vision")
    viewer = net.node("viewer")
    svc = VisionService(vision_node, VisionConfig(width=160, height=120, fps=0.02))
    try:
        assert wait_until(lambda: svc.pipeline.stats()["idle_waits"] == 1, what="vision asleep")
        frames = viewer.subscribe(keys.STEREO_R)
        assert frames.wait_count(1, 20.0), "no pair for the first subscriber"
    finally:
        svc.close()
