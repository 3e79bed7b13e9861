"""The objects' math every view shares (services/world/workcell/bodies.py): the bottle's
liquid on top of its physics pose (W3, W4) and task 2's stack count, plus a bottle the
physics tilts past its spill angle spilling and weighing less."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.arm.model import load_model
from services.geometry import rot_x
from services.world.workcell.bodies import (
    holdable_volume_m3,
    placed_bodies,
    spill_step,
    spill_tilt_rad,
    stack_heights,
)
from services.world.workcell.engine import CellPhysics
from services.world.workcell.scene import default_scene

R_BOTTLE, H_BOTTLE, L_BOTTLE = 0.035, 0.20, 0.18


# --- W3, W4: liquid ----------------------------------------------------------------------------
def test_holdable_volume_hand_worked() -> None:
    full = math.pi * R_BOTTLE**2 * H_BOTTLE
    assert holdable_volume_m3(R_BOTTLE, H_BOTTLE, 0.0) == pytest.approx(full)
    t = math.radians(30.0)
    expected = math.pi * R_BOTTLE**2 * (H_BOTTLE - R_BOTTLE * math.tan(t))
    assert holdable_volume_m3(R_BOTTLE, H_BOTTLE, t) == pytest.approx(expected)
    assert holdable_volume_m3(R_BOTTLE, H_BOTTLE, math.pi / 2) == 0.0
    # the default bottle spills past atan(0.02 / 0.035) = 29.74°
    assert math.degrees(spill_tilt_rad(R_BOTTLE, H_BOTTLE, L_BOTTLE)) == pytest.approx(
        29.7449, abs=1e-3
    )


def test_holdable_volume_is_continuous_where_the_surface_reaches_the_base() -> None:
    t_edge = math.atan(H_BOTTLE / (2 * R_BOTTLE))
    below = holdable_volume_m3(R_BOTTLE, H_BOTTLE, t_edge - 1e-7)
    above = holdable_volume_m3(R_BOTTLE, H_BOTTLE, t_edge + 1e-7)
    assert above == pytest.approx(below, rel=2e-3)


@settings(max_examples=200, deadline=None)
@given(a=st.floats(0.0, math.pi / 2), b=st.floats(0.0, math.pi / 2))
def test_property_holdable_volume_shrinks_with_the_tilt(a: float, b: float) -> None:
    lo, hi = sorted((a, b))
    v_lo = holdable_volume_m3(R_BOTTLE, H_BOTTLE, lo)
    v_hi = holdable_volume_m3(R_BOTTLE, H_BOTTLE, hi)
    full = math.pi * R_BOTTLE**2 * H_BOTTLE
    assert 0.0 <= v_hi <= v_lo * (1 + 1e-12) <= full * (1 + 1e-9)


@settings(max_examples=200, deadline=None)
@given(
    tilts=st.lists(st.floats(0.0, math.pi / 2), min_size=1, max_size=30),
    dt=st.floats(0.001, 0.05),
)
def test_property_no_spill_below_the_spill_tilt_and_never_below_the_holdable_volume(
    tilts: list[float], dt: float
) -> None:
    v0 = math.pi * R_BOTTLE**2 * L_BOTTLE
    limit = spill_tilt_rad(R_BOTTLE, H_BOTTLE, L_BOTTLE)
    v = v0
    max_tilt = 0.0
    for t in tilts:
        v_max = holdable_volume_m3(R_BOTTLE, H_BOTTLE, t)
        before = v
        v = spill_step(v, v_max, 20.0, dt)
        max_tilt = max(max_tilt, t)
        assert v <= before
        assert v >= min(before, v_max) - 1e-15
        if max_tilt < limit - 1e-9:
            assert v == v0


def test_spill_rate_is_proportional_to_the_excess() -> None:
    v = spill_step(2.0, 1.0, 10.0, 0.01)
    assert v == pytest.approx(1.0 + math.exp(-0.1))
    assert spill_step(0.5, 1.0, 10.0, 0.01) == 0.5


def test_stack_heights_count_columns() -> None:
    bodies = [replace(b, on="table") for b in placed_bodies(default_scene())]
    assert stack_heights(bodies) == {"block0": 1, "block1": 1, "block2": 1}


def test_a_bottle_the_physics_tilts_past_its_spill_angle_spills_and_lightens() -> None:
    ph = CellPhysics(load_model("puma560"), default_scene())
    b = ph.body("bottle")
    full = b.liquid_m3
    mass0 = float(ph.model.body_mass[ph.cell.objects["bottle"]])
    # Lying on the table (tilted 90°, 5 cm up): everything above the lowest rim point leaves.
    ph.place("bottle", b.p + np.array([0.0, 0.0, 0.05]), rot_x(math.pi / 2))
    events = [e.kind for _ in range(50) for e in ph.step(10)]
    after = ph.body("bottle")
    assert "spill" in events
    assert after.spilled_m3 > 0.9 * full and after.liquid_m3 < 0.1 * full
    assert math.degrees(after.max_tilt_rad) > 60.0
    lost = mass0 - float(ph.model.body_mass[ph.cell.objects["bottle"]])
    assert lost == pytest.approx(1e3 * after.spilled_m3, rel=1e-6)
