"""The `arm` service on the bus: IProxyRobot at robot/arm/rpc, `robot/state`, `robot/arm/target`,
and the arm's description (`describe`, `robot/arm/description`, cached for late subscribers).

One tick at a time owns the arm (franka-node's rule: `_tick_lock`). A target is applied on
arrival, in Zenoh's callback while the arm keeps up (`Node.batches`): the newest of what
came is checked, solved and ticked at once, so the arm gets the new setpoint one IK and one
safety step after the target arrived, with no thread to wake. A target that comes while the
control thread ticks, or behind a backlog, is stored (latest wins) for that thread, which
takes it next. Between targets the control thread runs alone: while a motion, brake or
servo runs it ticks at
`control_rate_hz` and publishes `robot/state` at `state_rate_hz`; at rest it only watches the
arm and publishes the (unchanged, cached) state at `idle_state_rate_hz` (≥ 100 Hz, the
contract's floor). Methods that do not block run in Zenoh's callback, the others on the
node's worker pool; both only plan under the proxy's lock and wake the loop. Every exit path
(close, a crash of the loop, SIGTERM through `__main__`) holds the arm.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from typing import TYPE_CHECKING, Annotated, Any

from services.bus import codec, keys
from services.bus.bounds import check
from services.bus.errors import RpcError
from services.bus.messages import ArmDescription, ArmTarget, MaxLen, RobotState
from services.bus.node import Node
from services.control.arm.backends import open_arm
from services.control.arm.config import ArmConfig
from services.control.arm.driver import Clocked
from services.control.arm.model import ArmModel, load_model
from services.control.arm.proxy import ArmProxy

if TYPE_CHECKING:
    from services.world.workcell.channel import ArmChannel

log = logging.getLogger("telerobot.arm")

#: methods that start a motion and so accept `"wait": true` (initialize: until calibrated)
MOTIONS = ("initialize", "move_joints", "move_pose", "move_relative", "home")
#: motions the decision server supervises: while one is alive, only it may start them
SUPERVISED = ("move_joints", "move_pose", "move_relative", "home")
#: methods that never block (no I/O with the arm, no waiting): answered in Zenoh's callback
INLINE = ("status", "describe", "set_frame", "stop", "fk", "limits")
WAIT_TIMEOUT_S = 120.0
MAX_REQUESTS = 256
"""Motion request ids remembered (oldest forgotten first) so a retry never moves twice."""
RequestId = Annotated[str, MaxLen(64)]
"""A motion call's optional `request_id`: a retry with the same id gets the same motion."""
IDLE_STATE_RATE_HZ = 100.0
"""robot/state's rate while the arm rests (PROTOCOL §3: ≥ 100 Hz)."""
MIN_TICK_S = 1e-5
MAX_TICK_S = 0.01
"""A tick advances the motion by the time since the last one, within these bounds (a
command can arrive right after a tick; a stalled thread must not make one long step)."""


class ArmService:
    """Runs the arm's proxy on the bus; `close()` holds the arm and disconnects it.
    `channel`: the `ArmChannel` to a workcell running in this process, for a `sim` arm on
    `sim_physics = "embedded"`."""

    def __init__(
        self,
        node: Node,
        config: ArmConfig,
        arm: Any = None,
        model: ArmModel | None = None,
        channel: ArmChannel | None = None,
    ) -> None:
        self.node = node
        self.model = model if model is not None else load_model(config.model)
        self.config = config.bind(self.model)
        # the liveliness watch starts now, not at the first motion call: a set created on
        # demand has not yet heard of a decision that is already alive (unsupervised moves)
        _ = node.alive
        self.arm = arm if arm is not None else open_arm(self.config, self.model, node, channel)
        self.proxy = ArmProxy(self.arm, self.config, self._emit, self.model)
        self._clock: Clocked | None = self.arm if isinstance(self.arm, Clocked) else None
        """A driver with a robot clock of its own: ticks advance by it (docs/franka.md)."""
        self._state_pub = node.publisher(keys.STATE)
        self._description_pub = node.publisher(keys.ARM_DESCRIPTION, cache=1)
        self._description_seq = 0
        self._state_seq = 0
        self._cmd_lock = threading.Lock()
        self._pending: tuple[ArmTarget, int] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._tick_lock = threading.Lock()
        """Held by whoever applies a target or ticks the proxy: one at a time."""
        self._last_tick = self._next_tick = time.monotonic()
        self.late_ticks = 0
        self.late_max_ms = 0.0
        self._requests: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self._requests_lock = threading.Lock()
        self._targets = node.batches(keys.ARM_TARGET, self._on_targets)
        methods: dict[str, Any] = {
            name: getattr(self.proxy, f"rpc_{name}")
            for name in (
                "connect",
                "set_frame",
                "stop",
                "estop",
                "fk",
                "ik",
                "limits",
            )
        }
        methods["status"] = self.rpc_status
        methods["describe"] = self.proxy.rpc_describe
        methods["set_tool"] = self._set_tool
        # The e-stop acted before its arguments were read (`first`): the reply reports it.
        methods["estop"] = lambda args: {"status": self.proxy.status}
        for name in MOTIONS:
            methods[name] = self._motion_method(name)
        node.serve(
            "arm",
            {k: self._waking(h) for k, h in methods.items()},
            inline=INLINE,
            # Before the arguments are read: a stop or an e-stop acts whatever it carries.
            first={"stop": self._stop_first, "estop": self._estop_first},
        )
        self._thread = threading.Thread(target=self._loop, name="arm-control", daemon=True)
        self._thread.start()
        self._publish_description()
        node.announce()
        self._preflight()

    def _preflight(self) -> None:
        """Missing hardware is said at start-up, not first at `connect` (see `Arm`)."""
        check = getattr(self.arm, "preflight", None)
        problem = check() if callable(check) else None
        if problem:
            log.warning("%s", problem)
            self.node.event("error", problem, {"code": "not_ready", "driver": self.config.driver})

    def _publish_description(self) -> None:
        """robot/arm/description: at start-up and after every tool change (cached: a late
        subscriber with history gets the newest)."""
        self._description_seq += 1
        desc = self.proxy.rpc_describe({})
        self._description_pub.put(
            ArmDescription(seq=self._description_seq, t_ns=time.time_ns(), **desc)
        )

    def _set_tool(self, args: dict[str, Any]) -> dict[str, Any]:
        reply = self.proxy.rpc_set_tool(args)
        self._publish_description()
        return reply

    def _emit(self, kind: str, message: str, data: dict[str, Any]) -> None:
        self.node.event(kind, message, data)

    # --- targets (latest wins; applied on arrival, else by the control thread) ----------
    def _on_targets(self, targets: tuple[ArmTarget, ...]) -> None:
        """The newest of what arrived (in order) supersedes the rest: applied and ticked
        at once, unless a tick is running; then the control thread takes it next."""
        pending = (targets[-1], time.time_ns())
        if self._tick_lock.acquire(blocking=False):
            try:
                with self._cmd_lock:
                    self._pending = None  # older than this one
                self._apply(pending, time.monotonic())
            finally:
                self._tick_lock.release()
            return
        with self._cmd_lock:
            self._pending = pending
        self._wake.set()

    def _apply(self, pending: tuple[ArmTarget, int], now: float) -> None:
        """Apply a target and tick (the caller holds `_tick_lock`)."""
        tgt, rx_ns = pending
        self.proxy.on_target(tgt, rx_ns)
        self._tick(now)

    def _tick(self, now: float) -> None:
        """One tick of the proxy (the caller holds `_tick_lock`)."""
        dt = now - self._last_tick
        if self._clock is not None:
            dt = self._clock.robot_elapsed_s(dt)
        self.proxy.tick(min(max(dt, MIN_TICK_S), MAX_TICK_S))
        self._last_tick = now
        self._next_tick = now + 1.0 / self.config.control_rate_hz

    def _waking(self, handler: Any) -> Any:
        """A method handler that wakes the control loop afterwards: it may have started,
        stopped or re-planned a motion the loop must now tick."""

        def run(args: dict[str, Any]) -> dict[str, Any]:
            try:
                reply: dict[str, Any] = handler(args)
                return reply
            finally:
                self._wake.set()

        return run

    def _take_pending(self) -> tuple[ArmTarget, int] | None:
        with self._cmd_lock:
            pending, self._pending = self._pending, None
        return pending

    # --- the control loop -------------------------------------------------------------
    def _loop(self) -> None:
        period_s = 1.0 / self.config.control_rate_hz
        busy_state_s = 1.0 / self.config.state_rate_hz
        idle_state_s = 1.0 / min(IDLE_STATE_RATE_HZ, self.config.state_rate_hz)
        next_state = time.monotonic()
        try:
            while not self._stop.is_set():
                self._wake.clear()
                with self._tick_lock:
                    now = time.monotonic()
                    pending = self._take_pending()
                    busy = self.proxy.needs_tick
                    state_due = now >= next_state
                    next_tick = self._next_tick
                    if pending is not None:
                        self._apply(pending, now)
                    # At rest the loop only watches the arm, once per state it publishes.
                    elif (busy and now >= next_tick) or (state_due and not busy):
                        if busy and now - next_tick > period_s:
                            self._count_late(now - next_tick)
                        self._tick(now)
                    busy = self.proxy.needs_tick
                    next_tick = self._next_tick
                if state_due:
                    self._publish_state()
                    next_state += busy_state_s if busy else idle_state_s
                    if next_state <= now:  # late: re-anchor rather than burst
                        next_state = now + (busy_state_s if busy else idle_state_s)
                deadline = min(next_state, next_tick) if busy else next_state
                self._wake.wait(max(deadline - time.monotonic(), 0.0))
        except Exception as e:  # the loop must never die silently with the arm moving
            log.exception("control loop failed")
            self.node.event("error", f"arm control loop failed: {e}", {"code": "internal"})
            self.proxy.rpc_stop({})
            raise

    def _count_late(self, late_s: float) -> None:
        """Lateness is counted and reported in `status` (loop.late), never logged per tick."""
        self.late_ticks += 1
        self.late_max_ms = max(self.late_max_ms, late_s * 1e3)

    def _publish_state(self) -> None:
        st = self.proxy.state()
        self._state_seq += 1
        st["engage"] = max(0, int(st["engage"]))
        st["cmd_seq"] = max(0, int(st["cmd_seq"]))
        self._state_pub.put(RobotState(seq=self._state_seq, t_ns=time.time_ns(), **st))

    # --- methods ----------------------------------------------------------------------
    def rpc_status(self, args: dict[str, Any]) -> dict[str, Any]:
        """The proxy's status plus the control loop's lateness (count and worst)."""
        out = self.proxy.rpc_status(args)
        out["loop"] = {"late": self.late_ticks, "late_max_ms": round(self.late_max_ms, 3)}
        return out

    def _stop_first(self) -> None:
        self.proxy.rpc_stop({})
        self._wake.set()

    def _estop_first(self) -> None:
        self.proxy.rpc_estop({})
        self._wake.set()

    def _motion_method(self, name: str) -> Any:
        """A motion method: `wait` and `timeout_s` are checked before anything starts, so a
        call either fails having moved nothing or replies that its motion started (and,
        with `wait`, how it ended: a timeout says the motion goes on)."""
        rpc = getattr(self.proxy, f"rpc_{name}")

        def handler(args: dict[str, Any]) -> dict[str, Any]:
            if (
                name in SUPERVISED
                and args.get("supervised_by") != "decision"
                and self.node.alive.is_alive("decision")
            ):
                raise RpcError(
                    "busy",
                    f"{name} refused: a decision server supervises this arm (workspace, "
                    f"contact, speed); call robot/decision/rpc/{name} instead",
                )
            wait = codec.arg(args, "wait", bool, False)
            timeout_s = check(
                "timeout_s", codec.arg(args, "timeout_s", float, WAIT_TIMEOUT_S), "timeout_s"
            )
            request = codec.arg(args, "request_id", RequestId, None)
            reply: dict[str, Any] | None = None
            if request is not None and name != "initialize":
                with self._requests_lock:
                    known = self._requests.get(request)
                if known is not None:
                    # A retry (the first call timed out, its motion may be running): the
                    # same motion, never a second one.
                    reply = {**known, "duplicate": True}
            if reply is None:
                reply = rpc(args)
                if request is not None and "motion" in reply:
                    with self._requests_lock:
                        self._requests[request] = dict(reply)
                        while len(self._requests) > MAX_REQUESTS:
                            self._requests.popitem(last=False)
            if not wait:
                return reply
            if name == "initialize":
                return self.proxy.wait_initialized(timeout_s)
            return {**reply, **self.proxy.wait_motion(int(reply["motion"]), timeout_s)}

        return handler

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.proxy.close()
