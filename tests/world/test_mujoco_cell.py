"""The cell on MuJoCo (services/world/workcell/{mujoco_model,engine}.py): built from each arm's
description, contacts that push back, a gripper that holds by friction, and a wrist that
reads what the solver computes.

The arm is driven as the arm service drives it: a joint setpoint every 4 ms from the arm's
own IK along a smooth Cartesian path. Times are the simulator's (`CellPhysics.t_s`)."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pinocchio as pin
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.bus.errors import ConfigError
from services.control.arm.model import SHIPPED, load_model
from services.geometry import rot_y
from services.world.workcell.engine import CellPhysics
from services.world.workcell.mujoco_model import (
    FINGERS,
    PhysicsParams,
    build_cell,
    object_mass_kg,
)
from services.world.workcell.scene import BLOCK_SIZE_M, TABLE, default_scene

SCENE = default_scene()
G = 9.81
CTRL_STEPS = 4
"""MuJoCo steps (1 ms) per setpoint: the arm service's cycle in these tests."""
SENSOR_RANGE_N = 200.0
"""A wrist F/T sensor's force range (ATI Mini45: 290 N in x, y; a bit over 200 N is usual for
a 6-axis wrist of this size): no contact of the tool may read above it."""


class Driver:
    """The tool moved along straight lines by streaming IK setpoints, as the arm service
    does; the orientation of home unless given."""

    def __init__(self, ph: CellPhysics) -> None:
        self.ph = ph
        self.kin = ph.arm.kinematics()
        self.q = np.array(ph.arm.home, dtype=float)
        self.R = ph.tool_pose()[1]
        self.grip = 0.0
        self.events: list[str] = []

    def hold(self, t_s: float) -> None:
        for _ in range(round(t_s / (CTRL_STEPS * 1e-3))):
            self.ph.command(self.q, self.grip)
            self.events += [e.kind for e in self.ph.step(CTRL_STEPS)]

    def move(
        self, p: object, t_s: float = 0.8, R: object = None, speed: float | None = None
    ) -> None:
        p_goal = np.asarray(p, dtype=float)
        p0 = np.asarray(self.kin.fk_tool(self.q).translation)
        R_goal = self.R if R is None else np.asarray(R, dtype=float)
        if speed is not None:
            t_s = max(0.05, float(np.linalg.norm(p_goal - p0)) / speed)
        n = max(1, round(t_s / (CTRL_STEPS * 1e-3)))
        for k in range(1, n + 1):
            s = k / n if speed is not None else 0.5 - 0.5 * math.cos(math.pi * k / n)
            self.q = self.kin.solve(self.q, pin.SE3(R_goal, p0 + s * (p_goal - p0))).q
            self.ph.command(self.q, self.grip)
            self.events += [e.kind for e in self.ph.step(CTRL_STEPS)]
        self.R = R_goal

    def set_grip(self, grip: float, t_s: float = 0.4) -> None:
        self.grip = grip
        self.hold(t_s)


def up(p: np.ndarray, dz: float) -> np.ndarray:
    """`p` raised by `dz` (m)."""
    return p + np.array([0.0, 0.0, dz])


def top_of(ph: CellPhysics, name: str) -> np.ndarray:
    b = ph.body(name)
    return (
        b.p + np.array([0.0, 0.0, 0.5 * b.size[2]])
        if b.kind == "box"
        else b.p + b.R @ [0, 0, b.size[2]]
    )


@pytest.mark.parametrize("name", SHIPPED)
def test_the_cell_is_built_from_each_arms_description(name: str) -> None:
    arm = load_model(name)
    ph = CellPhysics(arm, SCENE)
    # The arm's joints, in its order; the tool where the arm's kinematics puts it.
    assert [ph.model.joint(int(j)).name for j in ph.model.dof_jntid[ph.cell.dof_adr]] == list(
        arm.joint_names
    )
    p, R = ph.tool_pose()
    oMt = arm.kinematics().fk_tool(ph.q)
    # (MuJoCo's poses are those of the step's start: a few µm behind its joints)
    np.testing.assert_allclose(p, oMt.translation, atol=1e-4)
    np.testing.assert_allclose(R, oMt.rotation, atol=1e-4)
    # Every movable object of the scene is a free body, resting where the scene puts it.
    assert sorted(ph.cell.objects) == sorted(s.name for s in SCENE.movables())
    for b in ph.bodies():
        assert b.phase == "resting" and b.on == "table", b
    np.testing.assert_allclose(ph.body("block0").p, SCENE.box("block0").center, atol=3e-4)
    # Hanging in free space, the wrist reads the tool's weight: m·g straight down.
    ph.step(200)
    f, _ = ph.wrench_t()
    np.testing.assert_allclose(R @ f, [0.0, 0.0, -ph.params.tool_mass_kg * G], atol=5e-3)


def test_a_bad_parameter_or_arm_fails_naming_the_key() -> None:
    with pytest.raises(ConfigError, match=r"physics\.timestep_s"):
        PhysicsParams(timestep_s=0.5)
    with pytest.raises(ConfigError, match=r"physics\.grip_force_n"):
        PhysicsParams(grip_force_n=float("nan"))
    arm = load_model("puma560")
    bad = type(arm).__new__(type(arm))
    for f in arm.__dataclass_fields__:
        object.__setattr__(bad, f, getattr(arm, f))
    object.__setattr__(bad, "urdf", arm.urdf.replace("</robot>", "<link name='x'><bogus/>"))
    with pytest.raises(ConfigError, match="physics"):
        build_cell(bad, SCENE)


@pytest.mark.parametrize("name", SHIPPED)
def test_the_gripper_holds_by_friction_and_the_wrist_weighs_the_block(name: str) -> None:
    ph = CellPhysics(load_model(name), SCENE)
    d = Driver(ph)
    top = top_of(ph, "block0")
    d.move(up(top, 0.1))
    d.hold(0.3)
    f_empty = ph.tool_pose()[1] @ ph.wrench_t()[0]
    d.move(up(top, 0.008))
    d.set_grip(1.0)
    d.move(up(top, 0.1))
    d.hold(0.3)
    assert ph.held == "block0" and ph.body("block0").phase == "held"
    assert ph.body("block0").p[2] > top[2] + 0.05, "lifted with the tool: friction holds it"
    f_held = ph.tool_pose()[1] @ ph.wrench_t()[0]
    m = object_mass_kg(SCENE.box("block0"), ph.params)
    weight = f_empty - f_held  # world: the block pulls the tool down by m·g
    assert abs(weight[2] - m * G) <= 0.05 * m * G, (weight, m * G)
    assert np.hypot(weight[0], weight[1]) <= 0.05 * m * G
    assert d.events.count("grasp") == 1 and "missed" not in d.events


def test_a_stack_stands_by_physics_and_a_released_block_settles_on_it() -> None:
    ph = CellPhysics(load_model("puma560"), SCENE)
    d = Driver(ph)
    top0, top1 = top_of(ph, "block0"), top_of(ph, "block1")
    d.move(up(top0, 0.03))
    d.move(up(top0, 0.008))
    d.set_grip(1.0)
    d.move(up(top0, 0.09))
    d.move(up(top1, 0.09))
    d.move(up(top1, BLOCK_SIZE_M + 0.008 + 0.003))
    d.set_grip(0.0, 0.6)
    d.move(up(top1, 0.15))
    d.hold(0.5)
    b0, b1 = ph.body("block0"), ph.body("block1")
    assert (b0.phase, b0.on) == ("resting", "block1")
    assert abs(b0.p[2] - (b1.p[2] + BLOCK_SIZE_M)) < 1e-3
    assert np.hypot(*(b0.p - b1.p)[:2]) < 0.005
    assert d.events.count("release") == 1 and d.events.count("settled") >= 1
    # A block placed half over the edge of the one under it falls off by itself.
    ph.place("block2", b1.p + np.array([0.035, 0.0, 2 * BLOCK_SIZE_M + 0.001]))
    ph.step(1500)
    b2 = ph.body("block2")
    assert b2.on == "table" and b2.p[2] < TABLE.top_z + BLOCK_SIZE_M, b2


def test_the_tool_pushing_a_block_slides_it() -> None:
    ph = CellPhysics(load_model("puma560"), SCENE)
    d = Driver(ph)
    start = ph.body("block2").p.copy()
    # Fingers down beside the block (y), then sweep along −y: the finger pushes it.
    low = TABLE.top_z + 0.03 + 0.01
    d.move([start[0], start[1] + 0.06, low + 0.05])
    d.move([start[0], start[1] + 0.06, low])
    d.move([start[0], start[1] - 0.02, low], t_s=1.5)
    d.move([start[0], start[1] - 0.02, low + 0.1])
    d.hold(0.3)
    b = ph.body("block2")
    moved = start - b.p
    assert moved[1] > 0.03, moved
    assert abs(b.p[2] - start[2]) < 1e-3 and b.phase == "resting", b


@pytest.mark.parametrize("name", SHIPPED)
def test_a_steady_press_is_what_the_joint_torques_balance(name: str) -> None:
    ph = CellPhysics(load_model(name), SCENE)
    d = Driver(ph)
    spot = np.array([0.60, 0.15, TABLE.top_z])
    reach = ph.params.finger_length_m
    d.move(up(spot, reach + 0.02))
    d.move(up(spot, reach - 0.003), t_s=0.5)  # the fingertips 3 mm into the table
    d.hold(0.8)
    f_t, m_t = ph.wrench_t()
    p, R = ph.tool_pose()
    f_w, m_w = R @ f_t, R @ m_t
    # The press: some tens of newtons up.
    assert f_w[2] > 10.0, f_w
    # The joint servos balance what presses on the tool: τ = −Jᵀ w, w the wrist's wrench less
    # the tool's own weight (the links' and the tool's gravity are the servos' feed-forward).
    m, dd = ph.model, ph.data
    tool_bodies = [m.body(n).id for n in ("tr_gripper", "tr_tool", *FINGERS)]
    f_g = np.zeros(3)
    m_g = np.zeros(3)
    for b in tool_bodies:
        w = np.array([0.0, 0.0, -m.body_mass[b] * G])
        f_g += w
        m_g += np.cross(dd.xipos[b] - p, w)
    jacp = np.zeros((3, m.nv))
    jacr = np.zeros((3, m.nv))
    mujoco.mj_jac(m, dd, jacp, jacr, p, ph.cell.gripper_body)
    cols = ph.cell.dof_adr
    tau_wrench = jacp[:, cols].T @ (f_w - f_g) + jacr[:, cols].T @ (m_w - m_g)
    balance = -ph.tau
    assert np.linalg.norm(tau_wrench - balance) <= 0.05 * np.linalg.norm(balance), (
        tau_wrench,
        balance,
    )


@settings(
    max_examples=6,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=True,
)
@given(
    speed=st.floats(0.02, 0.25),
    tilt_deg=st.floats(0.0, 25.0),
    target=st.sampled_from(["table", "block1"]),
)
@pytest.mark.parametrize("name", SHIPPED)
def test_no_approach_reads_above_the_sensors_range(
    name: str, speed: float, tilt_deg: float, target: str
) -> None:
    ph = CellPhysics(load_model(name), SCENE)
    d = Driver(ph)
    surface = np.array([0.62, 0.15, TABLE.top_z]) if target == "table" else top_of(ph, "block1")
    R = ph.tool_pose()[1] @ rot_y(math.radians(tilt_deg))
    reach = ph.params.finger_length_m * math.cos(math.radians(tilt_deg))
    d.move(up(surface, reach + 0.03), R=R)
    peak = 0.0
    # Into the surface at `speed`, 3 mm past it, then held: every 1 ms sample checked.
    p0 = up(surface, reach + 0.03)
    p1 = up(surface, reach - 0.003)
    n = max(1, round(float(np.linalg.norm(p1 - p0)) / speed / 1e-3))
    for k in range(1, n + 200):
        s = min(1.0, k / n)
        if (k - 1) % CTRL_STEPS == 0:
            d.q = d.kin.solve(d.q, pin.SE3(R, p0 + s * (p1 - p0))).q
            ph.command(d.q, 0.0)
        ph.step(1)
        peak = max(peak, float(np.linalg.norm(ph.wrench_t()[0])))
    assert peak < SENSOR_RANGE_N, (speed, tilt_deg, target, peak)
    assert peak > 1.0  # it did touch
