"""The `workcell` service: the simulated workcell's physics on the bus.

It follows `robot/state` (the tool pose and the gripper command the arm reports), steps
`WorkcellSim` at `rate_hz` on a thread of its own, publishes `workcell/state` (extension,
docs/tasks.md) and reports grasps, releases, landings, collisions and spills as Events of
kind `workcell` (`data.action` says which). Methods at `robot/workcell/rpc/…`: `status`
(the state as a map) and `reset` (every object back in place).

Every view of the world follows `workcell/state` with the one scene description
(`scene.py`): the force service's simulated wrist, the vision renderer, the console and the
recorder's 3D topics; see docs/tasks.md.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from services.bus import keys
from services.bus.codec import to_fields
from services.bus.messages import RobotState, mat3, vec
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.world.workcell.config import WorkcellConfig
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState, grip_of, object_map
from services.world.workcell.physics import WorkcellSim
from services.world.workcell.scene import Scene, default_scene

log = logging.getLogger("telerobot.workcell")

SERVICE = "workcell"
EVENT_KIND = "workcell"


class WorkcellService:
    """Runs `WorkcellSim` on the bus; `close()` stops the loop (it does not close the node)."""

    def __init__(self, node: Node, config: WorkcellConfig, scene: Scene | None = None) -> None:
        self.node = node
        self.config = config
        self.sim = WorkcellSim(scene if scene is not None else default_scene(), config.physics)
        self._lock = threading.Lock()
        self._state: tuple[RobotState, int] | None = None
        self._seq = 0
        self._stop = threading.Event()
        self.steps = 0
        self._pub = node.publisher(WORKCELL_STATE)
        node.subscribe(keys.STATE, self._on_state)
        node.serve(SERVICE, {"status": self._rpc_status, "reset": self._rpc_reset})
        self._thread = threading.Thread(target=self._loop, name="workcell-loop", daemon=True)
        self._thread.start()
        node.announce()

    def _on_state(self, st: RobotState) -> None:
        self._state = (st, time.monotonic_ns())

    # --- the loop --------------------------------------------------------------------------
    def _loop(self) -> None:
        rate = RateLoop(self.config.rate_hz, on_late=self._on_late)
        every = max(1, round(self.config.rate_hz / self.config.publish_rate_hz))
        last = time.perf_counter()
        while not self._stop.is_set():
            now = time.perf_counter()
            dt, last = now - last, now
            self._step(dt)
            if self.steps % every == 0:
                self._publish()
            rate.sleep()

    def _step(self, dt_s: float) -> None:
        item = self._state
        fresh = item is not None and (
            time.monotonic_ns() - item[1] <= self.config.state_stale_ms * 1e6
        )
        with self._lock:
            if item is not None:
                st = item[0]
                # A stale stream leaves the gripper as it was (grip None): whatever it
                # holds stays held until the robot reports again.
                grip = st.grip if fresh else None
                events = self.sim.step(np.asarray(st.tool_p), mat3(st.tool_R), grip, dt_s)
            else:
                events = self.sim.step(np.zeros(3), np.eye(3), None, dt_s)
            self.steps += 1
        for ev in events:
            self.node.event(
                EVENT_KIND, ev.message, {"action": ev.kind, "object": ev.body, **ev.data}
            )

    def _message(self) -> WorkcellState:
        item = self._state
        with self._lock:
            self._seq += 1
            return WorkcellState(
                seq=self._seq,
                t_ns=time.time_ns(),
                tool_p=vec(item[0].tool_p) if item is not None else (0.0, 0.0, 0.0),
                grip=grip_of(item[0].grip if item is not None else None),
                held=self.sim.held or "",
                objects={b.name: object_map(b) for b in self.sim.bodies()},
                data={
                    **self.sim.counters,
                    "max_penetration_mm": self.sim.max_penetration_m * 1e3,
                    "steps": self.steps,
                },
            )

    def _publish(self) -> None:
        if not self.node.closed:
            self._pub.put(self._message())

    def _on_late(self, late_s: float, n_late: int) -> None:
        log.debug("workcell loop late by %.1f ms (%d late ticks)", late_s * 1e3, n_late)

    # --- methods ---------------------------------------------------------------------------
    def _rpc_status(self, args: dict[str, Any]) -> dict[str, Any]:
        """The current `workcell/state` as a map."""
        return to_fields(self._message())

    def _rpc_reset(self, args: dict[str, Any]) -> dict[str, Any]:
        """Every object back where the scene puts it, the gripper emptied (a closed one
        must open before it can grasp again)."""
        with self._lock:
            self.sim.reset(gripper_closed=self.sim.gripper_closed)
        self.node.event(EVENT_KIND, "workcell reset", {"action": "reset"})
        return to_fields(self._message())

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
