"""The vision service over Zenoh: synchronized pairs that decode, stats, following the arm."""

from __future__ import annotations

import threading

import cv2
import numpy as np

from services.bus import keys
from services.bus.messages import RobotState, StereoFrame, vec
from services.puma.kinematics import DEFAULT_eMt, Puma560, qn
from services.vision.config import VisionConfig
from services.vision.service import VisionService


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


def test_sim_camera_follows_robot_state(net) -> None:
    vision_node = net.node("vision")
    puma = net.node("puma")
    svc = VisionService(vision_node, VisionConfig(width=160, height=120, fps=20.0))
    kin = Puma560()
    oMt = kin.fk_tool(qn, DEFAULT_eMt)
    oMe = kin.fk_flange(qn)
    pub = puma.publisher(keys.STATE)
    try:
        for seq in range(1, 4):
            pub.put(
                RobotState(
                    seq=seq,
                    t_ns=seq,
                    status="ready",
                    q=vec(qn),
                    tool_p=vec(oMt.translation),
                    tool_R=vec(oMt.rotation),
                    flange_p=vec(oMe.translation),
                    flange_R=vec(oMe.rotation),
                    engage=0,
                    cmd_seq=0,
                )
            )
        camera = svc.camera
        deadline_ok = threading.Event()
        for _ in range(200):
            robot = getattr(camera, "_robot", None)
            if robot is not None:
                deadline_ok.set()
                break
            deadline_ok.wait(0.05)
        assert deadline_ok.is_set(), "the sim camera never received the arm"
    finally:
        svc.close()
