"""Motions of the PUMA proxy: the handle callers wait on and the generators that drive it.

A generator gives the desired setpoint each control cycle: `Planned` follows a plan,
`Servo` chases a goal (streamed commands, or the end of a plan the filter held back), `Brake`
decelerates to rest. The safety filter then checks what they ask for. Units: rad, s.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.control.puma.planning import PLAN_SPEED_MARGIN
from services.control.puma.safety import MotionLimits, ToolPoseFn
from services.control.puma.trajectory import Trapezoid, discrete_brake_speed
from services.geometry import angle_between

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

    def finish(self, reason: str, q: Vec) -> None:
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
    """Chases a goal (rad) as fast as the joint limits allow, slowing so the tool stays
    below its speed limits; used for streamed commands and to finish a planned motion."""

    def __init__(self, goal: Vec, t_s: float, settle_s: float) -> None:
        self.goal = goal
        self.last_goal_t_s = t_s
        self.settle_s = settle_s


class Brake:
    """Decelerates every joint in proportion, so the path stays straight, to rest."""


Generator = Planned | Servo | Brake


def servo_target(
    goal: Vec,
    q: Vec,
    qd: Vec,
    pose_now: tuple[Vec, Vec],
    dt_s: float,
    lim: MotionLimits,
    tool_pose: ToolPoseFn,
) -> Vec:
    """The next setpoint chasing `goal`: per joint as fast as its speed allows while it can
    still stop at the goal, within the acceleration box around the present velocity, and
    with the tool kept under 90 % of its speeds (so `safe_step` has nothing to cut)."""
    e = goal - q
    v_des = np.sign(e) * np.minimum(lim.vmax, discrete_brake_speed(e, lim.amax, dt_s))
    p0, R0 = pose_now
    max_dp = PLAN_SPEED_MARGIN * lim.tool_speed_m_s * dt_s
    max_dth = PLAN_SPEED_MARGIN * lim.tool_rot_speed_rad_s * dt_s

    def over(v: Vec) -> float:
        p1, R1 = tool_pose(q + v * dt_s)
        return max(float(np.linalg.norm(p1 - p0)) / max_dp, angle_between(R0, R1) / max_dth)

    k = over(v_des)
    if k > 1.0:
        v_des = v_des / k
    dv = lim.amax * dt_s
    v = np.clip(v_des, qd - dv, qd + dv)
    if over(v) > 1.0:
        # The acceleration box bent the step into a faster tool motion: ask for less until
        # it fits (λ = 0 is the hardest braking the box allows).
        lo, hi = 0.0, 1.0
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            if over(np.clip(mid * v_des, qd - dv, qd + dv)) <= 1.0:
                lo = mid
            else:
                hi = mid
        v = np.clip(lo * v_des, qd - dv, qd + dv)
    return np.asarray(q + v * dt_s, dtype=np.float64)
