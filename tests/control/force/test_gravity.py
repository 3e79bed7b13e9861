"""Gravity compensation: a resting tool reads ≈ 0 in any orientation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from services.control.force.gravity import ToolLoad, compensate
from services.control.force.model import WristModel
from services.control.force.sim_sensor import SimSensor
from tests.control.force.helpers import quat_to_R, rot

G = 9.81
DOWN = np.diag([1.0, -1.0, -1.0])  # tool z pointing at the floor
FREE_SPACE = (0.0, 0.0, 3.0)  # above everything in the workcell


def test_weight_of_a_tool_pointing_down() -> None:
    # Tool z down: the weight pulls along +z_tool; the centre of mass is on the axis: no moment.
    f, c = ToolLoad(1.0, (0.0, 0.0, -0.1), G).wrench(DOWN)
    assert_allclose(f, [0, 0, G], atol=1e-12)
    assert_allclose(c, [0, 0, 0], atol=1e-12)


def test_weight_of_a_horizontal_tool_has_a_lever() -> None:
    # Tool z along world x (R = Ry(90°)): the weight (world −z) is along tool +x;
    # c = (0, 0, −0.1) × (m g, 0, 0) = (0, −0.1 m g, 0).
    f, c = ToolLoad(2.0, (0.0, 0.0, -0.1), G).wrench(rot("y", math.pi / 2))
    assert_allclose(f, [2 * G, 0, 0], atol=1e-12)
    assert_allclose(c, [0, -0.1 * 2 * G, 0], atol=1e-12)


def test_load_is_validated() -> None:
    with pytest.raises(ValueError, match="mass_kg"):
        ToolLoad(-1.0)
    with pytest.raises(ValueError, match="com_m"):
        ToolLoad(1.0, (0.0, float("inf"), 0.0))


quats = st.tuples(
    st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)
).filter(lambda q: sum(x * x for x in q) > 1e-3)


@settings(max_examples=150, deadline=None)
@given(
    q=quats,
    mass=st.floats(0.0, 5.0),
    com=st.tuples(*[st.floats(-0.2, 0.2)] * 3),
    q_et=quats,
)
def test_resting_tool_reads_zero_in_any_orientation(
    q: tuple[float, float, float, float],
    mass: float,
    com: tuple[float, float, float],
    q_et: tuple[float, float, float, float],
) -> None:
    """Weight in the raw signals (through the inverse of eq. 4), removed after eq. 4."""
    load = ToolLoad(mass, com, G)
    wrist = WristModel(R_et=quat_to_R(q_et), p_et=np.array([0.01, 0.0, 0.2]))
    sensor = SimSensor(wrist, load)
    sensor.open()
    R = quat_to_R(q)
    sensor.update_pose(FREE_SPACE, R)
    reading = sensor.read()
    assert reading is not None
    f, c = wrist.wrench_from_signals(reading.values)
    raw_norm = float(np.linalg.norm(f))
    assert raw_norm == pytest.approx(mass * G, abs=1e-6)  # the raw reading has the weight
    f, c = compensate(f, c, load, R)
    assert_allclose(f, 0, atol=1e-6)
    assert_allclose(c, 0, atol=1e-6)
