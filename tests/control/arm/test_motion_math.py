"""The proxy's pure pieces on their own: time laws, paths, braking, the safety filter."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.arm.config import ArmConfig
from services.control.arm.kinematics import se3_floats
from services.control.arm.model import load_model
from services.control.arm.puma560 import DEFAULT_eMt, Puma560
from services.control.arm.safety import MotionLimits, safe_step
from services.control.arm.trajectory import SampledPath, Trapezoid, discrete_brake_speed
from services.geometry import angle_between

KIN = Puma560()
CFG = ArmConfig().bind(load_model())
LIM = MotionLimits(
    q_lo=KIN.q_lo.copy(),
    q_hi=KIN.q_hi.copy(),
    vmax=np.array(CFG.max_joint_speed_rad_s),
    amax=np.array(CFG.max_joint_accel_rad_s2),
    tool_speed_m_s=CFG.max_tool_speed_m_s,
    tool_rot_speed_rad_s=CFG.max_tool_rot_speed_rad_s,
)
DT_S = 1.0 / CFG.control_rate_hz


def tool_pose(q: Sequence[float]) -> tuple[list[float], list[float]]:
    """(p, R row-major), as the proxy's loop measures it (`services.geometry.PoseFloats`)."""
    return se3_floats(KIN.fk_tool(q, DEFAULT_eMt))


@settings(max_examples=200, deadline=None)
@given(st.floats(0.05, 20.0), st.floats(0.05, 50.0))
def test_trapezoid_goes_from_0_to_1_within_its_speed_and_acceleration(
    v_max: float, a_max: float
) -> None:
    law = Trapezoid.plan(v_max, a_max)
    assert law.s_at(0.0) == 0.0 and law.s_at(law.duration_s) == 1.0
    assert law.v_peak <= v_max * (1 + 1e-12)
    t = np.linspace(0.0, law.duration_s, 401)
    s = np.array([law.s_at(x) for x in t])
    h = t[1] - t[0]
    assert np.all(np.diff(s) >= 0.0)
    assert np.max(np.diff(s)) / h <= v_max * (1 + 1e-9)
    assert np.max(np.abs(np.diff(s, n=2))) / (h * h) <= a_max * (1 + 1e-6)


def test_triangular_and_trapezoidal_laws_by_hand() -> None:
    tri = Trapezoid.plan(10.0, 4.0)  # v² ≥ a: never reaches v_max; t_acc = √(1/a) = 0.5 s
    assert (tri.t_acc_s, tri.duration_s, tri.v_peak) == pytest.approx((0.5, 1.0, 2.0))
    trap = Trapezoid.plan(0.5, 2.0)  # t_acc = 0.25 s, cruise 1/v = 2 s
    assert (trap.t_acc_s, trap.duration_s, trap.v_peak) == pytest.approx((0.25, 2.25, 0.5))
    assert trap.s_at(trap.duration_s / 2) == pytest.approx(0.5)


def test_sampled_path_passes_through_its_samples_and_bounds_its_derivatives() -> None:
    q = np.array([[0.0] * 6, [0.1] * 6, [0.3] * 6, [0.4] * 6])
    path = SampledPath(q)
    for i, qi in enumerate(q):
        np.testing.assert_allclose(path.at(i / 3), qi, atol=1e-15)
    np.testing.assert_allclose(path.at(-1.0), q[0])
    np.testing.assert_allclose(path.at(2.0), q[-1])
    d1, d2 = path.derivative_bounds()
    np.testing.assert_allclose(d1, 0.6)  # largest step 0.2 × 3 segments
    np.testing.assert_allclose(d2, 0.9)  # |0.2 − 0.1| × 3²
    with pytest.raises(ValueError):
        SampledPath(q[:1])


@settings(max_examples=200, deadline=None)
@given(st.floats(1e-6, 3.0), st.floats(0.5, 20.0), st.sampled_from([1e-3, 2e-3, 4e-3]))
def test_discrete_brake_speed_stops_within_the_distance(e: float, a: float, dt: float) -> None:
    v = discrete_brake_speed(e, a, dt)
    assert 0.0 <= v <= e / dt * (1 + 1e-12)
    travelled = 0.0
    while v > 0.0:
        travelled += v * dt
        v -= a * dt
    # The closed form treats the number of braking steps as continuous: with a fractional
    # count the stop lands within a·dt²/8 past and a·dt²/2 short of |e| (≤ 4e-5 rad here).
    assert e - a * dt * dt / 2.0 - 1e-12 <= travelled <= e + a * dt * dt / 8.0 + 1e-12


joint = st.floats(-1.0, 1.0)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.floats(0.0, 1.0), min_size=6, max_size=6),
    st.lists(joint, min_size=6, max_size=6),
    st.lists(st.floats(-8.0, 8.0), min_size=6, max_size=6),
)
def test_safe_step_never_leaves_the_limits(
    where: list[float], speed: list[float], target: list[float]
) -> None:
    q = LIM.q_lo + np.array(where) * (LIM.q_hi - LIM.q_lo)
    qd = np.array(speed) * LIM.vmax
    qd = np.where((q <= LIM.q_lo) | (q >= LIM.q_hi), 0.0, qd)
    pose = tool_pose(q)
    step = safe_step(q.tolist(), qd.tolist(), target, DT_S, LIM, tool_pose, pose)
    q1, qd1 = np.array(step.q), np.array(step.qd)
    assert np.all(q1 >= LIM.q_lo) and np.all(q1 <= LIM.q_hi)
    assert np.all(np.abs(qd1) <= LIM.vmax * (1 + 1e-9))
    np.testing.assert_allclose(qd1, (q1 - q) / DT_S)
    oMt0, oMt1 = KIN.fk_tool(q), KIN.fk_tool(q1)
    np.testing.assert_allclose(step.tool_p, oMt1.translation, atol=1e-12)
    np.testing.assert_allclose(np.reshape(step.tool_R, (3, 3)), oMt1.rotation, atol=1e-12)
    dp = np.linalg.norm(oMt1.translation - oMt0.translation)
    assert dp <= LIM.tool_speed_m_s * DT_S * (1 + 1e-9)
    dth = angle_between(oMt0.rotation, oMt1.rotation)
    assert dth <= LIM.tool_rot_speed_rad_s * DT_S * (1 + 1e-9)
    inside = np.all(q1 > LIM.q_lo) and np.all(q1 < LIM.q_hi)
    if "tool_speed" not in step.limited and inside:
        assert np.all(np.abs(qd1 - qd) <= LIM.amax * DT_S * (1 + 1e-9))
    assert step.limited <= {"joint_limit", "joint_speed", "joint_accel", "tool_speed"}


def test_safe_step_reports_what_acted() -> None:
    q = np.array([0.3, 0.8, -2.5, 0.1, 0.6, 0.2])
    pose = tool_pose(q)
    rest = [0.0] * 6
    near = safe_step(q.tolist(), rest, (q + 1e-6).tolist(), DT_S, LIM, tool_pose, pose)
    assert near.limited == frozenset()
    np.testing.assert_allclose(near.q, q + 1e-6)
    far = safe_step(q.tolist(), rest, (q + 1.0).tolist(), DT_S, LIM, tool_pose, pose)
    assert {"joint_speed", "joint_accel"} <= far.limited
    np.testing.assert_allclose(far.qd, LIM.amax * DT_S)  # from rest: one step of acceleration
    out = safe_step(q.tolist(), rest, (LIM.q_hi + 1.0).tolist(), DT_S, LIM, tool_pose, pose)
    assert "joint_limit" in out.limited
