"""The target master, pure: what is refused, and the engagement arithmetic of PROTOCOL §2."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.frontends.ros2.convert import quat_of, rotation_of
from services.frontends.ros2.target_master import (
    HOLD_REPEATS,
    Target,
    TargetLimits,
    TargetMaster,
    TargetRefused,
    check_target,
)
from services.frontends.rosmsg.msgs import Header, PoseStamped

TOOL = (0.55, 0.0, 0.65)
DOWN = (-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0)
LIMITS = TargetLimits()


def pose(
    p: tuple[float, ...], q: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0), frame: str = "world"
) -> PoseStamped:
    return PoseStamped(Header(0, 0, frame), p, q)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("msg", "why"),
    [
        (pose((0.55, 0.0, 0.6), frame="map"), "frame_id"),
        (pose((0.55, 0.0, 0.6), frame=""), "frame_id"),
        (pose((math.nan, 0.0, 0.6)), "not finite"),
        (pose((0.55, 0.0, 0.6), (math.inf, 0.0, 0.0, 1.0)), "not finite"),
        (pose((1e308, 0.0, 0.0)), "from the world origin"),
        (pose((100.0, 0.0, 0.6)), "from the world origin"),
        (pose((0.55, 0.0, 0.6), (0.0, 0.0, 0.0, 2.0)), "unit quaternion"),
        (pose((0.55, 0.0, 0.6), (0.0, 0.0, 0.0, 0.0)), "unit quaternion"),
        (pose((0.55, 1.0, 0.6)), "from the tool"),
    ],
)
def test_refusals(msg: PoseStamped, why: str) -> None:
    with pytest.raises(TargetRefused, match=why):
        check_target(msg, LIMITS, TOOL)


def test_no_state_no_target() -> None:
    with pytest.raises(TargetRefused, match="no robot/state"):
        check_target(pose((0.55, 0.0, 0.6)), LIMITS, None)


def test_a_near_unit_quaternion_is_normalised() -> None:
    t = check_target(pose((0.55, 0.0, 0.6), (1.0005, 0.0, 0.0, 0.0)), LIMITS, TOOL)
    R = np.array(t.R).reshape(3, 3)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.allclose(R, np.diag([1.0, -1.0, -1.0]), atol=1e-12)


def test_engage_stream_timeout_hold_and_reengage() -> None:
    m = TargetMaster(timeout_s=0.5, seq_start=0, engage_start=0)
    assert m.tick(0.0, (TOOL, DOWN)) is None  # no target: idle
    m.on_target(Target((0.55, 0.02, 0.65), DOWN), 1.0)
    assert m.tick(1.0, None) is None  # no fresh robot state: no engagement
    c1 = m.tick(1.01, (TOOL, DOWN))
    assert c1 is not None and c1.active and c1.engage == 1
    assert np.allclose(c1.dp, (0.0, 0.02, 0.0)) and np.allclose(c1.dR, np.eye(3).reshape(9))
    c2 = m.tick(1.2, ((0.55, 0.01, 0.65), DOWN))  # the arm moved: p0 stays the engagement's
    assert c2 is not None and c2.engage == 1 and np.allclose(c2.dp, (0.0, 0.02, 0.0))
    assert c2.seq > c1.seq
    holds = [m.tick(1.6, (TOOL, DOWN)) for _ in range(HOLD_REPEATS)]
    assert all(h is not None and not h.active and h.dp == c2.dp for h in holds)
    assert m.tick(1.7, (TOOL, DOWN)) is None and not m.busy
    m.on_target(Target((0.55, 0.05, 0.65), DOWN), 3.0)
    c3 = m.tick(3.0, ((0.55, 0.02, 0.65), DOWN))
    assert c3 is not None and c3.active and c3.engage == 2
    assert np.allclose(c3.dp, (0.0, 0.03, 0.0))  # rebased on where the arm is now
    h = m.hold()
    assert not h.active and not m.engaged


quats = st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: math.hypot(*q) > 0.1)
points = st.tuples(*[st.floats(-1.0, 1.0)] * 3)


@settings(max_examples=200, deadline=None)
@given(points, quats, points, quats)
def test_the_slave_goes_exactly_to_the_target(
    p0: tuple[float, ...], q0: tuple[float, ...], p: tuple[float, ...], q: tuple[float, ...]
) -> None:
    """PROTOCOL §2 slave: R0·dR and p0 + dp are the ROS target, whatever the start pose."""
    n0, n = math.hypot(*q0), math.hypot(*q)
    R0 = rotation_of(tuple(x / n0 for x in q0))  # type: ignore[arg-type]
    R = rotation_of(tuple(x / n for x in q))  # type: ignore[arg-type]
    m = TargetMaster(timeout_s=1.0, seq_start=0, engage_start=0)
    m.on_target(Target(p, R), 0.0)  # type: ignore[arg-type]
    c = m.tick(0.0, (p0, R0))
    assert c is not None
    R_slave = np.array(R0).reshape(3, 3) @ np.array(c.dR).reshape(3, 3)
    assert np.allclose(R_slave, np.array(R).reshape(3, 3), atol=1e-12)
    assert np.allclose(np.add(p0, c.dp), p, atol=1e-12)
    dR = np.array(c.dR).reshape(3, 3)
    assert np.linalg.norm(dR.T @ dR - np.eye(3)) < 1e-9 and np.linalg.det(dR) > 0


@settings(max_examples=200, deadline=None)
@given(quats)
def test_quaternion_round_trip(q: tuple[float, ...]) -> None:
    n = math.hypot(*q)
    R = rotation_of(tuple(x / n for x in q))  # type: ignore[arg-type]
    back = quat_of(R)
    assert np.allclose(rotation_of(back), R, atol=1e-12)
    ref = pin.Quaternion(np.array(R).reshape(3, 3))
    sign = 1.0 if ref.w >= 0 else -1.0
    assert np.allclose(back, sign * np.array([ref.x, ref.y, ref.z, ref.w]), atol=1e-12)
