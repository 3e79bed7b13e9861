"""The workcell service owns the cell's physics on the bus: it builds the arm the arm service
describes, the arm's `sim` driver's joints are its joints (`sim/arm/cmd` → `sim/arm/state`),
a setpoint it cannot take is refused with an event and moves nothing, and `workcell/state`
and its methods report the objects. Real services on a private Zenoh network."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from services.bus import codec, keys
from services.bus.config import section
from services.bus.errors import ConfigError, ProtocolError
from services.bus.messages import Event, vec
from services.control.arm.config import ArmConfig
from services.control.arm.model import load_model
from services.control.arm.service import ArmService
from services.world.workcell.channel import ArmChannel
from services.world.workcell.config import WorkcellConfig
from services.world.workcell.engine import CellPhysics
from services.world.workcell.messages import (
    SIM_ARM_CMD,
    SIM_ARM_STATE,
    WORKCELL_STATE,
    SimArmCmd,
    WorkcellState,
    object_map,
    objects_of,
)
from services.world.workcell.scene import TABLE, default_scene
from services.world.workcell.service import WorkcellService
from tests.conftest import Net, wait_until

TOP = TABLE.top_z


def test_workcell_state_round_trips_through_the_codec() -> None:
    ph = CellPhysics(load_model("puma560"), default_scene())
    msg = WorkcellState(
        seq=1,
        t_ns=2,
        tool_p=(0.5, 0.0, 0.6),
        grip=0.0,
        held="",
        objects={b.name: object_map(b) for b in ph.bodies()},
        data={"grasps": 0},
    )
    back = codec.decode(WorkcellState, codec.encode(msg))
    objs = objects_of(back)
    assert sorted(objs) == ["block0", "block1", "block2", "bottle"]
    # resting on the table (MuJoCo's contacts take the load within a tenth of a mm)
    np.testing.assert_allclose(objs["block1"].centre, [0.5, -0.1, TOP + 0.025], atol=2e-4)
    np.testing.assert_allclose(objs["bottle"].top, [0.55, 0.25, TOP + 0.2], atol=2e-4)
    assert objs["bottle"].liquid_ml == pytest.approx(692.7, abs=0.1)
    assert objs["block0"].liquid_ml is None


def test_a_bad_object_is_named() -> None:
    msg = WorkcellState(
        seq=1,
        t_ns=2,
        tool_p=(0.5, 0.0, 0.6),
        grip=0.0,
        held="",
        objects={"b": {"kind": "box", "p": [0, 0], "R": list(vec(np.eye(3)))}},
    )
    with pytest.raises(ProtocolError, match=r"objects\.b\.p"):
        objects_of(msg)


def test_config_is_checked() -> None:
    cfg = section(WorkcellConfig, {"rate_hz": 250, "physics": {"grip_force_n": 30.0}}, "workcell")
    assert cfg.physics.grip_force_n == 30.0
    with pytest.raises(ConfigError, match="publish_rate_hz"):
        WorkcellConfig(rate_hz=50.0, publish_rate_hz=100.0)
    with pytest.raises(ConfigError, match=r"workcell\.physics\.grip_forse_n"):
        section(WorkcellConfig, {"physics": {"grip_forse_n": 1}}, "workcell")
    with pytest.raises(ConfigError, match=r"physics\.kp_nm_rad"):
        section(WorkcellConfig, {"physics": {"kp_nm_rad": -1.0}}, "workcell")


@pytest.mark.parametrize("via", ["workcell", "embedded"])
def test_the_arm_moves_in_the_workcells_physics_and_bad_setpoints_are_refused(
    net: Net, via: str
) -> None:
    """`workcell`: setpoints and joints over the bus; `embedded` (the sim profile's): the
    workcell in the arm's process, through an ArmChannel; the same checks either way."""
    model = load_model("fr3")
    channel = ArmChannel() if via == "embedded" else None
    arm = ArmService(
        net.node("arm"),
        ArmConfig(model="fr3", sim_physics=via, sim_calibration_s=0.05),
        channel=channel,
    )
    cell = WorkcellService(net.node("workcell"), WorkcellConfig(), channel=channel)
    watcher = net.node("console")
    events: list[Event] = []
    lock = threading.Lock()

    def on_event(ev: Event) -> None:
        with lock:
            events.append(ev)

    watcher.subscribe(keys.EVENTS, on_event)
    sim = watcher.subscribe(SIM_ARM_STATE)
    scene = watcher.subscribe(WORKCELL_STATE)
    try:
        # The cell is built from the arm's description: the FR3's joints, at home.
        st = sim.wait_for(lambda s: len(s.q) == model.n, 10.0)
        assert st is not None
        np.testing.assert_allclose(st.q, model.home, atol=1e-6)
        assert cell.physics is not None and cell.physics.arm.name == "fr3"
        # The tool hangs in free space: the wrist weighs it (N, tool frame, world down).
        R = np.asarray(st.tool_R).reshape(3, 3)
        np.testing.assert_allclose(R @ st.f_t, [0, 0, -0.25 * 9.81], atol=0.02)
        proxy = arm.proxy
        proxy.rpc_connect({})
        proxy.rpc_initialize({})
        assert wait_until(lambda: proxy.status == "ready", 10.0, what="ready")
        # A joint move: the physics' joints get there, the arm reads them back.
        goal = np.array(model.home) + np.resize([0.1, -0.1, 0.1, 0.1, -0.1, 0.1, 0.1], model.n)
        r = proxy.rpc_move_joints({"q": list(goal)})
        done = proxy.wait_motion(r["motion"], 20.0)
        assert done["completed"], done
        assert sim.wait_for(lambda s: np.max(np.abs(np.array(s.q) - goal)) < 1e-3, 5.0)
        np.testing.assert_allclose(arm.arm.read_joints(), goal, atol=2e-3)
        q_here = np.array(sim.latest.q)
        rogue = watcher.publisher(SIM_ARM_CMD)
        if channel is not None:
            # Embedded, the physics takes no setpoint from the bus: one published there is
            # not even looked at (nothing refused, nothing moves) …
            far = np.where(np.arange(model.n) == 0, q_here[0] + 0.2, q_here)
            rogue.put(SimArmCmd(seq=9_999, t_ns=time.time_ns(), q=tuple(map(float, far))))
            seq0 = sim.latest.seq
            assert sim.wait_for(lambda s: s.seq >= seq0 + 5, 5.0) is not None
            assert cell.rejected == 0
            assert np.max(np.abs(np.array(sim.latest.q) - q_here)) < 5e-3
            rogue = channel.cmd  # … the driver's own hand-off is what is checked below
        # A rogue setpoint: a jump, the wrong size, past a limit: refused, nothing moves.
        bad = [
            q_here + np.resize([0.0, 0.0, 0.0, 1.0], model.n),
            q_here[:3],
            np.where(np.arange(model.n) == 0, model.q_hi[0] + 0.01, q_here),
        ]
        for k, q in enumerate(bad):
            rogue.put(SimArmCmd(seq=10_000 + k, t_ns=time.time_ns(), q=tuple(map(float, q))))
            assert wait_until(lambda k=k: cell.rejected == k + 1, 5.0, what="refused")  # type: ignore[misc]
        # five more states of the physics (a jump, were one taken, would show in them)
        seq0 = sim.latest.seq
        now = sim.wait_for(lambda s: s.seq >= seq0 + 5, 5.0)
        assert now is not None, "the physics stopped publishing sim/arm/state"
        # (still settling onto the goal by a millimetre-radian or so; a jump is 1 rad)
        assert np.max(np.abs(np.array(now.q) - q_here)) < 5e-3
        with lock:
            refused = [e for e in events if (e.data or {}).get("action") == "rejected"]
        assert refused and "jump" in refused[0].message
        # workcell/state reports the objects; reset puts them back, the arm stays.
        got = scene.wait_for(lambda w: "block1" in w.objects, 5.0)
        assert got is not None
        reply = watcher.call("workcell", "reset", {}, 5.0)
        assert reply["objects"]["block1"]["p"][2] == pytest.approx(TOP + 0.025, abs=3e-4)
        assert watcher.call("workcell", "status", {}, 5.0)["held"] == ""
        seq0 = sim.latest.seq  # a state published after the reset: the arm stayed
        after = sim.wait_for(lambda s: s.seq > seq0, 5.0)
        assert after is not None, "no sim/arm/state after the reset"
        assert np.max(np.abs(np.array(after.q) - q_here)) < 5e-3
        # The physics goes away: the arm's driver notices within its deadline and errs, so
        # the arm service holds (a lost link stops motion); nothing is commanded after.
        cell.close()
        assert wait_until(lambda: arm.arm.status == "error", 5.0, what="the lost physics")
        assert "physics" in (arm.arm.last_error or "")
        assert wait_until(lambda: proxy.status == "error", 5.0, what="the arm service's error")
    finally:
        arm.close()
        cell.close()


def test_a_resting_cell_wakes_seldom_and_still_takes_the_next_setpoint(
    net: Net, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After a long rest the loop looks for a setpoint every REST_POLL_S, not at its
    500 Hz (those wake-ups were the idle cell's CPU), and sends workcell/state at
    REST_STATE_HZ, not 50 Hz; the next setpoint is taken and stepped at once, and the
    states are at their full rate again. Wake-ups counted against the states the same
    loop sends: a loop waking at its rate would wake 5 times as often."""
    from services.world.workcell.service import REST_POLL_S, REST_STATE_HZ

    monkeypatch.setattr("services.world.workcell.service.DEEP_REST_AFTER_S", 0.2)
    model = load_model("puma560")
    cell = WorkcellService(net.node("workcell"), WorkcellConfig(), arm=model)
    watcher = net.node("watcher")
    scene = watcher.subscribe(WORKCELL_STATE)
    sim = watcher.subscribe(SIM_ARM_STATE)
    try:
        assert wait_until(lambda: cell.resting, 20.0, what="the cell at rest")
        rest = scene.wait_for(lambda w: True, 5.0)
        assert rest is not None
        # 3 states (0.6 s at REST_STATE_HZ) into the rest: past DEEP_REST_AFTER_S
        first = scene.wait_for(lambda w: w.seq >= rest.seq + 3, 5.0)
        assert first is not None and cell.resting
        w0, steps0, seq0 = cell.wakes, cell.steps, first.seq
        later = scene.wait_for(lambda w: w.seq >= seq0 + 5, 10.0)
        assert later is not None
        assert cell.resting and cell.steps == steps0, "the physics stepped while at rest"
        # the states' spacing by their own stamps: REST_STATE_HZ, not publish_rate_hz
        gap_s = (later.t_ns - first.t_ns) * 1e-9 / (later.seq - seq0)
        assert gap_s >= 0.8 / REST_STATE_HZ, gap_s
        states = later.seq - seq0
        per_state = 1.0 / REST_STATE_HZ / REST_POLL_S  # wake-ups per state, polling
        assert cell.wakes - w0 <= 1.5 * per_state * states + 3, (cell.wakes - w0, states)
        # A setpoint after the rest: taken, stepped, the joint on its way.
        q = np.array(model.home, dtype=float)
        goal = q + np.resize([0.02, 0.0], model.n)
        cmd = watcher.publisher(SIM_ARM_CMD)
        cmd.put(SimArmCmd(seq=1, t_ns=time.time_ns(), q=tuple(map(float, goal))))
        moved = sim.wait_for(lambda s: s.cmd_seq == 1 and s.q[0] - q[0] > 0.01, 10.0)
        assert moved is not None, "the setpoint after the rest moved nothing"
        assert cell.steps > steps0
        # moving: workcell/state at its full rate again, counted against the loop's own
        # wake-ups (rate_hz / publish_rate_hz = 10 per state; 100 at REST_STATE_HZ), not
        # against the wall clock
        a = scene.wait_for(lambda w: w.t_ns > moved.t_ns, 5.0)
        assert a is not None
        w1 = cell.wakes
        b = scene.wait_for(lambda w: w.seq >= a.seq + 10, 5.0)
        assert b is not None
        cfg = WorkcellConfig()
        per_state = (cell.wakes - w1) / (b.seq - a.seq)
        assert per_state <= 3 * cfg.rate_hz / cfg.publish_rate_hz, per_state
    finally:
        cell.close()


def test_telerobot_arm_embedded_runs_the_workcell_in_its_process(net: Net) -> None:
    """`telerobot arm --sim-physics embedded` (the sim profile's): one process announces
    both `arm` and `workcell`, the arm comes up ready on the cell's physics (its joints on
    `sim/arm/state`, the workcell's queryables answer), and SIGTERM stops both, exit 0."""
    import signal

    from tests.bus.test_router import spawned, telerobot

    watcher = net.node("console")
    sim = watcher.subscribe(SIM_ARM_STATE)
    state = watcher.subscribe(keys.STATE)
    argv = telerobot(
        "arm", "--sim-physics", "embedded", "--autostart", "--connect", net.endpoint
    )  # fmt: skip
    with spawned(argv) as child:
        assert watcher.alive.wait("workcell", 30.0) and watcher.alive.wait("arm", 30.0)
        ready = state.wait_for(lambda s: s.status == "ready", 30.0)
        assert ready is not None, child.lines[-20:]
        got = sim.wait_for(lambda s: len(s.q) == len(ready.q), 10.0)
        assert got is not None
        np.testing.assert_allclose(got.q, ready.q, atol=1e-3)  # the arm's joints: the cell's
        assert watcher.call("workcell", "status", {}, 5.0)["held"] == ""
        child.proc.send_signal(signal.SIGTERM)
        assert child.wait(30.0) == 0, child.lines[-20:]
    assert wait_until(lambda: not watcher.alive.is_alive("workcell"), 10.0, what="gone")


def test_embedded_physics_is_a_config_value_and_needs_its_channel() -> None:
    from services.control.arm.backends import arm_options

    assert ArmConfig(sim_physics="embedded").sim_physics == "embedded"
    with pytest.raises(ConfigError, match=r"arm\.sim_physics.*own, workcell, embedded"):
        ArmConfig(sim_physics="elsewhere")
    with pytest.raises(ConfigError, match=r"arm\.sim_physics"):
        arm_options(ArmConfig(sim_physics="embedded"))  # no workcell in this process
