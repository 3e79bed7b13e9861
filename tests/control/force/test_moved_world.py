"""The force of the moved world (#22): contact where the objects are now, the carried load.

The sim sensor follows `workcell/state`: a block moved elsewhere is touched at its new
place and not at its old one; a block in the gripper weighs m·g on the wrist (tool frame),
and gravity compensation removes only the tool, so the operator feels the load.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from services.bus import keys
from services.bus.errors import ProtocolError
from services.bus.messages import Event, ForceSample, RobotState, vec
from services.control.force.config import ForceConfig
from services.control.force.core import ForceCore
from services.control.force.service import ForceService
from services.control.force.sim_sensor import SimSensor
from services.world.workcell.config import WorkcellConfig
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState, object_map, objects_of
from services.world.workcell.physics import WorkcellSim
from services.world.workcell.scene import BLOCK_SIZE_M, TABLE, default_scene
from services.world.workcell.service import WorkcellService
from tests.conftest import Net, wait_until

DOWN = np.diag([-1.0, 1.0, -1.0])  # tool z at the floor, as the gripper grasps (W1)
TOP = TABLE.top_z
G = 9.80665
BLOCK_KG = 700.0 * BLOCK_SIZE_M**3  # ForceConfig's default block density
R_PROBE = 0.005


def workcell_state(moves: dict[str, tuple[float, float, float]], held: str = "") -> WorkcellState:
    bodies = WorkcellSim(default_scene()).bodies()
    objects = {
        b.name: object_map(replace(b, p=np.array(moves[b.name])) if b.name in moves else b)
        for b in bodies
    }
    return WorkcellState(
        seq=1, t_ns=1, tool_p=(0.0, 0.0, 0.0), grip=0.0, held=held, objects=objects
    )


@pytest.fixture
def core() -> Iterator[ForceCore]:
    c = ForceCore.from_config(
        ForceConfig(noise_n=0.0, noise_nm=0.0), lambda s: None, lambda *a: None
    )
    c.rpc_sensor_start({})
    yield c
    c.close()


def fresh(core: ForceCore) -> ForceSample:
    """A sample taken after everything before this call."""
    start = core.latest.seq if core.latest else 0
    assert wait_until(lambda: core.latest is not None and core.latest.seq > start + 2)
    assert core.latest is not None
    return core.latest


def test_contact_is_felt_at_a_moved_blocks_new_place_not_its_old(core: ForceCore) -> None:
    old = default_scene().box("block2").center  # (0.50, 0.0, top + h/2)
    new = (0.70, 0.30, old[2])
    press = 0.002  # the probe 2 mm into the block's top
    z = TOP + BLOCK_SIZE_M + R_PROBE - press
    k = default_scene().box("block2").stiffness_n_per_m
    pushed = DOWN.T @ np.array([0.0, 0.0, k * press])  # the block pushes the tool up

    core.update_robot_state((old[0], old[1], z), DOWN)
    np.testing.assert_allclose(fresh(core).f, pushed, atol=1e-6)  # the static scene
    core.update_robot_state((new[0], new[1], z), DOWN)
    np.testing.assert_allclose(fresh(core).f, 0.0, atol=1e-6)  # nothing there yet

    core.update_workcell(workcell_state({"block2": new}))
    np.testing.assert_allclose(fresh(core).f, pushed, atol=1e-6)  # felt where it is now
    core.update_robot_state((old[0], old[1], z), DOWN)
    np.testing.assert_allclose(fresh(core).f, 0.0, atol=1e-6)  # and no longer where it was


def test_a_bad_workcell_state_is_refused_and_changes_nothing(core: ForceCore) -> None:
    far = workcell_state({"block2": (0.7, 0.3, 1e9)})
    with pytest.raises(ProtocolError, match=r"objects\.block2\.p"):
        core.update_workcell(far)
    with pytest.raises(ProtocolError, match="tool_p"):
        core.update_workcell(replace(workcell_state({}), tool_p=(0.0, 0.0, -1e300)))
    sensor = core.sensor
    assert isinstance(sensor, SimSensor)
    # block2 still where the scene puts it: pressing its top is felt.
    old = default_scene().box("block2").center
    core.update_robot_state((old[0], old[1], TOP + BLOCK_SIZE_M + R_PROBE - 0.002), DOWN)
    assert fresh(core).f[2] < -30.0


def test_the_carried_objects_inertia_adds_to_its_weight() -> None:
    sensor = SimSensor(noise_n=0.0, noise_nm=0.0, inertia=True)
    sensor.open()
    p0 = np.array([0.5, -0.2, TOP + 0.2])
    sensor.update_pose_checked(tuple(p0), tuple(DOWN.reshape(9)), 0)
    ws = workcell_state({"block0": tuple(p0 - (0, 0, 0.008 + BLOCK_SIZE_M / 2))}, held="block0")
    sensor.update_workcell(objects_of(ws), "block0", tuple(p0))
    assert sensor.carried is not None and sensor.carried.mass_kg == pytest.approx(BLOCK_KG)
    a_up = 3.0  # m/s², a lift accelerating upward, robot/state every 2 ms
    for i in range(1, 400):
        t = i * 0.002
        sensor.update_pose_checked(
            tuple(p0 + np.array([0.0, 0.0, 0.5 * a_up * t * t])),
            tuple(DOWN.reshape(9)),
            int(t * 1e9),
        )
    w = sensor.wrench_t()  # a SimSensor() without a ToolLoad: the block only
    assert w is not None
    np.testing.assert_allclose(w[0], (0.0, 0.0, BLOCK_KG * (G + a_up)), rtol=1e-3, atol=1e-9)
    np.testing.assert_allclose(w[1], 0.0, atol=1e-9)  # its centre is on the tool's axis


class Driver:
    """Publishes robot/state at 100 Hz as the arm would (the pose and grip set last)."""

    def __init__(self, net: Net) -> None:
        self.pub = net.node("arm").publisher(keys.STATE)
        self.p = (0.5, -0.2, TOP + 0.3)
        self.grip = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        seq = 0
        while not self._stop.wait(0.01):
            seq += 1
            p = np.array(self.p)
            flange = p - DOWN @ np.array([0.0, 0.0, 0.2])
            self.pub.put(
                RobotState(
                    seq=seq,
                    t_ns=time.time_ns(),
                    status="ready",
                    q=(0.0,) * 6,
                    tool_p=vec(p),
                    tool_R=vec(DOWN),
                    flange_p=vec(flange),
                    flange_R=vec(DOWN),
                    engage=1,
                    cmd_seq=seq,
                    grip=self.grip,
                )
            )

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


def test_lifting_a_block_adds_its_weight_to_robot_force(net: Net) -> None:
    force = ForceService(net.node("force"), ForceConfig(seed=4))
    cell = WorkcellService(net.node("workcell"), WorkcellConfig(rate_hz=200.0))
    watcher = net.node("console")
    scene = watcher.subscribe(WORKCELL_STATE)
    samples: list[ForceSample] = []
    lock = threading.Lock()

    def on_force(s: ForceSample) -> None:
        with lock:
            samples.append(s)

    watcher.subscribe(keys.FORCE, on_force)
    driver = Driver(net)
    try:

        def mean_f(n: int = 300) -> np.ndarray:
            with lock:
                start = len(samples)
            assert wait_until(lambda: len(samples) >= start + n, timeout_s=20.0)
            with lock:
                return np.mean([s.f for s in samples[start : start + n]], axis=0)

        palm = (0.5, -0.2, TOP + BLOCK_SIZE_M + 0.008)  # 8 mm above block0, as W1 wants
        driver.p = palm
        assert scene.wait_for(lambda w: w.tool_p == palm, 5.0) is not None
        empty = mean_f()
        np.testing.assert_allclose(empty, 0.0, atol=0.02)  # the tool alone: compensated

        driver.grip = 1.0
        assert scene.wait_for(lambda w: w.held == "block0", 5.0) is not None
        driver.p = (0.5, -0.2, TOP + 0.25)
        lifted = scene.wait_for(
            lambda w: w.objects["block0"]["p"][2] > TOP + 0.2 and w.tool_p == driver.p, 5.0
        )
        assert lifted is not None
        sensor = force.core.sensor
        assert isinstance(sensor, SimSensor)
        assert wait_until(
            lambda: sensor.carried is not None, what="the force service sees the grasp"
        )
        # The lift was a jump: wait until its estimated acceleration (inertia) has died out.
        assert wait_until(lambda: max(map(abs, sensor.acceleration)) < 1e-3, what="the arm at rest")
        held = mean_f()
        weight = DOWN.T @ np.array([0.0, 0.0, -BLOCK_KG * G])  # m·g in the tool frame
        assert np.linalg.norm(held - empty - weight) <= 0.05 * BLOCK_KG * G
        assert held[2] > 0.8  # ≈ 0.86 N along the tool's z, which points down

        driver.grip = 0.0  # let go: the weight is gone
        assert scene.wait_for(lambda w: w.held == "", 5.0) is not None
        assert wait_until(lambda: sensor.carried is None)
        np.testing.assert_allclose(mean_f(), 0.0, atol=0.02)
    finally:
        driver.close()
        cell.close()
        force.close()


def test_workcell_state_is_ignored_by_a_real_sensor() -> None:
    cfg: dict[str, Any] = {"sensor": "serial", "port": "loop://"}
    core = ForceCore.from_config(ForceConfig(**cfg), lambda s: None, lambda *a: None)
    try:
        core.update_workcell(workcell_state({"block2": (0.7, 0.3, 0.425)}))
    finally:
        core.close()


def test_an_unchanged_world_is_not_rebuilt(core: ForceCore) -> None:
    sensor = core.sensor
    assert isinstance(sensor, SimSensor)
    ws = workcell_state({"block2": (0.7, 0.3, 0.425)})
    core.update_workcell(ws)
    built = sensor.world
    core.update_workcell(replace(ws, seq=2, t_ns=2))  # the 50 Hz repeat: same objects
    assert sensor.world is built
    core.update_workcell(workcell_state({"block2": (0.7, 0.2, 0.425)}))
    assert sensor.world is not built


def test_what_the_carried_block_touches_pushes_on_the_wrist() -> None:
    sensor = SimSensor(noise_n=0.0, noise_nm=0.0, inertia=False)
    sensor.open()
    h = BLOCK_SIZE_M
    k = TABLE.stiffness_n_per_m

    def hold_at(bottom_z: float, dx: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        tool = np.array([0.5 + dx, -0.2, bottom_z + h + 0.008])  # palm 8 mm above its top
        sensor.update_pose_checked(tuple(tool), tuple(DOWN.reshape(9)))
        ws = workcell_state({"block0": tuple(tool - np.array([0, 0, 0.008 + h / 2]))}, "block0")
        sensor.update_workcell(objects_of(ws), "block0", tuple(tool))
        w = sensor.wrench_t()
        assert w is not None
        return w

    weight = DOWN.T @ np.array([0.0, 0.0, -BLOCK_KG * G])
    f, c = hold_at(TOP + 0.01)  # 1 cm above the table: its weight only
    np.testing.assert_allclose(f, weight, atol=1e-9)
    np.testing.assert_allclose(c, 0.0, atol=1e-9)
    f, c = hold_at(TOP - 0.001)  # pressed 1 mm flat into the table: k · 1 mm, up
    np.testing.assert_allclose(f, weight + DOWN.T @ np.array([0.0, 0.0, k * 0.001]), atol=1e-6)
    np.testing.assert_allclose(c, 0.0, atol=1e-9)  # the base centred under the tool
    # Half over the table's far edge (x = 0.85): only its inner corners and centre press,
    # off the tool's axis, so a moment appears too.
    f, c = hold_at(TOP - 0.001, dx=0.85 - 0.5)
    assert f[2] < weight[2] and np.linalg.norm(c) > 1e-3

    quiet = SimSensor(noise_n=0.0, noise_nm=0.0, inertia=False, carried_contact=False)
    sensor = quiet
    sensor.open()
    f, _ = hold_at(TOP - 0.001)
    np.testing.assert_allclose(f, weight, atol=1e-9)  # switched off: the weight only


def test_a_forged_workcell_state_on_the_bus_is_reported_not_sensed(net: Net) -> None:
    force = ForceService(net.node("force"), ForceConfig(noise_n=0.0, noise_nm=0.0))
    other = net.node("intruder")
    events: list[Event] = []
    other.subscribe(keys.EVENTS, events.append)
    try:
        other.publisher(WORKCELL_STATE).put(workcell_state({"block2": (0.7, 0.3, 1e9)}))
        assert wait_until(lambda: force.node.rejected.get(WORKCELL_STATE.key, 0) >= 1)
        assert wait_until(lambda: any(e.kind == "rejected" and e.source == "force" for e in events))
        ev = next(e for e in events if e.kind == "rejected")
        assert "objects.block2.p" in ev.message
        sensor = force.core.sensor
        assert isinstance(sensor, SimSensor)
        assert sensor.carried is None
        # block2 still where the scene puts it (the forged message changed nothing)
        b2 = default_scene().box("block2").center
        assert sensor.world.force(b2[0], b2[1], TOP + BLOCK_SIZE_M + R_PROBE - 0.002)[2] > 30.0
    finally:
        force.close()


def test_a_contact_with_torsion_resists_a_turn_about_its_normal() -> None:
    """`torsion_nm_rad` = 30: the tool pressed 1 mm into the table top and turned 0.02 rad
    about the world's z (the contact normal) since the touch meets −0.6 N·m about z; a turn
    about x (not the normal) meets nothing; lifted off and pressed again, the new touch
    is the new zero. Without torsion (the default) a contact has no moment."""
    from services.geometry import rot_x, rot_z

    p = (0.5, -0.3, TOP + R_PROBE - 0.001)
    for k_t in (30.0, 0.0):
        sensor = SimSensor(noise_n=0.0, noise_nm=0.0, torsion_nm_rad=k_t)
        sensor.open()
        sensor.update_pose_checked(p, tuple(DOWN.reshape(9)))
        w0 = sensor.wrench_t()  # the touch: its orientation is the zero
        assert w0 is not None and np.allclose(w0[1], 0.0)
        turned = rot_z(0.02) @ DOWN
        sensor.update_pose_checked(p, tuple(turned.reshape(9)))
        w = sensor.wrench_t()
        assert w is not None
        c_world = turned @ w[1]
        np.testing.assert_allclose(c_world, (0.0, 0.0, -0.02 * k_t), atol=1e-9)
        tilted = rot_x(0.02) @ DOWN
        sensor.update_pose_checked(p, tuple(tilted.reshape(9)))
        w = sensor.wrench_t()
        assert w is not None and np.allclose(tilted @ w[1], 0.0, atol=1e-9)
    sensor = SimSensor(noise_n=0.0, noise_nm=0.0, torsion_nm_rad=30.0)
    sensor.open()
    sensor.update_pose_checked(p, tuple(DOWN.reshape(9)))
    sensor.wrench_t()
    sensor.update_pose_checked((p[0], p[1], p[2] + 0.01), tuple((rot_z(0.1) @ DOWN).reshape(9)))
    assert sensor.wrench_t() is not None  # lifted off: the touch is forgotten
    sensor.update_pose_checked(p, tuple((rot_z(0.1) @ DOWN).reshape(9)))
    w = sensor.wrench_t()
    assert w is not None and np.allclose(w[1], 0.0)
    with pytest.raises(ValueError, match="torsion_nm_rad"):
        SimSensor(torsion_nm_rad=-1.0)
