"""The `force` service on the bus: `robot/force` at 1 kHz and IForceSensor at robot/force/rpc.

Each sample is encoded by a dedicated ForceSample encoder (encoder.py, byte-identical to the
codec) and put on the bus from the sampling thread itself (`handoff = "inline"`, the
default): no queue and no thread wake-up per sample. The arm's pose from `robot/state`
drives gravity compensation (and the sim sensor's free-space weight and inertia) and
follows the arm's `set_tool`; with the sim sensor, `sim/arm/state` carries the wrench the
workcell's physics computes at the wrist (contacts, a carried object). A workcell that is
alive (`workcell/state` flows) while no physics wrench ever arrives is a configuration
error a user can make (the arm on `sim_physics = "own"`: its wrist touches nothing): said
once, `NO_PHYSICS_GRACE_S` after the first `workcell/state`, as a `status` event
(`data.code = "no_physics"`) and a warning in the log.

Nobody listening, nothing sent: while no one subscribes to `robot/force` (Zenoh's matching
status, `bus.audience`) the sensor keeps sampling (status, bias and `sensor_read` stay
current; the simulated sensor every 20 ms instead of every period, `ForceCore.set_unused`)
but no sample is encoded or put, and the router forwards nothing. The first subscriber is
seen within a round trip to the router; samples flow from then on at the full rate, their
`seq` counting the ones not sent (`sensor_status` adds `publishing`, `unsent`, `idle`).
"""

from __future__ import annotations

import logging
import time
from typing import Any

from services.bus import codec, keys
from services.bus.audience import Audience
from services.bus.bounds import check_norm
from services.bus.errors import RpcError
from services.bus.messages import IDENTITY_R, ForceSample, RobotState, Rot, Vec3
from services.bus.node import Node
from services.control.force.backends import open_force_sensor
from services.control.force.config import ForceConfig
from services.control.force.core import ForceCore
from services.control.force.encoder import ForceSampleEncoder
from services.world.workcell.messages import (
    SIM_ARM_STATE,
    WORKCELL_STATE,
    SimArmState,
    WorkcellState,
)

log = logging.getLogger("telerobot.force")

NO_PHYSICS_GRACE_S = 3.0
"""How long a live workcell may go without a physics wrench before that is said (s)."""


class ForceService:
    """Runs the force sensor; `close()` stops sensing and closes the sensor."""

    def __init__(self, node: Node, config: ForceConfig) -> None:
        self.node = node
        self.config = config
        self._pub = node.publisher(keys.FORCE)
        self._encode = ForceSampleEncoder().encode
        # Nobody subscribed to robot/force, nothing sent: the sensor keeps sampling (its
        # status, bias and `sensor_read` stay current), the samples are not encoded or put.
        self._watched = False
        self.unsent = 0
        self._cell_seen: float | None = None  # the first workcell/state (monotonic s)
        self.no_physics = False  # said: a live workcell, no physics wrench at the wrist
        self.core = ForceCore(open_force_sensor(config), config, self._publish, self._emit)
        # Before sensing starts (autostart, below): its first call says who listens now.
        self.audience = Audience(node.session, (keys.FORCE.key,), self._on_audience)
        node.subscribe(keys.STATE, self._on_state)
        if config.sensor == "sim":
            node.subscribe(WORKCELL_STATE, self._on_workcell)
            # the cell's physics (MuJoCo, docs/sim.md): the wrist's wrench as it computes it
            node.subscribe(SIM_ARM_STATE, self._on_physics)
        core = self.core
        node.serve(
            "force",
            {
                "sensor_status": self._rpc_sensor_status,
                # `status` like every other service (the same reply as sensor_status)
                "status": self._rpc_sensor_status,
                "sensor_start": core.rpc_sensor_start,
                "sensor_stop": core.rpc_sensor_stop,
                "sensor_config": core.rpc_sensor_config,
                "sensor_bias": core.rpc_sensor_bias,
                "sensor_compliance": core.rpc_sensor_compliance,
                "sensor_read": core.rpc_sensor_read,
                "set_tool": self._rpc_set_tool,
            },
            # never block (counters and the newest sample): answered in Zenoh's callback
            inline=("sensor_status", "status", "sensor_read"),
        )
        if config.autostart:
            try:
                core.rpc_sensor_start({})
            except RpcError as e:
                log.error("force sensor did not start: %s", e.message)
                node.event(
                    "error", f"force sensor did not start: {e.message}", {"sensor": config.sensor}
                )
        node.announce()

    def encode_sample(self, s: ForceSample) -> bytes:
        """The sample's `robot/force` payload (what `codec.encode(ForceSample(...))` gives)."""
        return self._encode(s.seq, s.t_ns, s.f, s.c, s.raw, s.estimate)

    def _publish(self, s: ForceSample) -> None:
        if not self._watched:
            self.unsent += 1
            return
        self._pub.put_bytes(self._encode(s.seq, s.t_ns, s.f, s.c, s.raw, s.estimate))

    def _on_audience(self, watched: bool) -> None:
        self._watched = watched
        self.core.set_unused(not watched)
        log.info("robot/force %s", "has subscribers: publishing" if watched else "unwatched")

    def _rpc_sensor_status(self, args: dict[str, Any]) -> dict[str, Any]:
        """PROTOCOL's `sensor_status`, plus `publishing` (anyone subscribes to robot/force),
        `unsent` (samples taken while nobody did) and `idle` (the simulated sensor sampled
        every IDLE_PERIOD_MS meanwhile)."""
        return {
            **self.core.rpc_sensor_status(args),
            "publishing": self._watched,
            "unsent": self.unsent,
            "idle": self.core.idle,
        }

    def _emit(self, kind: str, message: str, data: dict[str, Any]) -> None:
        """A sensor event on robot/events, and in the log: a silent or failing sensor is
        said where the operator and the lab's journal both see it."""
        if kind in ("stale", "error"):
            log.warning("%s", message)
        elif kind == "recovered":
            log.info("%s", message)
        self.node.event(kind, message, data)

    def _on_state(self, st: RobotState) -> None:
        # Decoded by the codec: finite, rotations proper (PROTOCOL.md conventions).
        self.core.update_robot_state_checked(
            st.tool_p,  # type: ignore[arg-type]
            st.tool_R,  # type: ignore[arg-type]
            (st.flange_p, st.flange_R),  # type: ignore[arg-type]
            st.t_ns,
        )

    def _on_physics(self, st: SimArmState) -> None:
        self.core.update_physics(st.f_t, st.c_t)  # type: ignore[arg-type]

    def _on_workcell(self, _ws: WorkcellState) -> None:
        """A live workcell: its physics' wrench should reach the wrist within the grace."""
        if self.no_physics or self.core.physics_updates:
            return
        now = time.monotonic()
        if self._cell_seen is None:
            self._cell_seen = now
            return
        if now - self._cell_seen < NO_PHYSICS_GRACE_S:
            return
        self.no_physics = True
        message = (
            f"the workcell is running but no physics wrench came in {NO_PHYSICS_GRACE_S:.0f} s:"
            ' the sim wrist is in free space (the arm on sim_physics = "own"?)'
        )
        log.warning("%s", message)
        self.node.event("status", message, {"code": "no_physics", "sensor": "sim"})

    def _rpc_set_tool(self, args: dict[str, Any]) -> dict[str, Any]:
        """The tool placement eMt (as arm's `set_tool {p, R}`); also followed from robot/state."""
        p = codec.arg(args, "p", Vec3)
        check_norm("p", p, "tool_offset_m")  # as the arm's set_tool: a tool within 1 m
        self.core.set_tool(p, codec.arg(args, "R", Rot, IDENTITY_R))
        return self._rpc_sensor_status({})

    def close(self) -> None:
        self.core.close()
        self.audience.close()
