"""Motions of the arm: the handle callers wait on and the generators that drive it.

A generator gives the desired setpoint each control cycle: `Planned` follows a plan,
`Servo` chases a goal (streamed commands, or the end of a plan the filter held back), `Brake`
decelerates to rest. The safety filter then checks what they ask for. Units: rad, s.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.control.arm.planning import PLAN_SPEED_MARGIN
from services.control.arm.safety import MotionLimits, ToolPoseFn, tool_motion
from services.control.arm.trajectory import Trapezoid, discrete_brake_speed
from services.geometry import PoseFloats

Vec = NDArray[np.float64]

GOAL_TOL_RAD = 1e-9
"""A motion has reached its goal within this (rounding of q + v·dt)."""


class Motion:
    """A handle on one motion: `id`, `kind`, and its result once it has ended.

    The result is a dict: `motion` (id), `done` (bool), `completed` (reached its target),
    `reason` (`completed`, `stopped`, `preempted`, `error`, `estop`, `closed`, or `running`
    while not done), `q` (setpoint joints at the end, rad).
    """

    def __init__(self, motion_id: int, kind: str) -> None:
        self.id = motion_id
        self.kind = kind
        self._done = threading.Event()
        self._result: dict[str, Any] = {
            "motion": motion_id,
            "done": False,
            "completed": False,
            "reason": "running",
        }

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def result(self) -> dict[str, Any]:
        return dict(self._result)

    def wait(self, timeout_s: float | None) -> dict[str, Any]:
        """Block until the motion ends or `timeout_s` passes; the result either way."""
        self._done.wait(timeout_s)
        return self.result()

    def finish(self, reason: str, q: Iterable[float]) -> None:
        if self._done.is_set():
            return
        self._result = {
            "motion": self.id,
            "done": True,
            "completed": reason == "completed",
            "reason": reason,
            "q": [float(x) for x in q],
        }
        self._done.set()


class Planned:
    """A planned motion: q(t) = path(s(t)), at rest at both ends."""

    def __init__(
        self, path: Callable[[float], Vec], law: Trapezoid, goal: Vec, hold_first: bool
    ) -> None:
        self.path = path
        self.law = law
        self.goal = goal
        self.t_s = 0.0
        self.hold_first = hold_first

    def next(self, dt_s: float) -> Vec:
        if self.hold_first:
            self.hold_first = False
            return self.path(0.0)
        self.t_s += dt_s
        if self.t_s >= self.law.duration_s:
            return self.goal
        return self.path(self.law.s_at(self.t_s))

    @property
    def finished(self) -> bool:
        return self.t_s >= self.law.duration_s


class Servo:
    """Chases a goal (n floats, rad) as fast as the joint limits allow, slowing so the tool
    stays below its speed limits; used for streamed targets and to finish a planned motion."""

    def __init__(self, goal: list[float], t_s: float, settle_s: float) -> None:
        self.goal = goal
        self.last_goal_t_s = t_s
        self.settle_s = settle_s


class Brake:
    """Decelerates every joint in proportion, so the path stays straight, to rest."""


Generator = Planned | Servo | Brake


def servo_target(
    goal: Sequence[float],
    q: Sequence[float],
    qd: Sequence[float],
    pose_now: PoseFloats,
    dt_s: float,
    lim: MotionLimits,
    tool_pose: ToolPoseFn,
) -> list[float]:
    """The next setpoint chasing `goal`: per joint as fast as its speed allows while it can
    still stop at the goal, within the acceleration box around the present velocity, and
    with the tool kept under 90 % of its speeds (so `safe_step` has nothing to cut).

    Joint vectors are n plain floats (rad, rad/s) and the pose is a
    `services.geometry.PoseFloats`: this runs every tick of a streamed motion."""
    v_des: list[float] = []
    v_lo: list[float] = []
    v_hi: list[float] = []
    for g, qj, qdj, (_, _, vmax, amax) in zip(goal, q, qd, lim.joints, strict=True):
        e = g - qj
        speed = min(vmax, discrete_brake_speed(e, amax, dt_s))
        v_des.append(speed if e > 0.0 else -speed if e < 0.0 else 0.0)  # sign(e)·speed
        dv = amax * dt_s
        v_lo.append(qdj - dv)
        v_hi.append(qdj + dv)
    max_dp = PLAN_SPEED_MARGIN * lim.tool_speed_m_s * dt_s
    max_dth = PLAN_SPEED_MARGIN * lim.tool_rot_speed_rad_s * dt_s

    def step(v: Sequence[float]) -> list[float]:
        return [qj + vj * dt_s for qj, vj in zip(q, v, strict=True)]

    def over(v: Sequence[float]) -> float:
        return tool_motion(pose_now, tool_pose(step(v)), max_dp, max_dth)

    def boxed(k: float) -> list[float]:
        """k·v_des within the acceleration box."""
        out = []
        for vj, lo, hi in zip(v_des, v_lo, v_hi, strict=True):
            x = k * vj
            out.append(lo if x < lo else hi if x > hi else x)
        return out

    k = over(v_des)
    if k > 1.0:
        v_des = [vj / k for vj in v_des]
    v = boxed(1.0)
    # When neither the scaling nor the box changed v_des, `over` has measured it already.
    if (k > 1.0 or v != v_des) and over(v) > 1.0:
        # The acceleration box bent the step into a faster tool motion: ask for less until
        # it fits (λ = 0 is the hardest braking the box allows).
        lo, hi = 0.0, 1.0
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            if over(boxed(mid)) <= 1.0:
                lo = mid
            else:
                hi = mid
        v = boxed(lo)
    return step(v)
