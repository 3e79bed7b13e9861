"""Running tasks (tasks.py's plans): the runs and their outcomes, and a streamed task's
steps, one per tick, through the same filters as teleoperation (the supervised target moves;
the step judges arrival, contact, blocking).

Pure: `Tasks` keeps the runs and reports their start and end; `run_tick` advances the running
one and says when it ends. The supervisor decides when a task may start, changes its mode
when one ends, and sends the commands.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from services.bus.errors import ErrorCode
from services.bus.messages import RobotState, mat3
from services.control.decision.filters import clip_norm
from services.control.decision.notices import Notices, floats
from services.control.decision.target import MOVING_STATUSES, STEP_EPS_M, Sensed, SupervisedTarget
from services.control.decision.tasks import Grip, GuardedMove, MoveTo, Step, TaskPlan
from services.geometry import norm3

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

SETTLE_S = 2.0
"""A task move may take this much longer than distance / speed before it fails."""
BLOCKED_SHARE = 0.01
"""A guarded move is blocked when a step moves less than this share of what it asked."""
FORCE_GAP_S = 0.5
"""A guarded move holds its target while the wrist force is stale (a sample late under
load, the stream just subscribed) and fails `not_ready` when it stays stale this long: it
never moves without a fresh force, and a hiccup of the stream does not abort it."""


@dataclass(slots=True, eq=False)
class TaskRun:
    """One run of a task: its plan, progress, and outcome (`result` or `error`).

    `external` runs (the forwarded `home`) are executed by the service, which calls
    `Supervisor.finish_external`. Read by the service's RPC threads under its lock.
    Compared by identity: each run is one waiter's.
    """

    id: int
    plan: TaskPlan
    external: bool = False
    started: bool = False
    done: bool = False
    cancelled: bool = False
    result: dict[str, Any] | None = None
    error: tuple[ErrorCode, str] | None = None
    step_index: int = 0
    step_start_ns: int = 0
    start_p: Vec = field(default_factory=lambda: np.zeros(3))
    """The target where the running step started (m, world)."""
    R_keep: Mat = field(default_factory=lambda: np.eye(3))
    """The tool orientation the task keeps (world ← tool)."""
    f0_w: Vec | None = None
    """The wrist force (N, world) when the running step started."""
    stale_since_ns: int | None = None
    """Since when a guarded move has had no fresh wrist force (None: it has one)."""
    grip: float | None = None

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

    def begin_step(self, now_ns: int, p: Vec) -> None:
        """The running step starts now with the target at `p`."""
        self.step_start_ns = now_ns
        self.start_p = p.copy()
        self.f0_w = None
        self.stale_since_ns = None

    def next_step(self, now_ns: int, p: Vec) -> None:
        self.step_index += 1
        self.begin_step(now_ns, p)


@dataclass(frozen=True, slots=True)
class TaskEnd:
    """How a run ended: a `result` for its reply, or an `error` (code, message)."""

    result: dict[str, Any] | None = None
    error: tuple[ErrorCode, str] | None = None


def _fail(code: ErrorCode, message: str) -> TaskEnd:
    return TaskEnd(error=(code, message))


class Tasks:
    """The task runs: the running one (`current`), the last that ended, and those that
    ended since the last `drain` (their waiters are woken). Each start and end is reported."""

    def __init__(self) -> None:
        self.current: TaskRun | None = None
        self.last: TaskRun | None = None
        self._ids = 0
        self._ended: list[TaskRun] = []

    def start(self, plan: TaskPlan, external: bool, notices: Notices, now_ns: int) -> TaskRun:
        """A new run of `plan`, now the current one."""
        self._ids += 1
        run = TaskRun(self._ids, plan, external)
        self.current = run
        notices.post(
            now_ns,
            "task",
            f"task {plan.name!r} started",
            {"task": plan.name, "id": run.id, "action": "started"},
        )
        return run

    def finish(
        self,
        run: TaskRun,
        result: dict[str, Any] | None,
        error: tuple[ErrorCode, str] | None,
        notices: Notices,
        now_ns: int,
    ) -> bool:
        """`run` ended with `result` or `error`; whether it was the current run."""
        run.done = True
        run.result = result
        run.error = error
        current = self.current is run
        if current:
            self.current = None
            self.last = run
        self._ended.append(run)
        if error is not None:
            notices.post(
                now_ns,
                "task",
                f"task {run.name!r} failed: {error[1]}",
                {"task": run.name, "id": run.id, "action": "failed", "error": error[0]},
            )
        else:
            action = "cancelled" if run.cancelled else "done"
            notices.post(
                now_ns,
                "task",
                f"task {run.name!r} {action}",
                {"task": run.name, "id": run.id, "action": action},
            )
        return current

    def drain(self) -> tuple[TaskRun, ...]:
        """The runs that ended since the last drain, in order."""
        out, self._ended = tuple(self._ended), []
        return out


def run_tick(
    run: TaskRun,
    target: SupervisedTarget,
    sensed: Sensed,
    state_ok: bool,
    begin: Callable[[RobotState], None],
) -> TaskEnd | None:
    """One tick of streamed task `run`: its first starts a new outgoing engagement
    (`begin`, rebased on the measured pose); the running step advances. A TaskEnd when the
    task ends in this tick (it needs a fresh robot/state and a robot not in error), else
    None: the target is to be sent, active."""
    state = sensed.state
    if not run.started:
        if not state_ok or state is None:
            return _fail("not_ready", "no fresh robot/state")
        if state.status not in MOVING_STATUSES:
            return _fail("not_ready", f"robot is {state.status}")
        begin(state)
        target.grip = state.grip
        run.started = True
        run.R_keep = target.R_sup.copy()
        run.grip = state.grip
        run.begin_step(sensed.now_ns, target.p_sup)
    if not state_ok or state is None:
        return _fail("not_ready", "robot/state is stale")
    if state.status == "error":
        return _fail("not_ready", "the robot reports an error")
    f_w: Vec | None = None
    if sensed.force is not None:
        f_w = mat3(state.tool_R) @ np.asarray(sensed.force.f, dtype=float)
        if run.f0_w is None:
            run.f0_w = f_w
    end = run_step(run, target, sensed, f_w)
    if end is None and run.step is None:
        end = TaskEnd(result={"task": run.name, "done": True, "tool_p": list(state.tool_p)})
    if end is None:
        target.grip = run.grip
    return end


def run_step(
    run: TaskRun, target: SupervisedTarget, sensed: Sensed, f_w: Vec | None
) -> TaskEnd | None:
    """Advance the running step of `run` by one tick (the target moves through the
    filters); a TaskEnd when the task ends in this step, else None. `f_w` is the wrist
    force in the world frame (N), None if stale; `sensed.state` is fresh."""
    step = run.step
    if isinstance(step, Grip):
        run.grip = step.value
        target.grip = step.value
        target.advance(target.p_sup, run.R_keep, sensed)
        if sensed.now_ns - run.step_start_ns >= step.dwell_s * 1e9:
            run.next_step(sensed.now_ns, target.p_sup)
        return None
    if isinstance(step, MoveTo):
        return _move(run, step, target, sensed, f_w)
    if isinstance(step, GuardedMove):
        return _guarded(run, step, target, sensed, f_w)
    return None


def _move(
    run: TaskRun, step: MoveTo, target: SupervisedTarget, sensed: Sensed, f_w: Vec | None
) -> TaskEnd | None:
    state = sensed.state
    assert state is not None
    goal = np.asarray(step.p, dtype=float)
    if step.guard_force_n is not None and f_w is not None and run.f0_w is not None:
        df = norm3(f_w - run.f0_w)
        if df > step.guard_force_n:
            return _fail(
                "limit",
                f"unexpected contact ({df:.1f} N) moving to "
                f"{floats(goal)}; tool at {list(state.tool_p)}",
            )
    g = target.p_sup + clip_norm(goal - target.p_sup, step.speed_m_s * target.dt_s)[0]
    target.advance(g, run.R_keep, sensed)
    at_goal = norm3(target.p_sup - goal) <= STEP_EPS_M
    arrived = norm3(np.asarray(state.tool_p) - goal) <= sensed.cfg.arrive_tol_m
    if at_goal and arrived:
        run.next_step(sensed.now_ns, target.p_sup)
        return None
    budget_s = norm3(goal - run.start_p) / step.speed_m_s + SETTLE_S
    if sensed.now_ns - run.step_start_ns > budget_s * 1e9:
        return _fail(
            "unreachable",
            f"did not reach {floats(goal)} in {budget_s:.1f} s (tool at {list(state.tool_p)})",
        )
    return None


def _guarded(
    run: TaskRun, step: GuardedMove, target: SupervisedTarget, sensed: Sensed, f_w: Vec | None
) -> TaskEnd | None:
    state = sensed.state
    assert state is not None
    if f_w is None or run.f0_w is None:
        # No fresh force this tick: hold the target (never move blind), give up only when
        # the stream stays stale for FORCE_GAP_S.
        if run.stale_since_ns is None:
            run.stale_since_ns = sensed.now_ns
        if sensed.now_ns - run.stale_since_ns > FORCE_GAP_S * 1e9:
            return _fail(
                "not_ready", f"guarded move needs a fresh force stream (none for {FORCE_GAP_S:g} s)"
            )
        target.advance(target.p_sup, run.R_keep, sensed)
        return None
    run.stale_since_ns = None
    d = np.asarray(step.direction, dtype=float)
    tool_p = np.asarray(state.tool_p, dtype=float)
    df = f_w - run.f0_w
    if norm3(df) > step.max_force_n:
        return _guarded_done(run, step, target, sensed, f_w, df, "contact")
    travelled = float((target.p_sup - run.start_p) @ d)
    left = step.max_distance_m - travelled
    if left <= STEP_EPS_M:
        if norm3(tool_p - target.p_sup) <= sensed.cfg.arrive_tol_m:
            return _guarded_done(run, step, target, sensed, f_w, df, "distance")
        if (
            sensed.now_ns - run.step_start_ns
            > (step.max_distance_m / step.speed_m_s + SETTLE_S) * 1e9
        ):
            return _fail("unreachable", "guarded move: the arm did not follow")
        return None
    before = target.p_sup.copy()
    want = min(step.speed_m_s * target.dt_s, left)
    g = target.p_sup + d * want
    target.advance(g, run.R_keep, sensed)
    # Blocked: a filter (contact, workspace) kept the step. A tick only an instant after
    # the last one asks for no step worth judging.
    if want > STEP_EPS_M and float((target.p_sup - before) @ d) <= BLOCKED_SHARE * want:
        return _guarded_done(run, step, target, sensed, f_w, df, "blocked")
    return None


def _guarded_done(
    run: TaskRun,
    step: GuardedMove,
    target: SupervisedTarget,
    sensed: Sensed,
    f_w: Vec,
    df: Vec,
    stopped: Literal["contact", "distance", "blocked"],
) -> TaskEnd | None:
    """A guarded move's outcome: the reply of a `guarded_move` task, or the step's result
    within a longer plan (which goes on with its next step)."""
    state: RobotState | None = sensed.state
    assert state is not None
    d = np.asarray(step.direction, dtype=float)
    tool_p = np.asarray(state.tool_p, dtype=float)
    contact = stopped == "contact"
    outcome = {
        "contact": contact,
        "stopped": stopped,
        "tool_p": floats(tool_p),
        "contact_p": floats(tool_p + sensed.cfg.tool_tip_radius_m * d) if contact else None,
        "f": floats(f_w),
        "df": floats(df),
        "force_n": norm3(df),
        "distance_m": float((tool_p - run.start_p) @ d),
    }
    if run.plan.name == "guarded_move":
        return TaskEnd(result={"task": run.name, "done": True, **outcome})
    run.result = outcome
    run.next_step(sensed.now_ns, target.p_sup)
    return None
