"""The libfranka driver's parts that need no robot: its configuration, the model's
franka.toml, the shared block, the reflex names, the O_T_EE cross-check and the franka
force source's frames."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from services.bus.errors import ConfigError
from services.control.arm.backends import arm_options
from services.control.arm.config import ArmConfig
from services.control.arm.franka.driver import FrankaArm
from services.control.arm.franka.errors import ERROR_FLAGS, error_names, fault_kind, fault_message
from services.control.arm.franka.params import load_params
from services.control.arm.franka.shm import (
    S_EE_T_K,
    S_F_EXT,
    S_F_T_EE,
    S_O_T_EE,
    S_Q,
    S_WALL_NS,
    Shared,
)
from services.control.arm.model import load_model
from services.control.force.config import ForceConfig
from services.control.force.franka_source import FrankaWrenchSource
from services.control.force.sensors import SensorError

FR3 = load_model("fr3")
FRANKY_Q0 = [0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785]


def test_config_needs_the_robot_ip_and_a_franka() -> None:
    with pytest.raises(ConfigError) as e:
        ArmConfig(model="fr3", driver="libfranka")
    assert e.value.key == "arm.robot_ip"
    with pytest.raises(ConfigError) as e:
        ArmConfig(model="fr3", driver="libfranka", robot_ip="10.0.0.2; rm -rf")
    assert e.value.key == "arm.robot_ip"
    with pytest.raises(ConfigError) as e:
        ArmConfig(model="ur5e", driver="libfranka", robot_ip="127.0.0.1").bind(load_model("ur5e"))
    assert e.value.key == "arm.driver"
    with pytest.raises(ConfigError) as e:
        ArmConfig.from_mapping({"driver": "libfranka", "robot_ip": "x", "franka_realtime": "maybe"})
    assert e.value.key == "arm.franka_realtime"
    opts = arm_options(ArmConfig(model="fr3", driver="libfranka", robot_ip="127.0.0.1"), FR3)
    assert opts["robot_ip"] == "127.0.0.1" and opts["realtime"] == "auto"
    assert opts["params"].jerk_rad_s3 == (2500.0,) * 7


def test_franka_toml_is_checked_naming_the_file_and_key(tmp_path: Path) -> None:
    p = load_params(FR3)
    assert p.joint_impedance == (3000.0, 3000.0, 3000.0, 2500.0, 2500.0, 2000.0, 2000.0)
    assert all(
        v <= s for v, s in zip(p.velocity_rad_s, [j.max_speed for j in FR3.joints], strict=True)
    )
    folder = tmp_path / "fr3"
    shutil.copytree(FR3.folder, folder)
    own = load_model(folder / "arm.toml")
    toml = folder / "franka.toml"
    text = toml.read_text()
    for bad, what in [
        (text.replace("jerk_rad_s3 = [", "jerk_rad_s3 = [0.0, "), "jerk_rad_s3"),
        (text.replace("[gripper]", "[grippr]"), "[grippr]"),
        (text.replace("speed_m_s = 0.1", "speed_m_s = 0.1\nforce_n = 3"), "force_n"),
        (text.replace("cartesian = [3000.0, ", "cartesian = [nan, "), "cartesian"),
    ]:
        toml.write_text(bad)
        with pytest.raises(ConfigError) as e:
            load_params(own)
        assert e.value.key == "arm.model" and str(toml) in str(e.value) and what in str(e.value)
    toml.unlink()
    with pytest.raises(ConfigError, match=r"franka\.toml: missing"):
        load_params(own)


def test_error_flags_are_named_and_reflexes_told_apart() -> None:
    assert len(ERROR_FLAGS) == 41 and len(set(ERROR_FLAGS)) == 41
    flags = [n in ("joint_reflex", "power_limit_violation") for n in ERROR_FLAGS]
    assert error_names(flags) == ["joint_reflex", "power_limit_violation"]
    assert fault_kind("Reflex", "Move command aborted") == "reflex"
    assert fault_kind("Idle", "motion aborted by reflex! [...]") == "reflex"
    assert fault_kind("Move", "command rejected") == "control"
    msg = fault_message("reflex", "aborted", ["joint_reflex"])
    assert msg.startswith("reflex: joint_reflex")


def test_the_shared_block_carries_setpoints_and_state_consistently(tmp_path: Path) -> None:
    shm = Shared.create(tmp_path / "b.shm")
    other = Shared.attach(tmp_path / "b.shm")
    try:
        assert other.get_command()[:2] == (0, 0)
        n = shm.put_setpoint([0.1 * i for i in range(7)], 123)
        seq, hold, q, t = other.get_command()
        assert (seq, hold, t) == (n, 0, 123) and q == pytest.approx([0.1 * i for i in range(7)])
        shm.request_hold()
        assert other.get_command()[1] == 1
        a = other.begin_state()
        a[S_Q : S_Q + 7] = 1.5
        other.end_state()
        snap = shm.snapshot()
        assert snap.q.tolist() == [1.5] * 7 and shm.state_seq() % 2 == 0
    finally:
        other.close()
        shm.close()
    assert not (tmp_path / "b.shm").exists()


def _franky_reply(q: list[float], shift_m: float = 0.0) -> dict[str, object]:
    """What franky-sim's robot says at q: O_T_EE from our own FK (plus a shift)."""
    arm = FrankaArm("127.0.0.1", model=FR3)
    try:
        O_T_F = arm._flange_in_base(q)
        F_T_EE = pin.SE3(np.array(FR3.tool_R).reshape(3, 3), np.array(FR3.tool_p))
        O_T_EE = O_T_F * F_T_EE
        O_T_EE.translation = O_T_EE.translation + np.array([shift_m, 0.0, 0.0])
        return {
            "q": q,
            "O_T_EE": O_T_EE.homogeneous.flatten(order="F").tolist(),
            "F_T_EE": F_T_EE.homogeneous.flatten(order="F").tolist(),
        }
    finally:
        arm.close_shared()


def test_the_robot_flange_must_be_where_our_fk_puts_it() -> None:
    arm = FrankaArm("127.0.0.1", model=FR3)
    try:
        assert arm._cross_check(_franky_reply(FRANKY_Q0)) is None
        assert arm._cross_check(_franky_reply(FRANKY_Q0, 0.0008)) is None
        why = arm._cross_check(_franky_reply(FRANKY_Q0, 0.002))
        assert why is not None and "2.0 mm" in why and "refusing to run" in why
        # franky-sim's own numbers at its start pose (float32 on the wire), measured
        measured = {
            "q": [
                -1.5e-08,
                4.29e-07,
                -1.8e-08,
                -1.5700011253356934,
                1.53e-06,
                1.5699999332427979,
                0.7850000262260437,
            ],
            "O_T_EE": [
                0.99999994,
                0.000398135,
                -1.228e-06,
                0.0,
                0.000398135,
                -0.99999994,
                -1.217e-06,
                0.0,
                -1.2285e-06,
                1.2166e-06,
                -1.0,
                0.0,
                0.5544341206550598,
                2.3987e-07,
                0.5214051604270935,
                1.0,
            ],
            "F_T_EE": [
                0.70710677,
                -0.70710677,
                0.0,
                0.0,
                0.70710677,
                0.70710677,
                0.0,
                0.0,
                0.0,
                0.0,
                1.0,
                0.0,
                0.0,
                0.0,
                0.1034,
                1.0,
            ],
        }
        assert arm._cross_check(measured) is None
    finally:
        arm.close_shared()


def test_the_franka_force_source_gives_the_flange_wrench(tmp_path: Path) -> None:
    path = tmp_path / "f.shm"
    src = FrankaWrenchSource("127.0.0.1", path=path)
    with pytest.raises(SensorError, match="no libfranka arm"):
        src.open()
    shm = Shared.create(path)
    try:
        src.open()
        assert src.read() is None  # nothing published yet
        # the EE 0.1 m below the flange along the base's z, turned 90° about z
        Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        O_T_F = np.eye(4)
        O_T_F[:3, :3] = Rz
        O_T_F[:3, 3] = [0.5, 0.0, 0.6]
        F_T_EE = np.eye(4)
        F_T_EE[2, 3] = 0.1
        O_T_EE = O_T_F @ F_T_EE
        a = shm.begin_state()
        a[S_O_T_EE : S_O_T_EE + 16] = O_T_EE.flatten(order="F")
        a[S_F_T_EE : S_F_T_EE + 16] = F_T_EE.flatten(order="F")
        a[S_EE_T_K : S_EE_T_K + 16] = np.eye(4).flatten(order="F")
        a[S_F_EXT : S_F_EXT + 6] = [2.0, 0.0, -10.0, 0.0, 0.0, 0.0]  # at the EE, base frame
        a[S_WALL_NS] = 1.0
        shm.end_state()
        r = src.read()
        assert r is not None and r.kind == "wrench" and r.estimate
        f, m = np.array(r.values[:3]), np.array(r.values[3:])
        # force in the flange frame: Rzᵀ·(2, 0, −10) = (0, −2, −10)
        np.testing.assert_allclose(f, [0.0, -2.0, -10.0], atol=1e-12)
        # moment about the flange origin: r × f with r = (0, 0, −0.1)·… in base = (0,0,-0.1)
        m_base = np.cross(O_T_EE[:3, 3] - O_T_F[:3, 3], [2.0, 0.0, -10.0])
        np.testing.assert_allclose(m, Rz.T @ m_base, atol=1e-12)
        assert not math.isclose(float(np.linalg.norm(m)), 0.0)
        assert src.read() is None  # the same state: no new sample
    finally:
        src.close()
        shm.close()


def test_force_config_for_the_franka_source() -> None:
    with pytest.raises(ConfigError) as e:
        ForceConfig(sensor="franka")
    assert e.value.key == "force.host"
    cfg = ForceConfig(sensor="franka", host="127.0.0.1")
    assert cfg.tool_load().mass_kg == 0.0  # the robot's estimate has its load removed
    assert ForceConfig().tool_load().mass_kg > 0.0


def test_up_passes_the_driver_and_robot_ip_to_the_arm_only() -> None:
    from services.tools.cli.launcher import Overrides, UpConfig, child_argv

    cfg = UpConfig(services=("arm", "force"))
    o = Overrides(model="fr3", driver="libfranka", robot_ip="127.1.2.3")
    arm = child_argv("arm", Path("deploy/sim.toml"), cfg, o)
    assert arm[arm.index("--driver") + 1] == "libfranka"
    assert arm[arm.index("--robot-ip") + 1] == "127.1.2.3"
    assert "--driver" not in child_argv("force", Path("deploy/sim.toml"), cfg, o)


def test_the_arm_ticks_by_the_robot_clock_while_the_loop_runs() -> None:
    from services.control.arm.driver import Clocked
    from services.control.arm.franka.shm import S_CONTROLLING, S_T_ROBOT

    arm = FrankaArm("127.0.0.1", model=FR3)
    try:
        assert isinstance(arm, Clocked)
        a = arm.shm.a
        assert arm.robot_elapsed_s(0.002) == 0.002  # no loop: the wall's
        a[S_CONTROLLING] = 1.0
        a[S_T_ROBOT] = 10.0
        assert arm.robot_elapsed_s(0.002) == 0.002  # the first look
        a[S_T_ROBOT] = 10.0007  # the robot ran 0.7 ms while the wall ran 2
        assert arm.robot_elapsed_s(0.002) == pytest.approx(0.0007)
        assert arm.robot_elapsed_s(0.002) == 0.0  # a stalled robot: no time
        a[S_T_ROBOT] = 1.0  # a new block: the wall's again
        assert arm.robot_elapsed_s(0.002) == 0.002
    finally:
        arm.close_shared()


def test_close_releases_the_block_and_connect_makes_a_fresh_one(tmp_path: Path) -> None:
    arm = FrankaArm("127.0.0.9", model=FR3)
    try:
        path = arm.shm.path
        arm.shm.put_setpoint([0.5] * 7, 1)
        arm.close()
        assert not path.exists()
        assert arm.shm.get_command()[2] == [0.5] * 7  # the last state stays readable
        with pytest.raises(Exception, match="cannot reach the robot"):
            arm.connect()  # nothing at 127.0.0.9: refused, but the block is back
        assert path.exists() and arm.shm.get_command()[2] == [0.5] * 7
        assert arm.status == "error"
    finally:
        arm.close()
        arm.close_shared()
