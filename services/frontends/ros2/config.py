"""Settings of the ROS 2 bridge: the `[ros2]` table of a deployment TOML, read at start-up."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields

from services.bus.errors import ConfigError
from services.frontends.ros2 import rmw

MAX_DOMAIN_ID = 232
"""ROS 2's largest domain id (the DDS port arithmetic limit, kept by every rmw)."""


@dataclass(frozen=True, slots=True)
class Ros2Config:
    """How Telerobot appears to ROS 2 (docs/ros2.md).

    domain_id: ROS_DOMAIN_ID of the published keys (None: the environment's, else 0).
    namespace: the ROS node's namespace ("": "/<zenoh ns>" with `--ns`, else "/").
    node_name: the ROS node's name.
    state_rate_hz: /joint_states and /tf, taken from robot/state downsampled by Zenoh.
    wrench_rate_hz: /wrench, from robot/force downsampled by Zenoh (default 250 Hz).
    video: bridge the stereo JPEG frames as CompressedImage + CameraInfo.
    master_id: the id of the target master (`robot/cmd` field `master`, token
      `alive/master/<id>`); master_rate_hz: its command rate while targets are fresh;
      target_timeout_s: a target older than this holds.
    max_target_distance_m, max_target_radius_m: a target farther than this from the tool,
      or from the world origin, is refused.
    tool_frame: the frame id of the tool (the link /robot_description adds at the arm's eMt,
      the child of the flange on /tf, /wrench's frame); camera_frames: the stereo images'.
      The world and the arm's links are the URDF's own (the arm's description).
    """

    domain_id: int | None = None
    namespace: str = ""
    node_name: str = "telerobot"
    state_rate_hz: float = 50.0
    wrench_rate_hz: float = 250.0
    video: bool = True
    master_id: str = "ros2"
    master_rate_hz: float = 100.0
    target_timeout_s: float = 0.5
    max_target_distance_m: float = 0.5
    max_target_radius_m: float = 2.0
    tool_frame: str = "tool"
    camera_frames: tuple[str, str] = ("stereo_left", "stereo_right")

    def __post_init__(self) -> None:
        if self.domain_id is not None and not 0 <= self.domain_id <= MAX_DOMAIN_ID:
            raise ConfigError("ros2.domain_id", f"must be within 0…{MAX_DOMAIN_ID}")
        for key in ("namespace", "node_name"):
            try:
                rmw.check_name(getattr(self, key), key)
            except ValueError as e:
                raise ConfigError(f"ros2.{key}", str(e)) from None
        if "/" in self.node_name or not self.node_name:
            raise ConfigError("ros2.node_name", "a plain name without '/'")
        for f in fields(self):
            v = getattr(self, f.name)
            positive = isinstance(v, float | int) and math.isfinite(v) and v > 0
            if f.name.endswith(("_hz", "_s", "_m")) and not positive:
                raise ConfigError(f"ros2.{f.name}", f"must be a positive number, got {v!r}")
        if self.master_rate_hz < 50.0:
            raise ConfigError("ros2.master_rate_hz", "must be ≥ 50 Hz (PROTOCOL §3 robot/cmd)")
        if self.state_rate_hz > 1000.0 or self.wrench_rate_hz > 1000.0:
            raise ConfigError("ros2", "state_rate_hz and wrench_rate_hz must be ≤ 1000 Hz")
        if not self.master_id or "/" in self.master_id or "*" in self.master_id:
            raise ConfigError("ros2.master_id", "a plain name without '/' or '*'")
        frames = (self.tool_frame, *self.camera_frames)
        if any(not f or len(f) > 128 for f in frames) or len(set(frames)) != len(frames):
            raise ConfigError("ros2", "frame ids must be distinct, non-empty, ≤ 128 characters")

    def resolved_domain_id(self) -> int:
        """`domain_id`, else ROS_DOMAIN_ID from the environment (as ROS reads it), else 0."""
        if self.domain_id is not None:
            return self.domain_id
        raw = os.environ.get("ROS_DOMAIN_ID", "").strip()
        if not raw:
            return 0
        if not raw.isdigit() or int(raw) > MAX_DOMAIN_ID:
            raise ConfigError("ROS_DOMAIN_ID", f"{raw!r} is not a domain id 0…{MAX_DOMAIN_ID}")
        return int(raw)

    def resolved_namespace(self, zenoh_ns: str) -> str:
        """The ROS namespace: `namespace`, else "/<zenoh ns>" (so cells stay apart), else "/"."""
        if self.namespace:
            return "/" + self.namespace.strip("/")
        return "/" + zenoh_ns.strip("/") if zenoh_ns else "/"
