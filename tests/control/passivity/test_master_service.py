"""The master service with `passivity = true` on the simulated haptic master: the displayed
force that would push the hand along its motion is damped until the slave side has put
energy into the channel, and the master's energies go out on `robot/passivity/master`."""

from __future__ import annotations

import threading
import time

import pytest

from services.bus import keys
from services.bus.messages import ForceSample, PassivityState
from services.control.master.config import MasterConfig
from services.control.master.service import MasterService
from tests.conftest import Net, wait_until
from tests.control.master.robot_side import moving_state

pytestmark = [pytest.mark.system, pytest.mark.timeout(60)]


def test_master_damps_the_display_until_the_slave_pays(net: Net) -> None:
    cfg = MasterConfig(
        master_id="p1",
        device="haptic_sim",
        passivity=True,
        passivity_device_mass_kg=0.8,
        rate_hz=200.0,
        force_ramp_s=0.0,
        max_force_n=10.0,
    )
    station = MasterService(net.node("master", instance="p1"), cfg)
    robot = net.node("robot")
    seen: list[PassivityState] = []
    lock = threading.Lock()

    def keep(m: PassivityState) -> None:
        with lock:
            seen.append(m)

    robot.subscribe(keys.PASSIVITY_MASTER, keep)
    force_pub = robot.publisher(keys.FORCE)
    state_pub = robot.publisher(keys.STATE)
    slave_pub = robot.publisher(keys.PASSIVITY_SLAVE)
    stop = threading.Event()
    paid = threading.Event()

    def robot_side() -> None:  # 200 Hz: a force pushing down, along the hand's motion
        k = 0
        while not stop.is_set():
            k += 1
            now = time.time_ns()
            state_pub.put(moving_state(k, now))
            force_pub.put(ForceSample(seq=k, t_ns=now, f=(0.0, 0.0, -6.0), c=(0.0, 0.0, 0.0)))
            if paid.is_set():
                engage = station.teleop.engage
                slave_pub.put(
                    PassivityState(
                        seq=k,
                        t_ns=now,
                        master="p1",
                        engage=engage,
                        side="slave",
                        enabled=True,
                        e_in=1e3,
                        e_out=0.0,
                        dissipated_j=0.0,
                        gain=0.0,
                        active_steps=0,
                    )
                )
            stop.wait(0.005)

    worker = threading.Thread(target=robot_side, daemon=True)
    worker.start()
    try:
        # The hand moves down (the sim's approach); with no energy from the slave the
        # downward force is damped away: what is shown stays far below the 6 N measured.
        assert wait_until(lambda: station.passivity is not None and station.ticks > 100)
        assert station.passivity is not None
        assert station.passivity.pc.mass_kg == 0.8  # [master] passivity_device_mass_kg
        assert wait_until(lambda: station.passivity.pc.telemetry.active_steps > 20)
        shown = []
        for _ in range(20):  # what the hand gets over a few ticks (it chatters at the rate)
            shown.append(abs(float(station.displayed.f[2])))
            time.sleep(0.01)
        assert sum(shown) / len(shown) < 3.0
        with lock:
            assert seen and seen[-1].master == "p1" and seen[-1].side == "master"
            assert seen[-1].engage == station.teleop.engage
        # The slave pays: the full force is shown while the hand keeps moving down.
        paid.set()
        assert wait_until(lambda: station.passivity.pc.remote.e_in == 1e3)
        assert wait_until(lambda: float(station.displayed.f[2]) == pytest.approx(-6.0))
        with lock:
            assert seen[-1].e_out > 0.0
    finally:
        stop.set()
        worker.join(timeout=2.0)
        station.close()


def test_a_master_showing_moments_runs_a_rotational_port_from_its_config(net: Net) -> None:
    """`passivity_moments` with `passivity_device_inertia_kg_m2`: the master service runs a
    rotational port with that inertia beside the force's, shows the wrist's moment through
    it (the hand does not turn: no work, shown in full) and sends its energies as
    `rot_e_in` / `rot_e_out`."""
    cfg = MasterConfig(
        master_id="p2",
        device="haptic_sim",
        passivity=True,
        passivity_moments=True,
        passivity_device_inertia_kg_m2=0.004,
        rate_hz=200.0,
        force_ramp_s=0.0,
    )
    station = MasterService(net.node("master", instance="p2"), cfg)
    robot = net.node("robot")
    seen: list[PassivityState] = []
    robot.subscribe(keys.PASSIVITY_MASTER, seen.append)
    force_pub = robot.publisher(keys.FORCE)
    state_pub = robot.publisher(keys.STATE)
    stop = threading.Event()

    def robot_side() -> None:
        k = 0
        while not stop.is_set():
            k += 1
            now = time.time_ns()
            state_pub.put(moving_state(k, now))
            force_pub.put(ForceSample(seq=k, t_ns=now, f=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.3)))
            stop.wait(0.005)

    worker = threading.Thread(target=robot_side, daemon=True)
    worker.start()
    try:
        assert wait_until(lambda: station.passivity is not None and station.ticks > 50)
        tdpa = station.passivity
        assert tdpa is not None and tdpa.rot is not None
        assert tdpa.rot.mass_kg == 0.004  # [master] passivity_device_inertia_kg_m2
        assert wait_until(lambda: float(station.displayed.c[2]) == pytest.approx(0.3))
        assert wait_until(lambda: bool(seen) and seen[-1].rot_e_in is not None)
        assert seen[-1].master == "p2" and seen[-1].rot_e_out == 0.0
    finally:
        stop.set()
        worker.join(timeout=2.0)
        station.close()
