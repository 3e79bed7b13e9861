"""The workcell model (services/world/workcell/physics.py): hand-worked cases and properties.

Safety-relevant behaviour as hypothesis properties: nothing is grasped outside the grasp
region; a carried object follows the tool rigidly; a released object always comes to rest
on a surface without sinking into anything; liquid never spills below the spill tilt and
never more than the excess above it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from services.geometry import exp_so3, rot_x, rot_z
from services.world.workcell.physics import (
    PhysicsParams,
    WorkcellSim,
    aabb,
    holdable_volume_m3,
    in_grasp_region,
    penetration_m,
    spill_step,
    spill_tilt_rad,
    stack_heights,
    tilt_of,
    tipping_angle,
    top_centre,
)
from services.world.workcell.scene import BLOCK_SIZE_M, TABLE, Box, Cylinder, Scene, default_scene

DOWN = np.diag([-1.0, 1.0, -1.0])
TOP = TABLE.top_z
DT = 0.01
H = BLOCK_SIZE_M
R_BOTTLE, H_BOTTLE, L_BOTTLE = 0.035, 0.20, 0.18


def settle(
    sim: WorkcellSim, tool_p: object = (0.55, 0.0, 0.8), grip: float = 0.0, n: int = 60
) -> list[str]:
    """Step with the tool parked above everything; the kinds of the events."""
    kinds = []
    for _ in range(n):
        kinds += [e.kind for e in sim.step(np.asarray(tool_p), DOWN, grip, DT)]
    return kinds


def grasp(sim: WorkcellSim, name: str, gap_m: float = 0.008) -> np.ndarray:
    """Put the palm gap_m above `name`'s top, close; the tool point."""
    b = sim.body(name)
    tool = top_centre(sim.scene.solid(name), b.p, b.R) + np.array([0.0, 0.0, gap_m])
    sim.step(tool, DOWN, 0.0, DT)
    events = sim.step(tool, DOWN, 1.0, DT)
    assert [e.kind for e in events] == ["grasp"]
    return tool


# --- the scene -------------------------------------------------------------------------------
def test_default_scene_objects_rest_on_the_table() -> None:
    sim = WorkcellSim(default_scene())
    bodies = {b.name: b for b in sim.bodies()}
    assert sorted(bodies) == ["block0", "block1", "block2", "bottle"]
    assert all(b.phase == "resting" and b.on == "table" for b in bodies.values())
    assert bodies["bottle"].liquid_m3 == pytest.approx(math.pi * R_BOTTLE**2 * L_BOTTLE)


def test_scene_moved_keeps_the_rest() -> None:
    scene = default_scene()
    moved = scene.moved({"block1": (0.6, 0.1, 0.5), "bottle": (0.7, 0.0, 0.4)})
    assert moved.box("block1").center == (0.6, 0.1, 0.5)
    assert moved.cylinder("bottle").base == (0.7, 0.0, 0.4)
    assert moved.box("block0") == scene.box("block0")
    assert moved.box("table") == TABLE
    assert [s.name for s in moved.movables()] == ["block0", "block1", "block2", "bottle"]


# --- W1: the gripper ---------------------------------------------------------------------------
def test_grasp_carry_and_release_onto_a_block_stacks_it_exactly() -> None:
    sim = WorkcellSim(default_scene())
    tool = grasp(sim, "block1")
    assert sim.held == "block1"
    # carry it over block0, 4 mm off its axis and turned 6°, release 3 mm above
    over = np.array([0.504, -0.2, TOP + H + 0.003 + H + 0.008])
    R = rot_z(math.radians(6.0)) @ DOWN
    sim.step(tool + np.array([0, 0, 0.1]), DOWN, 1.0, DT)
    sim.step(over, R, 1.0, DT)
    assert sim.step(over, R, 0.0, DT)[0].kind == "release"
    kinds = settle(sim, over + np.array([0, 0, 0.05]))
    b = sim.body("block1")
    assert kinds == ["settled"]
    assert b.on == "block0" and b.phase == "resting"
    np.testing.assert_allclose(b.p, [0.5, -0.2, TOP + 1.5 * H], atol=1e-12)
    np.testing.assert_allclose(b.R, np.eye(3), atol=1e-12)
    assert stack_heights(sim.bodies())["block1"] == 2


def test_closing_away_from_an_object_grasps_nothing() -> None:
    sim = WorkcellSim(default_scene())
    events = sim.step(np.array([0.6, 0.1, 0.6]), DOWN, 1.0, DT)
    assert [e.kind for e in events] == ["missed"]
    assert sim.held is None and sim.counters["missed"] == 1


def test_a_closed_gripper_cannot_pick_up() -> None:
    sim = WorkcellSim(default_scene())
    sim.step(np.array([0.5, -0.1, 0.6]), DOWN, 1.0, DT)  # closed in the air
    b = sim.body("block1")
    tool = top_centre(sim.scene.solid("block1"), b.p, b.R) + np.array([0, 0, 0.008])
    assert sim.step(tool, DOWN, 1.0, DT) == []
    assert sim.held is None


@settings(max_examples=200, deadline=None)
@given(
    dx=st.floats(-0.05, 0.05),
    dy=st.floats(-0.05, 0.05),
    dz=st.floats(-0.05, 0.06),
    w=st.tuples(*[st.floats(-1.0, 1.0)] * 3),
)
def test_property_grasp_only_inside_the_grasp_region(
    dx: float, dy: float, dz: float, w: tuple[float, float, float]
) -> None:
    params = PhysicsParams()
    # not on the region's boundary, where rounding decides
    assume(abs(math.hypot(dx, dy) - params.grasp_xy_m) > 1e-9)
    assume(abs(dz - params.grasp_gap_m) > 1e-9 and abs(dz) > 1e-9)
    sim = WorkcellSim(default_scene(), params)
    b = sim.body("block1")
    tool_p = top_centre(sim.scene.solid("block1"), b.p, b.R) + np.array([dx, dy, dz])
    tool_R = exp_so3(np.asarray(w)) @ DOWN
    inside = (
        math.hypot(dx, dy) <= params.grasp_xy_m
        and -1e-9 <= dz <= params.grasp_gap_m
        and math.degrees(tilt_of(tool_R @ DOWN)) <= params.max_grasp_angle_deg
    )
    assert in_grasp_region(sim.scene.solid("block1"), b.p, b.R, tool_p, tool_R, params) == inside
    sim.step(tool_p, tool_R, 1.0, DT)
    if sim.held is not None:
        assert inside or sim.held != "block1"
    elif inside:
        pytest.fail("a closed gripper in the grasp region grasped nothing")


@settings(max_examples=100, deadline=None)
@given(
    path=st.lists(
        st.tuples(
            st.floats(-0.1, 0.1), st.floats(-0.1, 0.1), st.floats(0.0, 0.2), st.floats(-3, 3)
        ),
        min_size=1,
        max_size=8,
    )
)
def test_property_a_carried_object_moves_rigidly_with_the_tool(
    path: list[tuple[float, float, float, float]],
) -> None:
    sim = WorkcellSim(default_scene())
    tool0 = grasp(sim, "bottle")
    b0 = sim.body("bottle")
    rel_p, rel_R = DOWN.T @ (b0.p - tool0), DOWN.T @ b0.R
    for dx, dy, dz, yaw in path:
        p = tool0 + np.array([dx, dy, dz + 0.05])
        R = rot_z(yaw) @ rot_x(0.1 * yaw) @ DOWN
        sim.step(p, R, 1.0, DT)
        b = sim.body("bottle")
        np.testing.assert_allclose(R.T @ (b.p - p), rel_p, atol=1e-12)
        np.testing.assert_allclose(R.T @ b.R, rel_R, atol=1e-12)


# --- W2: falling, support, stacking ----------------------------------------------------------
@settings(max_examples=150, deadline=None)
@given(
    x=st.floats(0.40, 0.80),
    y=st.floats(-0.40, 0.40),
    drop=st.floats(0.0, 0.3),
    yaw=st.floats(-math.pi, math.pi),
    tilt=st.floats(0.0, 1.2),
)
def test_property_a_released_block_comes_to_rest_on_a_surface(
    x: float, y: float, drop: float, yaw: float, tilt: float
) -> None:
    sim = WorkcellSim(default_scene())
    tool = grasp(sim, "block2")
    R = rot_z(yaw) @ rot_x(tilt) @ DOWN
    sim.step(tool + np.array([0.0, 0.0, 0.35]), DOWN, 1.0, DT)
    carry = np.array([x, y, TOP + 0.4 + drop])
    sim.step(carry, R, 1.0, DT)
    sim.step(carry, R, 0.0, DT)
    settle(sim, carry + np.array([0.0, 0.0, 0.3]), n=200)
    bodies = sim.bodies()
    b = sim.body("block2")
    assert b.phase in ("resting", "toppled")
    lo, hi = aabb(sim.scene.solid("block2"), b.p, b.R)
    if b.on == "floor":
        assert lo[2] == pytest.approx(0.0, abs=1e-9)
    else:
        if b.on == "table":
            top = TABLE.top_z
        else:
            s = sim.body(b.on)
            top = aabb(sim.scene.solid(b.on), s.p, s.R)[1][2]
        assert lo[2] == pytest.approx(top, abs=1e-9)
    if b.phase == "resting":
        assert tilt_of(b.R) == pytest.approx(0.0, abs=1e-9)
    for other in bodies:
        if other.name == "block2":
            continue
        olo, ohi = aabb(sim.scene.solid(other.name), other.p, other.R)
        assert penetration_m(lo, hi, olo, ohi) <= 1e-6


def test_a_block_released_with_its_centre_past_an_edge_slides_off() -> None:
    sim = WorkcellSim(default_scene())
    tool = grasp(sim, "block1")
    sim.step(tool + np.array([0, 0, 0.1]), DOWN, 1.0, DT)
    # 30 mm off block0's axis: the centre is past block0's edge (25 mm)
    over = np.array([0.53, -0.2, TOP + 2 * H + 0.01 + 0.033])
    sim.step(over, DOWN, 1.0, DT)
    sim.step(over, DOWN, 0.0, DT)
    settle(sim, over + np.array([0, 0, 0.1]), n=100)
    b = sim.body("block1")
    assert b.on == "table" and b.phase == "resting"
    lo, _ = aabb(sim.scene.solid("block1"), b.p, b.R)
    b0 = sim.body("block0")
    _, hi0 = aabb(sim.scene.solid("block0"), b0.p, b0.R)
    assert lo[0] >= hi0[0]


def test_a_covered_block_cannot_be_grasped() -> None:
    sim = WorkcellSim(default_scene())
    tool = grasp(sim, "block1")
    sim.step(tool + np.array([0, 0, 0.1]), DOWN, 1.0, DT)
    over = np.array([0.5, -0.2, TOP + 2 * H + 0.003 + 0.008])
    sim.step(over, DOWN, 1.0, DT)
    sim.step(over, DOWN, 0.0, DT)
    settle(sim, over + np.array([0, 0, 0.1]))
    assert sim.body("block1").on == "block0"
    b0 = sim.body("block0")
    palm = top_centre(sim.scene.solid("block0"), b0.p, b0.R) + np.array([0, 0, 0.008])
    assert [e.kind for e in sim.step(palm, DOWN, 1.0, DT)] == ["missed"]
    assert sim.held is None


def test_a_bottle_released_tilted_past_its_tipping_angle_falls_over_and_empties() -> None:
    sim = WorkcellSim(default_scene())
    tool = grasp(sim, "bottle")
    sim.step(tool + np.array([0, 0, 0.05]), DOWN, 1.0, DT)
    tilt = tipping_angle(sim.scene.solid("bottle")) + 0.1
    R = rot_x(tilt) @ DOWN
    p = np.array([0.7, 0.1, 0.75])
    sim.step(p, R, 1.0, DT)
    sim.step(p, R, 0.0, DT)
    kinds = settle(sim, p + np.array([0, 0, 0.2]), n=300)
    b = sim.body("bottle")
    assert "toppled" in kinds and b.phase == "toppled"
    assert b.tilt_rad == pytest.approx(math.pi / 2, abs=1e-9)
    assert b.liquid_m3 == pytest.approx(0.0, abs=1e-9)
    assert b.spilled_m3 == pytest.approx(math.pi * R_BOTTLE**2 * L_BOTTLE, rel=1e-9)


def test_stack_heights_count_columns() -> None:
    sim = WorkcellSim(default_scene())
    assert stack_heights(sim.bodies()) == {"block0": 1, "block1": 1, "block2": 1}


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


def test_a_carried_bottle_spills_past_30_degrees_and_not_before() -> None:
    sim = WorkcellSim(default_scene())
    tool = grasp(sim, "bottle")
    up = tool + np.array([0, 0, 0.1])
    for deg in range(0, 29):
        sim.step(up, rot_x(math.radians(deg)) @ DOWN, 1.0, DT)
    assert sim.body("bottle").spilled_m3 == 0.0
    events = []
    for _ in range(50):
        events += sim.step(up, rot_x(math.radians(40.0)) @ DOWN, 1.0, DT)
    b = sim.body("bottle")
    assert [e.kind for e in events] == ["spill"]
    expected = math.pi * R_BOTTLE**2 * L_BOTTLE - holdable_volume_m3(
        R_BOTTLE, H_BOTTLE, math.radians(40.0)
    )
    assert b.spilled_m3 == pytest.approx(expected, rel=1e-3)
    assert math.degrees(b.max_tilt_rad) == pytest.approx(40.0)


def test_collisions_of_a_carried_object_are_counted_once_per_contact() -> None:
    sim = WorkcellSim(default_scene())
    tool = grasp(sim, "block2")
    sim.step(tool + np.array([0, 0, 0.06]), DOWN, 1.0, DT)
    # push it down into block1's place, 10 mm into block1
    into = np.array([0.5, -0.1, TOP + H + 0.5 * H - 0.01 + 0.5 * H + 0.008])
    kinds = [e.kind for e in sim.step(into, DOWN, 1.0, DT) + sim.step(into, DOWN, 1.0, DT)]
    assert kinds == ["collision"]
    assert sim.max_penetration_m == pytest.approx(0.01, abs=1e-9)


def test_physics_params_are_checked() -> None:
    from services.bus.errors import ConfigError

    with pytest.raises(ConfigError, match="close_threshold"):
        PhysicsParams(close_threshold=1.0)
    with pytest.raises(ConfigError, match="grasp_xy_m"):
        PhysicsParams(grasp_xy_m=0.0)


def test_a_scene_with_a_block_in_the_air_lets_it_fall_at_start() -> None:
    scene = Scene(
        boxes=(TABLE, Box("b", center=(0.6, 0.0, TOP + 0.1), size=(H, H, H), movable=True)),
        cylinders=(Cylinder("c", base=(0.7, 0.0, TOP), radius=0.02, height=0.1, movable=True),),
    )
    sim = WorkcellSim(scene)
    assert sim.body("b").phase == "falling"
    assert settle(sim) == ["settled"]
    assert sim.body("b").p[2] == pytest.approx(TOP + 0.5 * H)
    assert sim.body("c").on == "table" and sim.body("c").liquid_m3 == 0.0


def test_a_block_released_pushed_into_another_comes_to_rest_on_top_of_it() -> None:
    sim = WorkcellSim(default_scene())
    tool = grasp(sim, "block1")
    sim.step(tool + np.array([0, 0, 0.1]), DOWN, 1.0, DT)
    # 4 mm into block0's top
    into = np.array([0.5, -0.2, TOP + H - 0.004 + H + 0.008])
    kinds = [e.kind for e in sim.step(into, DOWN, 1.0, DT)]
    assert kinds == ["collision"]
    sim.step(into, DOWN, 0.0, DT)
    settle(sim, into + np.array([0, 0, 0.1]))
    b = sim.body("block1")
    assert b.on == "block0"
    assert b.p[2] == pytest.approx(TOP + 1.5 * H, abs=1e-12)
