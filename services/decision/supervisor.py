"""The supervisory logic, free of I/O: one `tick()` per input, and per timer wake-up.

The decision server stands between the masters (`robot/cmd`) and the puma (`robot/puma/cmd`).
It keeps its own engagement towards the puma (`engage_out`, its own `seq`, master id
"decision"). When the lease holder's engagement starts, it records the tool pose (p0, R0)
from the newest robot/state and starts a new `engage_out`; each tick it maps the newest
command to the operator's desired tool pose (PROTOCOL §2) and moves the SUPERVISED target
towards it through the filters: (a) contact, (b) active compliance, (c) tool speed,
(d) workspace box. It sends the puma `dp = p_sup − p0`, `dR = R0ᵀ·R_sup` in the world frame,
so whatever a filter held back stays an offset of the target: it never turns into a jump.

Motion the filters remove (into a contact, out of the workspace) is dropped for good: it is
kept as an offset between the operator's target and the supervised one, so moving the hand
back moves the tool back at once. Motion the speed limit holds back is only delayed: the
target catches up with the operator at the limit speed.

Holding (watchdog, lost master, e-stop, stale streams, disengage) sends `active = false`
with the last dp/dR at once and then every HOLD_RESEND_NS, never `active = true` again for
that engagement; motion resumes only with a NEW engagement of a master, which is rebased on
the then-current pose.

Reactive: the service ticks once per operator command as it arrives (and per lost service),
so the supervised command goes out at once; between inputs it ticks only when
`next_wake_ns()` says: a watchdog deadline, the hold's re-send, a task's or a catching-up
target's next step. A tick with nothing new publishes nothing. The speed limits bound the
target's motion over the time since its last step (not per tick), so a master at any rate
may move at the limit speed on average.

Time: `now_ns` is a monotonic clock (ns) for watchdogs and ticks; `wall_ns` is the
`time.time_ns()` put in the commands' `t_ns`. Not thread-safe: the service calls it under
one lock.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from services.bus.bounds import norm_out_of_bounds
from services.bus.errors import ErrorCode, RpcError
from services.bus.messages import ForceSample, OperatorCommand, RobotState, mat3, vec
from services.decision.config import DecisionConfig
from services.decision.filters import (
    admittance_step,
    clamp_box,
    clip_norm,
    effective_box,
    engagement_command,
    exp_so3,
    in_box,
    log_so3,
    norm3,
    operator_target,
    orthonormalize,
    without_motion_into,
)
from services.decision.tasks import Grip, GuardedMove, MoveTo, Step, TaskPlan

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

MASTER_ID = "decision"
"""The decision's own master id on robot/puma/cmd."""
MAX_MASTERS = 64
"""Per-master records kept (oldest forgotten first): a flood of ids cannot grow memory."""
RESTART_GAP_NS = 250_000_000
"""A lower seq sent this long after the newest is a restarted master, not a stale command."""
EDGE_RELEASE_NS = 250_000_000
"""A continuous intervention (contact, limit) counts once until it has been off this long."""
SETTLE_S = 2.0
"""A task move may take this much longer than distance / speed before it fails."""
MOVING_STATUSES = ("ready", "moving")
STEP_EPS_M = 1e-9
STEP_EPS_RAD = 1e-9
BLOCKED_SHARE = 0.01
"""A guarded move is blocked when a step moves less than this share of what it asked."""
NOTICES_PER_S = 5
"""Rate-limited events of one kind sent per second, over all their keys."""
MAX_NOTICE_KEYS = 1024
"""Rate-limit keys remembered (oldest forgotten first): memory stays bounded."""
WATCH_PERIOD_NS = 5_000_000
"""A forwarded motion is checked this often (200 Hz): at 0.5 m/s, 2.5 mm between checks."""
WATCH_START_NS = 500_000_000
"""A forwarded motion that has not shown `moving` this long after it was sent is over."""
WATCH_BOX_TOL_M = 0.002
"""A forwarded motion stops when the tool leaves the workspace box by more than this."""
HOLD_RESEND_NS = 50_000_000
"""A hold is re-sent this often (20 Hz): one lost packet must not matter, and the puma needs
nothing more while nothing changes."""

#: the kinds of intervention events, each with a counter in `status`
INTERVENTIONS: tuple[str, ...] = (
    "watchdog",
    "lease",
    "limit",
    "contact",
    "estop",
    "rejected",
    "busy",
)


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
class Notice:
    """An event for robot/events: `kind`, a message for people, and data."""

    kind: str
    message: str
    data: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Inputs:
    """What one tick sees.

    now_ns: monotonic time (ns); wall_ns: time.time_ns() for the outgoing `t_ns`.
    state, force: the newest robot/state and robot/force (None if never received), with
    their arrival times state_rx_ns, force_rx_ns on the monotonic clock.
    commands: the robot/cmd messages received since the last tick, in arrival order (already
    validated by the codec). lost: liveliness names gone since the last tick ("master/<id>",
    "puma", "force").
    """

    now_ns: int
    wall_ns: int = 0
    state: RobotState | None = None
    state_rx_ns: int = 0
    force: ForceSample | None = None
    force_rx_ns: int = 0
    commands: tuple[OperatorCommand, ...] = ()
    lost: tuple[str, ...] = ()


@dataclass(slots=True)
class _Master:
    """What the supervisor remembers of one master (its newest command's seq/engage)."""

    seq: int
    engage: int
    t_ns: int
    blocked: int = -1
    """Active commands of engagements ≤ this one never move the arm (held or refused)."""


class TaskRun:
    """One run of a task: its plan, progress, and outcome (`result` or `error`).

    `external` runs (the forwarded `home`) are executed by the service, which calls
    `Supervisor.finish_external`. Read by the service's RPC threads under its lock.
    """

    __slots__ = (
        "R_keep",
        "cancelled",
        "done",
        "error",
        "external",
        "f0_w",
        "grip",
        "id",
        "plan",
        "result",
        "start_p",
        "started",
        "step_index",
        "step_start_ns",
    )

    def __init__(self, run_id: int, plan: TaskPlan, external: bool = False) -> None:
        self.id = run_id
        self.plan = plan
        self.external = external
        self.started = False
        self.done = False
        self.cancelled = False
        self.result: dict[str, Any] | None = None
        self.error: tuple[ErrorCode, str] | None = None
        self.step_index = 0
        self.step_start_ns = 0
        self.start_p: Vec = np.zeros(3)
        self.R_keep: Mat = np.eye(3)
        self.f0_w: Vec | None = None
        self.grip: float | None = None

    @property
    def name(self) -> str:
        return self.plan.name

    @property
    def step(self) -> Step | None:
        steps = self.plan.steps
        return steps[self.step_index] if self.step_index < len(steps) else None

    def summary(self) -> dict[str, Any]:
        """The run for `status` and for a reply."""
        return {
            "id": self.id,
            "name": self.name,
            "done": self.done,
            "cancelled": self.cancelled,
            "step": self.step_index,
            "steps": len(self.plan.steps),
            "result": self.result,
            "error": None
            if self.error is None
            else {"error": self.error[0], "message": self.error[1]},
        }


@dataclass(frozen=True, slots=True)
class TickResult:
    """A tick's output: the command for robot/puma/cmd (None: send nothing), the events,
    and the task runs that ended (their waiters are woken)."""

    command: OperatorCommand | None
    notices: tuple[Notice, ...]
    finished: tuple[TaskRun, ...]
    stop_arm: bool = False
    """A forwarded motion broke a limit: the service must call the puma's `stop` now."""


@dataclass(slots=True)
class _Watch:
    """A forwarded motion (`move_*`, `home`) the supervisor watches: the puma plans and
    executes it, the decision stops it at a contact or at the workspace's edge."""

    method: str
    since_ns: int
    moving: bool = False


def _norm(v: Vec) -> float:
    return norm3(v)


def _list(v: Vec) -> list[float]:
    return [float(x) for x in v]


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
        self.seq_out = seq_start
        self.engage_out = engage_start
        self._p0: Vec | None = None
        self._R0: Mat = np.eye(3)
        self.p_sup: Vec = np.zeros(3)
        self.R_sup: Mat = np.eye(3)
        self._off_p: Vec = np.zeros(3)
        self._off_R: Mat = np.eye(3)
        self._grip: float | None = None
        self._masters: OrderedDict[str, _Master] = OrderedDict()
        self.counters: dict[str, int] = dict.fromkeys(INTERVENTIONS, 0)
        self.stats: dict[str, int] = {
            "ticks": 0,
            "commands": 0,
            "stale_commands": 0,
            "engagements": 0,
            "published": 0,
            "holds": 0,
            "tasks": 0,
        }
        self._last_notice_ns: OrderedDict[str, int] = OrderedDict()
        self._kind_window: dict[str, tuple[int, int]] = {}
        self.suppressed: dict[str, int] = {}
        self._edges: dict[str, int] = {}
        self._notices: list[Notice] = []
        self._finished: list[TaskRun] = []
        self.task: TaskRun | None = None
        self.last_task: TaskRun | None = None
        self._task_ids = 0
        self._now_ns = 0
        self.hold_reason: str | None = None
        self._dt_s = config.period_s
        self._last_adv_ns: int | None = None
        self._last_out_ns: int | None = None
        self._last_out_active = False
        self._fresh = False
        self._lagging = False
        self._state_rx_ns = 0
        self._force_rx_ns = 0
        self.watch: _Watch | None = None
        self._stop_arm = False

    # --- settings ----------------------------------------------------------------------
    @property
    def config(self) -> DecisionConfig:
        return self._cfg

    def set_config(self, config: DecisionConfig) -> None:
        """New supervisory settings, effective at the next tick (the loop rate is fixed)."""
        if config.rate_hz != self._cfg.rate_hz:
            raise ValueError("rate_hz cannot change while the loop runs")
        self._cfg = config

    # --- the tick ------------------------------------------------------------------------
    def tick(self, inp: Inputs) -> TickResult:
        """Process new inputs (or none: a timer wake-up); return what to publish."""
        self._now_ns = inp.now_ns
        self._state_rx_ns, self._force_rx_ns = inp.state_rx_ns, inp.force_rx_ns
        self.stats["ticks"] += 1
        self._fresh = False
        last = self._last_adv_ns
        # The time the target may move over: since its last step, at most one watchdog
        # period (a longer gap is a hold anyway).
        self._dt_s = (
            self._cfg.period_s
            if last is None
            else min(max((inp.now_ns - last) * 1e-9, 0.0), self._cfg.watchdog_ms * 1e-3)
        )
        state_ok = self._state_fresh(inp)
        force_ok = self._force_fresh(inp)
        for name in inp.lost:
            self._on_lost(name)
        for cmd in inp.commands:
            self._on_command(cmd, inp, state_ok, force_ok)
        out: OperatorCommand | None = None
        if self.mode is Mode.FOLLOW:
            out = self._follow(inp, state_ok, force_ok)
        elif self.mode is Mode.TASK and self.task is not None and not self.task.external:
            sent = (self.p_sup.copy(), self.R_sup.copy())
            engage = self.engage_out
            out = self._run_task(inp, state_ok, force_ok)
            if out is None and self._p0 is not None:
                # The task ended this tick: hold at the target last sent (or where its
                # engagement began), not at one the arm was never asked to reach.
                began = self.engage_out != engage
                self.p_sup, self.R_sup = (self._p0.copy(), self._R0.copy()) if began else sent
        if (
            out is None
            and self.mode in (Mode.HOLD, Mode.ESTOP)
            and self._p0 is not None
            and self._hold_due()
        ):
            out = self._command(inp, active=False)
        if self.watch is not None:
            self._watch_step(inp, state_ok, force_ok)
        notices, self._notices = tuple(self._notices), []
        finished, self._finished = tuple(self._finished), []
        stop_arm, self._stop_arm = self._stop_arm, False
        return TickResult(out, notices, finished, stop_arm)

    def _hold_due(self) -> bool:
        """The first hold after motion goes out at once, then every HOLD_RESEND_NS."""
        last = self._last_out_ns
        return last is None or self._last_out_active or self._now_ns - last >= HOLD_RESEND_NS

    def next_wake_ns(self) -> int | None:
        """When the service must tick again without new input (monotonic ns), or None:
        only on input. Watchdogs wake at their deadline; a task, a target catching up with
        the operator, and compliance step every period; a hold is re-sent at 20 Hz."""
        cfg = self._cfg
        now = self._now_ns
        period_ns = int(cfg.period_s * 1e9)
        if self.mode is Mode.FOLLOW:
            if self._lagging or cfg.compliance:
                return now + period_ns
            deadline = min(
                self._cmd_rx_ns + int(cfg.watchdog_ms * 1e6),
                self._state_rx_ns + int(cfg.state_stale_ms * 1e6),
            )
            return max(deadline + 1, now + 1)
        if self.mode is Mode.TASK:
            run = self.task
            return now + period_ns if run is not None and not run.external else None
        if self.mode in (Mode.HOLD, Mode.ESTOP) and self._p0 is not None:
            last = self._last_out_ns
            if last is None or self._last_out_active:
                return now + 1
            return max(last + HOLD_RESEND_NS, now + 1)
        if self.watch is not None:
            return now + WATCH_PERIOD_NS
        return None

    def _state_fresh(self, inp: Inputs) -> bool:
        return (
            inp.state is not None and inp.now_ns - inp.state_rx_ns <= self._cfg.state_stale_ms * 1e6
        )

    def _force_fresh(self, inp: Inputs) -> bool:
        return inp.force is not None and inp.now_ns - inp.force_rx_ns <= self._cfg.stale_ms * 1e6

    # --- notices and counters -------------------------------------------------------------
    def _notice(
        self,
        kind: str,
        message: str,
        data: Mapping[str, Any] | None = None,
        limit_key: str | None = None,
    ) -> None:
        """Queue an event; with `limit_key`, at most one per event_interval_s for that key and
        NOTICES_PER_S per kind over all keys (a flood of master ids is one trickle); the
        next one sent says how many of its kind were suppressed."""
        if limit_key is not None:
            now = self._now_ns
            last = self._last_notice_ns.get(limit_key)
            start, sent = self._kind_window.get(kind, (now, 0))
            if now - start >= 1_000_000_000:
                start, sent = now, 0
            if (
                last is not None and now - last < self._cfg.event_interval_s * 1e9
            ) or sent >= NOTICES_PER_S:
                self.suppressed[kind] = self.suppressed.get(kind, 0) + 1
                self._kind_window[kind] = (start, sent)
                return
            self._kind_window[kind] = (start, sent + 1)
            self._last_notice_ns[limit_key] = now
            self._last_notice_ns.move_to_end(limit_key)
            while len(self._last_notice_ns) > MAX_NOTICE_KEYS:
                self._last_notice_ns.popitem(last=False)
            n = self.suppressed.pop(kind, 0)
            if n:
                data = {**(data or {}), "suppressed": n}
        self._notices.append(Notice(kind, message, dict(data or {})))

    def _intervene(self, kind: str, message: str, data: Mapping[str, Any], limit_key: str) -> None:
        """Count an intervention of `kind` and report it (rate-limited per `limit_key`)."""
        self.counters[kind] = self.counters.get(kind, 0) + 1
        self._notice(kind, message, data, limit_key)

    def _edge(
        self, name: str, active: bool, kind: str, message: str, data: Mapping[str, Any]
    ) -> None:
        """A continuous condition counts (and is reported) once when it starts, and starts
        again only after it has been off for EDGE_RELEASE_NS."""
        if not active:
            return
        last = self._edges.get(name)
        self._edges[name] = self._now_ns
        if last is None or self._now_ns - last > EDGE_RELEASE_NS:
            self._intervene(kind, message, data, limit_key=f"edge:{name}")

    # --- masters and the lease ------------------------------------------------------------
    def _record(self, cmd: OperatorCommand) -> _Master | None:
        """Update the per-master record; None if `cmd` is stale (lower seq or engage)."""
        rec = self._masters.get(cmd.master)
        if rec is not None and (cmd.seq <= rec.seq or cmd.engage < rec.engage):
            if cmd.seq < rec.seq and cmd.t_ns - rec.t_ns > RESTART_GAP_NS:
                # The master restarted and counts from the beginning again: forget it (and
                # end whatever it was doing) rather than ignore it for ever.
                self._forget_master(cmd.master, "restarted")
                rec = None
            else:
                return None
        if rec is None:
            rec = _Master(cmd.seq, cmd.engage, cmd.t_ns)
            self._masters[cmd.master] = rec
            while len(self._masters) > MAX_MASTERS:
                oldest = next(k for k in self._masters if k != self.lease)
                del self._masters[oldest]
        else:
            rec.seq, rec.engage, rec.t_ns = cmd.seq, cmd.engage, cmd.t_ns
            self._masters.move_to_end(cmd.master)
        return rec

    def _forget_master(self, master: str, why: str) -> None:
        if self.lease == master:
            self._hold("watchdog", f"master_{why}", f"master {master!r} {why}: holding")
        self._masters.pop(master, None)

    def _on_lost(self, name: str) -> None:
        if name.startswith("master/"):
            master = name[len("master/") :]
            if self.lease == master:
                self._hold("watchdog", "master_lost", f"master {master!r} lost: holding")
            rec = self._masters.get(master)
            if rec is not None:
                # Keep the record: if the token comes back while the master still streams
                # the same engagement (a network cut), that engagement must not resume.
                rec.blocked = max(rec.blocked, rec.engage)
        elif name == "puma" and self.mode in (Mode.FOLLOW, Mode.TASK):
            self._hold(
                "watchdog",
                "puma_lost",
                "the puma service is gone: holding",
                task_error="unavailable",
            )
        elif name == "force" and (
            (self._cfg.compliance and self.mode is Mode.FOLLOW)
            or (self.mode is Mode.TASK and self.task is not None and not self.task.external)
        ):
            self._hold(
                "watchdog",
                "force_lost",
                "the force service is gone: holding",
                task_error="unavailable",
            )

    def _refuse(self, kind: str, cmd: OperatorCommand, rec: _Master, why: str) -> None:
        """An active command that may not move the arm: its engagement is blocked for good."""
        rec.blocked = max(rec.blocked, cmd.engage)
        self._intervene(
            kind,
            f"command of master {cmd.master!r} refused: {why}",
            {
                "key": "robot/cmd",
                "master": cmd.master,
                "engage": cmd.engage,
                "action": "refused",
                "reason": why,
                "count": self.counters.get(kind, 0) + 1,
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
        if self.mode is Mode.ESTOP:
            if cmd.active:
                self._refuse("estop", cmd, rec, "emergency stop latched (call reset)")
            return
        if self.mode is Mode.TASK:
            if cmd.active:
                name = self.task.name if self.task is not None else "task"
                self._refuse("busy", cmd, rec, f"task {name!r} running")
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
                {"master": cmd.master, "engage": cmd.engage, "reason": "engagement_held"},
                limit_key=f"held:{cmd.master}",
            )
            return
        self._start_engagement(cmd, rec, inp, state_ok, force_ok)

    def _start_engagement(
        self, cmd: OperatorCommand, rec: _Master, inp: Inputs, state_ok: bool, force_ok: bool
    ) -> None:
        state = inp.state
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
        """Start a new engagement towards the puma, rebased on the current tool pose."""
        self.engage_out = max(self.engage_out, state.engage) + 1
        self._p0 = np.array(state.tool_p, dtype=float)
        self._R0 = orthonormalize(mat3(state.tool_R))
        self.p_sup = self._p0.copy()
        self.R_sup = self._R0.copy()
        self._off_p = np.zeros(3)
        self._off_R = np.eye(3)
        self._edges.clear()
        self._lagging = False
        # The engagement's first step may move one period's worth, as a tick always could.
        self._last_adv_ns = self._now_ns - int(self._cfg.period_s * 1e9)
        self._dt_s = self._cfg.period_s
        self.stats["engagements"] += 1

    def _release_lease(self, why: str) -> None:
        holder = self.lease
        if holder is None:
            return
        rec = self._masters.get(holder)
        if rec is not None:
            rec.blocked = max(rec.blocked, self.engage_in)
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
        if self.mode is Mode.TASK and self.task is not None:
            self._finish_task(self.task, error=(task_error, message))
        self._release_lease(reason)
        if self.mode is not Mode.ESTOP:
            self.mode = Mode.HOLD if self._p0 is not None else Mode.IDLE
        self.hold_reason = reason
        self.stats["holds"] += 1
        data = {"reason": reason, "engage": self.engage_out}
        if intervention:
            self._intervene(kind, message, data, limit_key=f"hold:{reason}")
        elif notify:
            self._notice(kind, message, data)

    # --- teleoperation ---------------------------------------------------------------------
    def _follow(self, inp: Inputs, state_ok: bool, force_ok: bool) -> OperatorCommand | None:
        cfg = self._cfg
        state = inp.state
        if inp.now_ns - self._cmd_rx_ns > cfg.watchdog_ms * 1e6:
            self._hold(
                "watchdog",
                "command_timeout",
                f"no command from master {self.lease!r} for {cfg.watchdog_ms:g} ms: holding",
            )
        elif not state_ok or state is None:
            self._hold("watchdog", "state_stale", "robot/state is stale: holding")
        elif state.status == "error":
            self._hold("watchdog", "robot_error", "the robot reports an error: holding")
        elif cfg.compliance and not force_ok:
            self._hold(
                "watchdog",
                "force_stale",
                f"no force sample for {cfg.stale_ms:g} ms with compliance on: holding",
            )
        if self.mode is not Mode.FOLLOW or self._cmd is None or self._p0 is None:
            return None
        if not (self._fresh or self._lagging or cfg.compliance):
            return None  # nothing new: the puma already has this target
        cmd = self._cmd
        p_des, R_des = operator_target(self._p0, self._R0, cmd.dp, mat3(cmd.dR), cmd.frame)
        g_p = p_des + self._off_p
        g_R = R_des @ self._off_R
        if not (np.isfinite(g_p).all() and np.isfinite(g_R).all()):
            # Unreachable with bounded inputs; if it ever happens the target keeps its
            # last finite value and the arm holds there.
            self._hold("limit", "non_finite", "the operator's target is not finite: holding")
            return None
        g_p, g_R = self._advance(g_p, g_R, inp, force_ok)
        self._off_p = g_p - p_des
        self._off_R = orthonormalize(R_des.T @ g_R)
        self._lagging = (
            _norm(g_p - self.p_sup) > STEP_EPS_M
            or _norm(log_so3(self.R_sup.T @ g_R)) > STEP_EPS_RAD
        )
        self._grip = cmd.grip
        return self._command(inp, active=True, origin_t_ns=cmd.t_ns if self._fresh else None)

    def _advance(self, g_p: Vec, g_R: Mat, inp: Inputs, force_ok: bool) -> tuple[Vec, Mat]:
        """Move the supervised target one tick towards the goal (g_p, g_R) through the
        filters; return the goal with what the filters removed folded in (the new offset).

        (a) contact: above max_force_n (max_torque_nm) the goal's component into the
            contact is removed (and a target deeper than the measured tool is pulled back);
        (b) compliance: the goal yields along the force (admittance);
        (c) speed: the step is at most max_tool_speed · dt, dt the time since the last
            step (rotation likewise): a rate limit over time, whatever the input rate;
        (d) workspace: goal and target are clamped to the box (grown to contain the current
            target, so a target outside may only come back).
        """
        cfg = self._cfg
        dt = self._dt_s
        self._last_adv_ns = self._now_ns
        lo, hi = effective_box(cfg.workspace_min, cfg.workspace_max, self.p_sup)
        g1 = clamp_box(g_p, lo, hi)
        clamped = _norm(g1 - g_p) > STEP_EPS_M
        inc = g1 - self.p_sup
        w = log_so3(self.R_sup.T @ g_R)
        state, force = inp.state, inp.force
        if force_ok and force is not None and state is not None:
            f_t = np.asarray(force.f, dtype=float)
            c_t = np.asarray(force.c, dtype=float)
            f_w = mat3(state.tool_R) @ f_t
            f_n = _norm(f_w)
            if f_n > cfg.max_force_n:
                inc, removed = without_motion_into(inc, f_w)
                n = f_w / f_n
                behind = float((np.asarray(state.tool_p) - self.p_sup) @ n)
                ahead = float(inc @ n)
                if behind > ahead:
                    # The arm lags its target: pull the target back to the tool, so the arm
                    # stops where the force crossed the threshold instead of pressing on.
                    inc = inc + (behind - ahead) * n
                    removed += behind - ahead
                self._edge(
                    "contact",
                    removed > STEP_EPS_M,
                    "contact",
                    f"contact force {f_n:.1f} N > {cfg.max_force_n:g} N: motion into it stopped",
                    {
                        "reason": "force",
                        "f": _list(f_w),
                        "force_n": f_n,
                        "tool_p": list(state.tool_p),
                    },
                )
            c_n = _norm(c_t)
            if c_n > cfg.max_torque_nm:
                w, removed_r = without_motion_into(w, c_t)
                self._edge(
                    "torque",
                    removed_r > STEP_EPS_M,
                    "contact",
                    f"contact moment {c_n:.2f} N·m > {cfg.max_torque_nm:g} N·m: rotation into "
                    "it stopped",
                    {"reason": "torque", "c": _list(c_t), "torque_nm": c_n},
                )
            if cfg.compliance:
                inc = inc + admittance_step(
                    f_w, cfg.admittance_m_per_n_s, cfg.admittance_deadband_n, dt
                )
                w = w + admittance_step(
                    c_t, cfg.admittance_rad_per_nm_s, cfg.admittance_deadband_nm, dt
                )
        goal_p = self.p_sup + inc
        goal_R = self.R_sup @ exp_so3(w)
        step, fast = clip_norm(inc, cfg.max_tool_speed_m_s * dt)
        wstep, spin = clip_norm(w, cfg.max_tool_rot_speed_rad_s * dt)
        free = self.p_sup + step
        p_new = clamp_box(free, lo, hi)
        if _norm(p_new - free) > STEP_EPS_M:
            clamped = True
            goal_p = goal_p + (p_new - free)
        self._edge(
            "workspace",
            clamped,
            "limit",
            "workspace limit: target clamped to the box",
            {
                "reason": "workspace",
                "goal": _list(g_p),
                "min": list(cfg.workspace_min),
                "max": list(cfg.workspace_max),
            },
        )
        self._edge(
            "speed",
            fast or spin,
            "limit",
            "tool speed limit: target slowed down",
            {
                "reason": "speed",
                "max_tool_speed_m_s": cfg.max_tool_speed_m_s,
                "max_tool_rot_speed_rad_s": cfg.max_tool_rot_speed_rad_s,
            },
        )
        self.p_sup = p_new
        self.R_sup = orthonormalize(self.R_sup @ exp_so3(wstep))
        return goal_p, orthonormalize(goal_R)

    def _command(
        self, inp: Inputs, active: bool, origin_t_ns: int | None = None
    ) -> OperatorCommand:
        assert self._p0 is not None
        dp, dR = engagement_command(self._p0, self._R0, self.p_sup, self.R_sup)
        self.seq_out += 1
        self.stats["published"] += 1
        self._last_out_ns = self._now_ns
        self._last_out_active = active
        return OperatorCommand(
            seq=self.seq_out,
            t_ns=inp.wall_ns,
            master=MASTER_ID,
            engage=self.engage_out,
            active=active,
            frame="world",
            dp=vec(dp),
            dR=vec(dR),
            grip=self._grip,
            origin_t_ns=origin_t_ns,
        )

    # --- e-stop, stop, hand-over to forwarded motions ---------------------------------------
    def estop(self, now_ns: int, why: str = "estop requested") -> None:
        """Latch the emergency stop: hold, end any task (error `estop`), refuse everything."""
        self._now_ns = now_ns
        if self.task is not None:
            self._finish_task(self.task, error=("estop", f"pre-empted by emergency stop: {why}"))
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
        for rec in self._masters.values():
            rec.blocked = max(rec.blocked, rec.engage)
        self.mode = Mode.HOLD if self._p0 is not None else Mode.IDLE
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

    def claim(self, method: str, now_ns: int | None = None) -> None:
        """Before forwarding a motion method: refuse it while the supervisor commands the
        arm, otherwise stop re-sending the hold so the puma's own motion is not disturbed,
        and watch the motion (contact, workspace) until it is over."""
        if now_ns is not None:
            self._now_ns = now_ns
        if self.mode is Mode.ESTOP:
            raise RpcError("estop", f"{method} refused: emergency stop latched (call reset)")
        if self.mode is Mode.FOLLOW:
            raise RpcError("busy", f"{method} refused: master {self.lease!r} is teleoperating")
        if self.mode is Mode.TASK:
            name = self.task.name if self.task is not None else "task"
            raise RpcError("busy", f"{method} refused: task {name!r} running")
        self.mode = Mode.IDLE
        self.watch = _Watch(method, self._now_ns)

    def end_watch(self) -> None:
        """The forwarded motion never started (its call failed): nothing to watch."""
        self.watch = None

    def target_problem(self, method: str, p: Sequence[float]) -> str | None:
        """Why a forwarded motion's target tool point `p` (m, world) may not be reached
        (outside the workspace box), or None."""
        cfg = self._cfg
        if in_box(p, cfg.workspace_min, cfg.workspace_max, tol=1e-9):
            return None
        return (
            f"{method}: target {[round(float(x), 4) for x in p]} m is outside the workspace "
            f"{list(cfg.workspace_min)} … {list(cfg.workspace_max)}"
        )

    def _watch_step(self, inp: Inputs, state_ok: bool, force_ok: bool) -> None:
        """A forwarded motion: over once the robot shows it ended; stopped (the service
        calls the puma's `stop`) at a contact above max_force_n or outside the box."""
        watch = self.watch
        state = inp.state
        if watch is None or self.mode is not Mode.IDLE:
            self.watch = None
            return
        if not state_ok or state is None:
            return
        if state.status == "moving":
            watch.moving = True
        elif watch.moving or inp.now_ns - watch.since_ns > WATCH_START_NS:
            self.watch = None  # over (ready, or error: the puma already holds)
            return
        cfg = self._cfg
        why: tuple[str, str, dict[str, Any]] | None = None
        if force_ok and inp.force is not None:
            f_w = mat3(state.tool_R) @ np.asarray(inp.force.f, dtype=float)
            f_n = _norm(f_w)
            if f_n > cfg.max_force_n:
                why = (
                    "contact",
                    f"{watch.method} stopped: contact force {f_n:.1f} N > {cfg.max_force_n:g} N",
                    {"reason": "force", "f": _list(f_w), "force_n": f_n},
                )
        lo, hi = cfg.workspace_min, cfg.workspace_max
        if why is None and not in_box(state.tool_p, lo, hi, tol=WATCH_BOX_TOL_M):
            why = (
                "limit",
                f"{watch.method} stopped: the tool left the workspace box",
                {"reason": "workspace", "tool_p": list(state.tool_p)},
            )
        if why is not None:
            kind, message, data = why
            self.watch = None
            self._stop_arm = True
            self._intervene(kind, message, {**data, "method": watch.method}, f"watch:{kind}")

    def shutdown(self, now_ns: int, wall_ns: int, repeats: int) -> list[OperatorCommand]:
        """The service is closing: end any task, release the lease, and return `repeats`
        inactive commands for the current engagement (none if there never was one)."""
        self._now_ns = now_ns
        if self.task is not None:
            self._finish_task(
                self.task, error=("unavailable", "the decision server is shutting down")
            )
        self._release_lease("shutdown")
        if self.mode is not Mode.ESTOP:
            self.mode = Mode.HOLD if self._p0 is not None else Mode.IDLE
        if self._p0 is None:
            return []
        inp = Inputs(now_ns=now_ns, wall_ns=wall_ns)
        return [self._command(inp, active=False) for _ in range(repeats)]

    # --- tasks ---------------------------------------------------------------------------
    def start_task(self, plan: TaskPlan, now_ns: int, external: bool = False) -> TaskRun:
        """Start a task; a streamed one begins at the next tick. Teleoperation is pre-empted
        (the master must engage anew afterwards). RpcError estop / busy."""
        self._now_ns = now_ns
        if self.mode is Mode.ESTOP:
            raise RpcError("estop", f"task {plan.name!r} refused: emergency stop latched")
        if self.mode is Mode.TASK:
            name = self.task.name if self.task is not None else "task"
            raise RpcError("busy", f"task {plan.name!r} refused: task {name!r} running")
        if self.mode is Mode.FOLLOW:
            self._hold(
                "task",
                "preempted",
                f"teleoperation pre-empted by task {plan.name!r}",
                intervention=False,
            )
        self.watch = None
        self._task_ids += 1
        run = TaskRun(self._task_ids, plan, external)
        self.task = run
        self.mode = Mode.TASK
        self.hold_reason = None
        self.stats["tasks"] += 1
        self._notice(
            "task",
            f"task {plan.name!r} started",
            {"task": plan.name, "id": run.id, "action": "started"},
        )
        return run

    def cancel_task(self, now_ns: int) -> TaskRun | None:
        """Cancel the running task (its reply: cancelled); the target holds."""
        self._now_ns = now_ns
        run = self.task
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
        run.done = True
        run.result = result
        run.error = error
        if self.task is run:
            self.task = None
            self.last_task = run
            if self.mode is Mode.TASK:
                streamed = not run.external and run.started and self._p0 is not None
                self.mode = Mode.HOLD if streamed else Mode.IDLE
                self.hold_reason = f"task {run.name} ended"
        self._finished.append(run)
        if error is not None:
            self._notice(
                "task",
                f"task {run.name!r} failed: {error[1]}",
                {"task": run.name, "id": run.id, "action": "failed", "error": error[0]},
            )
        else:
            action = "cancelled" if run.cancelled else "done"
            self._notice(
                "task",
                f"task {run.name!r} {action}",
                {"task": run.name, "id": run.id, "action": action},
            )

    def _fail(self, run: TaskRun, code: ErrorCode, message: str) -> None:
        self._finish_task(run, error=(code, message))

    def _next_step(self, run: TaskRun, now_ns: int) -> None:
        run.step_index += 1
        self._begin_step(run, now_ns)

    def _begin_step(self, run: TaskRun, now_ns: int) -> None:
        run.step_start_ns = now_ns
        run.start_p = self.p_sup.copy()
        run.f0_w = None

    def _run_task(self, inp: Inputs, state_ok: bool, force_ok: bool) -> OperatorCommand | None:
        run = self.task
        assert run is not None
        state = inp.state
        if not run.started:
            if not state_ok or state is None:
                self._fail(run, "not_ready", "no fresh robot/state")
                return None
            if state.status not in MOVING_STATUSES:
                self._fail(run, "not_ready", f"robot is {state.status}")
                return None
            self._begin_out(state)
            self._grip = state.grip
            run.started = True
            run.R_keep = self.R_sup.copy()
            run.grip = state.grip
            self._begin_step(run, inp.now_ns)
        if not state_ok or state is None:
            self._fail(run, "not_ready", "robot/state is stale")
            return None
        if state.status == "error":
            self._fail(run, "not_ready", "the robot reports an error")
            return None
        f_w: Vec | None = None
        if force_ok and inp.force is not None:
            f_w = mat3(state.tool_R) @ np.asarray(inp.force.f, dtype=float)
            if run.f0_w is None:
                run.f0_w = f_w
        step = run.step
        if isinstance(step, Grip):
            run.grip = step.value
            self._grip = step.value
            self._advance(self.p_sup, run.R_keep, inp, force_ok)
            if inp.now_ns - run.step_start_ns >= step.dwell_s * 1e9:
                self._next_step(run, inp.now_ns)
        elif isinstance(step, MoveTo):
            self._task_move(run, step, inp, force_ok, f_w)
        elif isinstance(step, GuardedMove):
            self._task_guarded(run, step, inp, force_ok, f_w)
        if run.done:
            return None
        if run.step is None:
            self._finish_task(
                run, result={"task": run.name, "done": True, "tool_p": list(state.tool_p)}
            )
            return None
        self._grip = run.grip
        return self._command(inp, active=True)

    def _task_move(
        self, run: TaskRun, step: MoveTo, inp: Inputs, force_ok: bool, f_w: Vec | None
    ) -> None:
        state = inp.state
        assert state is not None
        goal = np.asarray(step.p, dtype=float)
        if step.guard_force_n is not None and f_w is not None and run.f0_w is not None:
            df = _norm(f_w - run.f0_w)
            if df > step.guard_force_n:
                self._fail(
                    run,
                    "limit",
                    f"unexpected contact ({df:.1f} N) moving to "
                    f"{_list(goal)}; tool at {list(state.tool_p)}",
                )
                return
        g = self.p_sup + clip_norm(goal - self.p_sup, step.speed_m_s * self._dt_s)[0]
        self._advance(g, run.R_keep, inp, force_ok)
        at_goal = _norm(self.p_sup - goal) <= STEP_EPS_M
        arrived = _norm(np.asarray(state.tool_p) - goal) <= self._cfg.arrive_tol_m
        if at_goal and arrived:
            self._next_step(run, inp.now_ns)
            return
        budget_s = _norm(goal - run.start_p) / step.speed_m_s + SETTLE_S
        if inp.now_ns - run.step_start_ns > budget_s * 1e9:
            self._fail(
                run,
                "unreachable",
                f"did not reach {_list(goal)} in {budget_s:.1f} s (tool at {list(state.tool_p)})",
            )

    def _task_guarded(
        self, run: TaskRun, step: GuardedMove, inp: Inputs, force_ok: bool, f_w: Vec | None
    ) -> None:
        state = inp.state
        assert state is not None
        if f_w is None or run.f0_w is None:
            self._fail(run, "not_ready", "guarded move needs a fresh force stream")
            return
        d = np.asarray(step.direction, dtype=float)
        tool_p = np.asarray(state.tool_p, dtype=float)
        df = f_w - run.f0_w
        if _norm(df) > step.max_force_n:
            self._guarded_done(run, step, state, f_w, df, "contact")
            return
        travelled = float((self.p_sup - run.start_p) @ d)
        left = step.max_distance_m - travelled
        if left <= STEP_EPS_M:
            if _norm(tool_p - self.p_sup) <= self._cfg.arrive_tol_m:
                self._guarded_done(run, step, state, f_w, df, "distance")
            elif (
                inp.now_ns - run.step_start_ns
                > (step.max_distance_m / step.speed_m_s + SETTLE_S) * 1e9
            ):
                self._fail(run, "unreachable", "guarded move: the arm did not follow")
            return
        before = self.p_sup.copy()
        want = min(step.speed_m_s * self._dt_s, left)
        g = self.p_sup + d * want
        self._advance(g, run.R_keep, inp, force_ok)
        # Blocked: a filter (contact, workspace) kept the step. A tick only an instant after
        # the last one asks for no step worth judging.
        if want > STEP_EPS_M and float((self.p_sup - before) @ d) <= BLOCKED_SHARE * want:
            self._guarded_done(run, step, state, f_w, df, "blocked")

    def _guarded_done(
        self,
        run: TaskRun,
        step: GuardedMove,
        state: RobotState,
        f_w: Vec,
        df: Vec,
        stopped: Literal["contact", "distance", "blocked"],
    ) -> None:
        d = np.asarray(step.direction, dtype=float)
        tool_p = np.asarray(state.tool_p, dtype=float)
        contact = stopped == "contact"
        outcome = {
            "contact": contact,
            "stopped": stopped,
            "tool_p": _list(tool_p),
            "contact_p": _list(tool_p + self._cfg.tool_tip_radius_m * d) if contact else None,
            "f": _list(f_w),
            "df": _list(df),
            "force_n": _norm(df),
            "distance_m": float((tool_p - run.start_p) @ d),
        }
        if run.plan.name == "guarded_move":
            self._finish_task(run, result={"task": run.name, "done": True, **outcome})
            return
        run.result = outcome
        self._next_step(run, self._now_ns)

    # --- status ----------------------------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """The supervisor's part of `status`."""
        return {
            "mode": self.mode.value,
            "lease": self.lease,
            "engage_in": self.engage_in if self.lease is not None else None,
            "engage_out": self.engage_out,
            "seq_out": self.seq_out,
            "hold_reason": self.hold_reason,
            "estop": self.mode is Mode.ESTOP,
            "target_p": _list(self.p_sup) if self._p0 is not None else None,
            "offset_p": _list(self._off_p),
            "offset_rot_rad": float(np.linalg.norm(log_so3(self._off_R))),
            "task": self.task.summary() if self.task is not None else None,
            "last_task": self.last_task.summary() if self.last_task is not None else None,
            "interventions": dict(self.counters),
            "stats": dict(self.stats),
            "masters": sorted(self._masters),
        }
