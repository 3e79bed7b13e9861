"""The paper's three evaluation tasks (§3) as scripted scenarios for the `Operator`.

1. "setting up the slave tool in a given position by direct command from the operator hand
   motion": bring the tool to a goal pose (position and orientation) and let go.
2. "object manipulation and stacking": stack the three blocks into one column.
3. "manipulation of bottled liquid": carry the bottle to another spot, turning it a quarter
   turn on the way, and set it down without spilling.

Each scenario drives the arm only through the operator's hand at the master, and measures
its result from what the operator sees (robot/state, workcell/state). Success criteria:
task 1: pose error < 2 mm and < 1°; task 2: three blocks in one column; task 3: the bottle
stands at the target (≤ 10 mm), never tilted past 15°, spilled nothing.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.geometry import angle_between, rot_x, rot_z
from services.tools.tasks.operator import Operator, TaskFailed
from services.world.workcell.bodies import BodyState, stack_heights
from services.world.workcell.messages import ObjectView

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

UP = np.array([0.0, 0.0, 1.0])

TASK1_GOAL_P: Vec = np.array([0.68, 0.18, 0.52])


def task1_goal_R(home_R: Mat) -> Mat:
    """Task 1's goal orientation: the arm's home orientation (tool pointing down) turned
    30° about the vertical and tipped 12° about the tool's x; with TASK1_GOAL_P, 0.27 m from
    home."""
    return rot_z(math.radians(30.0)) @ home_R @ rot_x(math.radians(12.0))


TASK1_MAX_ERROR_M = 0.002
TASK1_MAX_ERROR_RAD = math.radians(1.0)

STACK_BASE = "block0"
STACK_MOVERS = ("block1", "block2")
TASK2_BLOCKS = 3

BOTTLE = "bottle"
TASK3_TARGET_XY: Vec = np.array([0.70, 0.05])
TASK3_TURN_RAD = math.radians(90.0)
TASK3_MAX_TILT_DEG = 15.0
TASK3_MAX_PLACE_ERROR_M = 0.01

HOVER_M = 0.05
"""How far the palm rises after letting go of an object."""
APPROACH_M = 0.015
"""The coarse motion ends this far above where the fine one does (a safe margin for the
coarse tolerance, short enough for the fine one to need no re-clutch)."""
GRASP_GAP_M = 0.008
"""The palm stops this far above the object's top to grasp (within W1's grasp region)."""
DROP_GAP_M = 0.003
"""A carried object is released this far above where it will rest."""
CLEARANCE_M = 0.03
"""A carried object travels this far above anything it passes over."""
COARSE_TOL_M = 0.003
FINE_TOL_M = 0.0007
FINE_SCALE_T = 0.25
FINE_SCALE_R = 0.5


@dataclass(frozen=True, slots=True)
class Outcome:
    """What a scenario measured: the task's figures and its success criteria."""

    measures: dict[str, Any]
    checks: dict[str, bool]

    @property
    def success(self) -> bool:
        return bool(self.checks) and all(self.checks.values())


@dataclass(frozen=True, slots=True)
class Scenario:
    """A task: its number, name, the paper's wording and the script."""

    number: int
    name: str
    paper: str
    run: Callable[[Operator], Outcome]


# --- shared moves -------------------------------------------------------------------------
def coarse(op: Operator) -> None:
    """Full-scale motion in the world frame (fast, re-clutching as needed)."""
    op.set_frame("world")
    op.set_scale(1.0, 1.0)


def fine(op: Operator) -> None:
    """Scaled-down motion for the last millimetres."""
    op.set_scale(FINE_SCALE_T, FINE_SCALE_R)


def held_offset(op: Operator, name: str) -> tuple[Vec, Mat]:
    """The held object's pose in the tool frame (tRo: position m, rotation), as seen."""
    p_t, R_t = op.eyes.tool()
    obj = op.eyes.object(name)
    return R_t.T @ (obj.p - p_t), R_t.T @ obj.R


def tool_goal_for(op: Operator, name: str, p_obj: ArrayLike, R_obj: ArrayLike) -> tuple[Vec, Mat]:
    """Where the tool must be for the held object to be at (p_obj, R_obj) (world)."""
    o_p, o_R = held_offset(op, name)
    R_t = np.asarray(R_obj, dtype=float) @ o_R.T
    return np.asarray(p_obj, dtype=float) - R_t @ o_p, R_t


def origin_for_bottom(obj: ObjectView, bottom: ArrayLike, R: ArrayLike) -> Vec:
    """The object's origin (`p`) that puts the centre of its base at `bottom` with R."""
    b = np.asarray(bottom, dtype=float)
    if obj.kind == "cylinder":
        return b
    return b + np.asarray(R, dtype=float) @ np.array([0.0, 0.0, 0.5 * obj.size[2]])


def pick(op: Operator, name: str, travel_bottom_z: float) -> None:
    """Grasp `name` from above and lift it until its base is at `travel_bottom_z`."""
    obj = op.eyes.object(name)
    coarse(op)
    down = op.eyes.home_R()
    op.reach(obj.top + (GRASP_GAP_M + APPROACH_M) * UP, down, tol_m=COARSE_TOL_M)
    fine(op)
    op.reach(obj.top + GRASP_GAP_M * UP, down, tol_m=FINE_TOL_M)
    op.grasp(name)
    coarse(op)
    p_t, _ = op.eyes.tool()
    lift = max(0.0, travel_bottom_z - float(op.eyes.object(name).bottom[2]))
    op.reach(p_t + lift * UP, tol_m=COARSE_TOL_M)


def place(op: Operator, name: str, bottom: ArrayLike, turn_rad: float = 0.0) -> ObjectView:
    """Carry the held `name` to just above `bottom` (where the centre of its base goes),
    turned by `turn_rad` about the vertical, lower it and let go; return it as it came to
    rest. The carry is one straight line from where it was lifted to: it passes over what
    it clears at the travel height and descends onto the target only at its end."""
    obj = op.eyes.object(name)
    R_obj = rot_z(turn_rad) @ obj.R
    target = np.asarray(bottom, dtype=float)
    above = origin_for_bottom(obj, target + (DROP_GAP_M + APPROACH_M) * UP, R_obj)
    coarse(op)
    p, R = tool_goal_for(op, name, above, R_obj)
    op.reach(p, R, tol_m=COARSE_TOL_M)
    fine(op)
    p, R = tool_goal_for(op, name, origin_for_bottom(obj, target + DROP_GAP_M * UP, R_obj), R_obj)
    op.reach(p, R, tol_m=FINE_TOL_M, tol_rad=math.radians(0.5))
    op.release(name)
    coarse(op)
    p_t, _ = op.eyes.tool()
    op.reach(p_t + HOVER_M * UP, tol_m=COARSE_TOL_M)
    return op.eyes.object(name)


# --- task 1 -------------------------------------------------------------------------------
def task1(op: Operator) -> Outcome:
    """Set the tool at TASK1_GOAL: coarse at full scale in the world frame with
    re-clutching, then fine at scale 0.25/0.5 in the tool frame; let go and measure."""
    goal_R = task1_goal_R(op.eyes.home_R())
    op.engage()
    coarse(op)
    op.reach(TASK1_GOAL_P + 0.02 * UP, goal_R, tol_m=COARSE_TOL_M)
    fine(op)
    op.set_frame("tool")
    op.reach(TASK1_GOAL_P, goal_R, tol_m=0.0003, tol_rad=math.radians(0.15))
    op.let_go()
    p, R = op.eyes.tool()
    err_m = float(np.linalg.norm(p - TASK1_GOAL_P))
    err_rad = angle_between(R, goal_R)
    return Outcome(
        measures={
            "position_error_mm": err_m * 1e3,
            "orientation_error_deg": math.degrees(err_rad),
            "tool_p": [float(x) for x in p],
        },
        checks={
            "position_error < 2 mm": err_m < TASK1_MAX_ERROR_M,
            "orientation_error < 1°": err_rad < TASK1_MAX_ERROR_RAD,
        },
    )


# --- task 2 -------------------------------------------------------------------------------
def task2(op: Operator) -> Outcome:
    """Stack block1 then block2 on block0: pick from above, carry above the column, lower
    at fine scale, release onto it."""
    op.engage()
    for name in STACK_MOVERS:
        top = op.eyes.object(STACK_BASE)
        column = [o for o in op.eyes.objects().values() if o.kind == "box"]
        column_top = max(float(o.top[2]) for o in column if o.phase != "held")
        pick(op, name, column_top + CLEARANCE_M)
        stack_top = _column_top(op, STACK_BASE)
        bottom = np.array([top.p[0], top.p[1], stack_top])
        rested = place(op, name, bottom)
        if rested.phase != "resting":
            raise TaskFailed(f"{name} fell over")
    op.let_go()
    objects = op.eyes.objects()
    heights = stack_heights_of(objects)
    tallest = max(heights.values(), default=0)
    return Outcome(
        measures={
            "blocks_stacked": tallest,
            "column": _column(objects, STACK_BASE),
            "misalignment_mm": _misalignment_mm(objects, STACK_BASE),
        },
        checks={"three blocks stacked": tallest == TASK2_BLOCKS},
    )


def stack_heights_of(objects: dict[str, ObjectView]) -> dict[str, int]:
    """Column heights (services.world.workcell.bodies.stack_heights) of what the operator sees."""
    bodies = [
        BodyState(o.name, o.kind, o.p, o.R, o.phase, o.on, o.size, 0.0, 0.0, 0.0, 0.0)
        for o in objects.values()
    ]
    return stack_heights(bodies)


def _column(objects: dict[str, ObjectView], base: str) -> list[str]:
    """The names from `base` up (each resting on the one before)."""
    out = [base]
    while True:
        above = [o.name for o in objects.values() if o.on == out[-1] and o.phase == "resting"]
        if not above:
            return out
        out.append(above[0])


def _column_top(op: Operator, base: str) -> float:
    objects = op.eyes.objects()
    return float(objects[_column(objects, base)[-1]].top[2])


def _misalignment_mm(objects: dict[str, ObjectView], base: str) -> float:
    names = _column(objects, base)
    c0 = objects[base].centre
    return max(
        (float(np.hypot(*(objects[n].centre[:2] - c0[:2]))) * 1e3 for n in names), default=0.0
    )


# --- task 3 -------------------------------------------------------------------------------
def task3(op: Operator) -> Outcome:
    """Carry the bottle to TASK3_TARGET_XY, turning it a quarter turn on the way, keep it
    upright, set it down on the table."""
    op.engage()
    start = op.eyes.object(BOTTLE)
    table_z = float(start.bottom[2])
    pick(op, BOTTLE, table_z + CLEARANCE_M)
    target = np.array([TASK3_TARGET_XY[0], TASK3_TARGET_XY[1], table_z])
    rested = place(op, BOTTLE, target, turn_rad=TASK3_TURN_RAD)
    op.let_go()
    bottle = op.eyes.object(BOTTLE)
    place_err_m = float(np.hypot(*(bottle.bottom[:2] - TASK3_TARGET_XY)))
    spilled = bottle.spilled_ml or 0.0
    turn = _yaw(bottle.R) - _yaw(start.R)
    turned = abs(math.degrees(math.atan2(math.sin(turn), math.cos(turn))))
    return Outcome(
        measures={
            "max_tilt_deg": bottle.max_tilt_deg,
            "spilled_ml": spilled,
            "liquid_ml": bottle.liquid_ml,
            "place_error_mm": place_err_m * 1e3,
            "turned_deg": turned,
            "final_tilt_deg": bottle.tilt_deg,
        },
        checks={
            "never tilted past 15°": bottle.max_tilt_deg < TASK3_MAX_TILT_DEG,
            "spilled nothing": spilled <= 0.0,
            "standing at the target": rested.phase == "resting"
            and place_err_m <= TASK3_MAX_PLACE_ERROR_M,
        },
    )


def _yaw(R: Mat) -> float:
    return math.atan2(float(R[1, 0]), float(R[0, 0]))


SCENARIOS: dict[int, Scenario] = {
    1: Scenario(1, "tool pose", "setting up the slave tool in a given position", task1),
    2: Scenario(2, "stacking", "object manipulation and stacking", task2),
    3: Scenario(3, "bottled liquid", "manipulation of bottled liquid", task3),
}
