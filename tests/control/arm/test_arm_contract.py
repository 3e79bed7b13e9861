"""The `Arm` contract, run against every driver and model: SimArm for every shipped model,
SerialArm talking to the fake PUMA controller over a loopback socket, and FrankaArm
(libfranka) driving franky-sim's FR3 on a loopback address. Real time with deadlines: all run
their own threads (franky-sim a process, slower than real time on a loaded machine)."""

from __future__ import annotations

import math
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, get_args

import numpy as np
import pytest

from services.bus.errors import ConfigError
from services.control.arm.backends import BACKENDS, open_arm
from services.control.arm.config import ArmConfig
from services.control.arm.driver import Arm, ArmError, DriverName
from services.control.arm.fake_controller import FakeController
from services.control.arm.franka.driver import FrankaArm
from services.control.arm.franka.frankysim import FrankySim
from services.control.arm.model import ArmModel, load_model
from services.control.arm.serial_arm import SerialArm
from services.control.arm.sim_arm import SimArm
from tests.conftest import wait_until
from tests.control.arm.franka import sim as franky

PUMA = load_model("puma560")
CASES = [
    ("puma560", "sim"),
    ("puma560", "serial"),
    ("fr3", "sim"),
    ("ur5e", "sim"),
    # franky-sim is a process of its own (MuJoCo at ~1 kHz): the serial pass of `make test`
    pytest.param(("fr3", "libfranka"), marks=pytest.mark.faults),
]


@dataclass
class Rig:
    """One driver under test: the arm, a way to fail it, the truth about its joints, the
    model it drives and where its joints are at power-on."""

    arm: Arm
    fail: Callable[[], None]
    true_q: Callable[[], np.ndarray]
    model: ArmModel
    q0: np.ndarray
    match: float = 1e-6
    """How close a read-back of a pose the arm holds is, and how far it may drift while no
    command moves it (rad): franky-sim's arm is MuJoCo's under a PD controller, which sags
    under gravity and settles within a few mrad of where it was sent (its last joint 1.8 mrad
    off, measured), and libfranka's wire carries float32."""
    settle: float = 1e-3
    """How close to a commanded pose a converged arm is (rad)."""
    still: float = 1e-9
    """How little an arm that holds still moves between two looks (rad)."""
    drift: float = 1e-9
    """How far the arm may move while nothing commands it to (rad)."""
    halt: float = 1e-9
    """How far an arm moves after `estop` (rad): franky-sim stops where it was last sent,
    which at speed is some mrad ahead of where its PD-driven joints are."""

    @property
    def n(self) -> int:
        return self.model.n


@pytest.fixture(scope="module")
def franky_sim() -> Iterator[dict[str, Any]]:
    """One franky-sim for the module's libfranka cases; the joints where the last left them."""
    if franky.MISSING:
        pytest.skip(f"not installed: {', '.join(franky.MISSING)}")
    sim: FrankySim = franky.start()
    try:
        yield {"sim": sim, "q": None}
    finally:
        sim.close()


@pytest.fixture(
    params=CASES, ids=["puma560-sim", "puma560-serial", "fr3-sim", "ur5e-sim", "fr3-libfranka"]
)
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    name, driver = request.param
    model = load_model(name)
    if driver == "libfranka":
        shared = request.getfixturevalue("franky_sim")
        sim = shared["sim"]
        # the hand is a process of its own and none of the contract's business
        franka = FrankaArm(sim.host, model=model, watchdog_s=1.0, gripper=False)
        if shared["q"] is None:  # where franky-sim's arm is: look once
            franka.connect()
            shared["q"] = franka.snapshot().q
            franka.close()
        try:
            yield Rig(
                franka,
                lambda: sim.send("reflex joint_reflex"),
                lambda: franka.snapshot().q,
                model,
                np.array(shared["q"]),
                match=5e-3,
                settle=3e-3,
                still=2e-5,
                drift=5e-3,
                halt=0.015,
            )
        finally:
            franka.close()
            shared["q"] = franka.snapshot().q
            franka.close_shared()
    elif driver == "sim":
        q0 = np.array(model.named.get("qn", model.home))
        sim = SimArm(q0, model=model, calibration_s=0.1)
        try:
            yield Rig(sim, lambda: sim.inject_fault("error"), lambda: sim.q_true, model, q0)
        finally:
            sim.close()
    else:
        fake = FakeController(calibration_s=0.1).start()
        # A generous reply timeout: the contract is about behaviour, and two loaded cores can
        # delay a reply past 100 ms (a timeout then reads as a controller fault).
        arm = SerialArm(fake.url, cycle_ms=4.0, timeout_s=1.0)
        try:
            q0 = np.array(PUMA.named["qn"])
            yield Rig(arm, fake.garble_next_reply, lambda: fake.q, PUMA, q0)
        finally:
            arm.close()
            fake.close()


def ready(rig: Rig) -> np.ndarray:
    rig.arm.connect()
    rig.arm.initialize()
    assert wait_until(lambda: rig.arm.status == "ready", what="ready")
    return rig.arm.read_joints()


def stream_to(arm: Arm, q_from: np.ndarray, q_to: np.ndarray, n: int = 100) -> None:
    """Stream a smooth ramp of setpoints, one every ~2 ms, as a control loop would."""
    for k in range(1, n + 1):
        s = 0.5 - 0.5 * np.cos(np.pi * k / n)
        arm.command(q_from + s * (q_to - q_from))
        time.sleep(0.002)


def settled(arm: Arm, target: np.ndarray, tol: float = 1e-3) -> bool:
    return bool(np.max(np.abs(arm.read_joints() - target)) < tol)


def holding_at(arm: Arm, target: np.ndarray, tol: float = 1e-3) -> Callable[[], bool]:
    """A condition that keeps commanding `target` (as a control loop does) until it is reached."""

    def check() -> bool:
        arm.command(target)
        return settled(arm, target, tol)

    return check


def resting(rig: Rig) -> np.ndarray:
    """Where the arm comes to rest (its joints still over 20 looks)."""
    held: list[np.ndarray] = []

    def still() -> bool:
        held.append(rig.true_q())
        return len(held) > 20 and bool(np.max(np.abs(held[-1] - held[-20])) < rig.still)

    assert wait_until(still, what="the arm to come to rest")
    return held[-1]


def test_is_an_arm(rig: Rig) -> None:
    assert isinstance(rig.arm, Arm)
    assert rig.arm.status == "disconnected"
    assert rig.arm.last_error is None


def test_connect_then_calibrate_then_joints_report(rig: Rig) -> None:
    rig.arm.connect()
    assert rig.arm.status == "connected"
    with pytest.raises(ArmError):
        rig.arm.read_joints()  # incremental encoders: nothing known before calibration
    rig.arm.initialize()
    assert rig.arm.status in ("initializing", "ready")
    assert wait_until(lambda: rig.arm.status == "ready", what="calibration")
    np.testing.assert_allclose(rig.arm.read_joints(), rig.q0, atol=rig.match)


def test_setpoints_before_ready_are_ignored(rig: Rig) -> None:
    rig.arm.connect()
    rig.arm.command(rig.q0 + 0.1)
    rig.arm.initialize()
    assert wait_until(lambda: rig.arm.status == "ready", what="ready")
    time.sleep(0.05)  # give a wrongly queued setpoint the time to show; not a synchronisation
    np.testing.assert_allclose(rig.true_q(), rig.q0, atol=rig.drift)


def test_command_and_readback_converge(rig: Rig) -> None:
    q0 = ready(rig)
    target = q0 + np.resize([0.2, -0.15, 0.1, 0.3, -0.2, 0.25], rig.n)
    stream_to(rig.arm, q0, target)
    assert wait_until(holding_at(rig.arm, target, rig.settle), what="convergence")
    assert rig.arm.status == "ready"
    np.testing.assert_allclose(rig.true_q(), target, atol=rig.settle)


def test_stop_holds_where_it_is(rig: Rig) -> None:
    q0 = ready(rig)
    far = q0 + 1.0
    # Stream towards a far target (0.003 rad per setpoint) until the arm is really moving
    # (condition, not a fixed count: a loaded machine sends fewer setpoints per cycle).
    deadline = time.monotonic() + 20.0
    k = 0
    while not np.all(rig.true_q() > q0 + 0.02):
        assert time.monotonic() < deadline, "the arm never started to move"
        k += 1
        rig.arm.command(q0 + min(k * 0.003, 0.3) * (far - q0))
        time.sleep(0.002)  # the streaming period, not a synchronisation
    rig.arm.stop()
    held: list[np.ndarray] = []

    def still() -> bool:
        held.append(rig.true_q())
        return len(held) > 20 and bool(np.max(np.abs(held[-1] - held[-20])) < rig.still)

    assert wait_until(still, what="the arm to come to rest")
    q_held = held[-1]
    # It moved, then stopped within its braking distance, far short of where it was going.
    assert np.all(q_held > q0 + 0.01) and np.all(q_held < q0 + 0.5)
    tol = max(2e-6, rig.match)
    assert wait_until(lambda: settled(rig.arm, q_held, tol), what="readback of the held pose")
    rig.arm.command(q_held)  # streaming may resume from where it holds
    assert rig.arm.status == "ready"


def test_estop_halts_and_reconnect_recovers_without_jump(rig: Rig) -> None:
    q0 = ready(rig)
    stream_to(rig.arm, q0, q0 + 0.2, n=30)
    rig.arm.estop()
    assert rig.arm.status == "error"
    assert "emergency" in (rig.arm.last_error or "")
    q_stop = rig.true_q()
    rig.arm.command(q_stop + 0.05)
    time.sleep(0.05)  # a refused setpoint must not move it: look a little later
    np.testing.assert_allclose(rig.true_q(), q_stop, atol=rig.halt)
    q_stop = resting(rig)
    rig.arm.connect()
    assert rig.arm.status == "connected"
    rig.arm.initialize()
    assert wait_until(lambda: rig.arm.status == "ready", what="ready after e-stop")
    np.testing.assert_allclose(rig.arm.read_joints(), q_stop, atol=rig.match)
    np.testing.assert_allclose(rig.true_q(), q_stop, atol=rig.drift)


def test_fault_gives_error_then_reconnect_without_jump(rig: Rig) -> None:
    q0 = ready(rig)
    target = q0 + 0.25
    rig.fail()
    # Keep streaming: the arm must refuse everything from the fault on.
    for _ in range(200):
        rig.arm.command(target)
        if rig.arm.status == "error":
            break
        time.sleep(0.002)
    assert wait_until(lambda: rig.arm.status == "error", what="error")
    assert rig.arm.last_error
    for _ in range(20):
        rig.arm.command(target)
    held: list[np.ndarray] = []

    def still() -> bool:
        held.append(rig.true_q())
        return len(held) > 20 and bool(np.max(np.abs(held[-1] - held[-20])) < rig.still)

    assert wait_until(still, what="the arm to hold")
    q_fault = held[-1]
    assert np.max(np.abs(q_fault - target)) > 0.1, "setpoints after the fault were executed"
    rig.arm.connect()
    rig.arm.initialize()
    assert wait_until(lambda: rig.arm.status == "ready", what="ready after the fault")
    q_back = rig.arm.read_joints()
    np.testing.assert_allclose(q_back, q_fault, atol=rig.match)
    rig.arm.command(q_back)  # the first setpoint after recovery is where the arm is
    time.sleep(0.05)  # a jump, were there one, would show by now
    assert rig.arm.status == "ready"
    np.testing.assert_allclose(rig.true_q(), q_fault, atol=rig.match)


def test_jumping_setpoint_is_refused(rig: Rig) -> None:
    q0 = ready(rig)
    jump = np.zeros(rig.n)
    # 1 rad, the way joint 4 has room for (the arm may start anywhere, e.g. franky-sim's
    # where the previous test left it)
    jump[3] = 1.0 if q0[3] + 1.0 <= rig.model.q_hi[3] else -1.0
    rig.arm.command(q0 + jump)
    assert wait_until(lambda: rig.arm.status == "error", what="the jump to be refused")
    assert "jump" in (rig.arm.last_error or "").lower() or "STEP" in (rig.arm.last_error or "")
    time.sleep(0.05)  # look again a little later: it must not have moved
    np.testing.assert_allclose(rig.true_q(), q0, atol=max(2e-6, rig.match))  # wire resolution


def test_setpoint_outside_the_limits_is_refused(rig: Rig) -> None:
    q0 = ready(rig)
    hi = np.array(rig.model.q_hi)
    j = int(np.argmin(hi - q0))  # the joint nearest its upper limit
    near = q0.copy()
    near[j] = hi[j] - 0.1  # close to its upper limit
    # In short legs, so the arm is never far behind its setpoint even on a loaded machine.
    for leg in np.linspace(0.0, 1.0, 5)[1:]:
        q_leg = q0 + leg * (near - q0)
        stream_to(rig.arm, rig.arm.read_joints(), q_leg, n=50)
        assert wait_until(holding_at(rig.arm, q_leg, rig.settle), what="the next leg")
    past = near.copy()
    past[j] = hi[j] + 0.01  # past the limit, though a small step
    rig.arm.command(past)
    assert wait_until(lambda: rig.arm.status == "error", what="the limit to be refused")
    assert "limit" in (rig.arm.last_error or "").lower()
    assert np.all(rig.true_q() <= hi + 1e-9)


def test_initialize_needs_a_connection(rig: Rig) -> None:
    with pytest.raises(ArmError, match="cannot initialize: arm is disconnected"):
        rig.arm.initialize()
    assert rig.arm.status == "disconnected"


def test_setpoints_outside_ready_are_counted_as_ignored(rig: Rig) -> None:
    arm = rig.arm
    assert isinstance(arm, SimArm | SerialArm | FrankaArm)
    arm.command(rig.q0)
    arm.connect()
    arm.command(rig.q0)
    assert arm.setpoints_ignored == 2
    assert arm.status == "connected"


@pytest.mark.parametrize("bad", ["nan", "short", "matrix"])
def test_a_malformed_setpoint_is_an_error_and_moves_nothing(rig: Rig, bad: str) -> None:
    q0 = ready(rig)
    n = rig.n
    setpoint: Any = {"nan": [math.nan] * n, "short": [0.0] * (n - 1), "matrix": [[0.0] * n]}
    rig.arm.command(setpoint[bad])
    assert wait_until(lambda: rig.arm.status == "error", what="the setpoint to be refused")
    assert (rig.arm.last_error or "").startswith("bad setpoint: setpoint must")
    time.sleep(0.05)  # look again a little later: it must not have moved
    np.testing.assert_allclose(rig.true_q(), q0, atol=max(2e-6, rig.match))


def test_close_is_idempotent(rig: Rig) -> None:
    ready(rig)
    rig.arm.close()
    rig.arm.close()
    assert rig.arm.status == "disconnected"


def test_every_arm_kind_has_a_backend() -> None:
    assert set(BACKENDS.names) == set(get_args(DriverName))


@pytest.mark.parametrize("name", ["puma560", "fr3"])
def test_open_arm_picks_the_backend_and_model_from_the_config(name: str) -> None:
    model = load_model(name)
    arm = open_arm(ArmConfig(model=name, sim_calibration_s=0.0))
    assert isinstance(arm, SimArm) and arm.n == model.n
    assert arm.status == "disconnected"
    arm.connect()
    arm.initialize()
    assert wait_until(lambda: arm.status == "ready", 10.0, what="the simulated arm to calibrate")
    np.testing.assert_allclose(arm.read_joints(), model.home)  # it powers on at home
    arm.close()


def test_open_arm_serial() -> None:
    ser = open_arm(ArmConfig(driver="serial", port="socket://127.0.0.1:9", serial_cycle_ms=10.0))
    assert isinstance(ser, SerialArm)
    assert ser.status == "disconnected"
    assert ser.port == "socket://127.0.0.1:9"


def test_open_arm_refuses_a_name_without_a_backend() -> None:
    # an ArmConfig refuses the name first; one that slipped through is refused here too
    config = ArmConfig()
    object.__setattr__(config, "driver", "usb")
    with pytest.raises(ConfigError) as info:
        open_arm(config)
    assert info.value.key == "arm.driver"


def test_sim_and_proxy_do_not_load_pyserial() -> None:
    code = (
        "import sys\n"
        "import services.control.arm.driver, services.control.arm.sim_arm\n"
        "import services.control.arm.proxy\n"
        "from services.control.arm.backends import open_arm\n"
        "from services.control.arm.config import ArmConfig\n"
        "open_arm(ArmConfig())\n"
        "print('serial' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
