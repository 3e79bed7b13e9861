"""The bridge on the bus: Telerobot streams → rmw_zenoh topics, /telerobot/tool_target → robot/cmd.

Our side is a `Node` like every service's (`alive/ros2`, events, `--ns`); the ROS side is a
`RosNode` on the same Zenoh session, or, with a Zenoh namespace (`--ns cell2`), on a second
session without one (ROS keys must not carry our prefix; the ROS namespace becomes /cell2).

Work happens only when something arrives, and only what someone reads:
- robot/state and robot/force reach this process already downsampled by Zenoh (a
  `downsampling` rule in this node's session, `bridge_node_config`), so Python sees
  `state_rate_hz` and `wrench_rate_hz` callbacks, not 250 + 1000 per second;
- robot/force and the video are subscribed on our side only while a ROS subscriber matches
  the ROS publisher (Zenoh's matching status); robot/state always (the master needs the
  tool pose), converted only when /joint_states or /tf has a subscriber;
- callbacks convert and publish, nothing else; the master's thread sleeps until a target
  arrives and streams commands only while targets are fresh.

The arm is the one robot/arm/description describes (any model: convert.ArmView): its URDF,
with the tool link added, is /robot_description (latched, republished when the description
changes, e.g. on `set_tool`); its joint names are /joint_states'; its URDF joints are /tf's.
Until a description has come, nothing about the arm is published and targets are refused
(the world frame is not known to ROS); `status()["arm_note"]` and the log say so.

The target master (services/frontends/ros2/target_master.py) drives the arm through the
decision server like any master: `robot/cmd` with master id `ros2`, token
`alive/master/ros2`; lease, limits and watchdogs apply. Every exit path sends inactive
commands, so the decision holds.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from services.bus import codec, keys
from services.bus.config import NodeConfig
from services.bus.errors import ConfigError, ProtocolError
from services.bus.keys import Topic, alive_key, with_ns
from services.bus.messages import (
    ArmDescription,
    ForceSample,
    OperatorCommand,
    RobotState,
    StereoFrame,
)
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.bus.streams import newer
from services.frontends.ros2 import convert, rmw
from services.frontends.ros2.config import Ros2Config
from services.frontends.ros2.graph import RosNode, RosPublisher
from services.frontends.ros2.target_master import (
    HOLD_REPEATS,
    TargetLimits,
    TargetMaster,
    TargetRefused,
    check_target,
)
from services.frontends.rosmsg import defs, msgs
from services.frontends.rosmsg.cdr import CdrError

log = logging.getLogger("telerobot.ros2")

STATE_STALE_S = 0.5
"""A robot/state older than this does not start an engagement (the pose is unknown)."""
NO_DESCRIPTION = "waiting for robot/arm/description: nothing about the arm is published"
TF_DEPTH = 100
"""tf2's broadcaster depth."""
TARGET_TOPIC = "telerobot/tool_target"


@dataclass(frozen=True, slots=True)
class DownsampledNodeConfig(NodeConfig):
    """A NodeConfig whose session receives some keys at a bounded rate (Zenoh `downsampling`,
    ingress): `rates_hz` pairs a key (without namespace) with its maximum rate."""

    rates_hz: tuple[tuple[str, float], ...] = ()

    def to_zenoh(self) -> zenoh.Config:
        cfg = NodeConfig.to_zenoh(self)
        if self.rates_hz:
            # The rules see keys as they travel, so with the namespace prefix.
            rules = [{"key_expr": with_ns(k, self.ns), "freq": hz} for k, hz in self.rates_hz]
            cfg.insert_json5(
                "downsampling",
                json.dumps([{"flows": ["ingress"], "messages": ["put"], "rules": rules}]),
            )
        return cfg


def bridge_node_config(base: NodeConfig, config: Ros2Config) -> DownsampledNodeConfig:
    """The bridge's node config: `base` plus the downsampling of robot/state and robot/force."""
    values = {f: getattr(base, f) for f in NodeConfig.__dataclass_fields__}
    return DownsampledNodeConfig(
        **values,
        rates_hz=(
            (keys.STATE.key, config.state_rate_hz),
            (keys.FORCE.key, config.wrench_rate_hz),
        ),
    )


def _loopback(endpoint: str) -> str:
    return endpoint.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")


def ros_side_config(base: NodeConfig) -> zenoh.Config:
    """The second session's config when our side has a Zenoh namespace: the same network, no
    namespace, no listener of its own (it dials what our node dials, or our node itself)."""
    endpoints = base.connect or tuple(_loopback(e) for e in base.listen)
    if not endpoints:
        raise ConfigError("zenoh.connect", "with --ns the ROS side needs an endpoint to reach")
    plain = NodeConfig(
        mode="client" if base.mode == "client" else "peer",
        connect=endpoints,
        listen=tuple(e for e in base.listen if e.endswith(":0")),  # loopback stays loopback
        lease_ms=base.lease_ms,
        multicast_scouting=base.multicast_scouting,
        zenoh_config=base.zenoh_config,
    )
    return plain.to_zenoh()


class _Gate:
    """A bus subscription that exists only while one of `pubs` has a ROS subscriber."""

    def __init__(
        self,
        node: Node,
        topic: Topic[Any],
        on_msg: Callable[[Any], None],
        pubs: list[RosPublisher],
    ) -> None:
        self._node = node
        self._topic = topic
        self._on_msg = on_msg
        self._pubs = pubs
        self._lock = threading.Lock()
        self._sub: Any = None
        self._closed = False
        for p in pubs:
            p.on_matching(self._changed)

    def _callback(self, sample: zenoh.Sample) -> None:
        try:
            msg = codec.decode(self._topic.type, sample.payload.to_bytes())
        except ProtocolError as e:
            self._node.report_rejected(str(sample.key_expr), str(e))
            return
        self._on_msg(msg)

    def _changed(self, _matching: bool) -> None:
        want = any(p.matching for p in self._pubs)
        with self._lock:
            if self._closed or self._node.closed:
                return
            if want and self._sub is None:
                self._sub = self._node.session.declare_subscriber(self._topic.key, self._callback)
            elif not want and self._sub is not None:
                self._sub.undeclare()
                self._sub = None

    @property
    def active(self) -> bool:
        with self._lock:
            return self._sub is not None

    def close(self) -> None:
        with self._lock:
            self._closed = True
            sub, self._sub = self._sub, None
        if sub is not None:
            try:
                sub.undeclare()
            except zenoh.ZError:
                log.debug("undeclare failed", exc_info=True)


class Ros2Service:
    """Runs the bridge on `node` (opened with `bridge_node_config`); `close()` holds the arm."""

    def __init__(
        self,
        node: Node,
        config: Ros2Config,
        *,
        seq_start: int | None = None,
        engage_start: int | None = None,
    ) -> None:
        self.node = node
        self.config = config
        self.domain_id = config.resolved_domain_id()
        self.namespace = config.resolved_namespace(node.config.ns)
        self._lock = threading.Lock()
        self._description_lock = threading.Lock()
        """Held while a description is turned into the arm's view (descriptions in order)."""
        self._description: ArmDescription | None = None
        self.arm: convert.ArmView | None = None
        """The arm as ROS sees it; None until a description that can be bridged has come."""
        self.limits: TargetLimits | None = None
        """What a target must satisfy: its frame is the described arm's world frame."""
        self._urdf_sent: str | None = None
        self._arm_note = NO_DESCRIPTION
        self._noted: set[str] = set()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._state: RobotState | None = None
        self._state_rx_s = -1e9
        self._warned_raw_video = False
        self.master = TargetMaster(config.target_timeout_s, seq_start, engage_start)
        self.targets_accepted = 0
        self.targets_refused = 0
        self.commands_sent = 0
        self._own_session: zenoh.Session | None = None
        try:
            rmw.check_name(self.namespace, "namespace")
        except ValueError as e:
            raise ConfigError("ros2.namespace", f"{e}; set [ros2] namespace") from None
        if node.config.ns:
            self._own_session = zenoh.open(ros_side_config(node.config))
        session = self._own_session or node.session
        try:
            self.ros = RosNode(session, self.domain_id, self.namespace, config.node_name)
            self._declare(session)
        except BaseException:
            if self._own_session is not None:
                self._own_session.close()
            raise
        self._thread = threading.Thread(target=self._master_loop, name="ros2-master", daemon=True)
        self._thread.start()
        node.announce()
        node.event(
            "status",
            f"ros2 bridge up: domain {self.domain_id}, node {self.ros.fqn(config.node_name)}",
            {"domain_id": self.domain_id, "namespace": self.namespace, "node": config.node_name},
        )

    # --- declarations -----------------------------------------------------------------
    def _declare(self, session: zenoh.Session) -> None:
        cfg, ros = self.config, self.ros
        reliable = rmw.Qos(depth=10)
        self.pub_joint_states = ros.publisher(
            "joint_states", defs.JOINT_STATE, reliable, zenoh.Priority.INTERACTIVE_HIGH
        )
        self.pub_tf = ros.publisher(
            "tf", defs.TF_MESSAGE, rmw.Qos(depth=TF_DEPTH), zenoh.Priority.INTERACTIVE_HIGH
        )
        self.pub_wrench = ros.publisher(
            "wrench", defs.WRENCH_STAMPED, reliable, zenoh.Priority.INTERACTIVE_HIGH
        )
        self.pub_description = ros.publisher("robot_description", defs.STRING_MSG, rmw.LATCHED)
        self.cmd = self.node.publisher(keys.CMD)
        self._master_token = self.node.session.liveliness().declare_token(
            alive_key("master", cfg.master_id)
        )
        self.state_sub = self.node.subscribe(keys.STATE, self._on_state)
        self.force_gate = _Gate(self.node, keys.FORCE, self._on_force, [self.pub_wrench])
        self.video_gates: list[_Gate] = []
        self.video_pubs: dict[str, tuple[RosPublisher, RosPublisher, str]] = {}
        if cfg.video:
            for eye, side, frame, topic in (
                ("l", "left", cfg.camera_frames[0], keys.STEREO_L),
                ("r", "right", cfg.camera_frames[1], keys.STEREO_R),
            ):
                image = ros.publisher(
                    f"stereo/{side}/image_raw/compressed",
                    defs.COMPRESSED_IMAGE,
                    rmw.SENSOR_DATA,
                    zenoh.Priority.DATA_LOW,
                )
                info = ros.publisher(
                    f"stereo/{side}/camera_info",
                    defs.CAMERA_INFO,
                    rmw.SENSOR_DATA,
                    zenoh.Priority.DATA_LOW,
                )
                self.video_pubs[eye] = (image, info, frame)
                self.video_gates.append(_Gate(self.node, topic, self._on_frame, [image, info]))
        self.sub_target = ros.subscription(
            TARGET_TOPIC, defs.POSE_STAMPED, reliable, self._on_target
        )
        self._target_where = f"ros2:{self.ros.fqn(TARGET_TOPIC)}"
        # Last: its history reply may come at once, and every publisher must exist by then.
        self.description_sub = self.node.subscribe(
            keys.ARM_DESCRIPTION, self._on_description, history=True
        )

    # --- the arm's description ----------------------------------------------------------
    def _on_description(self, desc: ArmDescription) -> None:
        """A new description: the arm's view, then its URDF on /robot_description (only
        when the text changed: a repeated description does not wake RViz)."""
        with self._description_lock:
            with self._lock:
                if not newer(desc, self._description):
                    return  # the history's copy of one already applied
                self._description = desc
            try:
                view = convert.ArmView(desc, self.config.tool_frame)
            except ConfigError as e:
                note = (
                    f"the description of {desc.model!r} cannot be bridged ({e.reason}): "
                    "nothing about the arm is published"
                )
                with self._lock:
                    self.arm, self.limits, self._arm_note = None, None, note
                log.error("ros2: %s", note)
                self.node.event("error", f"ros2: {note}", {"model": desc.model})
                return
            limits = TargetLimits(
                frame_id=view.world_frame,
                max_radius_m=self.config.max_target_radius_m,
                max_distance_m=self.config.max_target_distance_m,
            )
            with self._lock:
                first = self.arm is None
                self.arm, self.limits, self._arm_note = view, limits, ""
            if view.urdf != self._urdf_sent:
                self.pub_description.put(msgs.encode(msgs.String(view.urdf)))
                self._urdf_sent = view.urdf
            if first:
                log.info(
                    "ros2: arm %s (%d joints, %s → %s → %s) on /robot_description, "
                    "/joint_states and /tf",
                    view.model, view.n, view.world_frame, view.flange_frame, view.tool_frame,
                )  # fmt: skip

    def _note(self, note: str) -> None:
        """Say once (per reason) why a robot/state is not shown to ROS."""
        with self._lock:
            if note in self._noted:
                return
            self._noted.add(note)
        # Waiting is normal for a moment at start-up; anything else is worth a warning.
        log.log(logging.INFO if note == NO_DESCRIPTION else logging.WARNING, "ros2: %s", note)

    # --- Telerobot → ROS (Zenoh's threads: convert and publish) --------------------------
    def _on_state(self, st: RobotState) -> None:
        with self._lock:
            self._state, self._state_rx_s = st, time.monotonic()
            arm = self.arm
            if arm is not None:
                fits = arm.fits(st)
                self._arm_note = "" if fits else (
                    f"robot/state has {len(st.q)} joints, the described {arm.model} "
                    f"{arm.n}: nothing about the arm is published until they agree"
                )  # fmt: skip
            note = self._arm_note
        if note or arm is None:
            self._note(note or NO_DESCRIPTION)
            return
        if self.pub_joint_states.matching:
            self.pub_joint_states.put(msgs.encode(arm.joint_state(st)))
        if self.pub_tf.matching:
            self.pub_tf.put(msgs.encode(arm.tf(st)))

    def _on_force(self, f: ForceSample) -> None:
        self.pub_wrench.put(msgs.encode(convert.wrench(f, self.config.tool_frame)))

    def _on_frame(self, fr: StereoFrame) -> None:
        if fr.encoding != "jpeg":
            if not self._warned_raw_video:
                self._warned_raw_video = True
                self.node.event(
                    "error",
                    'ros2: raw bgr8 frames are not bridged (set [vision] encoding = "jpeg")',
                )
            return
        image, info, frame = self.video_pubs[fr.eye]
        if image.matching:
            image.put(msgs.encode(convert.compressed_image(fr, frame)))
        if info.matching:
            info.put(msgs.encode(convert.camera_info(fr, frame)))

    # --- ROS → Telerobot: the target master ----------------------------------------------
    def _fresh_tool(self) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
        with self._lock:
            st, rx = self._state, self._state_rx_s
        if (
            st is None
            or time.monotonic() - rx > STATE_STALE_S
            or st.status not in ("ready", "moving")
        ):
            return None
        return st.tool_p, st.tool_R

    def _on_target(self, payload: bytes, _attachment: bytes | None) -> None:
        tool = self._fresh_tool()
        with self._lock:
            limits, note = self.limits, self._arm_note
        try:
            pose = msgs.decode(msgs.PoseStamped, payload)
            if limits is None:
                raise TargetRefused(
                    "no robot/arm/description yet: the world frame is unknown"
                    if note == NO_DESCRIPTION
                    else f"no arm to drive: {note}"
                )
            target = check_target(pose, limits, None if tool is None else tool[0])
        except (CdrError, TargetRefused) as e:
            with self._lock:
                self.targets_refused += 1
            self.node.report_rejected(self._target_where, str(e))
            return
        with self._lock:
            self.master.on_target(target, time.monotonic())
            self.targets_accepted += 1
        self._wake.set()

    def _master_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait()
            self._wake.clear()
            rate = RateLoop(self.config.master_rate_hz)
            while not self._stop.is_set():
                tool = self._fresh_tool()
                with self._lock:
                    cmd = self.master.tick(time.monotonic(), tool)
                if cmd is None:
                    break
                self._send(cmd)
                rate.sleep()

    def _send(self, cmd: Any) -> None:
        msg = OperatorCommand(
            seq=cmd.seq,
            t_ns=time.time_ns(),
            master=self.config.master_id,
            engage=cmd.engage,
            active=cmd.active,
            frame="world",
            dp=cmd.dp,
            dR=cmd.dR,
        )
        try:
            self.cmd.put(msg)
        except (ProtocolError, zenoh.ZError) as e:
            log.warning("command not sent: %s", e)
            return
        with self._lock:
            self.commands_sent += 1

    # --- lifecycle -----------------------------------------------------------------------
    def close(self) -> None:
        """Hold the arm (inactive commands), stop the master, leave the ROS graph."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)
        with self._lock:
            was_engaged = self.master.engaged
            holds = [self.master.hold() for _ in range(HOLD_REPEATS)] if was_engaged else []
        if not self.node.closed:
            for cmd in holds:
                self._send(cmd)
        self.force_gate.close()
        for g in self.video_gates:
            g.close()
        self.ros.close()
        try:
            self._master_token.undeclare()
        except zenoh.ZError:
            log.debug("undeclare of the master token failed", exc_info=True)
        if self._own_session is not None:
            self._own_session.close()

    def status(self) -> dict[str, Any]:
        """Counters for tests and `telerobot call`-style introspection."""
        with self._lock:
            return {
                "domain_id": self.domain_id,
                "namespace": self.namespace,
                "arm": None if self.arm is None else self.arm.model,
                "arm_note": self._arm_note,
                "targets_accepted": self.targets_accepted,
                "targets_refused": self.targets_refused,
                "commands_sent": self.commands_sent,
                "engaged": self.master.engaged,
                "engage": self.master.engage,
                "force_subscribed": self.force_gate.active,
                "video_subscribed": [g.active for g in self.video_gates],
            }
