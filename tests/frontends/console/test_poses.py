"""The console's scene geometry: quaternions, cylinders between two points, the commanded
target, the force arrow, the workspace box, and the virtual master's hand mapping through
eq. 5 and PROTOCOL §2. (The arm itself: test_arm.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from services.control.master.teleop import scaled_motion
from services.frontends.console.poses import (
    box_edges,
    cylinder_pose,
    force_arrow,
    hand_pose,
    rotation_z_to,
)
from services.geometry import R_from_wxyz, tool_target_pose

finite = st.floats(-3.0, 3.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
quat = (
    st.tuples(finite, finite, finite, finite)
    .filter(lambda q: float(np.linalg.norm(q)) > 1e-3)
    .map(lambda q: np.array(q) / np.linalg.norm(q))
)


@given(vec3.filter(lambda d: float(np.linalg.norm(d)) > 1e-3))
@example(np.array([0.0, 1e-5, -1.625]))  # nearly antiparallel to z: once inaccurate
@example(np.array([0.0, 1.192092896e-07, -1.0]))
def test_rotation_z_to_turns_z_onto_the_direction(d: np.ndarray) -> None:
    R = rotation_z_to(d)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(R @ [0, 0, 1], d / np.linalg.norm(d), atol=1e-9)


def test_rotation_z_to_straight_down() -> None:
    assert np.allclose(rotation_z_to([0, 0, -2.0]) @ [0, 0, 1], [0, 0, -1])


def test_cylinder_pose_joins_the_two_points() -> None:
    a, b = np.array([0.1, 0.2, 0.3]), np.array([0.4, -0.2, 0.8])
    centre, wxyz, length = cylinder_pose(a, b)
    assert np.allclose(centre, (a + b) / 2)
    assert length == pytest.approx(float(np.linalg.norm(b - a)))
    R = R_from_wxyz(wxyz)
    assert np.allclose(centre + R @ [0, 0, length / 2], b)
    assert np.allclose(centre - R @ [0, 0, length / 2], a)


def test_force_arrow_is_rotated_into_the_world_and_clipped() -> None:
    tool_R = np.diag([-1.0, 1.0, -1.0])  # tool z down
    pts = force_arrow([0.5, 0.0, 0.6], tool_R, [0.0, 0.0, 10.0], 0.01, 0.4)
    # +10 N along the tool's z (pointing down) is a downward arrow of 0.1 m.
    assert np.allclose(pts, [[0.5, 0.0, 0.6], [0.5, 0.0, 0.5]])
    long = force_arrow([0, 0, 0], np.eye(3), [300.0, 400.0, 0.0], 0.01, 0.4)
    assert np.allclose(long[1], [0.24, 0.32, 0.0])


def test_box_edges() -> None:
    edges = box_edges([0.25, -0.5, 0.4], [0.95, 0.5, 1.2])
    assert edges.shape == (12, 2, 3)
    lengths = sorted(float(np.linalg.norm(b - a)) for a, b in edges)
    assert lengths == pytest.approx([0.7] * 4 + [0.8] * 4 + [1.0] * 4)
    corners = {tuple(np.round(p, 9)) for e in edges for p in e}
    assert len(corners) == 8


@settings(max_examples=200)
@given(vec3, quat, vec3, quat)
def test_with_scale_one_the_tool_target_is_the_gizmo(
    E0: np.ndarray, q0: np.ndarray, E: np.ndarray, q: np.ndarray
) -> None:
    """The virtual master's promise: the hand engaged at the tool pose (E0, M0) = (p0, R0),
    then moved to the gizmo pose (E, M); with s_t = s_r = 1 and frame world, eq. 5 followed
    by PROTOCOL §2 gives a tool target equal to the gizmo pose."""
    p0, M0 = hand_pose(E0, q0)
    p, M = hand_pose(E, q)
    motion = scaled_motion(p0, M0, p, M, 1.0, 1.0)
    tp, tR = tool_target_pose(p0, M0, motion.dp, motion.dR, "world")
    assert np.allclose(tp, p, atol=1e-9)
    assert np.allclose(tR, M, atol=1e-6)


@given(vec3, quat, vec3, st.floats(0.05, 1.0))
def test_a_scaled_translation_moves_the_target_by_the_scaled_hand_motion(
    E0: np.ndarray, q0: np.ndarray, dE: np.ndarray, s_t: float
) -> None:
    p0, M0 = hand_pose(E0, q0)
    motion = scaled_motion(p0, M0, p0 + dE, M0, s_t, 1.0)
    tp, tR = tool_target_pose(p0, M0, motion.dp, motion.dR, "world")
    assert np.allclose(tp, p0 + s_t * dE, atol=1e-9)
    assert np.allclose(tR, M0, atol=1e-9)
