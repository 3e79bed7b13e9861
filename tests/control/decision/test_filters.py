"""The supervisor's pure math against hand-worked cases."""

from __future__ import annotations

import numpy as np
import pytest

from services.control.decision.filters import (
    admittance_step,
    clamp_box,
    clip_norm,
    deadband,
    effective_box,
    slow_near_box,
    without_motion_into,
)

TOOL_DOWN = np.diag([-1.0, 1.0, -1.0])


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


def test_slow_near_box_limits_only_motion_towards_a_near_face() -> None:
    lo, hi = (0.0, 0.0, 0.4), (1.0, 1.0, 1.0)
    zone, v = 0.02, 0.0001  # 2 cm zone, 0.1 mm per tick
    # 5 cm above the floor, 1 mm down: outside the zone all the way, untouched
    assert slow_near_box((0.5, 0.5, 0.45), (0.0, 0.0, -0.001), lo, hi, zone, v) == (
        (0.0, 0.0, -0.001),
        False,
    )
    # 2.05 cm above the floor, 1 mm down: free to the zone's edge (0.5 mm), then 0.1 mm
    step, slowed = slow_near_box((0.5, 0.5, 0.4205), (0.0, 0.0, -0.001), lo, hi, zone, v)
    assert slowed and step[2] == pytest.approx(-0.0006)
    # inside the zone: 0.1 mm down at most; sideways and upwards untouched
    step, slowed = slow_near_box((0.5, 0.5, 0.41), (0.002, -0.003, -0.001), lo, hi, zone, v)
    assert slowed and step == pytest.approx((0.002, -0.003, -0.0001))
    assert slow_near_box((0.5, 0.5, 0.41), (0.0, 0.0, 0.001), lo, hi, zone, v) == (
        (0.0, 0.0, 0.001),
        False,
    )
    # every face: towards x max from 1 cm inside it
    step, slowed = slow_near_box((0.99, 0.5, 0.6), (0.001, 0.0, 0.0), lo, hi, zone, v)
    assert slowed and step == pytest.approx((0.0001, 0.0, 0.0))
    # a slow step inside the zone passes unchanged
    assert slow_near_box((0.5, 0.5, 0.41), (0.0, 0.0, -0.00005), lo, hi, zone, v)[1] is False
