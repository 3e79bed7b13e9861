"""The autonomous functions of the decision server (the paper's supervisory agent, §2.1.5).

A streamed task is a plan of steps that the supervisor executes tick by tick through the
same filters as teleoperation (contact, workspace, speed): `MoveTo` (a straight move of the
tool point), `GuardedMove` (move along a direction until the force changes by more than a
threshold) and `Grip` (set the gripper, wait). `guarded_move` and `pick_place` are built
from them here; `home` is forwarded to the arm and `cancel` stops the running task (see
service.py). Positions in m (world), forces in N, speeds in m/s.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.bus.bounds import check, check_each, check_norm
from services.bus.codec import arg
from services.bus.errors import ProtocolError, RpcError
from services.bus.messages import Unit, Vec3
from services.control.decision.config import DecisionConfig
from services.control.decision.filters import in_box
from services.geometry import V3

#: every `task` name: streamed (built here), forwarded (`home`) and control (`cancel`)
TASK_NAMES: tuple[str, ...] = ("guarded_move", "pick_place", "home", "cancel")
DOWN: V3 = (0.0, 0.0, -1.0)


@dataclass(frozen=True, slots=True)
class MoveTo:
    """Move the tool point in a straight line to `p` (m, world) at `speed_m_s`, keeping the
    tool's orientation. With `guard_force_n`, a change of the wrist force by more than that
    since the step started aborts the task (error `limit`): an unexpected contact."""

    p: V3
    speed_m_s: float
    guard_force_n: float | None = None


@dataclass(frozen=True, slots=True)
class GuardedMove:
    """Move along the unit `direction` (world) at `speed_m_s` until the wrist force has
    changed by more than `max_force_n` since the step started (contact) or `max_distance_m`
    was travelled. Its outcome (contact point, force) is the task's reply."""

    direction: V3
    speed_m_s: float
    max_force_n: float
    max_distance_m: float


@dataclass(frozen=True, slots=True)
class Grip:
    """Command the gripper to `value` (0 open … 1 closed) and wait `dwell_s` in place."""

    value: float
    dwell_s: float


Step = MoveTo | GuardedMove | Grip


@dataclass(frozen=True, slots=True)
class TaskPlan:
    """A named sequence of steps; `wait`: reply on completion (default) or on acceptance."""

    name: str
    steps: tuple[Step, ...]
    wait: bool = True
    args: Mapping[str, Any] | None = None


def _positive(args: Mapping[str, Any], name: str, default: float, kind: str) -> float:
    """A positive argument within the physical bound of `kind` (services/bus/bounds.py)."""
    v = float(arg(args, name, float, default))
    if not v > 0:
        raise ProtocolError(name, f"must be > 0, got {v:.6g}")
    return check(name, v, kind)


def _speed(args: Mapping[str, Any], name: str, default: float, cfg: DecisionConfig) -> float:
    v = _positive(args, name, default, "speed_m_s")
    if v > cfg.max_tool_speed_m_s:
        raise RpcError(
            "limit", f"{name} {v} m/s exceeds the tool speed limit {cfg.max_tool_speed_m_s} m/s"
        )
    return v


def _wait(args: Mapping[str, Any]) -> bool:
    return bool(arg(args, "wait", bool, True))


def _unit(name: str, v: tuple[float, ...]) -> V3:
    check_norm(name, v, "direction")  # before the norm: 1e308² would overflow
    a = np.asarray(v, dtype=float)
    n = float(np.linalg.norm(a))
    if n < 1e-9:
        raise ProtocolError(name, "must not be the zero vector")
    u = a / n
    return (float(u[0]), float(u[1]), float(u[2]))


def _point(args: Mapping[str, Any], name: str) -> V3:
    v = check_each(name, arg(args, name, Vec3), "position_m")
    return (float(v[0]), float(v[1]), float(v[2]))


def _inside(name: str, p: V3, cfg: DecisionConfig) -> None:
    if not in_box(p, cfg.workspace_min, cfg.workspace_max):
        raise RpcError(
            "limit",
            f"{name} {list(p)} is outside the workspace "
            f"{list(cfg.workspace_min)}…{list(cfg.workspace_max)}",
        )


def guarded_move_plan(args: Mapping[str, Any], cfg: DecisionConfig) -> TaskPlan:
    """`guarded_move {direction (3, world), speed_m_s?, max_force_n?, max_distance_m?, wait?}`.

    Raises ProtocolError (bad_request) for malformed arguments, RpcError("limit") for a speed
    above the tool speed limit.
    """
    direction = _unit("direction", arg(args, "direction", Vec3))
    step = GuardedMove(
        direction=direction,
        speed_m_s=_speed(args, "speed_m_s", cfg.guarded_speed_m_s, cfg),
        max_force_n=_positive(args, "max_force_n", cfg.guarded_max_force_n, "force_n"),
        max_distance_m=_positive(args, "max_distance_m", cfg.guarded_max_distance_m, "distance_m"),
    )
    return TaskPlan("guarded_move", (step,), _wait(args), dict(args))


def pick_place_plan(args: Mapping[str, Any], cfg: DecisionConfig) -> TaskPlan:
    """`pick_place {pick (3), place (3), approach_height_m?, speed_m_s?, max_force_n?,
    place_depth_m?, grip_closed?, grip_open?, wait?}` (m, world; N).

    Open the gripper; move above `pick` by `approach_height_m`; descend to `pick` with a
    force guard (an unexpected contact aborts); close the gripper; lift; move above `place`;
    descend with a guarded move of up to `approach_height_m + place_depth_m` that stops when
    the object touches down; open the gripper; lift. Every waypoint must lie in the
    workspace (else RpcError("limit")).
    """
    pick = _point(args, "pick")
    place = _point(args, "place")
    up = _positive(args, "approach_height_m", 0.10, "distance_m")
    speed = _speed(args, "speed_m_s", cfg.task_speed_m_s, cfg)
    guard = _positive(args, "max_force_n", cfg.guarded_max_force_n, "force_n")
    depth = check("place_depth_m", float(arg(args, "place_depth_m", float, 0.02)), "distance_m")
    closed = float(arg(args, "grip_closed", Unit, 1.0))
    opened = float(arg(args, "grip_open", Unit, 0.0))
    above_pick: V3 = (pick[0], pick[1], pick[2] + up)
    above_place: V3 = (place[0], place[1], place[2] + up)
    for name, p in (
        ("pick", pick),
        ("place", place),
        ("pick + approach_height_m", above_pick),
        ("place + approach_height_m", above_place),
    ):
        _inside(name, p, cfg)
    down_speed = min(speed, cfg.guarded_speed_m_s)
    steps: tuple[Step, ...] = (
        Grip(opened, cfg.grip_time_s),
        MoveTo(above_pick, speed),
        MoveTo(pick, down_speed, guard_force_n=guard),
        Grip(closed, cfg.grip_time_s),
        MoveTo(above_pick, speed),
        MoveTo(above_place, speed),
        GuardedMove(DOWN, down_speed, guard, up + depth),
        Grip(opened, cfg.grip_time_s),
        MoveTo(above_place, speed),
    )
    return TaskPlan("pick_place", steps, _wait(args), dict(args))


def plan_task(name: str, args: Mapping[str, Any], cfg: DecisionConfig) -> TaskPlan:
    """The plan of streamed task `name` (bad_request for an unknown one)."""
    if name == "guarded_move":
        return guarded_move_plan(args, cfg)
    if name == "pick_place":
        return pick_place_plan(args, cfg)
    raise ProtocolError("name", f"unknown task {name!r} (tasks: {', '.join(TASK_NAMES)})")
