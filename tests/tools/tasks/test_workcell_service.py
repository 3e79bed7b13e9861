"""The workcell service over Zenoh: it follows robot/state (published here as the arm
would), publishes workcell/state, reports its events, and its message survives the codec."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from services.bus import codec, keys
from services.bus.errors import ConfigError, ProtocolError
from services.bus.messages import Event, RobotState, vec
from services.world.workcell.config import WorkcellConfig
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState, objects_of
from services.world.workcell.physics import WorkcellSim
from services.world.workcell.scene import TABLE, default_scene
from services.world.workcell.service import WorkcellService
from tests.conftest import Net

DOWN = np.diag([-1.0, 1.0, -1.0])
TOP = TABLE.top_z


def state(seq: int, p: tuple[float, float, float], grip: float | None) -> RobotState:
    return RobotState(
        seq=seq,
        t_ns=time.time_ns(),
        status="ready",
        q=(0.0,) * 6,
        tool_p=p,
        tool_R=vec(DOWN),
        flange_p=p,
        flange_R=vec(DOWN),
        engage=1,
        cmd_seq=seq,
        grip=grip,
    )


def test_workcell_state_round_trips_through_the_codec() -> None:
    sim = WorkcellSim(default_scene())
    from services.world.workcell.messages import object_map

    msg = WorkcellState(
        seq=1,
        t_ns=2,
        tool_p=(0.5, 0.0, 0.6),
        grip=0.0,
        held="",
        objects={b.name: object_map(b) for b in sim.bodies()},
        data={"grasps": 0},
    )
    back = codec.decode(WorkcellState, codec.encode(msg))
    objs = objects_of(back)
    assert sorted(objs) == ["block0", "block1", "block2", "bottle"]
    np.testing.assert_allclose(objs["block1"].centre, [0.5, -0.1, TOP + 0.025])
    np.testing.assert_allclose(objs["bottle"].top, [0.55, 0.25, TOP + 0.2])
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
    from services.bus.config import section

    cfg = section(WorkcellConfig, {"rate_hz": 200, "physics": {"snap_xy_m": 0.005}}, "workcell")
    assert cfg.physics.snap_xy_m == 0.005
    with pytest.raises(ConfigError, match="publish_rate_hz"):
        WorkcellConfig(rate_hz=50.0, publish_rate_hz=100.0)
    with pytest.raises(ConfigError, match=r"workcell\.physics\.grasp_gapp"):
        section(WorkcellConfig, {"physics": {"grasp_gapp": 1}}, "workcell")


def test_service_grasps_carries_and_stacks_over_the_bus(net: Net) -> None:
    svc = WorkcellService(net.node("workcell"), WorkcellConfig(rate_hz=200.0))
    try:
        robot = net.node("arm")
        pub = robot.publisher(keys.STATE)
        watcher = net.node("console")
        scene = watcher.subscribe(WORKCELL_STATE)
        events: list[Event] = []
        lock = threading.Lock()

        def on_event(ev: Event) -> None:
            with lock:
                events.append(ev)

        watcher.subscribe(keys.EVENTS, on_event)
        assert scene.wait_for(lambda w: "block1" in w.objects, 5.0) is not None
        seq = 0

        def send_until(p: tuple[float, float, float], grip: float, pred: object) -> WorkcellState:
            nonlocal seq
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:
                seq += 1
                pub.put(state(seq, p, grip))
                got = scene.wait_for(pred, 0.02)  # type: ignore[arg-type]
                if got is not None:
                    return got
            raise AssertionError("workcell/state never satisfied the condition")

        palm = (0.5, -0.1, TOP + 0.05 + 0.008)
        send_until(palm, 0.0, lambda w: w.tool_p == palm)
        got = send_until(palm, 1.0, lambda w: w.held == "block1")
        assert got.grip == 1.0
        over = (0.5, -0.2, TOP + 0.1 + 0.003 + 0.008)
        send_until(over, 1.0, lambda w: abs(objects_of(w)["block1"].p[1] + 0.2) < 1e-9)
        got = send_until(
            over, 0.0, lambda w: w.held == "" and objects_of(w)["block1"].phase == "resting"
        )
        b1 = objects_of(got)["block1"]
        assert b1.on == "block0"
        np.testing.assert_allclose(b1.p, [0.5, -0.2, TOP + 0.075], atol=1e-12)
        assert (got.data or {}).get("grasps") == 1

        def actions() -> list[str]:
            with lock:
                return [str((e.data or {}).get("action")) for e in events if e.source == "workcell"]

        deadline = time.monotonic() + 5.0
        while actions() != ["grasp", "release", "settled"] and time.monotonic() < deadline:
            scene.wait_count(scene.received + 1, 0.1)
        assert actions() == ["grasp", "release", "settled"]

        reply = watcher.call("workcell", "reset", {}, 5.0)
        assert reply["objects"]["block1"]["p"] == [0.5, -0.1, pytest.approx(TOP + 0.025)]
        status = watcher.call("workcell", "status", {}, 5.0)
        assert status["held"] == ""
    finally:
        svc.close()
