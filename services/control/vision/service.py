"""The `vision` service on the bus: stereo pairs on `vision/stereo/l|r`, stats on `vision/stats`.

The simulated camera follows the arm from `robot/state` (link origins from the arm's
description, `robot/arm/description`)
and the workcell's movable objects from `workcell/state` (docs/vision.md, "The moved world");
video is published at DATA_LOW with drop-on-congestion (keys.STEREO_*), so it never delays
force or commands, and its level (JPEG quality, size, rate) follows what its receivers
report on `vision/arrival` (adapt.py): a link that cannot carry it gets less of it, each
change an event `video_level`.

Nobody watching, no work: Zenoh's matching status tells whether anyone subscribes to
`vision/stereo/l` or `/r`. While nobody does, the pipeline grabs, encodes and publishes
nothing (the simulator renders nothing; a real device is only kept fresh, see
`Camera.keep_alive`), and `vision/stats` keeps flowing with `idle` true. The first
subscriber wakes the capture thread at once: its first pair is a frame period away at most.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from services.bus import keys
from services.bus.audience import Audience
from services.bus.errors import ConfigError, ProtocolError
from services.bus.messages import ArmDescription, RobotState, StereoFrame, VisionStats, mat3
from services.bus.node import Node
from services.control.vision.adapt import VIDEO_ARRIVAL, Change, VideoAdapter, VideoArrival, ladder
from services.control.vision.backends import open_camera
from services.control.vision.config import VisionConfig
from services.control.vision.pipeline import StereoPipeline
from services.control.vision.sim_camera import SimStereoCamera
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState
from services.world.workcell.scene import Scene

STATS_PERIOD_S = 1.0
log = logging.getLogger("telerobot.vision")


class VisionService:
    """Runs the stereo pipeline and publishes it; `close()` stops it."""

    def __init__(self, node: Node, config: VisionConfig, scene: Scene | None = None) -> None:
        self.node = node
        self.config = config
        self.camera = open_camera(config, scene)
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
        self.adapter = VideoAdapter(
            ladder(config.jpeg_quality), config.adapt_queue_ms, config.adapt_up_s
        )
        self._adapt_lock = threading.Lock()
        if config.adapt:
            node.subscribe(VIDEO_ARRIVAL, self._on_arrival)
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

    def _on_arrival(self, report: VideoArrival) -> None:
        with self._adapt_lock:
            self.adapter.offer(report, time.monotonic())

    def _adapt(self) -> None:
        """Once a second: the adapter's decision on the fresh reports, applied."""
        if not self.config.adapt or not self.pipeline.watched:
            return
        sent = float(self.pipeline.stats()["fps"])
        with self._adapt_lock:
            change = self.adapter.update(time.monotonic(), sent)
            level = self.adapter.current
        if change is not None:
            self.pipeline.set_level(level)
            self._report_level(change)

    def _report_level(self, change: Change) -> None:
        level = self.adapter.levels[change.new]
        w, h = level.size(self.config.width, self.config.height)
        fps = self.config.fps / level.stride
        self.node.event(
            "status",
            f"video level {change.old} → {change.new} (JPEG {level.quality}, {w}x{h}, "
            f"{fps:g} fps): {change.reason}",
            {
                "code": "video_level",
                "level": change.new,
                "from": change.old,
                "levels": len(self.adapter.levels),
                "quality": level.quality,
                "width": w,
                "height": h,
                "fps": fps,
                "reason": change.reason[:200],
            },
        )

    def adapt_fields(self) -> dict[str, Any]:
        """The adaptation's figures for `vision/stats` `data` and `status`."""
        with self._adapt_lock:
            return {
                "adapt": self.config.adapt,
                "level": self.adapter.level,
                "levels": len(self.adapter.levels),
                "adapt_seen": dict(self.adapter.last),
            }

    def _on_audience(self, watched: bool) -> None:
        if not watched:
            with self._adapt_lock:
                self.adapter.forget()
            self.pipeline.set_level(self.adapter.current)
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
            try:
                self._adapt()
            except Exception:  # a bug in the adaptation must not stop the stats
                log.exception("video adaptation failed")
            self._stats_seq += 1
            fields = self.pipeline.stats_fields()
            fields["data"] = {**fields["data"], **self.adapt_fields()}
            self._stats_pub.put(VisionStats(seq=self._stats_seq, t_ns=time.time_ns(), **fields))

    def _rpc_status(self, args: dict[str, Any]) -> dict[str, Any]:
        return {"camera": self.camera.name, **self.pipeline.stats(), **self.adapt_fields()}

    def close(self) -> None:
        self._stop.set()
        self.audience.close()
        self.pipeline.stop()
        self._stats_thread.join(timeout=2.0)
