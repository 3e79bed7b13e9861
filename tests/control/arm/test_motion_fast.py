"""The plain-float control-loop math against a straightforward numpy reference.

The safety filter, the servo target, the braking speed, the tool pose measured every tick and
the simulated joint servo run on six joints at up to 1 kHz, so they compute in scalar Python
floats (a numpy call on six elements costs more than the arithmetic). These tests hold them to
the numpy versions they replaced, transcribed below: the same setpoints, velocities, poses and
reported limits within 1e-12 over random states.

One place is a knife edge by construction: after `servo_target` scales a step down to the tool
speed limit, it compares that step's tool motion with the limit again, and the two can differ by
rounding alone (a single wrist joint turning the tool exactly in proportion). There the numpy
and the float sums may round to different sides and both answers are right; such draws are
skipped (`assume`).
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from services.control.arm.kinematics import compose_floats, se3_floats
from services.control.arm.model import load_model
from services.control.arm.motions import servo_target
from services.control.arm.planning import PLAN_SPEED_MARGIN
from services.control.arm.puma560 import (
    DEFAULT_eMt,
    flange_pose_floats,
    manipulability_floats,
    tool_pose_floats,
)
from services.control.arm.safety import safe_step
from services.control.arm.sim_arm import ARRIVED_RAD, JointFollower
from services.control.arm.trajectory import discrete_brake_speed
from tests.control.arm.test_motion_math import KIN, LIM

PUMA = load_model("puma560")
ARM_MAX_JOINT_SPEED_RAD_S = tuple(j.max_speed for j in PUMA.joints)
ARM_MAX_JOINT_ACCEL_RAD_S2 = tuple(j.max_accel for j in PUMA.joints)

Vec = NDArray[np.float64]
EDGE = 1e-9
"""A tool-motion ratio this close to 1 is a decision rounding may take either way."""


# --- the reference: the numpy code the float paths replaced ----------------------------------


def ref_tool_pose(q: Vec) -> tuple[Vec, Vec]:
    oMt = KIN.fk_tool(q, DEFAULT_eMt)
    return np.array(oMt.translation), np.array(oMt.rotation)


def ref_angle_between(R_a: Vec, R_b: Vec) -> float:
    d = float(np.linalg.norm(R_a - R_b))
    return 2.0 * math.asin(min(1.0, d / (2.0 * math.sqrt(2.0))))


def ref_cut(a: Vec, b: Vec, tol: float) -> bool:
    return bool(np.any(np.abs(a - b) > tol * (1.0 + np.abs(b))))


def ref_safe_step(
    q: Vec, qd: Vec, q_des: Vec, dt_s: float, pose_now: tuple[Vec, Vec], overs: list[float]
) -> tuple[Vec, Vec, Vec, Vec, frozenset[str]]:
    limited: set[str] = set()
    target = np.clip(q_des, LIM.q_lo, LIM.q_hi)
    if ref_cut(target, q_des, 1e-12):
        limited.add("joint_limit")
    v = (target - q) / dt_s
    v_c = np.clip(v, -LIM.vmax, LIM.vmax)
    if ref_cut(v_c, v, 1e-9):
        limited.add("joint_speed")
    dv = LIM.amax * dt_s
    v_a = np.clip(v_c, qd - dv, qd + dv)
    if ref_cut(v_a, v_c, 1e-9):
        limited.add("joint_accel")
    v_a = np.clip(v_a, -LIM.vmax, LIM.vmax)
    q_next = np.clip(q + v_a * dt_s, LIM.q_lo, LIM.q_hi)
    p0, R0 = pose_now
    max_dp = LIM.tool_speed_m_s * dt_s
    max_dth = LIM.tool_rot_speed_rad_s * dt_s
    p1, R1 = ref_tool_pose(q_next)
    for _ in range(8):
        over = max(float(np.linalg.norm(p1 - p0)) / max_dp, ref_angle_between(R0, R1) / max_dth)
        overs.append(over)
        if over <= 1.0:
            break
        limited.add("tool_speed")
        q_next = q + (q_next - q) * (0.98 / over)
        p1, R1 = ref_tool_pose(q_next)
    else:
        q_next, p1, R1 = q.copy(), p0, R0
    return q_next, (q_next - q) / dt_s, p1, R1, frozenset(limited)


def ref_discrete_brake_speed(e_rad: Vec, amax: Vec, dt_s: float) -> Vec:
    ae = np.abs(e_rad)
    v = amax * dt_s * (np.sqrt(0.25 + 2.0 * ae / (amax * dt_s * dt_s)) - 0.5)
    return np.asarray(np.minimum(v, ae / dt_s), dtype=np.float64)


def ref_servo_target(
    goal: Vec, q: Vec, qd: Vec, pose_now: tuple[Vec, Vec], dt_s: float, overs: list[float]
) -> Vec:
    e = goal - q
    v_des = np.sign(e) * np.minimum(LIM.vmax, ref_discrete_brake_speed(e, LIM.amax, dt_s))
    p0, R0 = pose_now
    max_dp = PLAN_SPEED_MARGIN * LIM.tool_speed_m_s * dt_s
    max_dth = PLAN_SPEED_MARGIN * LIM.tool_rot_speed_rad_s * dt_s

    def over(v: Vec) -> float:
        p1, R1 = ref_tool_pose(q + v * dt_s)
        k = max(float(np.linalg.norm(p1 - p0)) / max_dp, ref_angle_between(R0, R1) / max_dth)
        overs.append(k)
        return k

    k = over(v_des)
    if k > 1.0:
        v_des = v_des / k
    dv = LIM.amax * dt_s
    v = np.clip(v_des, qd - dv, qd + dv)
    if over(v) > 1.0:
        lo, hi = 0.0, 1.0
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            if over(np.clip(mid * v_des, qd - dv, qd + dv)) <= 1.0:
                lo = mid
            else:
                hi = mid
        v = np.clip(lo * v_des, qd - dv, qd + dv)
    return np.asarray(q + v * dt_s, dtype=np.float64)


class RefFollower:
    """JointFollower as it was, on numpy arrays (with the arrival kept inside the limits,
    fixed in both: hypothesis found a setpoint 8e-11 rad below q_lo snapped to)."""

    def __init__(self, q: Vec, vmax: Vec, amax: Vec, kp_1_s: float = 50.0) -> None:
        self.q, self.v, self.setpoint = q.copy(), np.zeros(6), q.copy()
        self.vmax, self.amax, self.kp_1_s = vmax, amax, kp_1_s
        self.q_lo, self.q_hi = KIN.q_lo, KIN.q_hi

    def hold(self) -> None:
        stop_dist = self.v * np.abs(self.v) / (2.0 * self.amax)
        self.setpoint = np.clip(self.q + stop_dist, self.q_lo, self.q_hi)

    def step(self, dt_s: float) -> None:
        e = self.setpoint - self.q
        v_fb = np.sign(e) * np.minimum(
            self.kp_1_s * np.abs(e), np.sqrt(2.0 * self.amax * np.abs(e))
        )
        v_des = np.clip(v_fb, -self.vmax, self.vmax)
        dv = self.amax * dt_s
        self.v = np.clip(v_des, self.v - dv, self.v + dv)
        q_next = self.q + self.v * dt_s
        at_stop = (q_next < self.q_lo) | (q_next > self.q_hi)
        self.q = np.clip(q_next, self.q_lo, self.q_hi)
        self.v[at_stop] = 0.0
        if (
            np.abs(self.setpoint - self.q).max() <= ARRIVED_RAD
            and np.abs(self.v).max() <= ARRIVED_RAD
        ):
            self.setpoint = np.clip(self.setpoint, self.q_lo, self.q_hi)  # never past a limit
            self.q = self.setpoint.copy()
            self.v[:] = 0.0

    def at_rest(self) -> bool:
        return not self.v.any() and np.array_equal(self.q, self.setpoint)


# --- random states -----------------------------------------------------------------------


def six(lo: float, hi: float) -> st.SearchStrategy[Vec]:
    return st.lists(st.floats(lo, hi), min_size=6, max_size=6).map(np.array)


joints_in_limits = six(0.0, 1.0).map(lambda w: LIM.q_lo + w * (LIM.q_hi - LIM.q_lo))
speeds = six(-1.0, 1.0).map(lambda s: s * LIM.vmax)
offsets = six(-0.05, 0.05)
dts = st.sampled_from([1e-3, 2e-3, 4e-3])
tools = st.tuples(six(-3.0, 3.0), six(-0.3, 0.3)).map(
    lambda wp: pin.SE3(pin.exp3(wp[0][:3]), wp[1][:3])
)
EMT_FLOATS = se3_floats(DEFAULT_eMt)


def float_tool_pose(q: list[float]) -> tuple[list[float], list[float]]:
    return tool_pose_floats(q, EMT_FLOATS)


def close(a: object, b: object) -> bool:
    return bool(np.allclose(np.asarray(a, float), np.asarray(b, float), rtol=1e-12, atol=1e-12))


def at_an_edge(overs: list[float]) -> bool:
    return any(abs(k - 1.0) < EDGE for k in overs)


# --- the tests -----------------------------------------------------------------------------


@settings(max_examples=300)
@given(joints_in_limits, st.one_of(st.just(DEFAULT_eMt), tools))
def test_tool_pose_floats_are_pinocchio_s_fk(q: Vec, eMt: pin.SE3) -> None:
    p, R = tool_pose_floats(q.tolist(), se3_floats(eMt))
    oMt = KIN.fk_tool(q, eMt)
    assert close(p, oMt.translation) and close(R, oMt.rotation.reshape(-1))
    p_e, R_e = flange_pose_floats(q.tolist())
    oMe = KIN.fk_flange(q)
    assert close(p_e, oMe.translation) and close(R_e, oMe.rotation.reshape(-1))
    assert close(compose_floats((p_e, R_e), se3_floats(eMt))[0], oMt.translation)
    assert manipulability_floats(q.tolist()) == KIN.manipulability(q)


@settings(max_examples=300)
@given(
    joints_in_limits,
    speeds,
    st.one_of(offsets, six(-8.0, 8.0)),
    dts,
)
def test_safe_step_is_the_numpy_filter(q: Vec, qd: Vec, target: Vec, dt_s: float) -> None:
    qd = np.where((q <= LIM.q_lo) | (q >= LIM.q_hi), 0.0, qd)
    q_des = q + target if np.max(np.abs(target)) <= 0.05 else target
    overs: list[float] = []
    want = ref_safe_step(q, qd, q_des, dt_s, ref_tool_pose(q), overs)
    assume(not at_an_edge(overs))
    got = safe_step(
        q.tolist(), qd.tolist(), q_des.tolist(), dt_s, LIM, float_tool_pose, float_tool_pose(q)
    )
    assert close(got.q, want[0]) and close(got.qd, want[1])
    assert close(got.tool_p, want[2]) and close(got.tool_R, want[3].reshape(-1))
    assert got.limited == want[4]


@settings(max_examples=300)
@given(joints_in_limits, speeds, st.one_of(offsets, offsets.map(lambda d: d * 20.0)), dts)
def test_servo_target_is_the_numpy_servo(q: Vec, qd: Vec, offset: Vec, dt_s: float) -> None:
    goal = np.clip(q + offset, LIM.q_lo, LIM.q_hi)
    overs: list[float] = []
    want = ref_servo_target(goal, q, qd, ref_tool_pose(q), dt_s, overs)
    assume(not at_an_edge(overs))
    got = servo_target(
        goal.tolist(), q.tolist(), qd.tolist(), float_tool_pose(q), dt_s, LIM, float_tool_pose
    )
    assert close(got, want)


@settings(max_examples=40)
@given(joints_in_limits, six(-0.5, 0.5), dts)
def test_a_servo_chase_is_the_numpy_chase(q0: Vec, offset: Vec, dt_s: float) -> None:
    """The proxy's loop chasing a goal, tick by tick from the reference's state: once up to
    speed the acceleration box rarely binds, which random velocities seldom reach."""
    goal = np.clip(q0 + offset, LIM.q_lo, LIM.q_hi)
    q, qd = q0, np.zeros(6)
    pose = ref_tool_pose(q)
    for _ in range(150):
        overs: list[float] = []
        q_des = ref_servo_target(goal, q, qd, pose, dt_s, overs)
        q_next, qd_next, p1, R1, _ = ref_safe_step(q, qd, q_des, dt_s, pose, overs)
        assume(not at_an_edge(overs))
        fpose = (pose[0].tolist(), pose[1].reshape(-1).tolist())
        got_des = servo_target(
            goal.tolist(), q.tolist(), qd.tolist(), fpose, dt_s, LIM, float_tool_pose
        )
        assert close(got_des, q_des)
        got = safe_step(q.tolist(), qd.tolist(), got_des, dt_s, LIM, float_tool_pose, fpose)
        assert close(got.q, q_next) and close(got.qd, qd_next)
        q, qd, pose = q_next, qd_next, (p1, R1)


@settings(max_examples=300)
@given(st.floats(-3.0, 3.0), st.floats(0.5, 20.0), dts)
def test_discrete_brake_speed_is_the_numpy_formula(e: float, a: float, dt_s: float) -> None:
    want = ref_discrete_brake_speed(np.array([e]), np.array([a]), dt_s)[0]
    assert discrete_brake_speed(e, a, dt_s) == want


@settings(max_examples=40)
@given(
    joints_in_limits,
    six(-0.3, 0.3),
    st.lists(st.integers(1, 250), min_size=1, max_size=4),
    st.booleans(),
    st.booleans(),
)
def test_joint_follower_is_the_numpy_servo(
    q0: Vec, move: Vec, legs: list[int], hold: bool, settle: bool
) -> None:
    """Legs towards setpoints (some past the joint limits, which stop the joints), each
    maybe ended by a controlled stop, then maybe the approach to rest."""
    vmax, amax = np.array(ARM_MAX_JOINT_SPEED_RAD_S), np.array(ARM_MAX_JOINT_ACCEL_RAD_S2)
    ref = RefFollower(q0, vmax, amax)
    got = JointFollower(q0, vmax, amax, KIN.q_lo, KIN.q_hi)
    want_trace, got_trace = [], []
    for i, n in enumerate([*legs, 1200] if settle else legs):
        if i < len(legs):
            sp = np.clip(q0 + move * (i + 1) / len(legs), KIN.q_lo - 0.1, KIN.q_hi + 0.1)
            ref.setpoint, got.setpoint = sp.copy(), sp.copy()
        for _ in range(n):
            ref.step(1e-3)
            got.step(1e-3)
            want_trace.append((ref.q, ref.v.copy()))
            got_trace.append((got.q, got.v))
        if hold and i < len(legs):
            ref.hold()
            got.hold()
            assert close(got.setpoint, ref.setpoint)
    assert close(got_trace, want_trace)
    assert got.at_rest() == ref.at_rest()
    assert np.all(got.q >= KIN.q_lo) and np.all(got.q <= KIN.q_hi)


def test_arrival_just_past_a_limit_stops_at_the_limit_and_rests() -> None:
    """Found by hypothesis: a setpoint 8e-11 rad below q_lo was snapped to on arrival."""
    vmax, amax = np.array(ARM_MAX_JOINT_SPEED_RAD_S), np.array(ARM_MAX_JOINT_ACCEL_RAD_S2)
    got = JointFollower(KIN.q_lo.copy(), vmax, amax, KIN.q_lo, KIN.q_hi)
    sp = KIN.q_lo.copy()
    sp[5] -= 7.641020038017319e-11
    got.setpoint = sp
    got.step(1e-3)
    assert np.all(got.q >= KIN.q_lo)
    assert got.at_rest()
    np.testing.assert_array_equal(got.q, KIN.q_lo)
