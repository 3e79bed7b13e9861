"""The proxy's safety filter (pure): the last line between any motion and the arm.

`safe_step`, applied every control cycle whatever the source of the motion: a setpoint never
leaves the joint limits, no joint exceeds its speed limit, no joint its acceleration limit
(unless that is the only way to honour the other limits), and the tool point moves at most
`tool_speed_m_s` and the tool frame turns at most `tool_rot_speed_rad_s` between two ticks.
Units: rad, m, s.

It runs every tick on the arm's few joints, where a numpy call costs more than the
arithmetic: joint vectors are sequences of n plain floats, joint 1 first, and a tool pose is
(p, R), 3 floats (m) and 9 floats (row-major), as `Kinematics.tool_pose_floats` gives them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from services.geometry import PoseFloats, angle9

Vec = NDArray[np.float64]
ToolPoseFn = Callable[[list[float]], PoseFloats]
"""The tool pose in the world (p, R floats) at a joint vector (n floats, rad)."""


@dataclass(frozen=True, slots=True)
class MotionLimits:
    """What `safe_step` enforces: joint limits (rad), speeds (rad/s), accelerations (rad/s²),
    tool point speed (m/s) and tool frame angular speed (rad/s).

    `joints` holds the four joint tables as one tuple per joint (q_lo, q_hi, vmax, amax) of
    plain floats, for the per-tick arithmetic.
    """

    q_lo: Vec
    q_hi: Vec
    vmax: Vec
    amax: Vec
    tool_speed_m_s: float
    tool_rot_speed_rad_s: float
    joints: tuple[tuple[float, float, float, float], ...] = field(
        init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        tables = (self.q_lo, self.q_hi, self.vmax, self.amax)
        n = len(self.q_lo)
        rows = zip(
            *(np.asarray(t, dtype=np.float64).reshape(n).tolist() for t in tables), strict=True
        )
        object.__setattr__(self, "joints", tuple(rows))


@dataclass(frozen=True, slots=True)
class SafeStep:
    """One filtered setpoint: joints (rad), velocity (rad/s), the tool pose there (p, R as
    in `PoseFloats`), and which limits acted (`joint_limit`, `joint_speed`, `joint_accel`,
    `tool_speed`)."""

    q: list[float]
    qd: list[float]
    tool_p: Sequence[float]
    tool_R: Sequence[float]
    limited: frozenset[str]


def tool_motion(pose0: PoseFloats, pose1: PoseFloats, max_dp_m: float, max_dth_rad: float) -> float:
    """How far the tool moves from `pose0` to `pose1` as a share of what is allowed: the
    larger of |p1 − p0| / max_dp_m and angle(R0ᵀR1) / max_dth_rad (≤ 1: within both).

    The angle is `geometry.angle9` (the chord formula of `angle_between`), accurate for
    small angles."""
    (p0, R0), (p1, R1) = pose0, pose1
    return max(math.dist(p0, p1) / max_dp_m, angle9(R0, R1) / max_dth_rad)


def safe_step(
    q: Sequence[float],
    qd: Sequence[float],
    q_des: Sequence[float],
    dt_s: float,
    lim: MotionLimits,
    tool_pose: ToolPoseFn,
    pose_now: PoseFloats,
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
    q_next: list[float] = []
    for qj, qdj, dj, (lo, hi, vmax, amax) in zip(q, qd, q_des, lim.joints, strict=True):
        # A limit "acts" when it changes a value by more than rounding (q + v·dt is not exact).
        target = lo if dj < lo else hi if dj > hi else dj
        if abs(target - dj) > 1e-12 * (1.0 + abs(dj)):
            limited.add("joint_limit")
        v = (target - qj) / dt_s
        v_c = -vmax if v < -vmax else vmax if v > vmax else v
        if abs(v_c - v) > 1e-9 * (1.0 + abs(v)):
            limited.add("joint_speed")
        dv = amax * dt_s
        v_lo, v_hi = qdj - dv, qdj + dv
        v_a = v_lo if v_c < v_lo else v_hi if v_c > v_hi else v_c
        if abs(v_a - v_c) > 1e-9 * (1.0 + abs(v_c)):
            limited.add("joint_accel")
        v_a = -vmax if v_a < -vmax else vmax if v_a > vmax else v_a
        x = qj + v_a * dt_s
        q_next.append(lo if x < lo else hi if x > hi else x)
    max_dp = lim.tool_speed_m_s * dt_s
    max_dth = lim.tool_rot_speed_rad_s * dt_s
    pose = tool_pose(q_next)
    for _ in range(8):
        over = tool_motion(pose_now, pose, max_dp, max_dth)
        if over <= 1.0:
            break
        limited.add("tool_speed")
        k = 0.98 / over
        q_next = [a + (b - a) * k for a, b in zip(q, q_next, strict=True)]
        pose = tool_pose(q_next)
    else:
        # The step cannot be made slow enough (it never happens for steps this small, as the
        # tool pose is smooth in q): holding is always within every limit.
        q_next, pose = list(q), pose_now
    qd_next = [(b - a) / dt_s for a, b in zip(q, q_next, strict=True)]
    return SafeStep(q_next, qd_next, pose[0], pose[1], frozenset(limited))
