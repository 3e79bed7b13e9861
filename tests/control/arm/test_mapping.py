"""The teleoperation mapping of PROTOCOL §2: engagement, world/tool modes, tool-point rotation."""

from __future__ import annotations

import math
from typing import cast

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import ArrayLike, NDArray

from services.control.arm.kinematics import Puma560, qn
from services.control.arm.mapping import TeleopInput, TeleopMapping, effector_target
from services.geometry import TeleopFrame, tool_target_pose

Mat = NDArray[np.float64]
ARM = Puma560()
I3 = np.eye(3)
ZERO = np.zeros(3)


def cmd(
    seq: int,
    engage: int,
    dp: ArrayLike = ZERO,
    dR: ArrayLike = I3,
    active: bool = True,
    frame: str = "world",
) -> TeleopInput:
    return TeleopInput(
        seq, engage, active, mode(frame), np.asarray(dp, float), np.asarray(dR, float)
    )


def mode(frame: str) -> TeleopFrame:
    # Hypothesis and parametrize hand out plain str; TeleopInput checks the value itself.
    return cast(TeleopFrame, frame)


def same_pose(a: pin.SE3, b: pin.SE3, tol: float = 1e-12) -> bool:
    return bool(
        np.max(np.abs(a.translation - b.translation)) < tol
        and np.max(np.abs(a.rotation - b.rotation)) < tol
    )


vec3 = st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3).map(np.array)
rotvec = st.lists(st.floats(-1.5, 1.5), min_size=3, max_size=3).map(np.array)
poses = st.tuples(rotvec, vec3).map(lambda rp: pin.SE3(pin.exp3(rp[0]), rp[1] + [0.5, 0, 0.8]))


def test_world_and_tool_translation() -> None:
    p0 = np.array([0.5, 0.1, 0.9])
    R0 = pin.utils.rotate("z", math.pi / 2)
    dp = np.array([0.1, 0.0, 0.0])
    p, R = tool_target_pose(p0, R0, dp, I3, "world")
    assert np.allclose(p, [0.6, 0.1, 0.9]) and np.allclose(R, R0)
    p, R = tool_target_pose(p0, R0, dp, I3, "tool")
    assert np.allclose(p, [0.5, 0.2, 0.9]) and np.allclose(R, R0)
    dR = pin.utils.rotate("x", 0.3)
    _, R = tool_target_pose(p0, R0, ZERO, dR, "world")
    assert np.allclose(R, R0 @ dR)  # dR acts in the tool frame in both modes
    with pytest.raises(ValueError):
        tool_target_pose(p0, R0, dp, I3, "wrist")  # type: ignore[arg-type]


def test_effector_target_inverts_the_tool_placement() -> None:
    eMt = pin.SE3(
        pin.utils.rotate("y", 0.6) @ pin.utils.rotate("x", -0.4), np.array([0.02, -0.05, 0.2])
    )
    oMt = pin.SE3(pin.utils.rotate("z", 1.0), np.array([0.4, 0.2, 0.7]))
    oMe = effector_target(oMt.translation, oMt.rotation, eMt)
    assert same_pose(oMe * eMt, oMt)


def test_pure_rotation_with_a_rotated_offset_tool_keeps_the_tool_point() -> None:
    eMt = pin.SE3(
        pin.utils.rotate("x", 0.5) @ pin.utils.rotate("z", 0.8), np.array([0.03, 0.04, 0.18])
    )
    oMe_now = ARM.fk_flange(qn)
    oMt_now = oMe_now * eMt
    m = TeleopMapping()
    assert same_pose(m.apply(cmd(1, 1), oMt_now) or pin.SE3(), oMt_now)
    dR = pin.utils.rotate("y", 0.3) @ pin.utils.rotate("x", -0.2)
    for frame in ("world", "tool"):
        oMt_target = m.apply(cmd(2 + (frame == "tool"), 1, dR=dR, frame=frame), oMt_now)
        assert oMt_target is not None
        oMe_target = effector_target(oMt_target.translation, oMt_target.rotation, eMt)
        # The tool point stays; the tool turns by dR in its own frame.
        assert np.allclose((oMe_target * eMt).translation, oMt_now.translation, atol=1e-12)
        assert np.allclose((oMe_target * eMt).rotation, oMt_now.rotation @ dR, atol=1e-12)
        # Eqs. (2) and (3) of the paper, with the transpose eq. (3) omits.
        M_wt, M_et = oMt_now.rotation, eMt.rotation
        T_t = M_et.T @ eMt.translation
        dE = M_wt @ (I3 - dR) @ T_t
        dM_e = M_et @ dR @ M_et.T
        assert np.allclose(oMe_target.translation, oMe_now.translation + dE, atol=1e-12)
        assert np.allclose(oMe_target.rotation, oMe_now.rotation @ dM_e, atol=1e-12)
        # Without the transpose the effector would turn wrongly for a rotated tool.
        assert not np.allclose(oMe_now.rotation @ (M_et @ dR @ M_et), oMe_target.rotation)
        # And the arm gets there: IK of the target keeps the tool point in place.
        best = ARM.choose(ARM.ik(oMt_target, eMt), qn)
        assert best is not None and best.config == ARM.config(qn)
        assert np.allclose(ARM.fk_tool(best.q, eMt).translation, oMt_now.translation, atol=1e-9)


def test_old_seq_and_old_engage_are_ignored() -> None:
    m = TeleopMapping()
    here = pin.SE3(I3, np.array([0.5, 0.0, 0.8]))
    assert m.apply(cmd(10, 3, dp=[0.01, 0, 0]), here) is not None
    assert (m.last_seq, m.engage) == (10, 3)
    assert m.apply(cmd(10, 3, dp=[0.5, 0, 0]), here) is None  # duplicate seq
    assert m.apply(cmd(9, 3, dp=[0.5, 0, 0]), here) is None  # older seq
    assert m.apply(cmd(11, 2, dp=[0.5, 0, 0]), here) is None  # older engage
    assert (m.last_seq, m.engage) == (10, 3)
    t = m.apply(cmd(12, 3, dp=[0.02, 0, 0]), pin.SE3(I3, np.array([9.0, 9.0, 9.0])))
    assert t is not None and np.allclose(t.translation, [0.52, 0.0, 0.8])


def test_inactive_commands_hold() -> None:
    m = TeleopMapping()
    here = pin.SE3(I3, np.array([0.5, 0.0, 0.8]))
    assert m.apply(cmd(1, 1, dp=[0.1, 0, 0], active=False), here) is None
    assert m.last_seq == 1 and m.engage is None
    assert m.apply(cmd(2, 1, dp=[0.1, 0, 0]), here) is not None
    assert m.apply(cmd(3, 1, dp=[0.2, 0, 0], active=False), here) is None
    assert m.last_seq == 3


@settings(max_examples=200, deadline=None)
@given(
    start=poses,
    moved=poses,
    dp1=vec3,
    dr1=rotvec,
    dp2=vec3,
    dr2=rotvec,
    frame=st.sampled_from(["world", "tool"]),
)
def test_re_engagement_after_the_arm_moved_never_jumps(
    start: pin.SE3, moved: pin.SE3, dp1: Mat, dr1: Mat, dp2: Mat, dr2: Mat, frame: str
) -> None:
    m = TeleopMapping()
    assert m.apply(cmd(1, 1, frame=frame), start) is not None
    assert m.apply(cmd(2, 1, dp=dp1, dR=pin.exp3(dr1), frame=frame), start) is not None
    assert m.apply(cmd(3, 1, dp=dp1, dR=pin.exp3(dr1), active=False, frame=frame), start) is None
    # Meanwhile the arm ended somewhere else (supervisor, limits, another command).
    first = m.apply(cmd(4, 2, frame=frame), moved)
    assert first is not None and same_pose(first, moved)
    # The engagement's later commands are relative to `moved`, whatever the arm does now.
    t = m.apply(cmd(5, 2, dp=dp2, dR=pin.exp3(dr2), frame=frame), start)
    p, R = tool_target_pose(moved.translation, moved.rotation, dp2, pin.exp3(dr2), mode(frame))
    assert t is not None and np.allclose(t.translation, p) and np.allclose(t.rotation, R)
    assert m.engage == 2


@settings(max_examples=100, deadline=None)
@given(
    start=poses,
    moved=poses,
    dp=vec3,
    dr=rotvec,
    dp2=vec3,
    frame=st.sampled_from(["world", "tool"]),
)
def test_rebase_inside_an_engagement_never_jumps(
    start: pin.SE3, moved: pin.SE3, dp: Mat, dr: Mat, dp2: Mat, frame: str
) -> None:
    m = TeleopMapping()
    m.apply(cmd(1, 1, frame=frame), start)
    m.apply(cmd(2, 1, dp=dp, dR=pin.exp3(dr), frame=frame), start)
    m.rebase()
    t = m.apply(cmd(3, 1, dp=dp, dR=pin.exp3(dr), frame=frame), moved)
    assert t is not None and same_pose(t, moved, 1e-9)
    # Further motion of the same engagement moves on from there by the difference.
    t2 = m.apply(cmd(4, 1, dp=dp + dp2, dR=pin.exp3(dr), frame=frame), moved)
    assert t2 is not None
    step = dp2 if frame == "world" else moved.rotation @ pin.exp3(dr).T @ dp2
    assert np.allclose(t2.translation, moved.translation + step, atol=1e-9)
    # A new engagement after a rebase records the plain current pose (PROTOCOL §2).
    m.rebase()
    t3 = m.apply(cmd(5, 2, dp=dp2, frame=frame), moved)
    p, _ = tool_target_pose(moved.translation, moved.rotation, dp2, I3, mode(frame))
    assert t3 is not None and np.allclose(t3.translation, p)


@settings(max_examples=100, deadline=None)
@given(
    start=poses,
    deltas=st.lists(st.tuples(vec3, rotvec), min_size=2, max_size=12),
    keep=st.lists(st.booleans(), min_size=12, max_size=12),
)
def test_lost_commands_cause_no_drift(
    start: pin.SE3, deltas: list[tuple[Mat, Mat]], keep: list[bool]
) -> None:
    full, lossy = TeleopMapping(), TeleopMapping()
    # The engagement's first command always arrives (else the reference is later; see above).
    last_full = last_lossy = None
    for i, (dp, dr) in enumerate(deltas):
        c = cmd(i + 1, 1, dp=dp if i else ZERO, dR=pin.exp3(dr) if i else I3, frame="tool")
        last_full = full.apply(c, start) or last_full
        if i == 0 or keep[i] or i == len(deltas) - 1:
            last_lossy = lossy.apply(c, start) or last_lossy
    assert last_full is not None and last_lossy is not None
    assert same_pose(last_full, last_lossy)


def test_teleop_input_validates_shapes() -> None:
    with pytest.raises(ValueError):
        cmd(1, 1, dp=np.zeros(2))
    with pytest.raises(ValueError):
        cmd(1, 1, dR=np.eye(4))
    with pytest.raises(ValueError):
        cmd(1, 1, dp=np.array([np.nan, 0, 0]))
    with pytest.raises(ValueError):
        cmd(1, 1, frame="wrist")
