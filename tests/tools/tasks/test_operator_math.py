"""The person's inverse of the master mapping (eq. 5, PROTOCOL.md §2), checked against the
master's own forward code (services/control/master/teleop.py) and the decision's §2 mapping."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from services.control.master.teleop import scaled_motion
from services.geometry import exp_so3, rotation_angle, rxyz_inv, tool_target_pose
from services.tools.tasks.operator import (
    OperatorConfig,
    Reference,
    ball_fraction,
    hand_for_tool,
    tool_for_hand,
)

DOWN = np.diag([-1.0, 1.0, -1.0])
small_vec = st.tuples(*[st.floats(-0.1, 0.1)] * 3)
small_rot = st.tuples(*[st.floats(-0.6, 0.6)] * 3)


def ref(
    frame: str, s_t: float, s_r: float, w0: tuple[float, ...], wm: tuple[float, ...]
) -> Reference:
    return Reference(
        E0=np.array([0.01, -0.02, 0.03]),
        M0=exp_so3(np.asarray(wm)),
        p0=np.array([0.55, 0.0, 0.65]),
        R0=exp_so3(np.asarray(w0)) @ DOWN,
        scale_t=s_t,
        scale_r=s_r,
        frame=frame,  # type: ignore[arg-type]
    )


@settings(max_examples=150, deadline=None)
@given(
    frame=st.sampled_from(["world", "tool"]),
    s_t=st.floats(0.05, 1.0),
    s_r=st.floats(0.1, 1.0),
    w0=small_rot,
    wm=small_rot,
    dp=small_vec,
    dw=small_rot,
    yaw_a=st.sampled_from([0.0, math.pi / 2]),
)
def test_property_the_hand_the_person_chooses_puts_the_tool_on_the_aim(
    frame: str,
    s_t: float,
    s_r: float,
    w0: tuple[float, ...],
    wm: tuple[float, ...],
    dp: tuple[float, ...],
    dw: tuple[float, ...],
    yaw_a: float,
) -> None:
    r = ref(frame, s_t, s_r, w0, wm)
    A = exp_so3((0.0, 0.0, yaw_a))
    aim_p = r.p0 + np.asarray(dp)
    aim_R = r.R0 @ exp_so3(np.asarray(dw))
    # within the hand's reach (the person re-clutches beyond): no Euler angle past ±1.2 rad
    assume(float(np.max(np.abs(rxyz_inv(exp_so3(np.asarray(dw)))))) / s_r < 1.2)
    E, M = hand_for_tool(r, aim_p, aim_R, A)
    # the master (eq. 5) and the slave (§2), as the services compute them
    motion = scaled_motion(r.E0, r.M0, E, M, s_t, s_r, A)
    p, R = tool_target_pose(r.p0, r.R0, motion.dp, motion.dR, frame)
    np.testing.assert_allclose(p, aim_p, atol=1e-9)
    assert rotation_angle(R.T @ aim_R) < 1e-7
    p2, R2 = tool_for_hand(r, E, M, A)
    np.testing.assert_allclose(p2, aim_p, atol=1e-9)
    assert rotation_angle(R2.T @ aim_R) < 1e-7


@settings(max_examples=200, deadline=None)
@given(start=small_vec, goal=st.tuples(*[st.floats(-0.5, 0.5)] * 3), r=st.floats(0.05, 0.2))
def test_property_ball_fraction_stays_inside(
    start: tuple[float, ...], goal: tuple[float, ...], r: float
) -> None:
    s, g, c = np.asarray(start), np.asarray(goal), np.zeros(3)
    a = ball_fraction(s, g, c, r)
    assert 0.0 <= a <= 1.0
    p = s + a * (g - s)
    if np.linalg.norm(s) <= r:
        assert np.linalg.norm(p) <= r + 1e-9
    if np.linalg.norm(g) <= r:
        assert a == 1.0


def test_operator_config_is_checked() -> None:
    with pytest.raises(ValueError, match="hand_speed_m_s"):
        OperatorConfig(hand_speed_m_s=0.0)
    with pytest.raises(ValueError, match="alignment"):
        OperatorConfig(alignment=(1.0,) * 9)
