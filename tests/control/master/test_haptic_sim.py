"""The simulated haptic master: follows the operator's path, presses to the force meant."""

from __future__ import annotations

import numpy as np
import pytest

from services.control.master.backends import open_master_device
from services.control.master.config import MasterConfig
from services.control.master.haptic_sim import SimHapticMaster


def test_free_motion_follows_the_intended_path() -> None:
    """Nothing to press against: down the path, a bounded extra push (5 cm at most) looking
    for the force meant, and back up after the release."""
    dev = SimHapticMaster(depth_m=0.05, approach_s=1.0, hold_s=2.0, release_s=1.0)
    zs = [float(dev.read(0.01).hand_p[2]) for _ in range(500)]  # 5 s
    assert zs[100] == pytest.approx(-0.05, abs=0.005)  # the path's bottom after 1 s
    assert -0.103 <= min(zs) < -0.05
    assert zs[-1] == pytest.approx(0.0, abs=0.003)
    assert dev.t_s == pytest.approx(5.0)


def test_against_a_wall_the_operator_presses_to_the_force_meant() -> None:
    dev = SimHapticMaster(depth_m=0.05, approach_s=1.0, hold_s=4.0, goal_force_n=8.0)
    wall_z, k = -0.02, 2000.0
    forces = []
    for _ in range(4500):  # 4.5 s at 1 kHz: approach and most of the hold
        z = float(dev.read(0.001).hand_p[2])
        push_up = k * max(wall_z - z, 0.0)
        dev.display_force([0.0, 0.0, push_up], [0.0, 0.0, 0.0])
        forces.append(push_up)
    settled = np.asarray(forces[3500:])
    assert settled.mean() == pytest.approx(8.0, rel=0.1)
    assert settled.std() < 0.5
    assert max(forces) < 40.0


def test_config_opens_it_engaged() -> None:
    cfg = MasterConfig(device="haptic_sim")
    assert cfg.engage_on_start
    dev = open_master_device(cfg)
    assert dev.can_display_force and dev.name == "haptic_sim"
    assert not dev.read(0.01).clutch
    with pytest.raises(ValueError, match="depth_m"):
        SimHapticMaster(depth_m=0.0)


def test_with_a_twist_the_hand_turns_the_handle_to_the_moment_meant() -> None:
    """`twist_rad` 0.35: the handle turns about the master's z with the press; against a
    torsional stop at 0.2 rad (30 N·m/rad) the hand turns on until it feels 0.5 N·m. The
    hand's orientation is that turn. Without a twist the handle never turns, whatever
    moment is shown."""
    from services.geometry import rot_z

    dev = SimHapticMaster(depth_m=0.05, approach_s=1.0, hold_s=4.0, twist_rad=0.35)
    stop, k = 0.2, 30.0
    moments = []
    for _ in range(4500):
        hand = dev.read(0.001)
        phi = float(np.arctan2(hand.hand_R[1, 0], hand.hand_R[0, 0]))
        assert hand.hand_R == pytest.approx(rot_z(phi))
        c = -k * max(phi - stop, 0.0)
        dev.display_force([0.0, 0.0, 0.0], [0.0, 0.0, c])
        moments.append(-c)
    settled = np.asarray(moments[3500:])
    assert settled.mean() == pytest.approx(0.5, rel=0.1)
    assert settled.std() < 0.05
    still = SimHapticMaster(depth_m=0.05)
    for _ in range(200):
        still.display_force([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
        assert np.array_equal(still.read(0.005).hand_R, np.eye(3))
