"""The decision service on the bus: the operator's single entry point (IDecisionServer).

It serves `robot/decision/rpc/…` (every IProxyRobot and IForceSensor method forwarded to the
arm and force services, plus `status`, `supervisor`, `estop`, `reset`, `task`), and
supervises `robot/cmd` into `robot/arm/target`.

Reactive: an operator command is supervised and its result published in the Zenoh callback
that delivers it, so the arm has it one hop later; a lost service is handled the same way.
Between inputs a timer thread sleeps until the supervisor's next deadline (a watchdog, the
20 Hz hold re-send, a task's or a catching-up target's next step): an idle decision server
does nothing. robot/state and robot/force are not decoded per sample: Zenoh keeps the newest
of each, read when a tick needs them (`Node.latest`). robot/force is subscribed only while
teleoperation or a task runs, or a forwarded motion is watched: idle (masters alive but not
engaged included), the 1 kHz stream is neither received here nor, with no other subscriber,
sent at all; a new engagement from idle waits (deferred, not refused) for its first sample.

Threads: every tick runs under one lock (`_cond`), and the command it yields is published
under it too, so `robot/arm/target` leaves in `seq` order whichever thread ticked; events go
out after the lock is released. RPC handlers touch the supervisor under the same lock,
briefly; a task's caller waits on its condition.
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

import numpy as np
import zenoh

from services.bus.bounds import out_of_bounds, short
from services.bus.codec import arg
from services.bus.config import section
from services.bus.errors import ConfigError, ErrorCode, ProtocolError, RpcError, Unavailable
from services.bus.keys import ARM_DESCRIPTION, ARM_TARGET, CMD, STATE
from services.bus.messages import (
    ArmDescription,
    ArmTarget,
    ForceSample,
    OperatorCommand,
    RobotState,
    mat3,
)
from services.bus.node import Node
from services.control.decision.config import STARTUP_ONLY, DecisionConfig
from services.control.decision.forcefeed import FORCE_WAIT_S, ForceFeed
from services.control.decision.notices import INTERVENTIONS, Notice
from services.control.decision.passivity import SlaveTdpa
from services.control.decision.peeks import Peek, read_sample, stamped
from services.control.decision.supervisor import Inputs, Mode, Supervisor
from services.control.decision.taskrun import TaskRun
from services.control.decision.tasks import TASK_NAMES, TaskPlan, plan_task
from services.control.decision.watch import Watch, forwarded_target, target_problem
from services.control.decision.watchdogs import fresh

log = logging.getLogger("telerobot.decision")

SERVICE = "decision"
#: IProxyRobot (PROTOCOL §4) forwarded to robot/arm/rpc/…; arm's `status` is part of ours.
ARM_METHODS: tuple[str, ...] = (
    "describe",
    "connect",
    "initialize",
    "set_tool",
    "set_frame",
    "move_joints",
    "move_pose",
    "move_relative",
    "stop",
    "home",
    "fk",
    "ik",
    "limits",
)

#: IForceSensor (PROTOCOL §4) forwarded to robot/force/rpc/…
FORCE_METHODS: tuple[str, ...] = (
    "sensor_status",
    "sensor_start",
    "sensor_stop",
    "sensor_config",
    "sensor_bias",
    "sensor_compliance",
    "sensor_read",
)
#: forwarded methods that move the arm: refused while teleoperation or a task commands it
#: (busy) and under the e-stop latch (estop)
MOTION_METHODS: frozenset[str] = frozenset({"move_joints", "move_pose", "move_relative", "home"})
SUPERVISED_BY = "supervised_by"
BACKOFF_MOVES = 5
"""A contact stop is backed off in at most this many moves (each force / stiffness)."""
BACKOFF_SETTLE_S = 0.1
"""The force is judged this long after a contact stop or a back-off move: the servo's own
deceleration carries the tool on a little after it is told to hold."""
"""The argument the decision adds to the motion calls it forwards (its service name): while a
decision server is alive, the arm refuses motion calls without it."""
ALIVE_WAIT_S = 0.5
"""How long a forwarded call waits for the target's liveliness token before `unavailable`."""
STATUS_CALL_TIMEOUT_S = 1.0
HOLD_REPEATS = 3
"""Holds sent at close (each a new seq): one lost packet must not matter."""
IDLE_WAIT_S = 1.0
"""The timer re-checks this often when nothing is due (a safety net; inputs wake it)."""


class DecisionService:
    """The DecisionServer: declares its streams and methods, starts the loop, announces.

    `close()` holds the arm (a hold target, then arm `stop`) and stops the loop; it
    does not close the node.
    """

    def __init__(self, node: Node, config: DecisionConfig) -> None:
        self.node = node
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        wall = time.time_ns()
        # Counters seeded from the wall clock, like the masters': a restarted decision server
        # still counts upwards, so the arm never ignores it as stale.
        self.supervisor = Supervisor(
            config, seq_start=wall // 1_000, engage_start=wall // 1_000_000
        )
        self._configured = config
        """The settings as configured; the supervisor runs them bound by the arm's
        description (`DecisionConfig.with_arm`) once one has come."""
        self._arm: ArmDescription | None = None
        self._stop = threading.Event()
        self._closed = False
        self.loop_errors = 0
        self.publish_errors = 0
        self.timer_ticks = 0
        self.timer_wakes = 0
        self.timer_late = 0
        self.timer_late_max_ms = 0.0
        self._planned_ns: int | None = None
        """The deadline the timer sleeps to (None: it is awake, or waits for input)."""
        self._settings_kept: tuple[DecisionConfig, dict[str, Any]] | None = None
        """`config.settings()` and the configuration it was built from (`_settings`)."""
        self._task_waiters = 0
        """Callers of `task` waiting for their task to end (every tick notifies them)."""

        self._pub = node.publisher(ARM_TARGET)
        self.passivity = (
            SlaveTdpa(
                node,
                contact_n=config.max_force_n,
                yield_m_s_n=config.passivity_yield_m_s_n,
                yield_max_rtt_s=config.passivity_yield_max_rtt_ms * 1e-3,
            )
            if config.passivity
            else None
        )
        if config.passivity and config.approach_zone_m <= 0.0:
            # Measured in-process without it: 96–107 N at the first impact, 10–35 N RMS over
            # the hold (docs/passivity.md, "Turning it on").
            log.warning(
                "passivity is on without a guarded approach (approach_zone_m = 0): the arm "
                "meets a surface at the operator's speed; set approach_zone_m = 0.02"
            )
        self._op_engage: dict[str, int] = {}
        self._intake = node.batches(CMD, self._on_commands)
        # What `status` shows of the other services: kept, refreshed behind (peeks.py).
        self._peeks = tuple(
            Peek(node, service, method, STATUS_CALL_TIMEOUT_S)
            for service, method in (
                ("arm", "status"),
                ("force", "sensor_status"),
                ("force", "sensor_read"),
            )
        )
        self._state = node.latest(STATE)
        node.subscribe(ARM_DESCRIPTION, self._on_description, history=True)
        # robot/force only while the arm moves or may start to (forcefeed.py).
        self._force = ForceFeed(node)
        node.alive.on_change(self._on_alive)
        node.serve(
            SERVICE,
            self._methods(),
            inline=("supervisor", "reset"),
            first={"estop": self._latch_estop, "stop": self._hold_first},
            inline_try={"status": self._status_kept},
        )
        self._thread = threading.Thread(target=self._timer, name="decision-timer", daemon=True)
        self._thread.start()
        node.announce()

    # --- Zenoh callbacks: react to commands and losses, store the rest --------------------
    def _on_commands(self, msgs: tuple[OperatorCommand, ...]) -> None:
        """Each arrival, at once; what piled up while the last one was handled, together."""
        self._react(commands=msgs)

    def _on_description(self, desc: ArmDescription) -> None:
        """The arm (re)described itself: supervise within its workspace and speeds."""
        with self._cond:
            self._arm = desc
            bound = self._configured.with_arm(desc)
            changed = bound != self.supervisor.config
            if changed:
                self.supervisor.set_config(bound)
                if self.passivity is not None:
                    self.passivity.contact_n = bound.max_force_n
                self._cond.notify_all()
        if changed:
            self._event(
                "status",
                f"supervising the {desc.model} arm: workspace and tool speeds from its description",
                {
                    "model": desc.model,
                    "workspace_min": list(bound.workspace_min),
                    "workspace_max": list(bound.workspace_max),
                    "max_tool_speed_m_s": bound.max_tool_speed_m_s,
                },
            )

    def _on_alive(self, name: str, up: bool) -> None:
        if not up:
            self._react(lost=(name,))

    def _watch_force(self) -> None:
        self._force.update(self.supervisor, time.monotonic_ns())

    # --- ticks -----------------------------------------------------------------------------
    @property
    def config(self) -> DecisionConfig:
        return self.supervisor.config

    def _inputs(
        self, commands: tuple[OperatorCommand, ...] = (), lost: tuple[str, ...] = ()
    ) -> Inputs:
        """The tick's inputs (under the lock: the newest state and force are read here)."""
        now_ns = time.monotonic_ns()
        warming = self._force.warm(commands, now_ns)
        state, force = self._state.read(), self._force.read()
        return Inputs(
            now_ns=now_ns,
            force_warming=warming,
            wall_ns=time.time_ns(),
            state=state[0] if state else None,
            state_rx_ns=state[1] if state else 0,
            force=force[0] if force else None,
            force_rx_ns=force[1] if force else 0,
            commands=commands,
            lost=lost,
        )

    def _react(
        self, commands: tuple[OperatorCommand, ...] = (), lost: tuple[str, ...] = ()
    ) -> None:
        """Tick now with these inputs (or none, after a method changed the mode): publish
        the result at once and let the timer re-plan its next wake-up."""
        with self._cond:
            if self._closed:
                return
            notices = self._tick_locked(self._inputs(commands, lost))
            self._replan_locked()
        self._emit(notices)

    def _replan_locked(self) -> None:
        """Wake the timer only if the supervisor's next deadline moved before the one it
        sleeps to (each command moves the watchdog's later: waking the timer for it on every
        command would cost a thread switch per command)."""
        wake = self.supervisor.next_wake_ns()
        planned = self._planned_ns
        if self._task_waiters or (wake is not None and (planned is None or wake < planned)):
            self._cond.notify_all()

    def _tick_locked(self, inp: Inputs) -> tuple[Notice, ...]:
        """One supervisor tick under the lock; the command goes out before the lock is
        released. Returns the notices to publish after it."""
        try:
            res = self.supervisor.tick(inp)
        except Exception as e:  # a bug: count it, report it, latch the safe state
            self.loop_errors += 1
            log.exception("supervisor tick failed")
            self.supervisor.estop(inp.now_ns, f"internal error in the supervisor: {e}")
            bug = Notice(
                "error",
                f"supervisor tick failed: {e}",
                {"traceback": traceback.format_exc(limit=8)},
            )
            return (bug,)
        if res.command is not None:
            cmd = res.command
            if self.passivity is not None:
                cmd = self.passivity.apply(
                    cmd, self._operator(inp), inp.state, self._fresh_force(inp), inp.now_ns
                )
            self._put(cmd)
        if res.stop_arm is not None:
            self._stop_arm_soon(res.stop_arm)
        self._watch_force()
        return res.notices

    def _operator(self, inp: Inputs) -> tuple[str, int] | None:
        """(lease holder, its engage) for the passivity count, or None without a lease."""
        for c in inp.commands:
            if len(self._op_engage) >= 16 and c.master not in self._op_engage:
                self._op_engage.clear()  # masters come and go; only the lease holder matters
            self._op_engage[c.master] = c.engage
        lease = self.supervisor.lease
        if lease is None or lease not in self._op_engage:
            return None
        return (lease, self._op_engage[lease])

    def _fresh_force(self, inp: Inputs) -> ForceSample | None:
        if inp.force is None or not fresh(self.config.stale_ms, inp.now_ns, inp.force_rx_ns):
            return None
        return inp.force

    def _stop_arm_soon(self, args: dict[str, Any]) -> None:
        """A watched motion broke a limit: the arm's `stop` (at once, `now`, at a contact,
        and then the back-off), from a worker (never from the tick, which holds the lock)."""

        def stop() -> None:
            try:
                self._forward("arm", "stop", args)
            except RpcError as e:
                log.warning("could not stop a forwarded motion: %s", e.message)
                return
            if args.get("now") is True:
                self._back_off()

        threading.Thread(target=stop, name="decision-stop", daemon=True).start()

    def _back_off(self) -> None:
        """After a contact stop: while the arm still presses harder than max_force_n, move
        it back along the contact force, force / contact_stiffness_n_per_m each time (so the
        force falls to about half the limit), at most BACKOFF_MOVES moves. Each is a watched
        motion like any other; it gives way to anything that claims the arm meanwhile (a
        motion call, a task, an operator): it never takes over another motion's watch."""
        cfg = self.config
        mine: Watch | None = None
        for attempt in range(BACKOFF_MOVES):
            with self._cond:
                # the servo comes to rest and the force settles after a stop (or a move)
                self._cond.wait_for(lambda: self._closed, BACKOFF_SETTLE_S)
                sup = self.supervisor
                if self._closed or sup.mode in (Mode.FOLLOW, Mode.TASK, Mode.ESTOP):
                    return
                if sup.watch is not None and sup.watch is not mine:
                    return  # someone else's motion runs: theirs, and watched
                try:
                    sup.claim("move_relative", time.monotonic_ns(), guarded=True)
                except RpcError:
                    return  # a task or an operator has the arm: theirs to release it
                mine = sup.watch
                self._watch_force()
                self._force.wait_fresh(self._cond, cfg.stale_ms, FORCE_WAIT_S)
                if sup.watch is not mine:
                    return  # claimed by a call while the force came
                state, force = self._state.read(), self._force.read()
                if state is None or force is None:
                    sup.end_watch(mine)
                    return
                f_w = mat3(state[0].tool_R) @ np.asarray(force[0].f, dtype=float)
                f_n = float(np.linalg.norm(f_w))
                if f_n <= cfg.max_force_n:
                    sup.end_watch(mine)
                    if attempt:
                        self._event(
                            "contact",
                            f"backed off the contact: {f_n:.1f} N ≤ {cfg.max_force_n:g} N",
                            {"reason": "backoff", "force_n": f_n, "moves": attempt},
                        )
                    return
                self._cond.notify_all()
            d = min(max((f_n - 0.5 * cfg.max_force_n) / cfg.contact_stiffness_n_per_m, 5e-4), 0.02)
            dp = [float(x) for x in f_w / f_n * d]
            with self._cond:
                if mine is not None:  # along the force: the watch lets it leave the contact
                    g = np.asarray(state[0].tool_p, dtype=float) + f_w / f_n * d
                    mine.goal = (float(g[0]), float(g[1]), float(g[2]))
            self._event(
                "contact",
                f"backing off a contact of {f_n:.1f} N > {cfg.max_force_n:g} N by {d * 1e3:.1f} mm",
                {"reason": "backoff", "force_n": f_n, "dp": dp},
            )
            try:
                self._forward(
                    "arm",
                    "move_relative",
                    {
                        "dp": dp,
                        "frame": "world",
                        "speed": self._guard_fraction(),
                        "wait": True,
                        SUPERVISED_BY: SERVICE,
                    },
                )
            except RpcError as e:
                with self._cond:
                    self.supervisor.end_watch(mine)
                log.warning("could not back off a contact: %s", e.message)
                return

    def _timer(self) -> None:
        """Sleep until the supervisor's next deadline (or an input re-plans it); tick."""
        while True:
            with self._cond:
                if self._stop.is_set():
                    return
                wake = self.supervisor.next_wake_ns()
                now = time.monotonic_ns()
                if wake is None or wake > now:
                    left_s = IDLE_WAIT_S if wake is None else min((wake - now) * 1e-9, IDLE_WAIT_S)
                    self._planned_ns = wake
                    self._cond.wait(left_s)
                    self._planned_ns = None
                    self.timer_wakes += 1
                    continue
                late_ms = (now - wake) * 1e-6
                if late_ms > self.config.period_s * 1e3:
                    self.timer_late += 1
                    self.timer_late_max_ms = max(self.timer_late_max_ms, late_ms)
                self.timer_ticks += 1
                notices = self._tick_locked(self._inputs())
                self._cond.notify_all()
            self._emit(notices)

    def _emit(self, notices: tuple[Notice, ...]) -> None:
        for n in notices:
            self._event(n.kind, n.message, n.data)

    def _put(self, tgt: ArmTarget) -> None:
        try:
            self._pub.put(tgt)
        except (zenoh.ZError, ProtocolError):
            self.publish_errors += 1
            log.warning("could not publish on robot/arm/target", exc_info=True)

    def _event(self, kind: str, message: str, data: Mapping[str, Any]) -> None:
        if not self.node.closed:
            self.node.event(kind, message, data)

    # --- methods ---------------------------------------------------------------------------
    def _methods(self) -> dict[str, Callable[[dict[str, Any]], dict[str, Any]]]:
        methods: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {}
        for name in ARM_METHODS:
            methods[name] = partial(self._arm_method, name)
        for name in FORCE_METHODS:
            methods[name] = partial(self._forward, "force", name)
        methods.update(
            status=self.rpc_status,
            supervisor=self.rpc_supervisor,
            estop=self.rpc_estop,
            reset=self.rpc_reset,
            task=self.rpc_task,
        )
        return methods

    def _forward(
        self, service: str, method: str, args: Mapping[str, Any], timeout_s: float | None = None
    ) -> dict[str, Any]:
        """Call `service.method` with the same arguments; its error codes pass through, and a
        service that is down is `unavailable`."""
        if timeout_s is None:
            wait = args.get("wait") is True
            timeout_s = self.config.wait_timeout_s if wait else self.config.rpc_timeout_s
            asked = args.get("timeout_s")
            # The caller's own wait (the target checks its bounds): ours outlasts it.
            if (
                wait
                and isinstance(asked, int | float)
                and not isinstance(asked, bool)
                and out_of_bounds("timeout_s", float(asked), "timeout_s") is None
            ):
                timeout_s = max(timeout_s, float(asked) + self.config.rpc_timeout_s)
        if not self.node.alive.wait(service, min(ALIVE_WAIT_S, timeout_s)):
            raise RpcError("unavailable", f"the {service} service is not running")
        try:
            return self.node.call(service, method, args, timeout_s)
        except Unavailable as e:
            raise RpcError("unavailable", f"{service}.{method}: {e}") from None

    def _arm_method(self, method: str, args: dict[str, Any]) -> dict[str, Any]:
        # `stop` held already, before its arguments were read (`_hold_first`).
        if method in MOTION_METHODS:
            goal = self._check_target(method, args)
            args, guarded = self._guarded(method, args, goal)
            with self._cond:
                self.supervisor.claim(method, time.monotonic_ns(), guarded=guarded, goal=goal)
                mine = self.supervisor.watch
                self._watch_force()  # the watch stops the motion on a contact
                if guarded and not self._force.wait_fresh(
                    self._cond, self.config.stale_ms, FORCE_WAIT_S
                ):
                    self.supervisor.end_watch(mine)
                    raise RpcError(
                        "not_ready",
                        f"{method} refused: its goal is near the table and no force comes "
                        "from the wrist (is the force service running?)",
                    )
                if guarded and mine is not None:
                    # the watch's start-up allowance counts from the forward, not the wait
                    mine.since_ns = time.monotonic_ns()
                self._cond.notify_all()  # the timer watches the motion
            try:
                return self._forward("arm", method, {**args, SUPERVISED_BY: SERVICE})
            except RpcError:
                with self._cond:
                    self.supervisor.end_watch(mine)
                raise
        elif method == "set_tool":
            with self._cond:
                if self.supervisor.mode in (Mode.FOLLOW, Mode.TASK):
                    raise RpcError("busy", "set_tool refused: the supervisor is commanding the arm")
        return self._forward("arm", method, args)

    def _check_target(self, method: str, args: Mapping[str, Any]) -> list[float] | None:
        """Refuse (`limit`) a forwarded motion whose target tool point lies outside the
        workspace box (watch.forwarded_target; what the arm would refuse is left to it)."""

        def newest_state() -> RobotState | None:
            with self._cond:
                read = self._state.read()
            return None if read is None else read[0]

        def ask_arm(arm_method: str, arm_args: dict[str, Any]) -> dict[str, Any] | None:
            try:
                return self._forward("arm", arm_method, arm_args)
            except RpcError:
                return None  # the arm will refuse the call for the same reason

        p = forwarded_target(method, args, newest_state, ask_arm)
        if p is None:
            return None
        with self._cond:
            why = target_problem(self.config, method, p)
        if why is not None:
            raise RpcError("limit", why)
        return p

    def _guarded(
        self, method: str, args: dict[str, Any], p: list[float] | None
    ) -> tuple[dict[str, Any], bool]:
        """(`args`, guarded): the motion's speed lowered to motion_guard_speed_m_s when its
        goal `p` lies within motion_guard_zone_m above the workspace floor (objects stand
        there: a contact met faster could not be stopped within the force limit). The arm's
        `speed` is a fraction of the tool speed it plans with (its description's)."""
        cfg = self.config
        if p is None or method == "home" or cfg.motion_guard_zone_m <= 0.0:
            return args, False
        if p[2] - cfg.workspace_min[2] >= cfg.motion_guard_zone_m:
            return args, False
        asked = args.get("speed")
        asked = float(asked) if isinstance(asked, int | float) and 0.0 < asked <= 1.0 else 1.0
        speed = min(asked, self._guard_fraction())
        return ({**args, "speed": speed} if speed < asked else args), True

    def _guard_fraction(self) -> float:
        """motion_guard_speed_m_s as a fraction of the tool speed the arm plans with."""
        with self._cond:
            top = None if self._arm is None else self._arm.max_tool_speed_m_s
            cfg = self.config
        return min(1.0, cfg.motion_guard_speed_m_s / (top or cfg.max_tool_speed_m_s))

    def rpc_status(self, args: dict[str, Any]) -> dict[str, Any]:
        """The superset status: robot (robot/state and arm's `status`), sensor (robot/force
        and `sensor_status`), supervisor (mode, lease, task, settings), alive services and the
        intervention counters."""
        out = self._status(wait=True)
        assert out is not None  # waiting, every peek answers
        return out

    def _status_kept(self, args: dict[str, Any]) -> dict[str, Any] | None:
        """`status` from the kept replies only (in Zenoh's callback), or None if one of them
        would have to be asked for (then `rpc_status` answers on a worker)."""
        return self._status(wait=False)

    def _status(self, wait: bool) -> dict[str, Any] | None:
        arm, sensor = self._peeks[0].get(wait), self._peeks[1].get(wait)
        if arm is None or sensor is None:
            return None
        with self._cond:
            watching = self._force.watching
            snap = self.supervisor.snapshot()
            settings = self._settings()
            state, force = self._state.read(), self._force.read()
        # Not subscribed to robot/force (idle): the sensor's newest sample, asked for.
        read = None if watching else self._peeks[2].get(wait)
        if not watching and read is None:
            return None
        now = time.monotonic_ns()
        interventions = dict(snap["interventions"])
        interventions["rejected"] = interventions.get("rejected", 0) + self._cmd_rejections()
        return {
            "service": SERVICE,
            "mode": snap["mode"],
            "lease": snap["lease"],
            "estop": snap["estop"],
            "supervisor": snap,
            "settings": settings,
            "interventions": interventions,
            "robot": stamped(state, now),
            "force": stamped(force, now) if read is None else read_sample(read),
            "arm": arm,
            "sensor": sensor,
            "alive": sorted(self.node.alive.names()),
            "loop": {
                "rate_hz": self.config.rate_hz,
                "ticks": snap["stats"]["ticks"],
                "timer_ticks": self.timer_ticks,
                "timer_wakes": self.timer_wakes,
                "late": self.timer_late,
                "late_max_ms": round(self.timer_late_max_ms, 3),
                "errors": self.loop_errors,
                "publish_errors": self.publish_errors,
                "intake": {
                    "inline": self._intake.inline,
                    "handed": self._intake.handed,
                    "dropped": self._intake.dropped,
                    "batches": self._intake.batches,
                },
            },
        }

    def _settings(self) -> dict[str, Any]:
        """`config.settings()`, built once per configuration (a third of `status`'s own
        work; the configuration changes only through `supervisor`). Not to be mutated."""
        cfg = self.config
        kept = self._settings_kept
        if kept is None or kept[0] is not cfg:
            kept = self._settings_kept = (cfg, cfg.settings())
        return kept[1]

    def _cmd_rejections(self) -> int:
        return sum(
            n
            for key, n in dict(self.node.rejected).items()
            if key == CMD.key or key.endswith("/" + CMD.key)
        )

    def rpc_supervisor(self, args: dict[str, Any]) -> dict[str, Any]:
        """No arguments: the supervisory settings and mode. With arguments: change those
        settings (same names and checks as the `[decision]` table; bad_request otherwise)."""
        if args:
            fixed = sorted(set(args) & STARTUP_ONLY)
            if fixed:
                raise RpcError("bad_request", f"{', '.join(fixed)}: fixed at start-up")
            with self._cond:
                current = self._configured.settings()
                if {"workspace_min", "workspace_max"} & set(args):
                    # A box given here wins over the arm's: the one not given is the one
                    # in force now, not the table's that the arm's replaced.
                    effective = self.supervisor.config
                    current["workspace_min"] = list(effective.workspace_min)
                    current["workspace_max"] = list(effective.workspace_max)
                    args = {"workspace_from_arm": False, **args}
            try:
                new = section(DecisionConfig, {**current, **args}, "decision")
            except ConfigError as e:
                raise RpcError("bad_request", str(e)) from None
            with self._cond:
                self._configured = new
                bound = new if self._arm is None else new.with_arm(self._arm)
                self.supervisor.set_config(bound)
                if self.passivity is not None:
                    self.passivity.contact_n = bound.max_force_n
                self._cond.notify_all()  # the timer's next deadline may have moved
            changed = sorted(k for k in args if current.get(k) != new.settings().get(k))
            self._event(
                "status",
                f"supervisor settings changed: {', '.join(changed) or 'none'}",
                {"changed": {k: new.settings()[k] for k in changed}},
            )
        with self._cond:
            return {
                "settings": self.config.settings(),
                "mode": self.supervisor.mode.value,
                "startup_only": sorted(STARTUP_ONLY),
            }

    def _latch_estop(self) -> None:
        """`estop`'s first action, before its arguments are even read: latch and hold."""
        with self._cond:
            self.supervisor.estop(time.monotonic_ns(), "estop requested")
        self._react()  # the hold goes out now

    def _hold_first(self) -> None:
        """`stop`'s first action, before its arguments are read: hold teleoperation, cancel
        a task."""
        with self._cond:
            self.supervisor.stop(time.monotonic_ns())
        self._react()

    def rpc_estop(self, args: dict[str, Any]) -> dict[str, Any]:
        """Latch the emergency stop (done before this runs, whatever the arguments: see
        `_latch_estop`), pre-empt any task, stop the arm; everything that moves is refused
        until `reset`. An optional `reason` (str) is echoed back, shortened."""
        reason = args.get("reason")
        method = "estop" if self.config.estop_power_off else "stop"
        try:
            arm: dict[str, Any] = self._forward("arm", method, {})
        except RpcError as e:
            arm = {"error": e.code, "message": e.message}
        out: dict[str, Any] = {"estop": True, "arm": arm}
        if isinstance(reason, str):
            out["reason"] = short(reason)
        return out

    def rpc_reset(self, args: dict[str, Any]) -> dict[str, Any]:
        """Clear the e-stop latch; masters must engage anew to move."""
        with self._cond:
            was = self.supervisor.reset(time.monotonic_ns())
            self._cond.notify_all()
        return {"estop": False, "was_latched": was}

    def rpc_task(self, args: dict[str, Any]) -> dict[str, Any]:
        """`task {name, …}`: guarded_move, pick_place (streamed by the supervisor), home
        (forwarded), cancel. Replies on completion unless `"wait": false`."""
        name = arg(args, "name", str)
        if self._closed:
            raise RpcError("unavailable", "the decision server is shutting down")
        if name not in TASK_NAMES:
            raise ProtocolError("name", f"unknown task {name!r} (tasks: {', '.join(TASK_NAMES)})")
        now = time.monotonic_ns()
        if name == "cancel":
            with self._cond:
                run = self.supervisor.cancel_task(now)
            self._react()
            if run is not None and run.external:
                self._forward("arm", "stop", {})
            return {"cancelled": run.name if run is not None else None}
        if name == "home":
            return self._home_task(args, now)
        with self._cond:
            plan = plan_task(name, args, self.config)
            # A task senses contact from its first step: subscribe (if idle) and give the
            # stream up to FORCE_WAIT_S to arrive; without it the task refuses as before.
            self._force.pins += 1
            try:
                self._watch_force()
                self._force.wait_fresh(self._cond, self.config.stale_ms, FORCE_WAIT_S)
                run = self.supervisor.start_task(plan, time.monotonic_ns())
            finally:
                self._force.pins -= 1
        self._react()  # the task's first step now; the timer takes the next ones
        if not plan.wait:
            return {"accepted": True, "task": name, "id": run.id}
        return self._wait(run)

    def _wait(self, run: TaskRun) -> dict[str, Any]:
        with self._cond:
            self._task_waiters += 1
            try:
                done = self._cond.wait_for(lambda: run.done, self.config.wait_timeout_s)
            finally:
                self._task_waiters -= 1
            if not done:
                self.supervisor.cancel_task(time.monotonic_ns())
                raise RpcError("internal", f"task {run.name!r} did not finish in time: cancelled")
        return _outcome(run)

    def _home_task(self, args: Mapping[str, Any], now: int) -> dict[str, Any]:
        wait = bool(arg(args, "wait", bool, True))
        with self._cond:
            run = self.supervisor.start_task(TaskPlan("home", (), wait), now, external=True)

        def go() -> None:
            result: dict[str, Any] | None = None
            error: tuple[ErrorCode, str] | None = None
            try:
                reply = self._forward(
                    "arm",
                    "home",
                    {"wait": True, SUPERVISED_BY: SERVICE},
                    self.config.wait_timeout_s,
                )
                result = {"task": "home", "done": True, **reply}
            except RpcError as e:
                error = (e.code, e.message)
            with self._cond:
                self.supervisor.finish_external(run, result=result, error=error)
            self._react()

        if not wait:
            threading.Thread(target=go, name="decision-home", daemon=True).start()
            return {"accepted": True, "task": "home", "id": run.id}
        go()
        return _outcome(run)

    # --- shutdown --------------------------------------------------------------------------
    def close(self) -> None:
        """Hold the arm (a hold target, arm `stop`), stop the loop. Idempotent."""
        if self._closed:
            return
        with self._cond:
            self._closed = True
            self._stop.set()
            self._cond.notify_all()
        self._thread.join(timeout=2.0)
        with self._cond:
            final = self.supervisor.shutdown(time.monotonic_ns(), time.time_ns(), HOLD_REPEATS)
            self._cond.notify_all()
            for cmd in final:
                self._put(cmd)
        if self.node.closed or not self.node.alive.is_alive("arm"):
            return
        try:
            self.node.call("arm", "stop", {}, self.config.rpc_timeout_s)
        except (RpcError, Unavailable) as e:
            log.info("arm stop at close: %s", e)


def _outcome(run: TaskRun) -> dict[str, Any]:
    if run.error is not None:
        raise RpcError(run.error[0], run.error[1])
    return dict(run.result or {"task": run.name, "done": run.done})


__all__ = ["ARM_METHODS", "FORCE_METHODS", "INTERVENTIONS", "DecisionService"]
