"""The `vision` service on the bus: stereo pairs on `vision/stereo/l|r`, stats on `vision/stats`.

The simulated camera follows the arm from `robot/state` (link origins from the arm's
description, `robot/arm/description`)
and the workcell's movable objects from `workcell/state` (docs/vision.md, "The moved world");
video is published at DATA_LOW with drop-on-congestion (keys.STEREO_*), so it never delays
force or commands.

Nobody watching, no work: Zenoh's matching status tells whether anyone subscribes to
`vision/stereo/l` or `/r`. While nobody does, the pipeline grabs, encodes and publishes
nothing (the simulator renders nothing; a real device is only kept fresh, see
`Camera.keep_alive`), and `vision/stats` keeps flowing with `idle` true. The first
subscriber wakes the capture thread at once: its first pair is a frame period away at most.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from services.bus import keys
from services.bus.audience import Audience
from services.bus.errors import ConfigError, ProtocolError
from services.bus.messages import ArmDescription, RobotState, StereoFrame, VisionStats, mat3
from services.bus.node import Node
from services.control.vision.backends import open_camera
from services.control.vision.config import VisionConfig
from services.control.vision.pipeline import StereoPipeline
from services.control.vision.sim_camera import SimStereoCamera
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState

STATS_PERIOD_S = 1.0


class VisionService:
    """Runs the stereo pipeline and publishes it; `close()` stops it."""

    def __init__(self, node: Node, config: VisionConfig) -> None:
        self.node = node
        self.config = config
        self.camera = open_camera(config)
        self._left = node.publisher(keys.STEREO_L)
        self._right = node.publisher(keys.STEREO_R)
        self._stats_pub = node.publisher(keys.VISION_STATS)
        self._stats_seq = 0
        self._stop = threading.Event()
        self._robot_period_ns = int(0.5e9 / config.fps)
        self._robot_last_ns = 0
        self._robot: RobotState | None = None
        self._kin: Any = None
        self.pipeline = StereoPipeline(
            self.camera, config, self._publish, self._emit, watched=False
        )
        if isinstance(self.camera, SimStereoCamera):
            # The simulated camera draws the arm the arm service describes (its skeleton
            # from the description's URDF), as soon as a description has come.
            node.subscribe(keys.ARM_DESCRIPTION, self._on_description, history=True)
            node.subscribe(keys.STATE, self._on_state)
            node.subscribe(WORKCELL_STATE, self._on_workcell)
        self.audience = Audience(
            node.session, (keys.STEREO_L.key, keys.STEREO_R.key), self._on_audience
        )
        self.pipeline.start()
        self._stats_thread = threading.Thread(
            target=self._stats_loop, name="vision-stats", daemon=True
        )
        self._stats_thread.start()
        node.serve("vision", {"status": self._rpc_status})
        node.announce()

    def _on_description(self, desc: ArmDescription) -> None:
        from services.control.arm.model import model_from_description

        try:
            kin = model_from_description(desc).kinematics()
        except ConfigError as e:
            self.node.report_rejected(keys.ARM_DESCRIPTION.key, e.reason)
            return
        self._kin = kin
        robot = self._robot
        if robot is not None and self.pipeline.watched:
            self._draw_robot(robot)

    def _on_state(self, st: RobotState) -> None:
        # Called at the state rate; the renderer needs at most two updates per frame, and
        # none while nobody watches (the newest state is drawn as soon as someone does).
        self._robot = st
        now = time.monotonic_ns()
        if not self.pipeline.watched or now - self._robot_last_ns < self._robot_period_ns:
            return
        self._robot_last_ns = now
        self._draw_robot(st)

    def _on_workcell(self, st: WorkcellState) -> None:
        # The objects where the workcell has them; the capture thread ray-casts only those
        # that moved, at its next pair.
        assert isinstance(self.camera, SimStereoCamera)
        try:
            self.camera.set_workcell(st)
        except (ProtocolError, ValueError) as e:
            self.node.report_rejected(WORKCELL_STATE.key, str(e))

    def _draw_robot(self, st: RobotState) -> None:
        assert isinstance(self.camera, SimStereoCamera)
        kin = self._kin
        if kin is None or len(st.q) != kin.n:
            return  # no description yet, or a state of another arm than the one described
        self.camera.set_robot(kin.link_origins(st.q), st.tool_p, mat3(st.tool_R), st.grip)

    def _on_audience(self, watched: bool) -> None:
        robot = self._robot
        if watched and robot is not None:
            self._draw_robot(robot)  # the first pair shows the arm where it is now
        self.pipeline.set_watched(watched)

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
        self.audience.close()
        self.pipeline.stop()
        self._stats_thread.join(timeout=2.0)
