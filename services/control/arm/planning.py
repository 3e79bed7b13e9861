"""Motion planning of the proxy's methods: joint moves and straight tool lines.

A plan is a joint path q(s), s ∈ [0, 1], with a trapezoidal time law, made within the motion
limits with margin (so the safety filter seldom has to act). Planning solves IK many times:
the proxy runs it outside its lock, on a kinematics instance of its own. Units: m, rad, s.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from services.bus.errors import RpcError
from services.control.arm.kinematics import Kinematics
from services.control.arm.safety import MotionLimits
from services.control.arm.trajectory import SampledPath, Trapezoid

Vec = NDArray[np.float64]

PLAN_STEP_M = 0.01
PLAN_STEP_RAD = 0.05
"""Cartesian paths are solved every 1 cm / 0.05 rad of tool motion and interpolated between."""
PLAN_MAX_JOINT_STEP_RAD = 0.2
"""Two consecutive path samples further apart than this in any joint: the straight line
crosses a singularity or a branch change, so the move is made in joint space instead."""
PLAN_SPEED_MARGIN = 0.9
PLAN_ACCEL_SHARE = 0.45
"""Plans use 90 % of each speed limit; a Cartesian path gives 45 % of each joint's
acceleration to the path's acceleration and 45 % to its curvature (q'·s̈ + q''·ṡ²)."""

Plan = tuple[Callable[[float], Vec], Trapezoid, Vec, str]
"""A planned motion: q(s) for s ∈ [0, 1], its time law, the goal joints, `joint`|`cartesian`."""
PlanFn = Callable[[Kinematics, Vec, pin.SE3], Plan]


def plan_joint(
    kin: Kinematics, lim: MotionLimits, q0: Vec, q1: Vec, eMt: pin.SE3, speed: float
) -> Plan:
    """A straight line in joint space with one trapezoidal law for all joints: each
    joint within its speed and acceleration, the tool within its speeds (sampled)."""
    dq = q1 - q0
    if not np.any(dq):
        return (lambda s: q1), Trapezoid(0.0, 1.0, 0.0, 0.0), q1.copy(), "joint"
    adq = np.abs(dq)
    moving = adq > 0.0
    v_max = speed * PLAN_SPEED_MARGIN * float(np.min(lim.vmax[moving] / adq[moving]))
    a_max = PLAN_SPEED_MARGIN * float(np.min(lim.amax[moving] / adq[moving]))
    lin, ang = 0.0, 0.0
    for s in np.linspace(0.0, 1.0, 41):
        J = kin.jacobian(q0 + s * dq, eMt)
        lin = max(lin, float(np.linalg.norm(J[:3] @ dq)))
        ang = max(ang, float(np.linalg.norm(J[3:] @ dq)))
    v_max = min(v_max, tool_speed_bound(lim, lin, ang, speed))
    law = Trapezoid.plan(v_max, a_max)
    return (lambda s: q0 + s * dq), law, q1.copy(), "joint"


def tool_speed_bound(lim: MotionLimits, lin: float, ang: float, speed: float) -> float:
    """The largest ṡ for which |dp/ds|·ṡ and |dθ/ds|·ṡ stay under the tool limits."""
    bound = math.inf
    k = speed * PLAN_SPEED_MARGIN
    if lin > 0.0:
        bound = min(bound, k * lim.tool_speed_m_s / lin)
    if ang > 0.0:
        bound = min(bound, k * lim.tool_rot_speed_rad_s / ang)
    return bound


def plan_pose(
    kin: Kinematics,
    lim: MotionLimits,
    q0: Vec,
    target: pin.SE3,
    eMt: pin.SE3,
    config: str | None,
    speed: float = 1.0,
) -> Plan:
    sols = kin.ik(target, eMt, q_ref=q0)
    if not sols:
        raise RpcError("unreachable", "the target pose is out of reach")
    if config is not None:
        branch = [s for s in sols if s.config == config]
        if not branch:
            raise RpcError("unreachable", f"no solution on branch {config}")
        best = kin.choose(branch, q0)
        if best is None:
            raise RpcError("limit", f"the {config} solution is outside the joint limits")
    else:
        best = kin.choose(sols, q0)
        if best is None:
            raise RpcError("limit", "every solution is outside the joint limits")
    if config is None or config == kin.config(q0):
        line = plan_line(kin, lim, q0, target, eMt, speed)
        if line is not None:
            return line
    return plan_joint(kin, lim, q0, best.q, eMt, speed)


def plan_line(
    kin: Kinematics, lim: MotionLimits, q0: Vec, target: pin.SE3, eMt: pin.SE3, speed: float = 1.0
) -> Plan | None:
    """A straight tool line (position lerp, rotation slerp) at `speed` (a fraction of the
    limits), or None if it leaves the workspace or the joint limits or needs a joint jump on
    the way."""
    start = kin.fk_tool(q0, eMt)
    dp = target.translation - start.translation
    w = pin.log3(start.rotation.T @ target.rotation)
    length, angle = float(np.linalg.norm(dp)), float(np.linalg.norm(w))
    n = max(2, math.ceil(max(length / PLAN_STEP_M, angle / PLAN_STEP_RAD)))
    qs = [q0]
    for i in range(1, n + 1):
        s = i / n
        pose = pin.SE3(start.rotation @ pin.exp3(s * w), start.translation + s * dp)
        sol = kin.choose(kin.ik(pose, eMt, q_ref=qs[-1]), qs[-1])
        if sol is None or float(np.max(np.abs(sol.q - qs[-1]))) > PLAN_MAX_JOINT_STEP_RAD:
            return None
        qs.append(sol.q)
    path = SampledPath(np.array(qs))
    if length == 0.0 and angle == 0.0:
        return (lambda s: q0), Trapezoid(0.0, 1.0, 0.0, 0.0), q0.copy(), "cartesian"
    d1, d2 = path.derivative_bounds()
    v_max = tool_speed_bound(lim, length, angle, speed)
    a_max = math.inf
    for j in range(kin.n):
        if d1[j] > 0.0:
            v_max = min(v_max, speed * PLAN_SPEED_MARGIN * lim.vmax[j] / d1[j])
            a_max = min(a_max, PLAN_ACCEL_SHARE * lim.amax[j] / d1[j])
        if d2[j] > 0.0:
            v_max = min(v_max, math.sqrt(PLAN_ACCEL_SHARE * lim.amax[j] / d2[j]))
    law = Trapezoid.plan(v_max, a_max)
    return path.at, law, path.q[-1].copy(), "cartesian"
