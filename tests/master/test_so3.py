"""Rotation helpers: Rxyz and its inverse branches, exp/log, slerp."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from services.master.so3 import (
    exp_so3,
    is_rotation,
    log_so3,
    orthonormalize,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle,
    rxyz,
    rxyz_inv,
    rxyz_inv_near,
    slerp,
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
