"""Eq. 5 against hand-worked cases, and the master-shift state machine."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import ArrayLike

from services.bus import codec
from services.bus.messages import OperatorCommand
from services.control.master.config import MasterConfig
from services.control.master.device import HandReading
from services.control.master.teleop import Teleop, check_command, scaled_motion
from services.geometry import exp_so3, rot_x, rot_y, rot_z, rotation_angle, rxyz

DEG = math.pi / 180.0
SCALES = (0.1, 0.25, 0.5, 1.0)


def reading(
    p: ArrayLike = (0.0, 0.0, 0.0),
    R: np.ndarray | None = None,
    clutch: bool = False,
    grip: float | None = None,
) -> HandReading:
    return HandReading(np.array(p, dtype=float), np.eye(3) if R is None else R, clutch, grip)


def teleop(**overrides: Any) -> Teleop:
    cfg = MasterConfig(master_id="m1", device="virtual", **overrides)
    return Teleop(cfg, "test", seq_start=0, engage_start=0)


# --- eq. 5, hand-worked -------------------------------------------------------------------


@pytest.mark.parametrize("s", SCALES)
def test_translation_is_scaled_difference(s: float) -> None:
    m = scaled_motion((0.1, 0.2, 0.3), np.eye(3), (0.2, 0.2, 0.1), np.eye(3), s, 1.0)
    np.testing.assert_allclose(m.dp, [0.1 * s, 0.0, -0.2 * s], atol=1e-15)
    np.testing.assert_allclose(m.dR, np.eye(3), atol=1e-15)


def test_alignment_maps_master_axes_onto_slave_axes() -> None:
    # The operator faces the robot from its side: master x (right) is slave y.
    A = rot_z(90 * DEG)
    m = scaled_motion(np.zeros(3), np.eye(3), (0.1, 0.0, 0.0), np.eye(3), 1.0, 1.0, A)
    np.testing.assert_allclose(m.dp, [0.0, 0.1, 0.0], atol=1e-15)
    m = scaled_motion(np.zeros(3), np.eye(3), (0.0, 0.1, 0.0), np.eye(3), 0.5, 1.0, A)
    np.testing.assert_allclose(m.dp, [-0.05, 0.0, 0.0], atol=1e-15)


def test_rotation_120_deg_about_x_halved_is_60_about_x() -> None:
    m = scaled_motion(np.zeros(3), np.eye(3), np.zeros(3), rot_x(120 * DEG), 1.0, 0.5)
    np.testing.assert_allclose(m.angles_rad, [120 * DEG, 0.0, 0.0], atol=1e-12)
    c, s = 0.5, math.sqrt(3) / 2
    np.testing.assert_allclose(m.dR, [[1, 0, 0], [0, c, -s], [0, s, c]], atol=1e-12)


@pytest.mark.parametrize("s", SCALES)
def test_rotation_150_deg_about_z_scaled(s: float) -> None:
    m = scaled_motion(np.zeros(3), np.eye(3), np.zeros(3), rot_z(150 * DEG), 1.0, s)
    np.testing.assert_allclose(m.angles_rad, [0.0, 0.0, 150 * DEG], atol=1e-12)
    np.testing.assert_allclose(m.dR, rot_z(150 * DEG * s), atol=1e-12)


@pytest.mark.parametrize("s", SCALES)
def test_rotation_170_deg_about_x_relative_to_a_turned_reference(s: float) -> None:
    M0 = rot_z(30 * DEG) @ rot_y(-20 * DEG)
    M = M0 @ rot_x(170 * DEG)
    m = scaled_motion(np.zeros(3), M0, np.zeros(3), M, 1.0, s)
    np.testing.assert_allclose(m.dR, rot_x(170 * DEG * s), atol=1e-12)


def test_composite_euler_angles_each_scaled() -> None:
    M = rot_x(0.3) @ rot_y(0.2) @ rot_z(0.1)
    m = scaled_motion(np.zeros(3), np.eye(3), np.zeros(3), M, 1.0, 0.5)
    np.testing.assert_allclose(m.angles_rad, [0.3, 0.2, 0.1], atol=1e-12)
    np.testing.assert_allclose(m.dR, rot_x(0.15) @ rot_y(0.1) @ rot_z(0.05), atol=1e-12)


def test_unit_rotation_scale_gives_the_relative_rotation_exactly() -> None:
    rng = np.random.default_rng(5)
    for _ in range(50):
        M0 = exp_so3(rng.uniform(-3, 3, 3))
        M = exp_so3(rng.uniform(-3, 3, 3))
        m = scaled_motion(np.zeros(3), M0, np.zeros(3), M, 1.0, 1.0)
        np.testing.assert_allclose(m.dR, M0.T @ M, atol=1e-12)


def test_past_90_deg_about_y_principal_branch_is_the_documented_caveat() -> None:
    # Rxyz⁻¹(Ry(120°)) on the principal branch is (180°, 60°, 180°): scaling those angles is
    # not a 60° turn about y. Approached continuously, the tracked branch gives Ry(60°).
    rel = rot_y(120 * DEG)
    principal = scaled_motion(np.zeros(3), np.eye(3), np.zeros(3), rel, 1.0, 0.5)
    np.testing.assert_allclose(principal.angles_rad, [math.pi, math.pi / 3, math.pi], atol=1e-12)
    assert rotation_angle(principal.dR.T @ rot_y(60 * DEG)) > 1.0
    near = np.zeros(3)
    for k in range(1, 121):
        near = scaled_motion(
            np.zeros(3), np.eye(3), np.zeros(3), rot_y(k * DEG), 1.0, 0.5, near_rad=near
        ).angles_rad
    np.testing.assert_allclose(near, [0.0, 120 * DEG, 0.0], atol=1e-9)
    np.testing.assert_allclose(rxyz(0.5 * near), rot_y(60 * DEG), atol=1e-9)


# --- the state machine ----------------------------------------------------------------------


def test_engaged_at_start_first_command_is_identity() -> None:
    t = teleop(engage_on_start=True)
    cmd = t.tick(reading((0.3, -0.2, 0.5), rot_z(1.0)), 1000)
    assert (cmd.seq, cmd.engage, cmd.active, cmd.frame) == (1, 1, True, "world")
    assert cmd.dp == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(cmd.dR, np.eye(3).reshape(9))
    assert cmd.t_ns == 1000 and cmd.master == "m1"


def test_not_engaged_until_first_clutch_release() -> None:
    t = teleop(engage_on_start=False)
    first = t.tick(reading((0.1, 0, 0)), 1)
    assert (first.active, first.engage) == (False, 0)
    assert t.tick(reading((0.2, 0, 0)), 2).active is False
    pressed = t.tick(reading((0.3, 0, 0), clutch=True), 3)
    assert (pressed.active, pressed.engage) == (False, 0)
    released = t.tick(reading((0.4, 0, 0)), 4)
    assert (released.active, released.engage, released.dp) == (True, 1, (0.0, 0.0, 0.0))
    moved = t.tick(reading((0.5, 0, 0)), 5)
    np.testing.assert_allclose(moved.dp, [0.1, 0.0, 0.0], atol=1e-15)


def test_master_shift_holds_then_rebases() -> None:
    t = teleop(scale_t=0.5)
    t.tick(reading((0.0, 0, 0)), 1)
    engaged = t.tick(reading((0.2, 0, 0)), 2)
    np.testing.assert_allclose(engaged.dp, [0.1, 0, 0])
    held = t.tick(reading((0.9, 0.5, 0), clutch=True), 3)
    assert held.active is False and held.engage == 1
    assert held.dp == engaged.dp and held.dR == engaged.dR  # last values, documented
    again = t.tick(reading((0.9, 0.5, 0)), 4)
    assert (again.active, again.engage, again.dp) == (True, 2, (0.0, 0.0, 0.0))
    later = t.tick(reading((1.0, 0.5, 0)), 5)
    np.testing.assert_allclose(later.dp, [0.05, 0, 0], atol=1e-15)


def test_scale_change_while_engaged_rebases_and_applies_the_new_scale() -> None:
    t = teleop()
    t.tick(reading((0, 0, 0)), 1)
    assert t.tick(reading((0.1, 0, 0)), 2).dp == pytest.approx((0.1, 0, 0))
    t.set_scale(scale_t=0.1)
    rebased = t.tick(reading((0.2, 0, 0)), 3)
    assert (rebased.engage, rebased.dp) == (2, (0.0, 0.0, 0.0))
    assert t.tick(reading((0.3, 0, 0)), 4).dp == pytest.approx((0.01, 0, 0))
    t.set_scale(scale_t=0.1)  # unchanged: no rebase
    assert t.tick(reading((0.4, 0, 0)), 5).engage == 2


def test_frame_change_while_engaged_rebases() -> None:
    t = teleop()
    t.tick(reading((0, 0, 0)), 1)
    t.tick(reading((0.1, 0, 0)), 2)
    t.set_frame("tool")
    cmd = t.tick(reading((0.2, 0, 0)), 3)
    assert (cmd.frame, cmd.engage, cmd.dp) == ("tool", 2, (0.0, 0.0, 0.0))


def test_changes_while_disengaged_do_not_count_an_engagement() -> None:
    t = teleop(engage_on_start=False)
    t.tick(reading(clutch=True), 1)
    t.set_scale(0.5, 0.5)
    t.set_frame("tool")
    cmd = t.tick(reading(), 2)
    assert (cmd.engage, cmd.frame) == (1, "tool")
    assert (t.scale_t, t.scale_r) == (0.5, 0.5)


@pytest.mark.parametrize("bad", [0.0, -0.1, 1.5, math.nan])
def test_scale_out_of_range_is_rejected(bad: float) -> None:
    t = teleop()
    with pytest.raises(ValueError):
        t.set_scale(scale_t=bad)
    with pytest.raises(ValueError):
        t.set_scale(scale_r=bad)
    with pytest.raises(ValueError):
        t.set_frame("flange")


def test_hold_disengages_and_needs_a_clutch_cycle() -> None:
    t = teleop()
    t.tick(reading(), 1)
    held = t.hold(2)
    assert held.active is False and held.seq == 2
    assert t.tick(reading((0.1, 0, 0)), 3).active is False
    t.tick(reading(clutch=True), 4)
    assert t.tick(reading(), 5).active is True


def test_rotation_is_tracked_continuously_past_180_deg() -> None:
    t = teleop(scale_r=0.5)
    for k in range(0, 271, 5):
        cmd = t.tick(reading(R=rot_x(k * DEG)), k)
    np.testing.assert_allclose(np.array(cmd.dR).reshape(3, 3), rot_x(135 * DEG), atol=1e-9)


def test_state_carries_the_contract_fields() -> None:
    t = teleop(scale_t=0.5, scale_r=0.25, frame="tool")
    t.tick(reading((0.1, 0.2, 0.3), rot_z(0.5), grip=0.5), 77)
    s1, s2 = t.state(), t.state(99)
    assert (s1.seq, s2.seq) == (1, 2)
    assert (s1.t_ns, s2.t_ns) == (77, 99)
    d = codec.to_fields(s1)
    assert d["master"] == "m1" and d["device"] == "test" and d["frame"] == "tool"
    assert (d["scale_t"], d["scale_r"], d["engage"], d["active"]) == (0.5, 0.25, 1, True)
    np.testing.assert_allclose(d["hand_p"], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(np.array(d["hand_R"]).reshape(3, 3), rot_z(0.5))


def test_command_as_dict_and_grip() -> None:
    t = teleop()
    with_grip = codec.to_fields(t.tick(reading(grip=0.75), 1))
    without = codec.to_fields(t.tick(reading(), 2))
    assert with_grip["grip"] == 0.75 and "grip" not in without
    assert set(without) == {"seq", "t_ns", "master", "engage", "active", "frame", "dp", "dR"}
    assert len(without["dR"]) == 9 and len(without["dp"]) == 3


def test_counters_start_from_the_clock_by_default() -> None:
    t = Teleop(MasterConfig(master_id="m1"))
    cmd = t.tick(reading(), 1)
    assert cmd.seq > 10**15 and cmd.engage > 10**12


# --- no jump, ever: the slave of PROTOCOL §2 simulated ----------------------------------------


class Slave:
    """PROTOCOL §2's slave with perfect tracking: records (p0, R0) at the first active
    command of each engagement; ignores inactive, older-seq and older-engage commands."""

    def __init__(self) -> None:
        self.p = np.array([0.5, 0.1, 0.6])
        self.R = rot_x(math.pi)
        self.engage: int | None = None
        self.seq = -1
        self.p0, self.R0 = self.p.copy(), self.R.copy()

    def apply(self, cmd: OperatorCommand) -> None:
        check_command(cmd)
        if cmd.seq <= self.seq or (self.engage is not None and cmd.engage < self.engage):
            return
        self.seq = cmd.seq
        if not cmd.active:
            return
        if cmd.engage != self.engage:
            self.engage = cmd.engage
            self.p0, self.R0 = self.p.copy(), self.R.copy()
        dp = np.array(cmd.dp)
        self.p = self.p0 + (dp if cmd.frame == "world" else self.R0 @ dp)
        self.R = self.R0 @ np.array(cmd.dR).reshape(3, 3)


step = st.tuples(
    st.lists(st.floats(-0.05, 0.05), min_size=3, max_size=3),
    st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3),
    st.booleans(),
    st.one_of(
        st.none(),
        st.tuples(st.floats(0.1, 1.0), st.floats(0.1, 1.0)),
        st.sampled_from(["world", "tool"]),
    ),
)


@settings(max_examples=150, deadline=None)
@given(
    steps=st.lists(step, min_size=10, max_size=80),
    scale_t=st.floats(0.1, 1.0),
    engage_on_start=st.booleans(),
    yaw=st.floats(-math.pi, math.pi),
)
def test_target_never_jumps_more_than_the_scaled_hand_motion(
    steps: list, scale_t: float, engage_on_start: bool, yaw: float
) -> None:
    t = teleop(
        scale_t=scale_t, alignment=tuple(rot_z(yaw).reshape(9)), engage_on_start=engage_on_start
    )
    slave = Slave()
    E, M = np.zeros(3), np.eye(3)
    for k, (dE, w, clutch, change) in enumerate(steps):
        E_prev = E
        E, M = E + np.array(dE), M @ exp_so3(w)
        if isinstance(change, tuple):
            t.set_scale(*change)
        elif isinstance(change, str):
            t.set_frame(change)
        s_t = t.scale_t
        p_before = slave.p.copy()
        cmd = t.tick(HandReading(E, M, clutch), k)
        slave.apply(cmd)
        jump = float(np.linalg.norm(slave.p - p_before))
        assert jump <= s_t * float(np.linalg.norm(E - E_prev)) + 1e-12
        if cmd.active and cmd.dp == (0.0, 0.0, 0.0):
            assert jump == 0.0


@settings(max_examples=100, deadline=None)
@given(steps=st.lists(step, min_size=10, max_size=80))
def test_orientation_never_jumps_more_than_the_hand_turn_at_unit_scale(steps: list) -> None:
    t = teleop(scale_r=1.0)
    slave = Slave()
    M = np.eye(3)
    for k, (_dE, w, clutch, change) in enumerate(steps):
        M_prev = M
        M = M @ exp_so3(w)
        if isinstance(change, str):
            t.set_frame(change)
        R_before = slave.R.copy()
        cmd = t.tick(HandReading(np.zeros(3), M, clutch), k)
        slave.apply(cmd)
        turn = rotation_angle(R_before.T @ slave.R)
        assert turn <= rotation_angle(M_prev.T @ M) + 1e-7


@settings(max_examples=100, deadline=None)
@given(steps=st.lists(step, min_size=10, max_size=60))
def test_first_command_of_every_engagement_is_identity_and_seq_increases(steps: list) -> None:
    t = teleop(scale_t=0.3, scale_r=0.3)
    E, M = np.zeros(3), np.eye(3)
    last_seq, last_engage = 0, 0
    for k, (dE, w, clutch, change) in enumerate(steps):
        E, M = E + np.array(dE), M @ exp_so3(w)
        if isinstance(change, tuple):
            t.set_scale(*change)
        cmd = t.tick(HandReading(E, M, clutch), k)
        assert cmd.seq == last_seq + 1 and cmd.engage >= last_engage
        if cmd.engage > last_engage:
            assert cmd.active and cmd.dp == (0.0, 0.0, 0.0)
            np.testing.assert_array_equal(cmd.dR, np.eye(3).reshape(9))
        last_seq, last_engage = cmd.seq, cmd.engage


def test_fields_build_the_bus_messages() -> None:
    import dataclasses

    from services.bus import codec, messages

    t = teleop(scale_r=0.5)
    t.tick(reading((0.1, 0.2, 0.3), rot_z(0.3), grip=0.5), 10)
    cmd = t.tick(reading((0.2, 0.2, 0.3), rot_z(0.9), grip=0.5), 11)
    msg = messages.OperatorCommand(**dataclasses.asdict(cmd))
    assert codec.decode(messages.OperatorCommand, codec.encode(msg)) == msg
    state = messages.MasterState(**dataclasses.asdict(t.state()))
    assert codec.decode(messages.MasterState, codec.encode(state)) == state
