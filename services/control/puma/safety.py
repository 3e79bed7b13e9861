"""The proxy's safety filter (pure): the last line between any motion and the arm.

`safe_step`, applied every control cycle whatever the source of the motion: a setpoint never
leaves the joint limits, no joint exceeds its speed limit, no joint its acceleration limit
(unless that is the only way to honour the other limits), and the tool point moves at most
`tool_speed_m_s` and the tool frame turns at most `tool_rot_speed_rad_s` between two ticks.
Units: rad, m, s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.geometry import angle_between

Vec = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class MotionLimits:
    """What `safe_step` enforces: joint limits (rad), speeds (rad/s), accelerations (rad/s²),
    tool point speed (m/s) and tool frame angular speed (rad/s)."""

    q_lo: Vec
    q_hi: Vec
    vmax: Vec
    amax: Vec
    tool_speed_m_s: float
    tool_rot_speed_rad_s: float


@dataclass(frozen=True, slots=True)
class SafeStep:
    """One filtered setpoint: joints (rad), velocity (rad/s), the tool pose there, and which
    limits acted (`joint_limit`, `joint_speed`, `joint_accel`, `tool_speed`)."""

    q: Vec
    qd: Vec
    tool_p: Vec
    tool_R: Vec
    limited: frozenset[str]


ToolPoseFn = Callable[[Vec], tuple[Vec, Vec]]


def _cut(a: Vec, b: Vec, tol: float) -> bool:
    """Whether a limit changed b into a by more than rounding (q + v·dt is not exact)."""
    return bool(np.any(np.abs(a - b) > tol * (1.0 + np.abs(b))))


def safe_step(
    q: Vec,
    qd: Vec,
    q_des: Vec,
    dt_s: float,
    lim: MotionLimits,
    tool_pose: ToolPoseFn,
    pose_now: tuple[Vec, Vec],
) -> SafeStep:
    """The next setpoint towards `q_des` that honours `lim`, from setpoint `q` moving at `qd`.

    In order: clamp the target into the joint limits; clip the joint velocity to ±vmax and
    its change to ±amax·dt; clamp again; then, if the tool point or tool frame would move
    faster than allowed between the two setpoints (measured exactly with `tool_pose`, the
    tool pose of a joint vector), shrink the step towards `q` until it does not — shrinking
    keeps the joints inside the limits and below their speeds. The joint limits and the tool
    speeds always hold; the acceleration limit gives way only to them.
    """
    limited: set[str] = set()
    target = np.clip(q_des, lim.q_lo, lim.q_hi)
    if _cut(target, q_des, 1e-12):
        limited.add("joint_limit")
    v = (target - q) / dt_s
    v_c = np.clip(v, -lim.vmax, lim.vmax)
    if _cut(v_c, v, 1e-9):
        limited.add("joint_speed")
    dv = lim.amax * dt_s
    v_a = np.clip(v_c, qd - dv, qd + dv)
    if _cut(v_a, v_c, 1e-9):
        limited.add("joint_accel")
    v_a = np.clip(v_a, -lim.vmax, lim.vmax)
    q_next = np.clip(q + v_a * dt_s, lim.q_lo, lim.q_hi)
    p0, R0 = pose_now
    max_dp = lim.tool_speed_m_s * dt_s
    max_dth = lim.tool_rot_speed_rad_s * dt_s
    p1, R1 = tool_pose(q_next)
    for _ in range(8):
        over = max(float(np.linalg.norm(p1 - p0)) / max_dp, angle_between(R0, R1) / max_dth)
        if over <= 1.0:
            break
        limited.add("tool_speed")
        q_next = q + (q_next - q) * (0.98 / over)
        p1, R1 = tool_pose(q_next)
    else:
        # The step cannot be made slow enough (it never happens for steps this small, as the
        # tool pose is smooth in q): holding is always within every limit.
        q_next, p1, R1 = q.copy(), p0, R0
    return SafeStep(q_next, (q_next - q) / dt_s, p1, R1, frozenset(limited))
