"""The `workcell` service: the one process that owns the simulated cell's physics (MuJoCo).

It builds the cell from the arm's description (`robot/arm/description`: its URDF, tool and
meshes) and the scene (`scene.py`), and steps it in real time (docs/sim.md):

- **in**: `sim/arm/cmd` (the arm's `sim` driver's joint setpoints, each checked: n joints,
  finite, within the joint limits, no jump) and the grip of `robot/state` (with no fresh
  state for `state_stale_ms` the gripper is left as it was);
- **out**: `sim/arm/state` (the joints, the wrist's wrench, the tool pose) every loop while
  anything moves, for the arm's driver and the force service's `sim` sensor;
  with an arm in the same process (`channel`, `[arm] sim_physics = "embedded"`) its
  setpoints and joints pass in memory instead (channel.py), `sim/arm/state` still out;
  `workcell/state` (extension, docs/tasks.md) at `publish_rate_hz` (`REST_STATE_HZ` while
  the physics rests); Events of kind
  `workcell` (`data.action`: grasp, missed, release, settled, toppled, spill, reset, and
  `rejected` for a refused setpoint).

Methods at `robot/workcell/rpc/…`: `status` (the state as a map) and `reset` (every object
back in place; the arm stays where it is). While nothing moves and no setpoint comes the
physics rests (it is not stepped), after `DEEP_REST_AFTER_S` of that the loop looks for a
setpoint every `REST_POLL_S` instead of at its rate, and the joints are published at the
idle rate.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

import numpy as np

from services.bus import keys
from services.bus.codec import to_fields
from services.bus.errors import ConfigError, RpcError
from services.bus.events import EventLimiter
from services.bus.messages import ArmDescription, RobotState, vec
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.world.workcell.arm import DescribedArm
from services.world.workcell.channel import ArmChannel
from services.world.workcell.config import WorkcellConfig
from services.world.workcell.engine import CellPhysics
from services.world.workcell.messages import (
    SIM_ARM_CMD,
    SIM_ARM_STATE,
    WORKCELL_STATE,
    SimArmCmd,
    SimArmState,
    WorkcellState,
    grip_of,
    object_map,
)
from services.world.workcell.scene import Scene, default_scene

log = logging.getLogger("telerobot.workcell")

SERVICE = "workcell"
EVENT_KIND = "workcell"
IDLE_AFTER_S = 0.5
"""No setpoint for this long, the arm still (below REST_SPEED) and every object resting:
the physics rests."""
REST_SPEED = 1e-5
"""rad/s, m/s: the arm's and the gripper's joints slower than this are still."""
IDLE_STATE_HZ = 20.0
REST_STATE_HZ = 5.0
"""`workcell/state` while the physics rests (nothing moves, so every message says the same):
this often instead of `publish_rate_hz`, back to that rate at the first step. At 50 Hz the
idle cell's states were decoded by vision and the force service 50 times a second."""
REST_POLL_S = 0.01
"""Once the physics has rested `DEEP_REST_AFTER_S`, the loop looks for a setpoint or a grip
this often (instead of at `rate_hz`); the first step after it covers the time since."""
DEEP_REST_AFTER_S = 2.0
"""A shorter rest (the arm holding a press between the decision's moves, a pause) keeps the
loop at its rate: a setpoint there is stepped within a tick, as before."""
MAX_CATCH_UP_S = 0.01
"""A loop late by more than this steps this much physics (it runs slower than real time
then, rather than in one leap)."""
MAX_SETPOINT_STEP_RAD = 0.5
"""A setpoint further than this from the joints is a jump: refused (the driver refuses
such a setpoint before it is sent; here is the physics' own check)."""


class WorkcellService:
    """The cell's physics on the bus (see the module docstring). `arm`: the arm to build
    (an ArmModel or DescribedArm); None: the one `robot/arm/description` describes, when it
    arrives. `close()` stops the loop (it does not close the node)."""

    def __init__(
        self,
        node: Node,
        config: WorkcellConfig,
        scene: Scene | None = None,
        arm: Any = None,
        channel: ArmChannel | None = None,
    ) -> None:
        self.node = node
        self._channel = channel
        self.config = config
        self.scene = scene if scene is not None else default_scene()
        self.physics: CellPhysics | None = None
        self._lock = threading.Lock()
        self._seq = 0
        self._arm_seq = 0
        self._cmd_seq = -1
        self._cmd_t_ns = 0
        self._last_cmd_s = 0.0
        self._last_tick_s = time.monotonic()
        self._stop = threading.Event()
        self._limiter = EventLimiter(1.0, max_keys=16)
        self.steps = 0
        self.rejected = 0
        self.wakes = 0
        """The loop's wake-ups (at `rate_hz`, and every `REST_POLL_S` once the physics has
        rested `DEEP_REST_AFTER_S`)."""
        self.resting = False
        self._pub = node.publisher(WORKCELL_STATE)
        self._arm_pub = node.publisher(SIM_ARM_STATE)
        # the arm's setpoints: in memory from an arm in this process, else over the bus
        self._cmd: Any = channel.cmd if channel is not None else node.latest(SIM_ARM_CMD)
        self._robot = node.latest(keys.STATE)
        self._desc = None if arm is not None else node.subscribe(keys.ARM_DESCRIPTION, history=True)
        self._desc_seen: tuple[str, str] | None = None
        self._desc_last: ArmDescription | None = None
        if arm is not None:
            self._build(arm)
        node.serve(SERVICE, {"status": self._rpc_status, "reset": self._rpc_reset})
        self._thread = threading.Thread(target=self._loop, name="workcell-loop", daemon=True)
        self._thread.start()
        node.announce()

    # --- the cell ---------------------------------------------------------------------
    def _build(self, arm: Any) -> None:
        """The cell of `arm`; rebuilt (a new tool) with the arm's joints where they are, so
        the arm never jumps (the objects start over where the scene puts them)."""
        old = self.physics
        q0 = old.q if old is not None and old.n == len(arm.joint_names) else None
        physics = CellPhysics(arm, self.scene, self.config.physics, q0=q0)
        with self._lock:
            self.physics = physics
        log.info("the cell of %s built (MuJoCo, %d bodies)", arm.name, physics.model.nbody)

    def _watch_description(self) -> None:
        sub = self._desc
        if sub is None:
            return
        desc: ArmDescription | None = sub.latest
        if desc is None or desc is self._desc_last:
            return  # (the same message as at the last tick: nothing to compare)
        self._desc_last = desc
        key = (desc.model, desc.urdf[:64] + repr(desc.eMt))
        if key == self._desc_seen:
            return
        self._desc_seen = key
        try:
            self._build(DescribedArm.of(desc))
        except ConfigError as e:
            log.error("%s", e)
            self.node.event("error", f"the cell cannot be built: {e}", {"code": "config"})

    # --- the loop ---------------------------------------------------------------------
    def _loop(self) -> None:
        rate = RateLoop(self.config.rate_hz, on_late=self._on_late)
        state_s = 1.0 / self.config.publish_rate_hz
        next_state = next_idle_arm = time.monotonic()
        rested_since: float | None = None
        while not self._stop.is_set():
            self.wakes += 1
            self._watch_description()
            ph = self.physics
            stepped = False
            if ph is not None:
                stepped = self._tick(ph)
                self.resting = not stepped
                now = time.monotonic()
                if stepped or now >= next_idle_arm:
                    self._publish_arm(ph)
                    next_idle_arm = now + 1.0 / IDLE_STATE_HZ
                period = state_s if stepped else 1.0 / REST_STATE_HZ
                if now >= next_state:
                    self._publish()
                    next_state += period
                    if next_state <= now:  # a late loop: on from now, no burst
                        next_state = now + period
                elif stepped and next_state > now + state_s:
                    next_state = now  # moving again after a rest: at the full rate at once
            if stepped or ph is None:
                rested_since = None
                rate.sleep()
                continue
            now = time.monotonic()
            rested_since = rested_since or now
            if now - rested_since < DEEP_REST_AFTER_S:
                rate.sleep()  # a short rest (a press held, a pause): at once on a setpoint
            elif not self._stop.wait(REST_POLL_S):
                # A long rest (nobody operating): a look every REST_POLL_S, not every tick
                # (the loop's wake-ups were the idle cell's CPU), then the rate from now.
                rate.reanchor()

    def _tick(self, ph: CellPhysics) -> bool:
        """Take the newest setpoint and grip, step if anything moves; whether it stepped."""
        now = time.monotonic()
        got = self._cmd.read()
        item = self._robot.read()
        events = []
        with self._lock:
            if got is not None and got[0].seq != self._cmd_seq:
                self._cmd_seq = got[0].seq
                if self._take(ph, got[0]):
                    self._last_cmd_s = now
            grip: float | None = None
            if item is not None:
                st: RobotState = item[0]
                fresh = (time.monotonic_ns() - item[1]) <= self.config.state_stale_ms * 1e6
                if fresh and st.grip is not None:
                    grip = st.grip
                    if (grip > 0.5) != ph.gripper_closed:
                        self._last_cmd_s = now
            ph.command(None, grip)
            elapsed, self._last_tick_s = now - self._last_tick_s, now
            if now - self._last_cmd_s > IDLE_AFTER_S and self._resting(ph):
                return False
            # Real time: the steps of the wall time since the last tick (a late loop
            # catches up, within MAX_CATCH_UP_S; beyond, the simulation runs slower).
            h = ph.model.opt.timestep
            n = max(1, min(round(elapsed / h), round(MAX_CATCH_UP_S / h)))
            events = ph.step(n)
            self.steps += n
        for ev in events:
            self.node.event(
                EVENT_KIND, ev.message, {"action": ev.kind, "object": ev.body, **ev.data}
            )
        return True

    def _take(self, ph: CellPhysics, cmd: SimArmCmd) -> bool:
        """The setpoint to the servos if it is one the arm can take; else an event."""
        why = self._check(ph, cmd.q)
        if why is not None:
            self.rejected += 1
            if self._limiter.allow("rejected") is not None:
                self.node.event(
                    EVENT_KIND, f"setpoint refused: {why}", {"action": "rejected", "why": why}
                )
            return False
        if cmd.halt:
            ph.brake()
        else:
            dt = (cmd.t_ns - self._cmd_t_ns) * 1e-9 if self._cmd_t_ns else None
            ph.command(cmd.q, dt_s=dt)
        self._cmd_t_ns = cmd.t_ns
        return True

    @staticmethod
    def _check(ph: CellPhysics, q: tuple[float, ...]) -> str | None:
        if len(q) != ph.n:
            return f"{len(q)} joints, the arm has {ph.n}"
        if not all(map(math.isfinite, q)):
            return "not finite"
        lo, hi = ph.model.jnt_range[ph.model.dof_jntid[ph.cell.dof_adr]].T
        now = ph.q
        for j, x in enumerate(q):
            if not lo[j] - 1e-9 <= x <= hi[j] + 1e-9:
                return f"q{j + 1} = {x:.4f} rad outside the joint limits"
            if abs(x - now[j]) > MAX_SETPOINT_STEP_RAD:
                return f"q{j + 1} jumps {abs(x - now[j]):.3f} rad"
        return None

    @staticmethod
    def _resting(ph: CellPhysics) -> bool:
        """The arm and the gripper still, every object resting (a bottle standing on the
        table rocks by a mm/s in MuJoCo's contacts, which need not be stepped)."""
        arm = float(np.max(np.abs(ph.data.qvel[ph.arm_dofs]), initial=0.0))
        return arm < REST_SPEED and ph.held is None and ph.all_resting()

    def _publish_arm(self, ph: CellPhysics) -> None:
        if self.node.closed:
            return
        with self._lock:
            self._arm_seq += 1
            f, c = ph.wrench_t()
            p, R = ph.tool_pose()
            msg = SimArmState(
                seq=self._arm_seq,
                t_ns=time.time_ns(),
                sim_ns=int(ph.t_s * 1e9),
                q=vec(ph.q),
                qd=vec(ph.qd),
                f_t=vec(f),
                c_t=vec(c),
                tool_p=vec(p),
                tool_R=vec(R),
                cmd_seq=max(0, self._cmd_seq),
            )
        if self._channel is not None:
            self._channel.state.put(msg)
        self._arm_pub.put(msg)

    def _message(self) -> WorkcellState:
        with self._lock:
            self._seq += 1
            ph = self.physics
            if ph is None:
                return WorkcellState(
                    seq=self._seq, t_ns=time.time_ns(), tool_p=(0.0, 0.0, 0.0), grip=0.0,
                    held="", objects={}, data={"steps": 0},
                )  # fmt: skip
            p, _ = ph.tool_pose()
            return WorkcellState(
                seq=self._seq,
                t_ns=time.time_ns(),
                tool_p=vec(p),
                grip=grip_of(1.0 if ph.gripper_closed else 0.0),
                held=ph.held or "",
                objects={b.name: object_map(b) for b in ph.bodies()},
                data={
                    **ph.counters,
                    "steps": self.steps,
                    "rejected": self.rejected,
                    "wakes": self.wakes,
                },
            )

    def _publish(self) -> None:
        if not self.node.closed:
            self._pub.put(self._message())

    def _on_late(self, late_s: float, n_late: int) -> None:
        log.debug("workcell loop late by %.1f ms (%d late ticks)", late_s * 1e3, n_late)

    # --- methods ----------------------------------------------------------------------
    def _rpc_status(self, args: dict[str, Any]) -> dict[str, Any]:
        """The current `workcell/state` as a map."""
        return to_fields(self._message())

    def _rpc_reset(self, args: dict[str, Any]) -> dict[str, Any]:
        """Every object back where the scene puts it; the arm stays where it is, the
        gripper as commanded."""
        with self._lock:
            ph = self.physics
            if ph is None:
                raise RpcError("unavailable", "the cell is not built yet (no arm description)")
            q, sp = ph.q, ph.setpoint()
            ph.reset(q, grip=1.0 if ph.gripper_closed else 0.0)
            ph.command(sp)
            self._last_cmd_s = time.monotonic()
        self.node.event(EVENT_KIND, "workcell reset", {"action": "reset"})
        return to_fields(self._message())

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
