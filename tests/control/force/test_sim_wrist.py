"""The sim wrist: the cell's physics at the wrist, or free space (docs/force.md, docs/sim.md).

With the workcell's physics, the wrench its solver computes on the tool (`sim/arm/state`)
is the wrist's, and gravity compensation removes only the tool, so the operator feels a
carried load. Without it (an arm on its own physics) the wrist is in free space: the tool's
weight and inertia, a push, noise, and no contact anywhere. A live workcell whose physics
never reaches the wrist is said once.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
import pytest

from services.bus import keys
from services.bus.messages import Event, ForceSample, RobotState, vec
from services.control.force import service as force_service
from services.control.force.config import ForceConfig
from services.control.force.core import ForceCore
from services.control.force.gravity import ToolLoad
from services.control.force.service import ForceService
from services.control.force.sim_sensor import PHYSICS_STALE_S, SimSensor
from services.world.workcell.bodies import placed_bodies
from services.world.workcell.messages import (
    SIM_ARM_STATE,
    WORKCELL_STATE,
    SimArmState,
    WorkcellState,
    object_map,
)
from services.world.workcell.scene import BLOCK_SIZE_M, TABLE, default_scene
from tests.conftest import Net, wait_until

DOWN = np.diag([-1.0, 1.0, -1.0])  # tool z at the floor, as the gripper grasps (W1)
TOP = TABLE.top_z
G = 9.80665
BLOCK_KG = 700.0 * BLOCK_SIZE_M**3  # the cell's block density (PhysicsParams)
TOOL = ToolLoad(mass_kg=0.25, com_m=(0.0, 0.0, -0.1))


def workcell_state(seq: int = 1) -> WorkcellState:
    objects = {b.name: object_map(b) for b in placed_bodies(default_scene())}
    return WorkcellState(
        seq=seq, t_ns=seq, tool_p=(0.0, 0.0, 0.0), grip=0.0, held="", objects=objects
    )


def weight_t(
    R: np.ndarray, m: float, a: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> np.ndarray:
    """m (g⃗ − a⃗) in the tool frame."""
    return R.T @ (-m * (np.array([0.0, 0.0, G]) + np.asarray(a)))


def test_in_free_space_the_wrist_reads_the_tools_weight_and_inertia_and_no_contact() -> None:
    """No physics wrench: wherever the tool is, even deep inside the table or a block, the
    wrist reads the tool's m·(g − a) at its centre of mass and the push, nothing else."""
    sensor = SimSensor(load=TOOL, noise_n=0.0, noise_nm=0.0, inertia=True)
    sensor.open()
    com = np.array(TOOL.com_m)
    b2 = default_scene().box("block2").center
    for p in ((0.5, -0.2, TOP + 0.3), (0.6, 0.0, TOP - 0.02), (b2[0], b2[1], b2[2])):
        sensor.update_pose_checked(tuple(map(float, p)), tuple(DOWN.reshape(9)))
        w = sensor.wrench_t()
        assert w is not None
        f = weight_t(DOWN, TOOL.mass_kg)
        np.testing.assert_allclose(w[0], f, atol=1e-12)
        np.testing.assert_allclose(w[1], np.cross(com, f), atol=1e-12)
    # A lift accelerating upward at 3 m/s², robot/state every 2 ms: m (g + a) once the
    # acceleration estimate has settled.
    p0 = np.array([0.5, -0.2, TOP + 0.2])
    a_up = 3.0
    for i in range(0, 400):
        t = i * 0.002
        p = p0 + np.array([0.0, 0.0, 0.5 * a_up * t * t])
        sensor.update_pose_checked(tuple(map(float, p)), tuple(DOWN.reshape(9)), int(t * 1e9))
    w = sensor.wrench_t()
    assert w is not None
    np.testing.assert_allclose(w[0], weight_t(DOWN, TOOL.mass_kg, (0, 0, a_up)), rtol=1e-3)
    # Without `inertia` (the default) the weight only; a push adds as given.
    still = SimSensor(load=TOOL)
    still.open()
    for i in range(0, 50):
        t = i * 0.002
        p = p0 + np.array([0.0, 0.0, 0.5 * a_up * t * t])
        still.update_pose_checked(tuple(map(float, p)), tuple(DOWN.reshape(9)), int(t * 1e9))
    still.push((1.0, -2.0, 3.0), (0.1, 0.0, -0.2))
    w = still.wrench_t()
    assert w is not None
    np.testing.assert_allclose(
        w[0], weight_t(DOWN, TOOL.mass_kg) + np.array([1.0, -2.0, 3.0]), atol=1e-12
    )
    f = weight_t(DOWN, TOOL.mass_kg)
    np.testing.assert_allclose(w[1], np.cross(com, f) + np.array([0.1, 0.0, -0.2]), atol=1e-12)


def test_a_physics_wrench_is_the_wrists_while_fresh_then_free_space_again() -> None:
    sensor = SimSensor(load=TOOL)
    sensor.open()
    assert sensor.wrench_t() is None  # no pose, no physics: nothing to sense
    sensor.update_physics((1.0, 2.0, -30.0), (0.0, 0.1, 0.0))
    w = sensor.wrench_t()
    assert w is not None and sensor.physics_fresh
    np.testing.assert_allclose(w[0], (1.0, 2.0, -30.0))
    np.testing.assert_allclose(w[1], (0.0, 0.1, 0.0))
    sensor.update_pose_checked((0.6, 0.0, TOP - 0.01), tuple(DOWN.reshape(9)))
    assert wait_until(lambda: not sensor.physics_fresh, timeout_s=5 * PHYSICS_STALE_S + 1.0)
    w = sensor.wrench_t()  # the physics went quiet: free space, though inside the table
    assert w is not None
    np.testing.assert_allclose(w[0], weight_t(DOWN, TOOL.mass_kg), atol=1e-12)


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


def test_the_physics_wrench_reaches_robot_force_with_only_the_tool_compensated(net: Net) -> None:
    """The hand-off from the cell's physics (docs/sim.md): `sim/arm/state` carries the wrench
    the solver computes on the tool; the sim sensor reads it, and gravity compensation
    removes the tool's weight only, so a carried block's m·g reaches the operator."""
    force = ForceService(net.node("force"), ForceConfig(seed=4))
    physics = net.node("workcell").publisher(SIM_ARM_STATE)
    samples: list[ForceSample] = []
    lock = threading.Lock()

    def on_force(s: ForceSample) -> None:
        with lock:
            samples.append(s)

    net.node("console").subscribe(keys.FORCE, on_force)
    driver = Driver(net)  # robot/state: the tool pointing down (compensation's orientation)
    carried = [0.0]
    stop = threading.Event()

    def publish() -> None:
        seq = 0
        tool_kg = ForceConfig().tool_mass_kg
        while not stop.wait(0.002):
            seq += 1
            w = DOWN.T @ np.array([0.0, 0.0, -(tool_kg + carried[0]) * G])  # tool frame
            physics.put(
                SimArmState(
                    seq=seq, t_ns=time.time_ns(), sim_ns=seq * 2_000_000, q=(0.0,) * 6,
                    qd=(0.0,) * 6, f_t=vec(w), c_t=(0.0, 0.0, 0.0), tool_p=driver.p,
                    tool_R=vec(DOWN),
                )
            )  # fmt: skip

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:

        def mean_f(n: int = 200) -> np.ndarray:
            with lock:
                start = len(samples)
            assert wait_until(lambda: len(samples) >= start + n, timeout_s=20.0)
            with lock:
                return np.mean([s.f for s in samples[start : start + n]], axis=0)

        sensor = force.core.sensor
        assert isinstance(sensor, SimSensor)

        def newest_f() -> float:
            with lock:
                return float(np.linalg.norm(samples[-1].f)) if samples else math.inf

        assert wait_until(lambda: sensor.physics_updates > 10, what="the physics' wrench")
        # robot/state's orientation reached the compensation: the tool's weight is gone
        assert wait_until(lambda: newest_f() < 0.02, timeout_s=20.0, what="compensation")
        np.testing.assert_allclose(mean_f(), 0.0, atol=0.02)  # the tool alone: compensated
        carried[0] = BLOCK_KG
        # the block's weight reached robot/force (half of it: any sample from before is 0)
        assert wait_until(lambda: newest_f() > 0.5 * BLOCK_KG * G, timeout_s=20.0, what="m·g")
        held = mean_f()
        weight = DOWN.T @ np.array([0.0, 0.0, -BLOCK_KG * G])  # m·g in the tool frame
        assert np.linalg.norm(held - weight) <= 0.05 * BLOCK_KG * G
        assert held[2] > 0.8  # ≈ 0.86 N along the tool's z, which points down
    finally:
        stop.set()
        thread.join(2.0)
        driver.close()
        force.close()


def test_a_real_sensor_ignores_the_physics_wrench() -> None:
    cfg: dict[str, Any] = {"sensor": "serial", "port": "loop://"}
    core = ForceCore.from_config(ForceConfig(**cfg), lambda s: None, lambda *a: None)
    try:
        core.update_physics((0.0, 0.0, 50.0), (0.0, 0.0, 0.0))
        assert core.physics_updates == 0
    finally:
        core.close()


@pytest.mark.parametrize("physics", [False, True], ids=["alone", "with_physics"])
def test_a_live_workcell_without_physics_at_the_wrist_is_said_once(
    net: Net, monkeypatch: pytest.MonkeyPatch, physics: bool
) -> None:
    """The force service's sim wrist next to a running workcell (workcell/state flows) that
    never gets a physics wrench (the arm on `sim_physics = "own"`: its wrist touches
    nothing) says so once, as a status event `no_physics`; with the physics' wrench
    flowing it says nothing."""
    monkeypatch.setattr(force_service, "NO_PHYSICS_GRACE_S", 0.2)
    force = ForceService(net.node("force"), ForceConfig(seed=1))
    cell = net.node("workcell")
    pub, phys = cell.publisher(WORKCELL_STATE), cell.publisher(SIM_ARM_STATE)
    events: list[Event] = []
    lock = threading.Lock()

    def on_event(e: Event) -> None:
        with lock:
            events.append(e)

    net.node("console").subscribe(keys.EVENTS, on_event)
    if physics:
        state = SimArmState(
            seq=1, t_ns=1, sim_ns=1, q=(0.0,) * 6, qd=(0.0,) * 6, f_t=(0.0, 0.0, -2.45),
            c_t=(0.0, 0.0, 0.0), tool_p=(0.5, 0.0, 0.6), tool_R=vec(DOWN),
        )  # fmt: skip
        phys.put(state)
        assert wait_until(lambda: force.core.physics_updates >= 1, what="the physics' wrench")
    try:
        seq = 0
        t_end = time.monotonic() + 0.8  # four graces of workcell/state at 50 Hz
        while time.monotonic() < t_end:
            seq += 1
            pub.put(workcell_state(seq))
            time.sleep(0.02)  # the workcell's 50 Hz, not a synchronisation
        if physics:
            assert not force.no_physics
            with lock:
                assert not [e for e in events if (e.data or {}).get("code") == "no_physics"]
            return
        assert wait_until(lambda: force.no_physics, what="the no-physics notice")

        def said() -> list[Event]:
            with lock:
                return [e for e in events if (e.data or {}).get("code") == "no_physics"]

        assert wait_until(lambda: len(said()) >= 1, what="the no_physics event")
        seen: list[int] = []
        net.node("viewer").subscribe(WORKCELL_STATE, lambda ws: seen.append(ws.seq))
        for _ in range(20):
            seq += 1
            pub.put(workcell_state(seq))
            time.sleep(0.02)
        assert wait_until(lambda: bool(seen) and seen[-1] >= seq - 2, what="20 more states")
        (ev,) = said()  # once
        assert ev.kind == "status" and ev.source == "force" and "free space" in ev.message
    finally:
        force.close()
