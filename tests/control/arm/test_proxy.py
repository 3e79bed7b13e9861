"""ArmProxy on a SimArm stepped deterministically: the test drives `tick(dt)` and the arm's
`step(dt)` itself, so no wall clock is involved (except where a method must block).

Every setpoint the proxy sends is recorded and checked: joint limits, joint speeds and
accelerations, and the tool's linear and angular speed between consecutive setpoints."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.bus.errors import ConfigError, RpcError
from services.bus.messages import ArmTarget
from services.control.arm.backends import arm_options
from services.control.arm.config import ArmConfig
from services.control.arm.model import load_model
from services.control.arm.proxy import ArmProxy
from services.control.arm.puma560 import Puma560, qn
from services.control.arm.sim_arm import SimArm
from services.geometry import angle_between, tool_target_pose

KIN = Puma560()
HOME_Q_RAD = load_model().home
HOME = np.array(HOME_Q_RAD)
CFG = ArmConfig().bind(load_model())
DT = 1.0 / CFG.control_rate_hz
TABLE_Z_M = 0.40


class RecordingSimArm(SimArm):
    """A SimArm that keeps every setpoint it is given: what would go on the wire."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.sent: list[np.ndarray] = []

    def command(self, q_setpoint: np.ndarray) -> None:
        self.sent.append(np.array(q_setpoint, dtype=np.float64))
        super().command(q_setpoint)


@dataclass
class Rig:
    arm: RecordingSimArm
    proxy: ArmProxy
    dt: float = DT
    events: list[tuple[str, str, dict[str, Any]]] = field(default_factory=list)

    def tick(self, n: int = 1) -> None:
        for _ in range(n):
            self.proxy.tick(self.dt)
            self.arm.step(self.dt)

    def run_until(self, pred: Callable[[], bool], max_ticks: int = 10_000) -> int:
        for n in range(max_ticks):
            if pred():
                return n
            self.tick()
        raise AssertionError("condition not reached")

    def status(self) -> str:
        return self.proxy.status

    def finish(self, max_ticks: int = 10_000) -> int:
        """Tick until the robot is no longer moving."""
        return self.run_until(lambda: self.status() != "moving", max_ticks)

    def kinds(self) -> list[str]:
        return [k for k, _, _ in self.events]

    def q_cmd(self) -> np.ndarray:
        return self.arm.sent[-1]

    def tool(self, q: np.ndarray | None = None) -> pin.SE3:
        return KIN.fk_tool(self.q_cmd() if q is None else q)


def make_rig(
    q_init: np.ndarray = HOME,
    connect: bool = True,
    dt: float = DT,
    config: ArmConfig = CFG,
    **overrides: Any,
) -> Rig:
    arm = RecordingSimArm(q_init, calibration_s=0.02, threaded=False, **overrides)
    rig = Rig(arm, ArmProxy.__new__(ArmProxy), dt)
    rig.proxy = ArmProxy(arm, config, lambda k, m, d: rig.events.append((k, m, d)))
    if connect:
        rig.proxy.rpc_connect({})
        rig.proxy.rpc_initialize({})
        rig.run_until(lambda: rig.status() == "ready")
        rig.tick()
    return rig


def check_setpoints(sent: list[np.ndarray], dt: float = DT) -> None:
    """Every limit the proxy promises, between every two consecutive setpoints."""
    S = np.array(sent)
    assert np.all(KIN.q_lo <= S) and np.all(KIN.q_hi >= S), "joint limit exceeded"
    vmax = np.array(CFG.max_joint_speed_rad_s)
    amax = np.array(CFG.max_joint_accel_rad_s2)
    v = np.diff(S, axis=0) / dt
    assert np.all(np.abs(v) <= vmax * (1 + 1e-9)), f"joint speed {np.max(np.abs(v) / vmax)}"
    if len(S) > 2:
        a = np.diff(S, n=2, axis=0) / dt**2
        assert np.all(np.abs(a) <= amax * (1 + 1e-6) + 1e-6), f"accel {np.max(np.abs(a) / amax)}"
    poses = [KIN.fk_tool(q) for q in S]
    for i in range(len(poses) - 1):
        dp = float(np.linalg.norm(poses[i + 1].translation - poses[i].translation))
        dth = angle_between(poses[i].rotation, poses[i + 1].rotation)
        assert dp <= CFG.max_tool_speed_m_s * dt * (1 + 1e-9), f"tool speed {dp / dt} m/s"
        assert dth <= CFG.max_tool_rot_speed_rad_s * dt * (1 + 1e-9), f"tool turn {dth / dt}"


def rx(a: float) -> np.ndarray:
    return np.array(pin.utils.rotate("x", a))


def rz(a: float) -> np.ndarray:
    return np.array(pin.utils.rotate("z", a))


def flat(R: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(R).reshape(-1)]


class Supervisor:
    """The decision's side of the contract, as a test needs it: motions since an engagement
    (PROTOCOL §2) sent as absolute ArmTargets, from where the arm is told to be (the
    setpoint's tool pose) when each engagement begins."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.engage: int | None = None
        self.p0 = np.zeros(3)
        self.R0 = np.eye(3)

    def target(self, seq: int, dp: Any, dR: Any = None, engage: int = 1, frame: str = "world",
               grip: float | None = None, hold: bool = False) -> ArmTarget:  # fmt: skip
        if engage != self.engage:
            st = self.rig.proxy.state()
            self.engage = engage
            self.p0 = np.array(st.get("tool_p_cmd", st["tool_p"]), dtype=float)
            self.R0 = np.array(st["tool_R"], dtype=float).reshape(3, 3)
        dR = np.eye(3) if dR is None else np.asarray(dR, dtype=float)
        p, R = tool_target_pose(self.p0, self.R0, np.asarray(dp, dtype=float), dR, frame)  # type: ignore[arg-type]
        return ArmTarget(seq=seq, t_ns=seq, origin_t_ns=seq, master="decision", engage=engage,
                         p=tuple(map(float, p)), R=tuple(map(float, np.asarray(R).reshape(-1))),
                         grip=grip, hold=True if hold else None)  # fmt: skip

    def send(self, seq: int, dp: Any, dR: Any = None, **kw: Any) -> None:
        self.rig.proxy.on_target(self.target(seq, dp, dR, **kw))


# --- configuration ---------------------------------------------------------------------------


def test_home_q_is_tool_down_above_the_table() -> None:
    oMt = KIN.fk_tool(HOME)
    np.testing.assert_allclose(oMt.translation, [0.55, 0.0, 0.65], atol=1e-5)
    assert oMt.translation[2] > TABLE_Z_M + 0.2
    np.testing.assert_allclose(oMt.rotation[:, 2], [0.0, 0.0, -1.0], atol=1e-6)
    assert KIN.within_limits(HOME)
    assert np.all(np.degrees(np.minimum(HOME - KIN.q_lo, KIN.q_hi - HOME)) > 25.0)
    assert KIN.singularity(HOME) is None
    assert KIN.manipulability(HOME) > 0.05


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        ({"state_rate_hz": 50.0}, "arm.state_rate_hz"),
        ({"control_rate_hz": 200.0}, "arm.control_rate_hz"),
        ({"max_joint_speed_rad_s": (1.0, 1.0, 1.0)}, "arm.max_joint_speed_rad_s"),
        ({"max_joint_speed_rad_s": (1.0, 1.0, 0.0, 1.0, 1.0, 1.0)}, "arm.max_joint_speed_rad_s"),
        ({"max_joint_speed_rad_s": (9.0, 1.0, 1.0, 1.0, 1.0, 1.0)}, "arm.max_joint_speed_rad_s"),
        (
            {"max_joint_accel_rad_s2": (1.0, 1.0, 1.0, 1.0, 1.0, -1.0)},
            "arm.max_joint_accel_rad_s2",
        ),
        ({"max_tool_speed_m_s": math.nan}, "arm.max_tool_speed_m_s"),
        ({"max_tool_rot_speed_rad_s": 0.0}, "arm.max_tool_rot_speed_rad_s"),
        ({"home_q": (0.0, 0.0, 0.0, 0.0, 2.0, 0.0)}, "arm.home_q"),
        ({"home_q": (0.0, 0.0, 0.0, 0.0, "x", 0.0)}, "arm.home_q"),
        ({"driver": "usb"}, "arm.driver"),
        ({"driver": "serial"}, "arm.port"),
        ({"baudrate": True}, "arm.baudrate"),
        ({"serial_cycle_ms": 40.0}, "arm.serial_cycle_ms"),
        ({"sim_calibration_s": -1.0}, "arm.sim_calibration_s"),
    ],
)
def test_config_rejects_bad_values_naming_the_key(overrides: dict[str, Any], key: str) -> None:
    # what depends on the model is checked against it (`bind`), at start-up as the rest
    with pytest.raises(ConfigError) as info:
        ArmConfig(**overrides).bind(load_model())
    assert info.value.key == key


def test_config_from_a_toml_table() -> None:
    cfg = ArmConfig.from_mapping({"driver": "serial", "port": "/dev/ttyUSB0", "home_q": list(qn)})
    assert cfg.home_q == tuple(qn)
    assert arm_options(cfg) == {
        "port": "/dev/ttyUSB0",
        "baudrate": 115_200,
        "cycle_ms": 28.0,
        "timeout_s": 0.1,
    }
    assert arm_options(ArmConfig()) == {
        "calibration_s": 0.5,
        "q_init": HOME_Q_RAD,
        "model": load_model(),
    }
    with pytest.raises(ConfigError) as info:
        ArmConfig.from_mapping({"state_rate": 100})
    assert info.value.key == "arm.state_rate"


# --- status machine ------------------------------------------------------------------------


def test_status_machine_and_its_events() -> None:
    rig = make_rig(connect=False)
    assert rig.status() == "disconnected"
    for method in (rig.proxy.rpc_initialize, rig.proxy.rpc_home):
        with pytest.raises(RpcError) as info:
            method({})
        assert info.value.code == "not_ready"
    assert rig.proxy.rpc_connect({}) == {"status": "connected"}
    assert rig.proxy.rpc_connect({}) == {"status": "connected"}  # idempotent
    with pytest.raises(RpcError) as info:
        rig.proxy.rpc_home({})
    assert info.value.code == "not_ready"
    assert rig.proxy.rpc_initialize({}) == {"status": "initializing"}
    rig.tick(2)
    assert rig.status() == "initializing"  # calibration takes 20 ms of simulated time
    rig.run_until(lambda: rig.status() == "ready")
    assert len(rig.arm.sent) == 1  # nothing before ready; at ready, one setpoint:
    np.testing.assert_array_equal(rig.arm.sent[0], HOME)  # where the arm is
    rig.tick(5)
    assert len(rig.arm.sent) == 1  # at rest nothing is re-sent: the arm holds it
    r = rig.proxy.rpc_move_joints({"q": list(HOME + 0.1)})
    assert r["accepted"] is True
    assert rig.status() == "moving"
    rig.finish()
    statuses = [d["status"] for k, _, d in rig.events if k == "status"]
    assert statuses == ["connected", "initializing", "ready", "moving", "ready"]
    assert rig.kinds() == ["status", "status", "status", "data", "status", "status", "moved"]
    moved = rig.events[-1][2]
    assert moved["motion"] == r["motion"] and moved["reason"] == "completed"
    np.testing.assert_allclose(moved["q"], HOME + 0.1, atol=1e-12)


def test_state_has_the_robot_state_fields() -> None:
    rig = make_rig()
    s = rig.proxy.state()
    assert s["status"] == "ready"
    for key, n in (("q", 6), ("tool_p", 3), ("tool_R", 9), ("flange_p", 3), ("flange_R", 9)):
        assert isinstance(s[key], list) and len(s[key]) == n
        assert all(type(x) is float for x in s[key])
    assert s["engage"] == -1 and s["cmd_seq"] == -1
    assert "grip" not in s
    assert isinstance(s["manipulability"], float) and s["manipulability"] > 0.05
    np.testing.assert_allclose(s["tool_p"], [0.55, 0.0, 0.65], atol=1e-5)
    R = np.array(s["tool_R"]).reshape(3, 3)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(
        np.array(s["flange_p"]) + np.array(s["flange_R"]).reshape(3, 3) @ [0, 0, 0.2],
        s["tool_p"],
        atol=1e-12,
    )


# --- methods -------------------------------------------------------------------------------


def test_move_joints_reaches_its_target_within_every_limit() -> None:
    rig = make_rig()
    target = HOME + np.array([0.5, -0.3, 0.4, 0.8, 0.3, -1.0])
    r = rig.proxy.rpc_move_joints({"q": list(target)})
    assert r["path"] == "joint"
    rig.finish()
    np.testing.assert_array_equal(rig.q_cmd(), target)
    assert rig.proxy.wait_motion(r["motion"], 0.0) == {
        "motion": r["motion"], "done": True, "completed": True, "reason": "completed",
        "q": list(target),
    }  # fmt: skip
    check_setpoints(rig.arm.sent)
    # Measured joints catch up with the last setpoint.
    rig.run_until(lambda: bool(np.max(np.abs(np.array(rig.proxy.state()["q"]) - target)) < 1e-6))


def test_speed_fraction_slows_a_joint_move() -> None:
    rig = make_rig()
    full = rig.proxy.rpc_move_joints({"q": list(HOME + 0.6)})
    rig.finish()
    half = rig.proxy.rpc_move_joints({"q": list(HOME), "speed": 0.25})
    rig.finish()
    assert half["duration_s"] > 1.5 * full["duration_s"]
    check_setpoints(rig.arm.sent)


@pytest.mark.parametrize(
    ("args", "field_name"),
    [
        ({}, "q"),
        ({"q": [0.0] * 5}, "q"),
        ({"q": [0.0] * 5 + [math.nan]}, "q"),
        ({"q": [0.0] * 5 + [math.inf]}, "q"),
        ({"q": [0.0] * 5 + [True]}, "q"),
        ({"q": "home"}, "q"),
        ({"q": list(HOME), "speed": 0.0}, "speed"),
        ({"q": list(HOME), "speed": 1.5}, "speed"),
        ({"q": list(HOME), "speed": "fast"}, "speed"),
        ({"q": list(HOME), "speed": math.nan}, "speed"),
    ],
)
def test_move_joints_refuses_bad_arguments(args: dict[str, Any], field_name: str) -> None:
    rig = make_rig()
    n = len(rig.arm.sent)
    with pytest.raises(RpcError) as info:
        rig.proxy.rpc_move_joints(args)
    assert info.value.code == "bad_request"
    assert info.value.message.startswith(field_name + ":")
    rig.tick(5)
    assert rig.status() == "ready"
    assert all(np.array_equal(q, HOME) for q in rig.arm.sent[n:])


def test_move_joints_outside_the_limits_is_refused() -> None:
    rig = make_rig()
    q = HOME.copy()
    q[4] = math.radians(101.0)
    with pytest.raises(RpcError) as info:
        rig.proxy.rpc_move_joints({"q": list(q)})
    assert info.value.code == "limit"
    assert "q[4]" in info.value.message
    assert rig.status() == "ready"


def test_move_pose_follows_a_straight_line() -> None:
    rig = make_rig()
    start = rig.tool()
    p1 = start.translation + np.array([0.12, -0.15, -0.1])
    R1 = start.rotation @ rz(0.4) @ rx(0.2)
    r = rig.proxy.rpc_move_pose({"p": list(p1), "R": flat(R1)})
    assert r["path"] == "cartesian"
    n0 = len(rig.arm.sent)
    rig.finish()
    end = rig.tool()
    np.testing.assert_allclose(end.translation, p1, atol=1e-9)
    np.testing.assert_allclose(end.rotation, R1, atol=1e-9)
    u = (p1 - start.translation) / np.linalg.norm(p1 - start.translation)
    for q in rig.arm.sent[n0:]:
        d = rig.tool(q).translation - start.translation
        assert np.linalg.norm(d - (d @ u) * u) < 2e-4  # off the line by < 0.2 mm
    check_setpoints(rig.arm.sent)


def test_move_pose_with_another_branch_moves_in_joint_space() -> None:
    rig = make_rig(qn)
    assert KIN.config(qn) == "rup"
    pose = KIN.fk_tool(qn)
    r = rig.proxy.rpc_move_pose(
        {"p": list(pose.translation), "R": flat(pose.rotation), "config": "lup"}
    )
    assert r["path"] == "joint"
    rig.finish()
    assert KIN.config(rig.q_cmd()) == "lup"
    end = rig.tool()
    np.testing.assert_allclose(end.translation, pose.translation, atol=1e-9)
    check_setpoints(rig.arm.sent)


@pytest.mark.parametrize(
    ("args", "code", "field_name"),
    [
        ({"p": [3.0, 0.0, 0.5], "R": flat(np.eye(3))}, "unreachable", None),
        (
            {"p": [0.55, 0.0, 0.65], "R": flat(np.diag([-1.0, 1.0, -1.0])), "config": "rup"},
            "limit",
            None,
        ),
        ({"p": [0.55, 0.0, 0.65], "R": flat(np.diag([1.0, 1.0, -1.0]))}, "bad_request", "R"),
        ({"p": [0.55, 0.0, 0.65], "R": flat(np.eye(3) * 1.001)}, "bad_request", "R"),
        ({"p": [0.55, 0.0, 0.65], "R": [1.0] * 8}, "bad_request", "R"),
        ({"p": [0.55, math.nan, 0.65], "R": flat(np.eye(3))}, "bad_request", "p"),
        ({"R": flat(np.eye(3))}, "bad_request", "p"),
        ({"p": [0.55, 0.0, 0.65], "R": flat(np.eye(3)), "config": "xyz"}, "bad_request", "config"),
    ],
)
def test_move_pose_refusals(args: dict[str, Any], code: str, field_name: str | None) -> None:
    rig = make_rig()
    with pytest.raises(RpcError) as info:
        rig.proxy.rpc_move_pose(args)
    assert info.value.code == code
    if field_name:
        assert info.value.message.startswith(field_name + ":")
    assert rig.status() == "ready"


@pytest.mark.parametrize("frame", ["world", "wrist", "tool"])
def test_move_relative_in_each_frame(frame: str) -> None:
    rig = make_rig()
    q0 = rig.q_cmd().copy()
    oMe, oMt = KIN.fk_flange(q0), KIN.fk_tool(q0)
    dp = np.array([0.05, -0.04, 0.03])
    dR = rz(0.3) @ rx(-0.2)
    R_f = {"world": np.eye(3), "wrist": oMe.rotation, "tool": oMt.rotation}[frame]
    r = rig.proxy.rpc_move_relative({"dp": list(dp), "dR": flat(dR), "frame": frame})
    assert r["path"] == "cartesian"
    rig.finish()
    end = rig.tool()
    np.testing.assert_allclose(end.translation, oMt.translation + R_f @ dp, atol=1e-9)
    np.testing.assert_allclose(end.rotation, R_f @ dR @ R_f.T @ oMt.rotation, atol=1e-9)
    check_setpoints(rig.arm.sent)


def test_a_pure_rotation_turns_the_tool_about_the_tool_point() -> None:
    rig = make_rig()
    p0 = rig.tool().translation.copy()
    n0 = len(rig.arm.sent)
    rig.proxy.rpc_move_relative({"dp": [0.0, 0.0, 0.0], "dR": flat(rx(0.4)), "frame": "tool"})
    rig.finish()
    for q in rig.arm.sent[n0:]:
        assert np.linalg.norm(rig.tool(q).translation - p0) < 2e-4
    check_setpoints(rig.arm.sent)


def test_set_frame_is_the_default_of_move_relative() -> None:
    rig = make_rig()
    assert rig.proxy.rpc_set_frame({"frame": "tool"}) == {"frame": "tool"}
    p0, R0 = rig.tool().translation.copy(), rig.tool().rotation.copy()
    rig.proxy.rpc_move_relative({"dp": [0.0, 0.0, 0.05]})  # tool z points down at home
    rig.finish()
    np.testing.assert_allclose(rig.tool().translation, p0 + R0 @ [0.0, 0.0, 0.05], atol=1e-9)
    np.testing.assert_allclose(rig.tool().translation, p0 + np.array([0.0, 0.0, -0.05]), atol=1e-6)
    for bad in ({}, {"frame": "base"}, {"frame": 3}):
        with pytest.raises(RpcError) as info:
            rig.proxy.rpc_set_frame(bad)
        assert info.value.code == "bad_request"


def test_move_relative_refuses_huge_or_bad_displacements() -> None:
    rig = make_rig()
    for args in (
        {"dp": [5.0, 0.0, 0.0]},
        {"dp": [1e300, 0.0, 0.0]},
        {"dp": [0.0, 0.0, math.nan]},
        {"dp": [0.0, 0.0, 0.0], "dR": flat(np.diag([1.0, -1.0, 1.0]))},
        {"dp": [0.0, 0.0, 0.0], "frame": "flange"},
    ):
        with pytest.raises(RpcError) as info:
            rig.proxy.rpc_move_relative(args)
        assert info.value.code == "bad_request"
    with pytest.raises(RpcError) as info:
        rig.proxy.rpc_move_relative({"dp": [0.0, 0.0, -0.9]})  # through the floor: no IK
    assert info.value.code in ("unreachable", "limit")
    assert rig.status() == "ready"


def test_set_tool_moves_the_tool_point_not_the_arm() -> None:
    rig = make_rig()
    r = rig.proxy.rpc_set_tool({"p": [0.0, 0.0, 0.1], "R": flat(rz(0.5))})
    assert r["tool_p"] == [0.0, 0.0, 0.1]
    s = rig.proxy.state()
    flange = np.array(s["flange_R"]).reshape(3, 3)
    np.testing.assert_allclose(
        s["tool_p"], np.array(s["flange_p"]) + flange @ [0, 0, 0.1], atol=1e-12
    )
    np.testing.assert_allclose(np.array(s["tool_R"]).reshape(3, 3), flange @ rz(0.5), atol=1e-12)
    rig.proxy.rpc_move_joints({"q": list(HOME + 0.1)})
    with pytest.raises(RpcError) as info:
        rig.proxy.rpc_set_tool({"p": [0.0, 0.0, 0.2], "R": flat(np.eye(3))})
    assert info.value.code == "busy"
    for bad in ({"p": [0, 0, 0.1]}, {"p": [0, 0, 5.0], "R": flat(np.eye(3))}):
        with pytest.raises(RpcError):
            rig.proxy.rpc_set_tool(bad)


def test_a_second_move_while_moving_is_busy() -> None:
    rig = make_rig()
    rig.proxy.rpc_move_joints({"q": list(HOME + 0.3)})
    rig.tick(10)
    for method, args in (
        (rig.proxy.rpc_move_joints, {"q": list(HOME)}),
        (rig.proxy.rpc_home, {}),
        (rig.proxy.rpc_move_relative, {"dp": [0.0, 0.0, 0.01]}),
        (rig.proxy.rpc_initialize, {}),
    ):
        with pytest.raises(RpcError) as info:
            method(args)
        assert info.value.code == "busy"


def test_stop_brakes_to_rest_within_the_limits() -> None:
    rig = make_rig()
    target = HOME + np.array([0.8, -0.5, 0.6, 1.0, 0.5, 1.2])
    r = rig.proxy.rpc_move_joints({"q": list(target)})
    rig.tick(300)
    assert rig.proxy.rpc_stop({}) == {"status": "moving", "motion": r["motion"]}
    braking = rig.finish()
    result = rig.proxy.wait_motion(r["motion"], 0.0)
    assert result["done"] and not result["completed"] and result["reason"] == "stopped"
    q_stop = rig.q_cmd()
    assert np.all((q_stop - HOME) * (target - HOME) > 0) and np.all(
        np.abs(q_stop - HOME) < np.abs(target - HOME)
    )
    assert 0 < braking < 500
    n = len(rig.arm.sent)
    rig.tick(20)
    assert len(rig.arm.sent) == n  # at rest: nothing new to send, the arm holds
    np.testing.assert_array_equal(rig.arm.sent[-1], q_stop)
    check_setpoints(rig.arm.sent)
    assert rig.proxy.rpc_stop({}) == {"status": "ready", "motion": None}


def test_stop_now_holds_the_measured_joints_at_once() -> None:
    """The decision's contact stop: no braking distance; the setpoint steps back to where
    the arm measurably is (never ahead of it); `now` must be a bool."""
    rig = make_rig()
    target = HOME + np.array([0.8, -0.5, 0.6, 1.0, 0.5, 1.2])
    r = rig.proxy.rpc_move_joints({"q": list(target)})
    rig.tick(300)
    q_meas = rig.arm.read_joints().copy()
    with pytest.raises(RpcError) as bad:
        rig.proxy.rpc_stop({"now": "yes"})
    assert bad.value.code == "bad_request" and rig.status() == "moving"
    assert rig.proxy.rpc_stop({"now": True}) == {"status": "ready", "motion": r["motion"]}
    result = rig.proxy.wait_motion(r["motion"], 0.0)
    assert result["done"] and result["reason"] == "stopped"
    # the joints the proxy last measured (a cycle ago): at most a cycle's travel behind the
    # arm, never ahead of it along the motion
    q_cmd = rig.q_cmd()
    np.testing.assert_array_equal(rig.arm.sent[-1], q_cmd)
    assert np.all(np.abs(q_cmd - q_meas) <= 5.0 * DT)  # ≤ vmax · one cycle
    assert np.all((q_meas - q_cmd) * (target - HOME) >= 0.0)
    n = len(rig.arm.sent)
    rig.tick(20)
    assert len(rig.arm.sent) == n  # at rest: the arm holds the measured joints


def test_a_speed_fraction_slows_a_cartesian_move() -> None:
    rig = make_rig()
    fk = rig.proxy.rpc_fk({"q": list(HOME)})
    p0 = np.asarray(fk["tool_p"])
    full = rig.proxy.rpc_move_pose({"p": list(p0 + np.array([0.0, 0.0, -0.1])), "R": fk["tool_R"]})
    rig.finish()
    slow = rig.proxy.rpc_move_relative({"dp": [0.0, 0.0, 0.1], "frame": "world", "speed": 0.2})
    rig.finish()
    assert slow["duration_s"] > 2.0 * full["duration_s"]
    with pytest.raises(RpcError):
        rig.proxy.rpc_move_pose({"p": list(p0), "R": fk["tool_R"], "speed": 0.0})


def test_wait_motion_blocks_until_the_motion_ends() -> None:
    rig = make_rig()
    r = rig.proxy.rpc_move_joints({"q": list(HOME + 0.2)})
    assert rig.proxy.wait_motion(r["motion"], 0.0)["done"] is False
    result: dict[str, Any] = {}
    waiter = threading.Thread(
        target=lambda: result.update(rig.proxy.wait_motion(r["motion"], 30.0))
    )
    waiter.start()
    while waiter.is_alive():
        rig.tick()  # the "control loop" runs here while the other thread waits
        waiter.join(timeout=0.0005)
    assert result["done"] and result["completed"] and result["reason"] == "completed"
    with pytest.raises(RpcError) as info:
        rig.proxy.wait_motion(12345, 0.0)
    assert info.value.code == "bad_request"


def test_home_fk_ik_and_limits() -> None:
    rig = make_rig(qn)
    r = rig.proxy.rpc_home({})
    rig.finish()
    assert rig.proxy.wait_motion(r["motion"], 0.0)["completed"]
    np.testing.assert_array_equal(rig.q_cmd(), HOME)
    fk = rig.proxy.rpc_fk({"q": list(qn)})
    np.testing.assert_allclose(fk["tool_p"], KIN.fk_tool(qn).translation, atol=1e-12)
    np.testing.assert_allclose(fk["flange_R"], flat(KIN.fk_flange(qn).rotation), atol=1e-12)
    ik = rig.proxy.rpc_ik({"p": fk["tool_p"], "R": fk["tool_R"]})
    assert len(ik["solutions"]) == 8
    assert sorted(s["config"] for s in ik["solutions"]) == sorted(
        a + b + c for a in "rl" for b in "ud" for c in "pm"
    )
    assert {s["config"] for s in ik["solutions"] if s["in_limits"]} == {"rup", "lup", "lum"}
    for s in ik["solutions"]:
        np.testing.assert_allclose(KIN.fk_tool(s["q"]).translation, fk["tool_p"], atol=1e-9)
    assert rig.proxy.rpc_ik({"p": [5.0, 0.0, 0.0], "R": flat(np.eye(3))}) == {"solutions": []}
    with pytest.raises(RpcError):
        rig.proxy.rpc_fk({"q": [0.0] * 6 + [1.0]})
    lim = rig.proxy.rpc_limits({})
    np.testing.assert_allclose(lim["q_hi"], KIN.q_hi)
    assert lim["max_tool_speed_m_s"] == 0.5
    assert lim["max_joint_speed_rad_s"] == list(CFG.max_joint_speed_rad_s)


# --- streamed targets ----------------------------------------------------------------------


def test_teleop_follows_the_engagement_in_world_and_tool_frames() -> None:
    rig = make_rig()
    sup = Supervisor(rig)
    p0 = rig.tool().translation.copy()
    R0 = rig.tool().rotation.copy()
    for k in range(1, 51):
        sup.send(k, [0.001 * k, 0.0, 0.0], rz(0.004 * k), grip=0.5)
        rig.tick(10)  # targets at 50 Hz, control at 500 Hz
    assert rig.status() == "moving"
    rig.finish()
    np.testing.assert_allclose(rig.tool().translation, p0 + np.array([0.05, 0.0, 0.0]), atol=1e-9)
    np.testing.assert_allclose(rig.tool().rotation, R0 @ rz(0.2), atol=1e-9)
    s = rig.proxy.state()
    assert (s["engage"], s["cmd_seq"], s["grip"]) == (1, 50, 0.5)
    assert rig.kinds().count("moved") == 1  # no flapping between commands
    # A new engagement in the tool frame starts from where the tool is now (as robot/state
    # shows it: the setpoint's pose, or the measured one within SETPOINT_SHOWN_M of it).
    p1 = rig.tool().translation.copy()
    sup.send(51, [0.0, 0.0, 0.03], engage=2, frame="tool")
    rig.finish()
    np.testing.assert_allclose(rig.tool().translation, p1 + R0 @ rz(0.2) @ [0, 0, 0.03], atol=1e-6)
    check_setpoints(rig.arm.sent)


def test_stale_targets_and_holds_do_not_move_the_arm() -> None:
    rig = make_rig()
    sup = Supervisor(rig)
    sup.send(10, [0.02, 0.0, 0.0])
    rig.finish()
    q = rig.q_cmd().copy()
    ignored = rig.proxy.counters["commands_ignored"]
    sup.send(9, [0.04, 0.0, 0.0])  # older seq
    rig.proxy.on_target(replace(sup.target(11, [0.04, 0.0, 0.0]), engage=0))  # older engagement
    sup.send(12, [0.02, 0.0, 0.0], hold=True)  # the supervisor holds: the same target again
    rig.tick(50)
    assert rig.status() == "ready"
    np.testing.assert_array_equal(rig.q_cmd(), q)
    assert rig.proxy.counters["commands_ignored"] == ignored + 2
    assert rig.proxy.state()["cmd_seq"] == 12


def test_a_target_rebuilt_each_tick_to_its_last_bits_lets_the_arm_settle() -> None:
    """A supervisor that rebuilds the target every tick from what the arm measures (the
    decision with compliance on, at rest) sends poses that differ in their last bits: the
    arm aims at the first, settles and says `ready`, and a real step after that moves it."""
    rig = make_rig()
    sup = Supervisor(rig)
    sup.send(1, [0.02, 0.0, 0.0])
    rig.finish()
    q = rig.q_cmd().copy()
    base = sup.target(2, [0.02, 0.0, 0.0])
    for k in range(2, 200):  # 2 s of targets at 100 Hz, each off by up to 0.5 µm
        e = 5e-7 * math.sin(k)
        p = tuple(x + e for x in base.p)
        R = tuple(x - e for x in base.R)
        rig.proxy.on_target(replace(base, seq=k, t_ns=k, origin_t_ns=k, p=p, R=R))
        rig.tick(5)
    assert rig.status() == "ready"
    np.testing.assert_array_equal(rig.q_cmd(), q)
    sup.send(300, [0.02 + 1e-5, 0.0, 0.0])  # 10 µm: a step, solved and followed
    rig.tick(5)
    assert rig.status() == "moving"
    rig.finish()
    assert rig.status() == "ready" and not np.array_equal(rig.q_cmd(), q)


def test_commands_are_ignored_unless_ready() -> None:
    rig = make_rig(connect=False)
    sup = Supervisor(rig)
    sup.send(1, [0.01, 0.0, 0.0])
    rig.proxy.rpc_connect({})
    sup.send(2, [0.01, 0.0, 0.0])
    assert rig.proxy.counters["commands_ignored"] == 2
    assert rig.proxy.state()["cmd_seq"] == -1


def test_a_command_preempts_a_move_and_moves_are_busy_during_teleop() -> None:
    rig = make_rig()
    r = rig.proxy.rpc_move_joints({"q": list(HOME + 0.4)})
    rig.tick(100)
    Supervisor(rig).send(1, [0.0, 0.0, 0.01])
    result = rig.proxy.wait_motion(r["motion"], 0.0)
    assert result["done"] and result["reason"] == "preempted"
    with pytest.raises(RpcError) as info:
        rig.proxy.rpc_move_joints({"q": list(HOME)})
    assert info.value.code == "busy"
    rig.finish()
    check_setpoints(rig.arm.sent)
    assert rig.proxy.rpc_home({})["accepted"]  # once teleop has settled


def test_unreachable_target_holds_and_reports_at_a_bounded_rate() -> None:
    # A step bound wide enough to let a target 0.5 m away through to the solver: the wrist
    # centre would be 1.07 m from the shoulder, the arm reaches 0.86 m.
    rig = make_rig(config=replace(CFG, max_target_step_m=1.0))
    sup = Supervisor(rig)
    sup.send(1, [0.02, 0.0, 0.0])
    rig.finish()
    q_hold = rig.q_cmd().copy()
    n_events = len(rig.events)
    for k in range(2, 1002):  # 2 s of 500 Hz targets, all out of reach
        sup.send(k, [0.5, 0.0, 0.0])
        rig.tick()
    assert rig.proxy.counters["unreachable"] == 1000
    errors = [d for k, _, d in rig.events[n_events:] if k == "unreachable"]
    assert 1 <= len(errors) <= 3
    assert all(d["code"] == "unreachable" for d in errors)
    assert errors[-1].get("suppressed", 0) > 0 or len(errors) == 1
    assert rig.status() == "ready"
    np.testing.assert_array_equal(rig.q_cmd(), q_hold)


# --- faults ----------------------------------------------------------------------------------


@pytest.mark.parametrize("fault", ["error", "disconnect", "stall"])
def test_arm_fault_mid_motion_gives_error_hold_and_recovery(fault: str) -> None:
    rig = make_rig()
    r = rig.proxy.rpc_move_joints({"q": list(HOME + 0.5)})
    rig.tick(150)
    rig.arm.inject_fault(fault, joint=2)  # type: ignore[arg-type]
    rig.run_until(lambda: rig.status() == "error", max_ticks=200)
    assert rig.proxy.wait_motion(r["motion"], 0.0)["reason"] == "error"
    err = [d for k, _, d in rig.events if k == "error"]
    assert err and err[-1]["code"] == "internal"
    n = len(rig.arm.sent)
    rig.tick(100)
    assert len(rig.arm.sent) == n  # nothing is sent in error
    with pytest.raises(RpcError) as info:
        rig.proxy.rpc_move_joints({"q": list(HOME)})
    assert info.value.code == "not_ready"
    rig.tick(500)  # the arm comes to rest
    rig.proxy.rpc_connect({})
    rig.proxy.rpc_initialize({})
    rig.run_until(lambda: rig.status() == "ready")
    rig.tick()
    np.testing.assert_allclose(rig.arm.sent[-1], rig.arm.q_true, atol=1e-12)  # no jump
    check_setpoints(rig.arm.sent[n:])
    r2 = rig.proxy.rpc_move_joints({"q": list(HOME)})
    rig.finish()
    assert rig.proxy.wait_motion(r2["motion"], 0.0)["completed"]


def test_following_error_is_an_error() -> None:
    rig = make_rig(stall_threshold_rad=10.0)  # the arm itself does not notice
    rig.proxy.rpc_move_joints({"q": list(HOME + 0.6)})
    rig.tick(50)
    rig.arm.inject_fault("stall", joint=3)
    rig.run_until(lambda: rig.status() == "error", max_ticks=1000)
    assert "following error" in str(rig.proxy.rpc_status({})["error"])


def test_estop_and_recovery() -> None:
    rig = make_rig()
    r = rig.proxy.rpc_move_joints({"q": list(HOME + 0.3)})
    rig.tick(100)
    assert rig.proxy.rpc_estop({}) == {"status": "error"}
    assert rig.proxy.wait_motion(r["motion"], 0.0)["reason"] == "estop"
    assert "estop" in rig.kinds()
    assert rig.arm.status == "error"
    for method in (rig.proxy.rpc_home, rig.proxy.rpc_initialize):
        with pytest.raises(RpcError) as info:
            method({})
        assert info.value.code == "estop"
    rig.proxy.rpc_connect({})
    rig.proxy.rpc_initialize({})
    rig.run_until(lambda: rig.status() == "ready")
    assert rig.proxy.rpc_status({})["estop"] is False


def test_close_holds_and_disconnects() -> None:
    rig = make_rig()
    r = rig.proxy.rpc_move_joints({"q": list(HOME + 0.3)})
    rig.tick(100)
    rig.proxy.close()
    assert rig.proxy.wait_motion(r["motion"], 0.0)["reason"] == "closed"
    assert rig.status() == "disconnected"
    assert rig.arm.status == "disconnected"
    q = rig.arm.q_true
    rig.arm.step(1.0)
    assert np.max(np.abs(rig.arm.q_true - q)) < 0.05  # only the braking distance


# --- properties ----------------------------------------------------------------------------

FUZZ = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
LONG_FUZZ = settings(FUZZ, max_examples=10)  # each example simulates seconds of motion
ANY_VALUE = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(10**6), 10**6),
    st.booleans(),
    st.text(max_size=4),
    st.none(),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=10),
)


@LONG_FUZZ
@given(
    target=st.lists(st.floats(0.0, 1.0), min_size=6, max_size=6),
    speed=st.one_of(st.none(), st.floats(0.05, 1.0)),
    dt=st.sampled_from([DT, 0.01]),  # the loop's rate is the service's choice
)
def test_any_joint_move_stays_within_every_limit(
    target: list[float], speed: float | None, dt: float
) -> None:
    rig = make_rig(dt=dt)
    # Up to ±1.5 rad from home, clipped: many targets sit exactly on a joint limit.
    q = np.clip(HOME + (2.0 * np.array(target) - 1.0) * 1.5, KIN.q_lo, KIN.q_hi)
    args: dict[str, Any] = {"q": list(q)}
    if speed is not None:
        args["speed"] = speed
    r = rig.proxy.rpc_move_joints(args)
    rig.finish(max_ticks=100_000)
    assert rig.proxy.wait_motion(r["motion"], 0.0)["completed"]
    np.testing.assert_array_equal(rig.q_cmd(), q)
    check_setpoints(rig.arm.sent, dt)


ARG_NAMES = ["q", "p", "R", "dp", "dR", "frame", "speed", "config"]


@FUZZ
@given(
    name=st.sampled_from(["move_joints", "move_pose", "move_relative", "set_tool", "fk", "ik"]),
    args=st.dictionaries(st.sampled_from(ARG_NAMES), ANY_VALUE, max_size=4),
)
def test_garbage_arguments_never_move_the_arm(name: str, args: dict[str, Any]) -> None:
    rig = make_rig()
    n = len(rig.arm.sent)
    try:
        getattr(rig.proxy, f"rpc_{name}")(args)
    except RpcError as e:
        assert e.code in ("bad_request", "limit", "unreachable")
        rig.tick(20)
        assert all(np.array_equal(q, HOME) for q in rig.arm.sent[n:])
    else:
        # Random values can make a valid request (q = 0 is within the limits): fine, if safe.
        rig.finish(max_ticks=100_000)
        check_setpoints(rig.arm.sent)


rotations = st.builds(
    lambda axis, angle: np.array(
        pin.exp3(np.asarray(axis) / max(np.linalg.norm(axis), 1e-9) * angle)
    ),
    st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda a: np.linalg.norm(a) > 0.1),
    st.floats(-0.6, 0.6),
)
bad_targets = st.one_of(
    st.tuples(st.just("huge"), st.floats(2.01, 1e12)),
    st.tuples(st.just("reflect"), st.integers(0, 2)),
    st.tuples(st.just("skew"), st.floats(1e-4, 0.5)),
    st.tuples(st.just("grip"), st.sampled_from([-0.1, 1.5, math.nan, math.inf])),
)


def make_bad(sup: Supervisor, k: int, bad: tuple[str, float], engage: int = 1) -> ArmTarget:
    kind, x = bad
    if kind == "huge":
        return sup.target(k, [x, 0.0, 0.0], engage=engage)
    if kind == "reflect":
        R = np.eye(3)
        R[int(x), int(x)] = -1.0
        return sup.target(k, [0.01, 0.0, 0.0], R, engage=engage)
    if kind == "skew":
        return sup.target(k, [0.01, 0.0, 0.0], np.eye(3) + x * np.ones((3, 3)), engage=engage)
    return sup.target(k, [0.01, 0.0, 0.0], grip=x, engage=engage)


@FUZZ
@given(stream=st.lists(bad_targets, min_size=1, max_size=30))
def test_invalid_targets_are_rejected_and_never_move(stream: list[tuple[str, float]]) -> None:
    rig = make_rig()
    sup = Supervisor(rig)
    n = len(rig.arm.sent)
    for k, bad in enumerate(stream, start=1):
        rig.proxy.on_target(make_bad(sup, k, bad))
        rig.tick(3)
    assert rig.proxy.counters["rejected"] == len(stream)
    assert "rejected" in rig.kinds()
    assert rig.status() == "ready"
    assert all(np.array_equal(q, HOME) for q in rig.arm.sent[n:])
    assert rig.proxy.state()["cmd_seq"] == -1


@FUZZ
@given(
    steps=st.lists(
        st.tuples(
            st.one_of(st.lists(st.floats(-0.1, 0.1), min_size=3, max_size=3), bad_targets),
            rotations,
            st.booleans(),  # hold
            st.sampled_from(["world", "tool"]),
            st.integers(0, 1),  # engage increment
            st.integers(1, 25),  # ticks until the next command
        ),
        min_size=1,
        max_size=25,
    )
)
def test_any_target_stream_stays_within_every_limit(steps: list[Any]) -> None:
    rig = make_rig()
    sup = Supervisor(rig)
    engage = 1
    for k, (dp, dR, hold, frame, inc, ticks) in enumerate(steps, start=1):
        engage += inc
        if isinstance(dp, tuple):
            tgt = make_bad(sup, k, dp, engage)
        else:
            tgt = sup.target(k, dp, dR, engage=engage, frame=frame, hold=hold)
        rig.proxy.on_target(tgt)
        rig.tick(ticks)
    rig.finish(max_ticks=20_000)
    assert rig.status() == "ready"
    check_setpoints(rig.arm.sent)


def test_a_target_turned_in_place_turns_the_tool_about_the_tool_point() -> None:
    """PROTOCOL §2: a pure rotation command turns the tool about the tool point, which stays
    put; the arm solves the tool target through its tool placement (eqs. 2–3)."""
    rig = make_rig()
    p0 = rig.tool().translation.copy()
    R0 = rig.tool().rotation.copy()
    sup = Supervisor(rig)
    for k in range(1, 31):
        sup.send(k, [0.0, 0.0, 0.0], rx(0.01 * k) @ rz(0.01 * k), frame="tool")
        rig.tick(5)
    rig.finish()
    np.testing.assert_allclose(rig.tool().translation, p0, atol=1e-6)
    np.testing.assert_allclose(rig.tool().rotation, R0 @ rx(0.3) @ rz(0.3), atol=1e-6)
    check_setpoints(rig.arm.sent)
