"""The supervisor's pure math against hand-worked cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.decision.filters import (
    admittance_step,
    clamp_box,
    clip_norm,
    deadband,
    effective_box,
    engagement_command,
    exp_so3,
    log_so3,
    operator_target,
    orthonormalize,
    without_motion_into,
)

TOOL_DOWN = np.diag([-1.0, 1.0, -1.0])


def test_operator_target_world_and_tool_modes() -> None:
    p0 = np.array([0.5, 0.1, 0.6])
    dR = exp_so3((0.0, 0.0, math.pi / 2))
    p, R = operator_target(p0, TOOL_DOWN, (0.01, 0.02, 0.03), dR, "world")
    assert np.allclose(p, [0.51, 0.12, 0.63])
    assert np.allclose(R, TOOL_DOWN @ dR)
    # tool mode: dp is in the tool frame at engagement (x → −x, z → −z for a tool pointing down)
    p, _ = operator_target(p0, TOOL_DOWN, (0.01, 0.02, 0.03), dR, "tool")
    assert np.allclose(p, [0.49, 0.12, 0.57])
    with pytest.raises(ValueError):
        operator_target(p0, TOOL_DOWN, (0, 0, 0), np.eye(3), "base")  # type: ignore[arg-type]


def test_engagement_command_inverts_the_mapping() -> None:
    p0 = np.array([0.5, 0.1, 0.6])
    R = TOOL_DOWN @ exp_so3((0.1, -0.2, 0.3))
    dp, dR = engagement_command(p0, TOOL_DOWN, (0.55, 0.0, 0.7), R)
    p, R2 = operator_target(p0, TOOL_DOWN, dp, dR, "world")
    assert np.allclose(p, [0.55, 0.0, 0.7])
    assert np.allclose(R2, R)


def test_so3_round_trip_including_near_pi() -> None:
    for w in ([0.0, 0.0, 0.0], [1e-9, 0, 0], [0.3, -0.2, 0.1], [0.0, math.pi - 1e-6, 0.0]):
        assert np.allclose(log_so3(exp_so3(w)), w, atol=1e-6)
    R = orthonormalize(exp_so3((0.2, 0.1, 0.0)) + 1e-4)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0


def test_contact_filter_removes_only_motion_into_the_contact() -> None:
    up = np.array([0.0, 0.0, 30.0])  # the table pushes the tool up
    inc, removed = without_motion_into((0.01, 0.02, -0.03), up)
    assert np.allclose(inc, [0.01, 0.02, 0.0])
    assert removed == pytest.approx(0.03)
    inc, removed = without_motion_into((0.0, 0.0, 0.02), up)  # away: kept
    assert np.allclose(inc, [0.0, 0.0, 0.02]) and removed == 0.0
    inc, removed = without_motion_into((0.0, 0.0, -0.02), np.zeros(3))  # no force: no filter
    assert np.allclose(inc, [0.0, 0.0, -0.02]) and removed == 0.0


def test_deadband_and_admittance() -> None:
    assert np.allclose(deadband((1.5, 0, 0), 2.0), 0.0)
    assert np.allclose(deadband((0, 5.0, 0), 2.0), [0, 3.0, 0])
    # 10 N, band 2 N, 0.002 m/(N·s), 2 ms → 8 N · 0.002 · 0.002 = 32 µm along the force
    assert np.allclose(admittance_step((10.0, 0, 0), 0.002, 2.0, 0.002), [3.2e-5, 0, 0])


def test_clip_norm() -> None:
    v, clipped = clip_norm((3.0, 4.0, 0.0), 1.0)
    assert np.allclose(v, [0.6, 0.8, 0.0]) and clipped
    v, clipped = clip_norm((0.3, 0.4, 0.0), 1.0)
    assert np.allclose(v, [0.3, 0.4, 0.0]) and not clipped


def test_box_clamp_and_the_grown_box() -> None:
    lo, hi = np.array([0.25, -0.5, 0.4]), np.array([0.95, 0.5, 1.2])
    assert np.allclose(clamp_box((1.2, 0.0, 0.2), lo, hi), [0.95, 0.0, 0.4])
    # a target outside (x = 1.1) may come back but never go further out
    lo2, hi2 = effective_box(lo, hi, (1.1, 0.0, 0.6))
    assert hi2[0] == pytest.approx(1.1) and lo2[0] == pytest.approx(0.25)
    assert np.allclose(clamp_box((1.3, 0.0, 0.6), lo2, hi2), [1.1, 0.0, 0.6])
    assert np.allclose(clamp_box((1.0, 0.0, 0.6), lo2, hi2), [1.0, 0.0, 0.6])
