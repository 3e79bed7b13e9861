"""The supervisory logic, free of I/O: one `tick()` per input, and per timer wake-up.

The decision server stands between the masters (`robot/cmd`) and the arm (`robot/arm/target`).
It keeps its own engagement towards the arm (`engage_out`, its own `seq`, master id
"decision"). When the lease holder's engagement starts, it records the tool pose (p0, R0)
from the newest robot/state and starts a new `engage_out`; each tick it maps the newest
command to the operator's desired tool pose (PROTOCOL §2) and moves the SUPERVISED target
towards it through the filters: (a) contact, (b) active compliance, (c) tool speed,
(d) workspace box. It sends the arm that supervised pose (ArmTarget), so whatever a filter
held back stays an offset of the target: it never turns into a jump.

Motion the filters remove (into a contact, out of the workspace) is dropped for good: it is
kept as an offset between the operator's target and the supervised one, so moving the hand
back moves the tool back at once. Motion the speed limit holds back is only delayed: the
target catches up with the operator at the limit speed.

Holding (watchdog, lost master, e-stop, stale streams, disengage) re-sends the last target
(marked `hold`) at once and then every HOLD_RESEND_NS, never a moving one again for that
engagement; motion resumes only with a NEW engagement of a master, which is rebased on
the then-current pose.

Reactive: the service ticks once per operator command as it arrives (and per lost service),
so the supervised command goes out at once; between inputs it ticks only when
`next_wake_ns()` says: a watchdog deadline, the hold's re-send, a task's or a catching-up
target's next step. A tick with nothing new publishes nothing. The speed limits bound the
target's motion over the time since its last step (not per tick), so a master at any rate
may move at the limit speed on average.

The parts, each pure: target.py (the supervised target, its filters and the outgoing
commands), masters.py (per-master records), notices.py (events, counters, rate limits),
taskrun.py (task runs and a streamed task's steps), watch.py (forwarded motions),
watchdogs.py (freshness and deadlines). This module is the state machine that drives them:
modes, the lease, holds, e-stop, tasks' start and end.

Time: `now_ns` is a monotonic clock (ns) for watchdogs and ticks; `wall_ns` is the
`time.time_ns()` put in the commands' `t_ns`. Not thread-safe: the service calls it under
one lock.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any

from services.bus.bounds import norm_out_of_bounds
from services.bus.errors import ErrorCode, RpcError
from services.bus.messages import ArmTarget, ForceSample, OperatorCommand, RobotState
from services.control.decision.config import DecisionConfig
from services.control.decision.masters import MasterRecord, Masters
from services.control.decision.notices import Notice, Notices
from services.control.decision.target import MOVING_STATUSES, Sensed, SupervisedTarget
from services.control.decision.taskrun import TaskRun, Tasks, run_tick
from services.control.decision.tasks import TaskPlan
from services.control.decision.watch import WATCH_PERIOD_NS, Watch, WatchStop, watch_step
from services.control.decision.watchdogs import follow_deadline_ns, follow_problem, fresh
from services.control.passivity.rotation import ROTATION_LENGTH_M
from services.control.passivity.slave import DEADBAND_N


class Mode(Enum):
    """What the supervisor is doing.

    IDLE: nothing to command (start-up, after a forwarded motion or an external task);
    nothing is published. FOLLOW: a master holds the lease and its engagement is followed,
    one command out per command in. HOLD: an engagement (teleoperation or task) ended; the
    hold is re-sent at 20 Hz. TASK: an autonomous task runs, one step per period.
    ESTOP: latched until `reset`; the hold is re-sent.
    """

    IDLE = "idle"
    FOLLOW = "follow"
    HOLD = "hold"
    TASK = "task"
    ESTOP = "estop"


@dataclass(frozen=True, slots=True)
class Inputs:
    """What one tick sees.

    now_ns: monotonic time (ns); wall_ns: time.time_ns() for the outgoing `t_ns`.
    state, force: the newest robot/state and robot/force (None if never received), with
    their arrival times state_rx_ns, force_rx_ns on the monotonic clock.
    commands: the robot/cmd messages received since the last tick, in arrival order (already
    validated by the codec). lost: liveliness names gone since the last tick ("master/<id>",
    "arm", "force"). force_warming: the service has just subscribed to robot/force for an
    engagement and no sample is in yet: a new engagement is deferred (not refused).
    """

    now_ns: int
    wall_ns: int = 0
    state: RobotState | None = None
    state_rx_ns: int = 0
    force: ForceSample | None = None
    force_rx_ns: int = 0
    commands: tuple[OperatorCommand, ...] = ()
    lost: tuple[str, ...] = ()
    force_warming: bool = False


@dataclass(frozen=True, slots=True)
class TickResult:
    """A tick's output: the target for robot/arm/target (None: send nothing), the events,
    and the task runs that ended (their waiters are woken)."""

    command: ArmTarget | None
    notices: tuple[Notice, ...]
    finished: tuple[TaskRun, ...]
    stop_arm: dict[str, Any] | None = None
    """A forwarded motion broke a limit: the arm's `stop` arguments (`now` at a contact:
    hold at once) for the service to call it with now; None: nothing to stop."""


class Supervisor:
    """The decision server's supervisory state machine (see the module docstring).

    `seq_start` and `engage_start` seed the outgoing counters (the service uses the wall
    clock, as the masters do, so a restarted decision server still counts upwards).
    """

    def __init__(self, config: DecisionConfig, seq_start: int = 0, engage_start: int = 0) -> None:
        self._cfg = config
        self.mode = Mode.IDLE
        self.lease: str | None = None
        self.engage_in = -1
        self._cmd: OperatorCommand | None = None
        self._cmd_rx_ns = 0
        self.target = SupervisedTarget(seq_start, engage_start, config.period_s)
        self.masters = Masters()
        self.notices = Notices(config.event_interval_s)
        self.stats: dict[str, int] = {
            "ticks": 0,
            "commands": 0,
            "stale_commands": 0,
            "engagements": 0,
            "deferred": 0,
            "published": 0,
            "holds": 0,
            "tasks": 0,
            "force_gap_ticks": 0,
        }
        self.tasks = Tasks()
        self._now_ns = 0
        self.hold_reason: str | None = None
        self._fresh = False
        self._contact = False
        self._force_flowing = False  # a fresh wrist force seen in this engagement
        self._force_lost_ns: int | None = None  # the force service's token went then
        self._state_rx_ns = 0
        self._force_rx_ns = 0
        self.watch: Watch | None = None
        self._stop_arm: dict[str, Any] | None = None

    # --- settings ----------------------------------------------------------------------
    @property
    def config(self) -> DecisionConfig:
        return self._cfg

    def set_config(self, config: DecisionConfig) -> None:
        """New supervisory settings, effective at the next tick (the loop rate is fixed)."""
        if config.rate_hz != self._cfg.rate_hz:
            raise ValueError("rate_hz cannot change while the loop runs")
        self._cfg = config
        self.notices.interval_s = config.event_interval_s

    # --- the tick ------------------------------------------------------------------------
    def tick(self, inp: Inputs) -> TickResult:
        """Process new inputs (or none: a timer wake-up); return what to publish."""
        self._now_ns = inp.now_ns
        self._state_rx_ns, self._force_rx_ns = inp.state_rx_ns, inp.force_rx_ns
        self.stats["ticks"] += 1
        self._fresh = False
        self.target.start_tick(inp.now_ns, self._cfg)
        cfg = self._cfg
        state_ok = inp.state is not None and fresh(cfg.state_stale_ms, inp.now_ns, inp.state_rx_ns)
        force_ok = inp.force is not None and fresh(cfg.stale_ms, inp.now_ns, inp.force_rx_ns)
        self._contact = cfg.passivity and force_ok and _touching(inp.force)
        if force_ok:
            lost = self._force_lost_ns
            if lost is None or inp.force_rx_ns > lost:  # a sample sent since it came back
                self._force_lost_ns = None
                self._force_flowing = True
        for name in inp.lost:
            self._on_lost(name)
        for cmd in inp.commands:
            self._on_command(cmd, inp, state_ok, force_ok)
        out: ArmTarget | None = None
        target = self.target
        if self.mode is Mode.FOLLOW:
            out = self._follow(inp, state_ok, force_ok)
        elif self._streaming():
            sent = (target.p_sup.copy(), target.R_sup.copy())
            engage = target.engage_out
            out = self._run_task(inp, state_ok, force_ok)
            if out is None and target.p0 is not None:
                # The task ended this tick: hold at the target last sent (or where its
                # engagement began), not at one the arm was never asked to reach.
                began = target.engage_out != engage
                target.p_sup, target.R_sup = (target.p0.copy(), target.R0.copy()) if began else sent
        if (
            out is None
            and self.mode in (Mode.HOLD, Mode.ESTOP)
            and target.p0 is not None
            and target.hold_due(self._now_ns)
        ):
            out = self._command(inp, active=False)
        if self.watch is not None:
            self._watch_step(inp, state_ok, force_ok)
        stop_arm, self._stop_arm = self._stop_arm, None
        return TickResult(out, self.notices.drain(), self.tasks.drain(), stop_arm)

    def next_wake_ns(self) -> int | None:
        """When the service must tick again without new input (monotonic ns), or None:
        only on input. Watchdogs wake at their deadline; a task, a target catching up with
        the operator, and compliance step every period; so does teleoperation with the
        slave's passivity port on (it watches for a contact, and in one re-sends the target
        every period for the port to correct between the operator's commands); a hold is
        re-sent at 20 Hz."""
        cfg = self._cfg
        now = self._now_ns
        period_ns = int(cfg.period_s * 1e9)
        if self.mode is Mode.FOLLOW:
            if self.target.lagging or cfg.compliance or cfg.passivity:
                return now + period_ns
            deadline = follow_deadline_ns(cfg, self._cmd_rx_ns, self._state_rx_ns)
            return max(deadline + 1, now + 1)
        if self.mode is Mode.TASK:
            return now + period_ns if self._streaming() else None
        if self.mode in (Mode.HOLD, Mode.ESTOP) and self.target.p0 is not None:
            return self.target.next_hold_ns(now)
        if self.watch is not None:
            return now + WATCH_PERIOD_NS
        return None

    def _streaming(self) -> bool:
        """A streamed task runs (the supervisor steps it; `home` runs in the arm)."""
        run = self.tasks.current
        return self.mode is Mode.TASK and run is not None and not run.external

    def _task_name(self) -> str:
        run = self.tasks.current
        return run.name if run is not None else "task"

    def _sensed(self, inp: Inputs, force_ok: bool) -> Sensed:
        force = inp.force if force_ok else None
        return Sensed(self._cfg, self._now_ns, inp.state, force, self.notices)

    # --- notices ---------------------------------------------------------------------------
    def _notice(
        self,
        kind: str,
        message: str,
        data: Mapping[str, Any] | None = None,
        limit_key: str | None = None,
    ) -> None:
        self.notices.post(self._now_ns, kind, message, data, limit_key)

    def _intervene(self, kind: str, message: str, data: Mapping[str, Any], limit_key: str) -> None:
        self.notices.intervene(self._now_ns, kind, message, data, limit_key)

    # --- masters and the lease ------------------------------------------------------------
    def _record(self, cmd: OperatorCommand) -> MasterRecord | None:
        """Update the per-master record; None if `cmd` is stale (lower seq or engage)."""
        verdict = self.masters.classify(cmd)
        if verdict == "stale":
            return None
        if verdict == "restarted":
            # The master restarted and counts from the beginning again: forget it (and
            # end whatever it was doing) rather than ignore it for ever.
            self._forget_master(cmd.master, "restarted")
        return self.masters.record(cmd, self.lease)

    def _forget_master(self, master: str, why: str) -> None:
        if self.lease == master:
            self._hold("watchdog", f"master_{why}", f"master {master!r} {why}: holding")
        self.masters.pop(master, None)

    def _on_lost(self, name: str) -> None:
        if name.startswith("master/"):
            master = name[len("master/") :]
            if self.lease == master:
                self._hold("watchdog", "master_lost", f"master {master!r} lost: holding")
            rec = self.masters.get(master)
            if rec is not None:
                # Keep the record: if the token comes back while the master still streams
                # the same engagement (a network cut), that engagement must not resume.
                rec.block(rec.engage)
        elif name == "arm" and self.mode in (Mode.FOLLOW, Mode.TASK):
            self._hold(
                "watchdog",
                "arm_lost",
                "the arm service is gone: holding",
                task_error="unavailable",
            )
        elif name == "force":
            # Gone: no stream to wait for; without compliance teleoperation goes on
            # unsupervised, as with no sensor at all (the lost token is an event).
            self._force_flowing = False
            self._force_lost_ns = self._now_ns
            if (self._cfg.compliance and self.mode is Mode.FOLLOW) or self._streaming():
                self._hold(
                    "watchdog",
                    "force_lost",
                    "the force service is gone: holding",
                    task_error="unavailable",
                )

    def _refuse(self, kind: str, cmd: OperatorCommand, rec: MasterRecord, why: str) -> None:
        """An active command that may not move the arm: its engagement is blocked for good."""
        rec.block(cmd.engage)
        self._intervene(
            kind,
            f"command of master {cmd.master!r} refused: {why}",
            {
                "key": "robot/cmd",
                "master": cmd.master,
                "engage": cmd.engage,
                "action": "refused",
                "reason": why,
                "count": self.notices.counters.get(kind, 0) + 1,
            },
            limit_key=f"{kind}:{cmd.master}",
        )

    def _on_command(
        self, cmd: OperatorCommand, inp: Inputs, state_ok: bool, force_ok: bool
    ) -> None:
        rec = self._record(cmd)
        if rec is None:
            self.stats["stale_commands"] += 1
            self._intervene(
                "rejected",
                f"stale command from master {cmd.master!r} ignored (seq {cmd.seq}, engage "
                f"{cmd.engage})",
                {
                    "key": "robot/cmd",
                    "reason": "stale seq or engage",
                    "master": cmd.master,
                    "count": self.stats["stale_commands"],
                },
                limit_key=f"stale:{cmd.master}",
            )
            return
        self.stats["commands"] += 1
        if cmd.active:
            why = norm_out_of_bounds("dp", cmd.dp, "displacement_m")
            if why is not None:
                # An absurd motion (a broken or hostile master): refused before any
                # arithmetic; its engagement is blocked and, if it leads, the arm holds.
                if self.lease == cmd.master:
                    self._hold("limit", "absurd_command", why, intervention=False, notify=False)
                self._refuse("limit", cmd, rec, why)
                return
        if self.mode in (Mode.ESTOP, Mode.TASK):
            if cmd.active:
                kind, why = self._busy_reason()
                self._refuse(kind, cmd, rec, why)
            return
        if self.lease is not None and self.lease != cmd.master:
            if cmd.active:
                self._refuse("lease", cmd, rec, f"master {self.lease!r} holds the lease")
            return
        if self.lease == cmd.master:
            if not cmd.active:
                self._hold(
                    "lease",
                    "disengaged",
                    f"master {cmd.master!r} disengaged",
                    intervention=False,
                    notify=False,
                )
                return
            if cmd.engage == self.engage_in:
                self._cmd, self._cmd_rx_ns = cmd, inp.now_ns
                self._fresh = True
                return
        elif not cmd.active:
            return
        elif cmd.engage <= rec.blocked:
            self._notice(
                "lease",
                f"master {cmd.master!r}: engagement {cmd.engage} was held; engage again to move",
                {
                    "master": cmd.master,
                    "engage": cmd.engage,
                    "reason": "engagement_held",
                    "held_by": self.hold_reason,
                },
                limit_key=f"held:{cmd.master}",
            )
            return
        self._start_engagement(cmd, rec, inp, state_ok, force_ok)

    def _busy_reason(self) -> tuple[ErrorCode, str]:
        """Why nothing else may move the arm in ESTOP or TASK mode: (error code, reason)."""
        if self.mode is Mode.ESTOP:
            return "estop", "emergency stop latched (call reset)"
        return "busy", f"task {self._task_name()!r} running"

    def _start_engagement(
        self, cmd: OperatorCommand, rec: MasterRecord, inp: Inputs, state_ok: bool, force_ok: bool
    ) -> None:
        state = inp.state
        if inp.force_warming:
            # The force stream is on its way (a sample kept from before it was dropped may
            # still look fresh, and go stale a tick later): the master's next command
            # starts the engagement, with the stream flowing.
            self.stats["deferred"] += 1
            return
        why = None
        if not state_ok or state is None:
            why = "no fresh robot/state"
        elif state.status not in MOVING_STATUSES:
            why = f"robot is {state.status}"
        elif self._cfg.compliance and not force_ok:
            why = "force stream stale (compliance on)"
        if why is not None or state is None:
            if self.lease == cmd.master:
                self._hold("watchdog", "cannot_rebase", f"cannot start a new engagement: {why}")
            self._refuse("rejected", cmd, rec, str(why))
            return
        self.watch = None  # teleoperation takes over from a forwarded motion
        if self.lease != cmd.master:
            self.lease = cmd.master
            self._notice(
                "lease",
                f"master {cmd.master!r} took the lease",
                {"master": cmd.master, "action": "taken"},
            )
        self.engage_in = cmd.engage
        self._cmd, self._cmd_rx_ns = cmd, inp.now_ns
        self._fresh = True
        self._begin_out(state)
        self.mode = Mode.FOLLOW
        self.hold_reason = None

    def _begin_out(self, state: RobotState) -> None:
        """Start a new engagement towards the arm, rebased on the current tool pose."""
        self.target.begin(state, self._now_ns, self._cfg.period_s)
        self.notices.clear_edges()
        self._force_flowing = False
        self.stats["engagements"] += 1

    def _release_lease(self, why: str) -> None:
        holder = self.lease
        if holder is None:
            return
        rec = self.masters.get(holder)
        if rec is not None:
            rec.block(self.engage_in)
        self.lease = None
        self._cmd = None
        self._notice(
            "lease",
            f"master {holder!r} released the lease ({why})",
            {"master": holder, "action": "released", "reason": why},
        )

    def _hold(
        self,
        kind: str,
        reason: str,
        message: str,
        intervention: bool = True,
        notify: bool = True,
        task_error: ErrorCode = "not_ready",
    ) -> None:
        """Stop following / end the task: the target stays, the hold is re-sent each tick.

        An intervention is counted under `kind` and reported (rate-limited per reason);
        otherwise the event is informative only (`notify` false: none)."""
        if self.mode is Mode.TASK and self.tasks.current is not None:
            self._finish_task(self.tasks.current, error=(task_error, message))
        holder = self.lease
        rec = None if holder is None else self.masters.get(holder)
        self._release_lease(reason)
        self._settle()
        self.hold_reason = reason
        self.stats["holds"] += 1
        # `engage` is the master's own engagement that was held (what the master shows and
        # must leave to move again); `engage_out` the arm-side counter of robot/arm/target
        data: dict[str, Any] = {"reason": reason, "engage_out": self.target.engage_out}
        if holder is not None:
            data["master"] = holder
        if rec is not None:
            data["engage"] = rec.engage
        if intervention:
            self._intervene(kind, message, data, limit_key=f"hold:{reason}")
        elif notify:
            self._notice(kind, message, data)

    def _settle(self) -> None:
        """Out of FOLLOW or TASK: hold if there is a target, else idle (an e-stop stays)."""
        if self.mode is not Mode.ESTOP:
            self.mode = Mode.HOLD if self.target.p0 is not None else Mode.IDLE

    # --- teleoperation ---------------------------------------------------------------------
    def _follow(self, inp: Inputs, state_ok: bool, force_ok: bool) -> ArmTarget | None:
        cfg = self._cfg
        state = inp.state
        why = follow_problem(
            cfg, inp.now_ns, self._cmd_rx_ns, self.lease, state, state_ok, force_ok
        )
        if why is not None:
            self._hold("watchdog", *why)
        if self.mode is not Mode.FOLLOW or self._cmd is None or self.target.p0 is None:
            return None
        if self._force_flowing and not force_ok:
            # The wrist force that flowed in this engagement stopped (a link stalled, the
            # host is loaded): the contact filter cannot see, so the target waits where it
            # is until a fresh sample is in (compliance on holds instead, above).
            self.stats["force_gap_ticks"] += 1
            self.target.wait(self._now_ns)
            self.notices.edge(
                self._now_ns,
                "force_gap",
                True,
                "limit",
                f"no force sample for {cfg.stale_ms:g} ms: the target waits for the force",
                {"reason": "force_gap", "stale_ms": cfg.stale_ms},
            )
            return None
        if not (self._fresh or self.target.lagging or cfg.compliance or self._contact):
            return None  # nothing new: the arm already has this target
        cmd = self._cmd
        if not self.target.follow(cmd, self._sensed(inp, force_ok)):
            # Unreachable with bounded inputs; if it ever happens the target keeps its
            # last finite value and the arm holds there.
            self._hold("limit", "non_finite", "the operator's target is not finite: holding")
            return None
        # A step that catches up with the operator still carries out their newest command.
        return self._command(inp, active=True, origin_t_ns=cmd.t_ns)

    def _command(self, inp: Inputs, active: bool, origin_t_ns: int | None = None) -> ArmTarget:
        """The target out: `origin_t_ns` the operator command it carries out (the tick's
        own wall time for holds and tasks)."""
        self.stats["published"] += 1
        origin = inp.wall_ns if origin_t_ns is None else origin_t_ns
        return self.target.command(self._now_ns, inp.wall_ns, active, origin)

    # --- e-stop, stop, hand-over to forwarded motions ---------------------------------------
    def estop(self, now_ns: int, why: str = "estop requested") -> None:
        """Latch the emergency stop: hold, end any task (error `estop`), refuse everything."""
        self._now_ns = now_ns
        if self.tasks.current is not None:
            self._finish_task(
                self.tasks.current, error=("estop", f"pre-empted by emergency stop: {why}")
            )
        self._release_lease("estop")
        self.watch = None
        self.mode = Mode.ESTOP
        self.hold_reason = "estop"
        self._intervene(
            "estop", f"emergency stop: {why}", {"latched": True, "reason": why}, limit_key="estop"
        )

    def reset(self, now_ns: int) -> bool:
        """Clear the e-stop latch; every master must engage anew. False if not latched."""
        self._now_ns = now_ns
        if self.mode is not Mode.ESTOP:
            return False
        self.masters.block_all()
        self.mode = Mode.HOLD if self.target.p0 is not None else Mode.IDLE
        self.hold_reason = "reset"
        self._notice("estop", "emergency stop reset", {"latched": False})
        return True

    def stop(self, now_ns: int) -> None:
        """The operator's `stop`: hold teleoperation, cancel a task."""
        self._now_ns = now_ns
        if self.mode is Mode.FOLLOW:
            self._hold("status", "stop", "stop requested: holding", intervention=False)
        elif self.mode is Mode.TASK:
            self.cancel_task(now_ns)

    def _refuse_call(self, what: str) -> None:
        """RpcError estop / busy for a call (`what`: its name in the message) that would
        move the arm while the e-stop is latched or a task runs."""
        if self.mode in (Mode.ESTOP, Mode.TASK):
            code, why = self._busy_reason()
            raise RpcError(code, f"{what} refused: {why}")

    def claim(
        self,
        method: str,
        now_ns: int | None = None,
        guarded: bool = False,
        goal: Sequence[float] | None = None,
    ) -> None:
        """Before forwarding a motion method: refuse it while the supervisor commands the
        arm, otherwise stop re-sending the hold so the arm's own motion is not disturbed,
        and watch the motion (contact, workspace) until it is over."""
        if now_ns is not None:
            self._now_ns = now_ns
        self._refuse_call(method)
        if self.mode is Mode.FOLLOW:
            raise RpcError("busy", f"{method} refused: master {self.lease!r} is teleoperating")
        self.mode = Mode.IDLE
        to = None if goal is None else (float(goal[0]), float(goal[1]), float(goal[2]))
        self.watch = Watch(method, self._now_ns, guarded=guarded, goal=to)

    def end_watch(self, watch: Watch | None = None) -> None:
        """The forwarded motion never started (its call failed): nothing to watch. With
        `watch`, only if it is still that one (a later claim's watch stays)."""
        if watch is None or self.watch is watch:
            self.watch = None

    def _watch_step(self, inp: Inputs, state_ok: bool, force_ok: bool) -> None:
        """A forwarded motion: over once the robot shows it ended; stopped (the service
        calls the arm's `stop`) at a contact above max_force_n or outside the box."""
        watch = self.watch
        state = inp.state
        if watch is None or self.mode is not Mode.IDLE:
            self.watch = None
            return
        if not state_ok or state is None:
            return
        force = inp.force if force_ok else None
        verdict = watch_step(watch, self._cfg, inp.now_ns, state, force)
        if isinstance(verdict, WatchStop):
            self.watch = None
            self._stop_arm = {"now": verdict.data.get("now") is True}
            self._intervene(verdict.kind, verdict.message, verdict.data, f"watch:{verdict.kind}")
        elif verdict is None:
            self.watch = None

    def shutdown(self, now_ns: int, wall_ns: int, repeats: int) -> list[ArmTarget]:
        """The service is closing: end any task, release the lease, and return `repeats`
        holds of the current engagement (none if there never was one)."""
        self._now_ns = now_ns
        if self.tasks.current is not None:
            self._finish_task(
                self.tasks.current, error=("unavailable", "the decision server is shutting down")
            )
        self._release_lease("shutdown")
        self._settle()
        if self.target.p0 is None:
            return []
        inp = Inputs(now_ns=now_ns, wall_ns=wall_ns)
        return [self._command(inp, active=False) for _ in range(repeats)]

    # --- tasks ---------------------------------------------------------------------------
    def start_task(self, plan: TaskPlan, now_ns: int, external: bool = False) -> TaskRun:
        """Start a task; a streamed one begins at the next tick. Teleoperation is pre-empted
        (the master must engage anew afterwards). RpcError estop / busy."""
        self._now_ns = now_ns
        self._refuse_call(f"task {plan.name!r}")
        if self.mode is Mode.FOLLOW:
            self._hold(
                "task",
                "preempted",
                f"teleoperation pre-empted by task {plan.name!r}",
                intervention=False,
            )
        self.watch = None
        self.mode = Mode.TASK
        self.hold_reason = None
        self.stats["tasks"] += 1
        return self.tasks.start(plan, external, self.notices, self._now_ns)

    def cancel_task(self, now_ns: int) -> TaskRun | None:
        """Cancel the running task (its reply: cancelled); the target holds."""
        self._now_ns = now_ns
        run = self.tasks.current
        if run is None:
            return None
        run.cancelled = True
        self._finish_task(run, result={"task": run.name, "cancelled": True, "done": False})
        return run

    def finish_external(
        self,
        run: TaskRun,
        result: dict[str, Any] | None = None,
        error: tuple[ErrorCode, str] | None = None,
    ) -> None:
        """An external task (forwarded `home`) ended; no-op if it already ended."""
        if run.done:
            return
        self._finish_task(run, result=result, error=error)

    def _finish_task(
        self,
        run: TaskRun,
        result: dict[str, Any] | None = None,
        error: tuple[ErrorCode, str] | None = None,
    ) -> None:
        if self.tasks.finish(run, result, error, self.notices, self._now_ns) and (
            self.mode is Mode.TASK
        ):
            streamed = not run.external and run.started and self.target.p0 is not None
            self.mode = Mode.HOLD if streamed else Mode.IDLE
            self.hold_reason = f"task {run.name} ended"

    def _run_task(self, inp: Inputs, state_ok: bool, force_ok: bool) -> ArmTarget | None:
        run = self.tasks.current
        assert run is not None
        end = run_tick(run, self.target, self._sensed(inp, force_ok), state_ok, self._begin_out)
        if end is not None:
            self._finish_task(run, result=end.result, error=end.error)
            return None
        return self._command(inp, active=True)

    # --- status ----------------------------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """The supervisor's part of `status`."""
        target = self.target
        return {
            "mode": self.mode.value,
            "lease": self.lease,
            "engage_in": self.engage_in if self.lease is not None else None,
            "engage_out": target.engage_out,
            "seq_out": target.seq_out,
            "hold_reason": self.hold_reason,
            "estop": self.mode is Mode.ESTOP,
            "target_p": target.p_sup.tolist() if target.p0 is not None else None,
            "offset_p": target.off_p.tolist(),
            "offset_rot_rad": target.offset_rot_rad,
            "task": self.tasks.current.summary() if self.tasks.current is not None else None,
            "last_task": self.tasks.last.summary() if self.tasks.last is not None else None,
            "interventions": dict(self.notices.counters),
            "stats": dict(self.stats),
            "masters": sorted(self.masters),
        }


def _touching(force: ForceSample | None) -> bool:
    """A wrist force at or above the passivity dead band, or a moment at or above the
    rotational port's (the same band at ROTATION_LENGTH_M: 0.1 N·m): the tool is in
    contact."""
    if force is None:
        return False
    if sum(x * x for x in force.f) >= DEADBAND_N * DEADBAND_N:
        return True
    band_nm = DEADBAND_N * ROTATION_LENGTH_M
    return sum(x * x for x in force.c) >= band_nm * band_nm
