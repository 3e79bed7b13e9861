"""Forwarded motions (`move_*`, `home`): the arm plans and executes them, the decision
server watches them and has them stopped at a contact or at the workspace's edge.

`forwarded_target` tells where a forwarded motion goes (the service refuses one outside
the workspace box). Pure: `watch_step` judges one tick's robot state and force; the
supervisor counts and reports what it returns and asks the service to call the arm's
`stop`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.bus.bounds import each_out_of_bounds, norm_out_of_bounds
from services.bus.messages import ForceSample, RobotState, mat3
from services.control.decision.config import DecisionConfig
from services.control.decision.filters import in_box
from services.control.decision.notices import floats
from services.geometry import norm3

WATCH_PERIOD_NS = 5_000_000
"""A forwarded motion is checked this often (200 Hz): at 0.5 m/s, 2.5 mm between checks."""
WATCH_START_NS = 3_000_000_000
"""A forwarded motion that has not shown `moving` this long after it was sent is over. The
arm plans before it moves (a Cartesian line is an IK solve per step): on a loaded host that
took over half a second, and a watch that had given up then let the motion run unwatched."""
WATCH_BOX_TOL_M = 0.002
"""A forwarded motion stops when the tool leaves the workspace box by more than this."""
CONTACT_REACT_S = 0.03
"""From a force sample to the arm at rest: the watch's period, the decision's stop, the
arm's next cycle and the servo's own deceleration (measured: a PUMA stopped at once from
5 cm/s goes on 0.8 mm, 16 N into a 20 kN/m block). A watched motion stops when the force,
carried on at its rate of rise for this long, would pass the limit."""
TOUCH_FRACTION = 0.25
"""The prediction acts only above this fraction of max_force_n (below it, the rate of a
noisy sensor's first newtons says nothing)."""
RELIEF_FRACTION = 0.1
"""A motion that starts pressing harder than max_force_n may go on while the force stays
within this fraction of the limit above where it started: the way out of a contact."""
LEAVING_COS = 0.5
"""A motion heading within 60° of the contact force (the force the environment applies to
the tool, pushing it the way the motion goes) leaves the contact: the force limit does not
stop it. Lifting off a block the tool pressed, the first millimetres can read more (the
tool's own acceleration, the servo unloading a stuck fingertip) and the limit stopped the
way out there (issue 42 item 1, on a loaded host)."""
LEAVING_MIN_M = 0.001
"""Closer than this to its goal, a motion has no direction to judge: the limit applies."""


@dataclass(slots=True)
class Watch:
    """A forwarded motion the supervisor watches: its method, when it was sent (monotonic
    ns), and whether the robot has shown `moving` since."""

    method: str
    since_ns: int
    moving: bool = False
    f0_n: float | None = None
    """The contact force when the motion began (N): the limit it must not push past."""
    last: tuple[int, float] | None = None
    """(t_ns, force N) of the sample judged last, for the force's rate of rise."""
    guarded: bool = False
    """Its goal is near the table (`motion_guard_zone_m`): it may not move blind, without
    a fresh wrist force."""
    goal: tuple[float, float, float] | None = None
    """Where the tool point goes (m, world), when known: a motion heading along the contact
    force leaves the contact (LEAVING_COS)."""


@dataclass(frozen=True, slots=True)
class WatchStop:
    """Why a watched motion must stop: the intervention's kind, message and event data."""

    kind: str
    message: str
    data: dict[str, Any]


def target_problem(cfg: DecisionConfig, method: str, p: Sequence[float]) -> str | None:
    """Why a forwarded motion's target tool point `p` (m, world) may not be reached
    (outside the workspace box), or None."""
    if in_box(p, cfg.workspace_min, cfg.workspace_max, tol=1e-9):
        return None
    return (
        f"{method}: target {[round(float(x), 4) for x in p]} m is outside the workspace "
        f"{list(cfg.workspace_min)} … {list(cfg.workspace_max)}"
    )


def forwarded_target(
    method: str,
    args: Mapping[str, Any],
    newest_state: Callable[[], RobotState | None],
    ask_arm: Callable[[str, dict[str, Any]], dict[str, Any] | None],
) -> list[float] | None:
    """The tool point (m, world) a forwarded motion goes to, or None when it cannot be told
    or the arm will refuse the call anyway (absurd or malformed arguments: `bad_request`
    is the arm's to give). `move_pose`: its `p`; `move_relative`: p + R_f·dp from the
    newest robot/state (R_f of its frame, PROTOCOL §4, the arm's `set_frame` default when
    absent); `move_joints`: the arm's `fk` of `q`. `ask_arm(method, args)` is None on an
    error reply."""
    if method == "move_pose":
        p = _floats3(args.get("p"))
        if p is not None and each_out_of_bounds("p", p, "position_m"):
            return None  # absurd, not merely outside the box
        return p
    if method == "move_relative":
        dp = _floats3(args.get("dp"))
        state = newest_state()
        if dp is None or state is None or norm_out_of_bounds("dp", dp, "displacement_m"):
            return None
        frame = args.get("frame")
        if frame is None:
            frame = (ask_arm("status", {}) or {}).get("frame", "world")
        if frame == "world":
            R_f = np.eye(3)
        elif frame == "wrist":
            R_f = mat3(state.flange_R)
        elif frame == "tool":
            R_f = mat3(state.tool_R)
        else:
            return None
        return [float(x) for x in np.asarray(state.tool_p) + R_f @ np.asarray(dp)]
    if method == "move_joints":
        q = args.get("q")
        if (
            isinstance(q, list)
            and 1 <= len(q) <= 32
            and all(_number(x) for x in q)
            and each_out_of_bounds("q", [float(x) for x in q], "joint_rad") is None
        ):
            return _floats3((ask_arm("fk", {"q": q}) or {}).get("tool_p"))
    return None


def _number(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _floats3(v: object) -> list[float] | None:
    """3 finite numbers as floats, or None."""
    if isinstance(v, list | tuple) and len(v) == 3 and all(_number(x) for x in v):
        return [float(x) for x in v]
    return None


def watch_step(
    watch: Watch,
    cfg: DecisionConfig,
    now_ns: int,
    state: RobotState,
    force: ForceSample | None,
) -> WatchStop | Watch | None:
    """One check of a watched motion, given a fresh robot/state and the force sample (None
    if stale): the watch itself while the motion goes on, None once the robot shows it
    ended (ready, or error: the arm already holds), or why it must stop (a contact above
    max_force_n, the tool outside the box by more than WATCH_BOX_TOL_M)."""
    if state.status == "moving":
        watch.moving = True
    elif watch.moving or now_ns - watch.since_ns > WATCH_START_NS:
        return None
    if force is None and watch.guarded and watch.moving:
        return WatchStop(
            "watchdog",
            f"{watch.method} stopped: no fresh force from the wrist, and its goal is near "
            "the table",
            {"reason": "force_stale", "method": watch.method, "now": True},
        )
    if force is not None:
        f_w = mat3(state.tool_R) @ np.asarray(force.f, dtype=float)
        f_n = norm3(f_w)
        stop = contact_stop(watch, cfg.max_force_n, force.t_ns, f_n)
        if stop is not None and not leaving(watch.goal, state.tool_p, f_w, f_n):
            return WatchStop(
                "contact",
                f"{watch.method} stopped: contact force {f_n:.1f} N {stop} {cfg.max_force_n:g} N",
                {
                    "reason": "force",
                    "f": floats(f_w),
                    "force_n": f_n,
                    "method": watch.method,
                    "now": True,
                },
            )
    if not in_box(state.tool_p, cfg.workspace_min, cfg.workspace_max, tol=WATCH_BOX_TOL_M):
        return WatchStop(
            "limit",
            f"{watch.method} stopped: the tool left the workspace box",
            {"reason": "workspace", "tool_p": list(state.tool_p), "method": watch.method},
        )
    return watch


def leaving(
    goal: Sequence[float] | None, tool_p: Sequence[float], f_w: np.ndarray, f_n: float
) -> bool:
    """Whether a motion from `tool_p` to `goal` heads within 60° of the contact force `f_w`
    (N, world; `f_n` its norm): away from what pushes the tool, never into it."""
    if goal is None or f_n <= 0.0:
        return False
    d = np.asarray(goal, dtype=float) - np.asarray(tool_p, dtype=float)
    dist = norm3(d)
    if not dist > LEAVING_MIN_M:
        return False
    return float(d @ f_w) >= LEAVING_COS * dist * f_n


def contact_stop(watch: Watch, max_force_n: float, t_ns: int, f_n: float) -> str | None:
    """Whether a watched motion must stop at contact force `f_n` (N, sampled at `t_ns`):
    ">" when it passed the limit, "heading past" when at its rate of rise it would within
    CONTACT_REACT_S; None while it may go on. The limit is max_force_n, or for a motion that
    began pressing harder, where it began plus RELIEF_FRACTION of max_force_n: a motion
    that lowers the force (the way out) is never stopped for it."""
    if watch.f0_n is None:
        watch.f0_n = f_n
    limit = max(max_force_n, watch.f0_n + RELIEF_FRACTION * max_force_n)
    rate = 0.0
    if watch.last is not None and t_ns > watch.last[0]:
        rate = (f_n - watch.last[1]) / ((t_ns - watch.last[0]) * 1e-9)
    watch.last = (t_ns, f_n)
    if f_n > limit:
        return ">"
    if f_n > TOUCH_FRACTION * max_force_n and f_n + max(rate, 0.0) * CONTACT_REACT_S > limit:
        return "heading past"
    return None
