"""The `vision` service on the bus: stereo pairs on `vision/stereo/l|r`, stats on `vision/stats`.

The simulated camera follows the arm from `robot/state` (link origins from the PUMA model);
video is published at DATA_LOW with drop-on-congestion (keys.STEREO_*), so it never delays
force or commands.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from services.bus import keys
from services.bus.messages import RobotState, StereoFrame, VisionStats, mat3
from services.bus.node import Node
from services.vision.camera import camera_from_config
from services.vision.config import VisionConfig
from services.vision.pipeline import StereoPipeline
from services.vision.sim_camera import SimStereoCamera

STATS_PERIOD_S = 1.0


class VisionService:
    """Runs the stereo pipeline and publishes it; `close()` stops it."""

    def __init__(self, node: Node, config: VisionConfig) -> None:
        self.node = node
        self.config = config
        self.camera = camera_from_config(config)
        self._left = node.publisher(keys.STEREO_L)
        self._right = node.publisher(keys.STEREO_R)
        self._stats_pub = node.publisher(keys.VISION_STATS)
        self._stats_seq = 0
        self._stop = threading.Event()
        self._robot_period_ns = int(0.5e9 / config.fps)
        self._robot_last_ns = 0
        self._kin: Any = None
        if isinstance(self.camera, SimStereoCamera):
            from services.puma.kinematics import Puma560

            self._kin = Puma560()
            node.subscribe(keys.STATE, self._on_state)
        self.pipeline = StereoPipeline(self.camera, config, self._publish, self._emit)
        self.pipeline.start()
        self._stats_thread = threading.Thread(
            target=self._stats_loop, name="vision-stats", daemon=True
        )
        self._stats_thread.start()
        node.serve("vision", {"status": self._rpc_status})
        node.announce()

    def _on_state(self, st: RobotState) -> None:
        # Called at the state rate; the renderer needs at most two updates per frame.
        now = time.monotonic_ns()
        if now - self._robot_last_ns < self._robot_period_ns:
            return
        self._robot_last_ns = now
        assert isinstance(self.camera, SimStereoCamera)
        self.camera.set_robot(self._kin.link_origins(st.q), st.tool_p, mat3(st.tool_R), st.grip)

    def _emit(self, kind: str, message: str, data: dict[str, Any]) -> None:
        self.node.event(kind, message, data)

    def _publish(self, left: dict[str, Any], right: dict[str, Any]) -> None:
        self._left.put(StereoFrame(**left))
        self._right.put(StereoFrame(**right))

    def _stats_loop(self) -> None:
        while not self._stop.wait(STATS_PERIOD_S):
            self._stats_seq += 1
            self._stats_pub.put(
                VisionStats(
                    seq=self._stats_seq, t_ns=time.time_ns(), **self.pipeline.stats_fields()
                )
            )

    def _rpc_status(self, args: dict[str, Any]) -> dict[str, Any]:
        return {"camera": self.camera.name, **self.pipeline.stats()}

    def close(self) -> None:
        self._stop.set()
        self.pipeline.stop()
        self._stats_thread.join(timeout=2.0)
