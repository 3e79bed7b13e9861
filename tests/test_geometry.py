"""services.geometry: Rxyz and its inverse branches (eq. 5), exp/log, angles, slerp,
quaternions, the one rotation-validity check, and the eq. 2–3 tool target."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.bus import codec
from services.geometry import (
    I9,
    ORTHONORMAL_TOL,
    ROTATION_TOL,
    R_from_wxyz,
    angle_between,
    exp_so3,
    is_rotation,
    log9,
    log_so3,
    m9,
    mul9,
    mv9,
    ortho9,
    orthonormalize,
    quat_of_rotation,
    rot_x,
    rot_y,
    rot_z,
    rotation_about,
    rotation_angle,
    rotation_defect,
    rotation_of_quat,
    rotation_problem,
    rxyz,
    rxyz_inv,
    rxyz_inv_near,
    skew,
    slerp,
    tmul9,
    tool_target_point,
    tool_target_pose,
    vee,
    wxyz_from_R,
)

angle = st.floats(-math.pi, math.pi)
rotvec = st.lists(st.floats(-3.1, 3.1), min_size=3, max_size=3)


def test_rxyz_is_rx_ry_rz_in_that_order() -> None:
    np.testing.assert_allclose(rxyz([0.1, 0.2, 0.3]), rot_x(0.1) @ rot_y(0.2) @ rot_z(0.3))


@settings(max_examples=200, deadline=None)
@given(w=rotvec)
def test_principal_inverse_reconstructs_and_stays_on_its_branch(w: list[float]) -> None:
    R = exp_so3(w)
    a = rxyz_inv(R)
    np.testing.assert_allclose(rxyz(a), R, atol=1e-9)
    assert -math.pi / 2 - 1e-12 <= a[1] <= math.pi / 2 + 1e-12
    assert all(-math.pi - 1e-12 <= v <= math.pi + 1e-12 for v in (a[0], a[2]))


@settings(max_examples=100, deadline=None)
@given(ax=angle, az=angle, sign=st.sampled_from([-1.0, 1.0]), near=rotvec)
def test_inverse_at_gimbal_lock_reconstructs(ax: float, az: float, sign: float, near: list) -> None:
    R = rxyz([ax, sign * math.pi / 2, az])
    np.testing.assert_allclose(rxyz(rxyz_inv(R)), R, atol=1e-9)
    np.testing.assert_allclose(rxyz(rxyz_inv_near(R, near)), R, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(w=rotvec, near=st.lists(st.floats(-7.0, 7.0), min_size=3, max_size=3))
def test_near_inverse_reconstructs_and_is_no_farther_than_the_principal(
    w: list[float], near: list[float]
) -> None:
    R = exp_so3(w)
    a = rxyz_inv_near(R, near)
    np.testing.assert_allclose(rxyz(a), R, atol=1e-9)
    p = rxyz_inv(R)
    p_unwrapped = p + 2 * math.pi * np.round((np.array(near) - p) / (2 * math.pi))
    assert np.linalg.norm(a - near) <= np.linalg.norm(p_unwrapped - near) + 1e-9


@settings(max_examples=200, deadline=None)
@given(w=rotvec)
def test_exp_log_round_trip(w: list[float]) -> None:
    R = exp_so3(w)
    assert is_rotation(R)
    np.testing.assert_allclose(exp_so3(log_so3(R)), R, atol=1e-9)


def test_log_near_pi_and_zero() -> None:
    for axis in (np.array([1.0, 0, 0]), np.array([0, 1.0, 1.0]) / math.sqrt(2)):
        R = exp_so3(math.pi * axis)
        np.testing.assert_allclose(exp_so3(log_so3(R)), R, atol=1e-9)
    np.testing.assert_allclose(log_so3(np.eye(3)), np.zeros(3))


def test_slerp_endpoints_and_midpoint() -> None:
    A, B = rot_z(0.2), rot_z(1.0)
    np.testing.assert_allclose(slerp(A, B, 0.0), A, atol=1e-12)
    np.testing.assert_allclose(slerp(A, B, 1.0), B, atol=1e-12)
    np.testing.assert_allclose(slerp(A, B, 0.5), rot_z(0.6), atol=1e-12)


def test_orthonormalize_and_is_rotation() -> None:
    R = rot_x(0.4) + 1e-4
    assert not is_rotation(R)
    assert is_rotation(orthonormalize(R))
    assert not is_rotation(-np.eye(3))
    assert not is_rotation(np.full((3, 3), np.nan))
    assert abs(rotation_angle(rot_y(2.0)) - 2.0) < 1e-12


# --- moved from the decision, force and console tests -------------------------------------

TOOL_DOWN = np.diag([-1.0, 1.0, -1.0])
quats = st.tuples(
    st.floats(0.1, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)
)
finite = st.floats(-3.0, 3.0, allow_nan=False)
quat = (
    st.tuples(finite, finite, finite, finite)
    .filter(lambda q: float(np.linalg.norm(q)) > 1e-3)
    .map(lambda q: np.array(q) / np.linalg.norm(q))
)


def _rot(axis: str, angle: float) -> np.ndarray:
    return {"x": rot_x, "y": rot_y, "z": rot_z}[axis](angle)


def quat_to_R(q: tuple[float, float, float, float]) -> np.ndarray:
    return R_from_wxyz(q)


def test_tool_target_pose_world_and_tool_modes() -> None:
    p0 = np.array([0.5, 0.1, 0.6])
    dR = exp_so3((0.0, 0.0, math.pi / 2))
    p, R = tool_target_pose(p0, TOOL_DOWN, (0.01, 0.02, 0.03), dR, "world")
    assert np.allclose(p, [0.51, 0.12, 0.63])
    assert np.allclose(R, TOOL_DOWN @ dR)
    # tool mode: dp is in the tool frame at engagement (x → −x, z → −z for a tool pointing down)
    p, _ = tool_target_pose(p0, TOOL_DOWN, (0.01, 0.02, 0.03), dR, "tool")
    assert np.allclose(p, [0.49, 0.12, 0.57])
    with pytest.raises(ValueError):
        tool_target_pose(p0, TOOL_DOWN, (0, 0, 0), np.eye(3), "base")  # type: ignore[arg-type]


def test_so3_round_trip_including_near_pi() -> None:
    for w in ([0.0, 0.0, 0.0], [1e-9, 0, 0], [0.3, -0.2, 0.1], [0.0, math.pi - 1e-6, 0.0]):
        assert np.allclose(log_so3(exp_so3(w)), w, atol=1e-6)
    R = orthonormalize(exp_so3((0.2, 0.1, 0.0)) + 1e-4)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0


@settings(max_examples=300, deadline=None)
@given(q=quats)
def test_log_is_the_inverse_of_exp(q: tuple[float, float, float, float]) -> None:
    R = quat_to_R(q)
    np.testing.assert_allclose(exp_so3(log_so3(R)), R, atol=1e-9)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, 1.0, math.pi - 1e-6, math.pi])
def test_log_exp_at_the_edges(angle: float) -> None:
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    R = exp_so3(angle * axis)
    np.testing.assert_allclose(exp_so3(log_so3(R)), R, atol=1e-9)
    assert np.linalg.norm(log_so3(R)) == pytest.approx(angle, abs=1e-9)


def test_quaternion_of_hand_worked_rotations() -> None:
    assert np.allclose(wxyz_from_R(np.eye(3)), [1, 0, 0, 0])
    h = np.sqrt(0.5)
    assert np.allclose(wxyz_from_R(_rot("z", np.pi / 2)), [h, 0, 0, h])
    # 180° about x: the trace branch fails, the diagonal branch takes over.
    assert np.allclose(wxyz_from_R(np.diag([1.0, -1.0, -1.0])), [0, 1, 0, 0])
    # The home tool orientation (tool z down): 180° about y.
    assert np.allclose(wxyz_from_R(np.diag([-1.0, 1.0, -1.0])), [0, 0, 1, 0])


@given(quat)
def test_quaternion_round_trip(q: np.ndarray) -> None:
    R = R_from_wxyz(q)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    back = wxyz_from_R(R)
    # q and −q are the same rotation.
    assert np.allclose(back, q, atol=1e-7) or np.allclose(back, -q, atol=1e-7)


def test_a_null_quaternion_is_refused() -> None:
    with pytest.raises(ValueError):
        R_from_wxyz([0.0, 0.0, 0.0, 0.0])


def test_commanded_target_world_and_tool_frames() -> None:
    """PROTOCOL §2 by hand: R0 = Rz(90°), dp = (0.1, 0, 0), dR = Rx(90°)."""
    p0, R0 = np.array([0.5, 0.0, 0.6]), _rot("z", np.pi / 2)
    dp, dR = np.array([0.1, 0.0, 0.0]), _rot("x", np.pi / 2)
    p, R = tool_target_pose(p0, R0, dp, dR, "world")
    assert np.allclose(p, [0.6, 0.0, 0.6])
    assert np.allclose(R, R0 @ dR)
    p, _ = tool_target_pose(p0, R0, dp, dR, "tool")
    assert np.allclose(p, [0.5, 0.1, 0.6])  # the tool's x axis is the world's y


def test_rotation_angle_of_a_known_turn() -> None:
    Rz = rot_z(0.3)
    assert angle_between(np.eye(3), Rz) == pytest.approx(0.3, rel=1e-12)
    assert angle_between(Rz, Rz) == 0.0


# --- properties -------------------------------------------------------------------------

rotvec_full = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(
    lambda w: 1e-6 < float(np.linalg.norm(w)) <= 1.0
)


@settings(max_examples=300, deadline=None)
@given(w=rotvec_full, angle=st.floats(0.0, math.pi * (1 - 1e-9)))
def test_log_inverts_exp_for_every_angle_below_pi(w: tuple[float, ...], angle: float) -> None:
    v = np.array(w) / np.linalg.norm(w) * angle
    np.testing.assert_allclose(log_so3(exp_so3(v)), v, atol=1e-7)
    assert rotation_angle(exp_so3(v)) == pytest.approx(angle, abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(wa=rotvec, wb=rotvec)
def test_angle_between_is_the_angle_of_the_relative_rotation(
    wa: list[float], wb: list[float]
) -> None:
    Ra, Rb = exp_so3(wa), exp_so3(wb)
    assert angle_between(Ra, Rb) == pytest.approx(rotation_angle(Ra.T @ Rb), abs=1e-7)
    assert angle_between(Ra, Rb) == pytest.approx(angle_between(Rb, Ra), abs=1e-12)


@settings(max_examples=200, deadline=None)
@given(
    a=st.tuples(st.floats(-math.pi, math.pi), st.floats(-1.5, 1.5), st.floats(-math.pi, math.pi))
)
def test_rxyz_inverse_returns_the_angles_on_the_principal_branch(
    a: tuple[float, float, float],
) -> None:
    got = rxyz_inv(rxyz(a))
    # On the principal branch (|a_y| < π/2) the angles come back themselves, up to 2π.
    d = (got - np.array(a) + math.pi) % (2 * math.pi) - math.pi
    np.testing.assert_allclose(d, 0.0, atol=1e-7)


def test_skew_and_vee_are_inverse_and_skew_is_the_cross_product() -> None:
    w, v = np.array([0.3, -1.2, 2.0]), np.array([-0.5, 0.1, 0.7])
    np.testing.assert_allclose(skew(w) @ v, np.cross(w, v))
    np.testing.assert_allclose(vee(skew(w)), w)


def test_rotation_about_an_unnormalised_axis() -> None:
    np.testing.assert_allclose(rotation_about([0.0, 0.0, 5.0], 0.7), rot_z(0.7), atol=1e-15)


# --- the one validity check ---------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(w=rotvec, eps=st.floats(-1e-3, 1e-3), i=st.integers(0, 8))
def test_validity_agrees_with_the_numpy_definition(w: list[float], eps: float, i: int) -> None:
    """One check, one tolerance: ‖RᵀR − I‖_F ≤ ROTATION_TOL and det R ≥ 0, for a 3×3 array
    and (`rotation_defect`, the codec's) for 9 plain floats."""
    R = exp_so3(w)
    R.flat[i] += eps
    expected = bool(np.linalg.norm(R.T @ R - np.eye(3)) <= ROTATION_TOL and np.linalg.det(R) >= 0.0)
    assert is_rotation(R) is expected
    assert not is_rotation(R.reshape(9))  # a shape error, never a rotation
    assert (rotation_problem(R) is None) is expected
    assert codec.rotation_defect is rotation_defect
    err, det = rotation_defect(R.reshape(9).tolist())
    assert err == pytest.approx(float(np.linalg.norm(R.T @ R - np.eye(3))), rel=1e-9, abs=1e-15)
    assert det == pytest.approx(float(np.linalg.det(R)), rel=1e-9, abs=1e-15)


@pytest.mark.parametrize(
    ("R", "why"),
    [
        (np.diag([1.0, 1.0, -1.0]), "a reflection"),
        (np.eye(3) * (1 + 1e-6), "not orthonormal"),
        (np.full((3, 3), np.inf), "not finite"),
        (np.eye(4), "not a 3x3 matrix"),
        (np.eye(3).reshape(9), "not a 3x3 matrix"),
    ],
)
def test_rotation_problem_says_why(R: np.ndarray, why: str) -> None:
    problem = rotation_problem(R)
    assert problem is not None and problem.startswith(why)
    assert not is_rotation(R)


def test_orthonormalize_leaves_a_clean_rotation_untouched_and_repairs_drift() -> None:
    R = rot_x(0.3) @ rot_y(-1.1)
    assert orthonormalize(R) is R  # within ORTHONORMAL_TOL: no SVD
    drifted = R * (1 + 10 * ORTHONORMAL_TOL)
    fixed = orthonormalize(drifted)
    assert fixed is not drifted
    assert rotation_defect(fixed.reshape(9).tolist())[0] < ORTHONORMAL_TOL
    np.testing.assert_allclose(fixed, R, atol=1e-8)


# --- quaternions --------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(q=quat)
def test_plain_float_and_array_quaternions_agree(q: np.ndarray) -> None:
    w, x, y, z = q.tolist()
    r = rotation_of_quat(w, x, y, z)
    np.testing.assert_allclose(np.array(r).reshape(3, 3), R_from_wxyz(q))
    assert quat_of_rotation(r) == pytest.approx(tuple(wxyz_from_R(np.array(r))))


# --- the eq. 2 tool point -----------------------------------------------------------------


def test_tool_target_point_is_the_point_of_the_pose() -> None:
    p0, R0, dp = np.array([0.5, 0.1, 0.6]), TOOL_DOWN @ rot_z(0.4), np.array([0.01, 0.0, -0.02])
    for frame in ("world", "tool"):
        p, _ = tool_target_pose(p0, R0, dp, np.eye(3), frame)  # type: ignore[arg-type]
        np.testing.assert_array_equal(tool_target_point(p0, R0, dp, frame), p)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="frame"):
        tool_target_point(p0, R0, dp, "wrist")  # type: ignore[arg-type]


_unit = st.floats(-1.0, 1.0, allow_nan=False)


@given(
    st.lists(_unit, min_size=3, max_size=3),
    st.lists(_unit, min_size=3, max_size=3),
    st.lists(st.floats(-10.0, 10.0, allow_nan=False), min_size=3, max_size=3),
)
def test_plain_float_products_agree_with_numpy(
    wa: list[float], wb: list[float], v: list[float]
) -> None:
    A, B = exp_so3(np.array(wa) * 3.0), exp_so3(np.array(wb) * 3.0)
    assert np.allclose(np.reshape(mul9(m9(A), m9(B)), (3, 3)), A @ B, atol=1e-15)
    assert np.allclose(np.reshape(tmul9(m9(A), m9(B)), (3, 3)), A.T @ B, atol=1e-15)
    assert np.allclose(mv9(m9(A), (v[0], v[1], v[2])), A @ np.array(v), atol=1e-13)


@given(st.lists(_unit, min_size=3, max_size=3), st.floats(0.0, math.pi))
def test_plain_float_log_matches_the_array_log_at_every_angle(
    axis: list[float], angle: float
) -> None:
    a = np.array(axis)
    if np.linalg.norm(a) < 1e-3:
        a = np.array([0.0, 0.0, 1.0])
    R = rotation_about(a, angle)
    assert np.allclose(log9(m9(R)), log_so3(R), atol=1e-12)
    assert np.allclose(exp_so3(np.array(log9(m9(R)))), R, atol=1e-9)


def test_plain_float_orthonormalize_keeps_a_rotation_and_repairs_drift() -> None:
    R = m9(exp_so3((0.3, -0.2, 0.1)))
    assert ortho9(R) is R  # nothing to repair: the same tuple
    drifted = m9((R[0] * (1 + 1e-7), *R[1:]))
    fixed = ortho9(drifted)
    assert rotation_defect(fixed)[0] < ORTHONORMAL_TOL
    assert np.allclose(np.reshape(fixed, (3, 3)), orthonormalize(np.reshape(drifted, (3, 3))))
    assert ortho9(I9) == I9
