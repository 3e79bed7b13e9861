"""Energy observers and passivity controllers against hand-worked sequences and properties."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.passivity.controller import TOLERANCE_J, MasterPassivity, SlavePassivity
from services.control.passivity.observer import EnergyObserver, RemoteEnergy, dot


def test_observer_splits_power_by_direction() -> None:
    obs = EnergyObserver()
    for e in (0.5, -0.2, 0.0, 1.0, -0.3):
        obs.record(e)
    assert obs.e_in == pytest.approx(1.5)
    assert obs.e_out == pytest.approx(0.5)
    assert obs.net_j == pytest.approx(1.0)
    with pytest.raises(ValueError):
        obs.record(math.nan)
    obs.reset()
    assert (obs.e_in, obs.e_out) == (0.0, 0.0)


def test_remote_energy_keeps_newest_largest_and_ignores_other_epochs() -> None:
    r = RemoteEnergy()
    assert r.update(0, 2.0)
    assert r.update(0, 1.0)  # reordered: older, smaller — harmless
    assert r.e_in == 2.0
    assert not r.update(1, 5.0)  # another engagement
    assert not r.update(0, -1.0)
    assert not r.update(0, math.inf)
    assert (r.e_in, r.received, r.ignored) == (2.0, 2, 3)
    r.reset(1)
    assert r.update(1, 0.5)
    assert (r.epoch, r.e_in) == (1, 0.5)


def test_master_controller_hand_worked() -> None:
    """The slave put 0.03 J in; a 10 N displayed force pushes the hand along at 0.5 m/s in
    4 ms ticks (0.02 J a tick). Tick 2 observes 0.02 J out and has 0.01 J left: β = 10
    N·s/m, 5 N shown; tick 3 observes 0.01 J more, nothing is left: β = 20, 0 N. Pushing
    back against the force is input and is never changed."""
    pc = MasterPassivity()
    pc.remote.update(0, 0.03)
    assert pc.step([10.0], [0.0], 0.004) == [10.0]  # no velocity known yet
    assert pc.step([10.0], [0.002], 0.004) == pytest.approx([5.0])
    assert pc.observer.e_out == pytest.approx(0.02)
    assert pc.telemetry.last_gain == pytest.approx(10.0)
    assert pc.step([10.0], [0.004], 0.004) == pytest.approx([0.0], abs=1e-9)
    assert pc.observer.e_out == pytest.approx(0.03)
    assert pc.telemetry.last_gain == pytest.approx(20.0)
    assert pc.step([10.0], [0.002], 0.004) == [10.0]  # moving back: input
    pc.step([10.0], [0.0], 0.004)
    assert pc.observer.e_in == pytest.approx(0.02)
    assert pc.observer.e_out == pytest.approx(0.03)
    assert pc.telemetry.dissipated_j == pytest.approx(0.01 + 0.02)


def test_master_controller_only_removes_the_component_along_the_velocity() -> None:
    pc = MasterPassivity()
    pc.step([3.0, 4.0, 0.0], [0.0, 0.0, 0.0], 0.001)
    f = pc.step([3.0, 4.0, 0.0], [0.001, 0.0, 0.0], 0.001)
    assert f == pytest.approx([0.0, 4.0, 0.0])


def test_master_observer_without_controller() -> None:
    pc = MasterPassivity(enabled=False)
    pc.step([10.0], [0.0], 0.001)
    assert pc.step([10.0], [0.001], 0.001) == [10.0]
    assert (pc.observer.e_in, pc.observer.e_out, pc.telemetry.active_steps) == (0.0, 0.01, 0)


def test_slave_controller_hand_worked() -> None:
    """The wall pushes back with 100 N (−x); the master commands 1 mm into it (0.1 J); the
    operator has put in 0.04 J: the step is cut to 0.4 mm (α = 6e-6 m/N), observed at the
    next step; the step back out is input, never changed."""
    wall = [-100.0, 0.0, 0.0]
    pc = SlavePassivity()
    pc.remote.update(0, 0.04)
    dx = pc.step(wall, [0.001, 0.0002, 0.0], 0.001)
    assert dx == pytest.approx([0.0004, 0.0002, 0.0])
    assert pc.telemetry.last_gain == pytest.approx(6e-6)
    assert pc.offset == pytest.approx([-0.0006, 0.0, 0.0])
    assert pc.step(wall, [-0.001, 0.0, 0.0], 0.001) == pytest.approx([-0.001, 0.0, 0.0])
    assert pc.observer.e_out == pytest.approx(0.04)
    pc.step(wall, [0.0, 0.0, 0.0], 0.001)
    assert pc.observer.e_in == pytest.approx(0.1)


def test_slave_observes_with_the_mean_force_of_the_step() -> None:
    """Into a 10 kN/m spring by 1 mm: the force goes 0 → 10 N, the work is 5 mJ."""
    pc = SlavePassivity(enabled=False)
    pc.step([0.0], [0.001], 0.001)
    pc.step([-10.0], [0.0], 0.001)
    assert pc.observer.e_out == pytest.approx(0.005)


def test_slave_drift_is_given_back_only_with_energy() -> None:
    pc = SlavePassivity(drift_m_s=1.0)
    pc.offset = [-0.002, 0.0, 0.0]
    wall = [-100.0, 0.0, 0.0]
    assert pc.step(wall, [0.0, 0.0, 0.0], 0.001) == pytest.approx([0.0, 0.0, 0.0])
    pc.remote.update(0, 1.0)  # energy to spare now: 1 mm per 1 ms tick
    assert pc.step(wall, [0.0, 0.0, 0.0], 0.001) == pytest.approx([0.001, 0.0, 0.0])
    assert pc.offset == pytest.approx([-0.001, 0.0, 0.0])
    # In free space the offset costs nothing.
    assert pc.step([0.0] * 3, [0.0] * 3, 0.001) == pytest.approx([0.001, 0.0, 0.0])
    assert pc.offset == pytest.approx([0.0, 0.0, 0.0])


def test_slave_slack_holds_through_small_steps_back() -> None:
    pc = SlavePassivity(slack_m=0.001)
    wall = [-10.0]
    assert pc.step(wall, [-0.0006], 0.001) == pytest.approx([0.0])
    assert pc.step(wall, [-0.0006], 0.001) == pytest.approx([-0.0002])
    assert pc.step(wall, [0.0003], 0.001) == pytest.approx([0.0])  # takes up the slack
    assert pc.offset == pytest.approx([0.0007])


def test_reset_starts_a_new_epoch_from_zero() -> None:
    pc = SlavePassivity()
    pc.remote.update(0, 1.0)
    pc.step([-10.0], [0.01], 0.001)
    pc.offset = [0.3]
    pc.reset(4)
    assert (pc.observer.e_in, pc.observer.e_out, pc.remote.e_in, pc.remote.epoch) == (
        0.0,
        0.0,
        0.0,
        4,
    )
    assert pc.offset == [0.0]


def test_without_delay_a_passive_environment_needs_no_controller() -> None:
    """A spring environment, no delay but the one-tick exchange of a sampled loop: each
    side's output is covered by the other's input all but for the sampling mismatch, so the
    controllers dissipate under 2.5 % of the energy exchanged and the slave drifts by less
    than a millimetre over two cycles (no drift compensation here)."""
    k, dt = 1000.0, 0.001
    master, slave = MasterPassivity(), SlavePassivity()
    x_m, x_s = 0.0, 0.0
    f_env = [0.0]
    for i in range(2000):
        x_new = 0.01 * math.sin(2 * math.pi * i / 1000)  # in and out of a spring at x ≥ 0
        dx = slave.step(f_env, [x_new - x_m], dt)
        x_m = x_new
        x_s += dx[0]
        f_env = [-k * max(x_s, 0.0)]
        master.remote.update(0, slave.observer.e_in)
        master.step(f_env, [x_m], dt)
        slave.remote.update(0, master.observer.e_in)
    exchanged = master.observer.e_in
    assert exchanged > 0.04  # the spring was really worked
    assert master.telemetry.dissipated_j + slave.telemetry.dissipated_j < 2.5e-2 * exchanged
    assert abs(slave.offset[0]) < 1e-3


vec3 = st.lists(st.floats(-100.0, 100.0), min_size=3, max_size=3)
small3 = st.lists(st.floats(-0.01, 0.01), min_size=3, max_size=3)


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(st.tuples(vec3, st.floats(0.0, 0.05)), min_size=1, max_size=60),
    v=small3,
    delay=st.integers(0, 30),
)
def test_master_controller_never_adds_energy(
    steps: list[tuple[list[float], float]], v: list[float], delay: int
) -> None:
    """Hand at constant velocity (so the one-tick prediction is exact), random forces and
    remote energy: the controller only damps, and the port never gives out more than the
    slave put in."""
    pc = MasterPassivity()
    sent: list[float] = []
    total = 0.0
    x = [0.0, 0.0, 0.0]
    pc.step([0.0, 0.0, 0.0], x, 1.0)  # the hand's place is known before any force is shown
    for k, (f, e_remote) in enumerate(steps):
        total += e_remote
        sent.append(total)
        if len(sent) > delay:
            pc.remote.update(0, sent[-1 - delay])
        x = [xi + vi for xi, vi in zip(x, v, strict=True)]
        f_out = pc.step(f, x, 1.0)
        assert dot(f_out, v) <= max(dot(f, v), 0.0) + 1e-9
        assert dot(f_out, f_out) <= dot(f, f) + 1e-9
        assert pc.observer.e_out <= pc.remote.e_in + TOLERANCE_J * (k + 1) + 1e-12


@settings(max_examples=60, deadline=None)
@given(
    f=vec3,
    steps=st.lists(st.tuples(small3, st.floats(0, 1)), min_size=1, max_size=60),
    delay=st.integers(0, 30),
    drift=st.floats(0.0, 1.0),
    slack=st.floats(0.0, 0.01),
)
def test_slave_controller_never_adds_energy(
    f: list[float],
    steps: list[tuple[list[float], float]],
    delay: int,
    drift: float,
    slack: float,
) -> None:
    """A constant environment force (so the prediction is exact), random commanded steps,
    drift compensation and slack: the robot never puts more into the environment than the
    operator put into the channel."""
    pc = SlavePassivity(drift_m_s=drift, slack_m=slack)
    sent: list[float] = []
    total = 0.0
    for k, (dx, e_remote) in enumerate(steps):
        total += e_remote * 0.01
        sent.append(total)
        if len(sent) > delay:
            pc.remote.update(0, sent[-1 - delay])
        before = max(pc.budget_j, 0.0)
        out = pc.step(f, dx, 0.001)
        assert -dot(f, out) <= before + 1e-9
        assert pc.observer.e_out <= pc.remote.e_in + TOLERANCE_J * (k + 1) + 1e-12


def test_slave_counts_the_motion_the_arm_made_not_the_one_commanded() -> None:
    pc = SlavePassivity(enabled=False)
    wall = [-10.0]
    pc.step(wall, [0.001], 0.001)  # commanded 1 mm in
    pc.step(wall, [-0.001], 0.001, done=[0.002])  # the arm went 2 mm in: 20 mJ out
    assert pc.observer.e_out == pytest.approx(0.02)
    assert pc.observer.e_in == 0.0
    pc.step(wall, [0.0], 0.001, done=[-0.0005])  # commanded 1 mm back, went 0.5: 5 mJ in
    assert pc.observer.e_in == pytest.approx(0.005)
    # An arm lagging its command (a speed limit): only the 0.2 mm it made crossed the port,
    # not the 1 mm still to come, which is counted again as the arm makes it.
    pc.step(wall, [0.0], 0.001, done=[0.0])
    out_before = pc.observer.e_out
    pc.step(wall, [0.001], 0.001, done=[0.0])
    pc.step(wall, [0.0008], 0.001, done=[0.0002])
    assert pc.observer.e_out - out_before == pytest.approx(0.002)
    pc.step(wall, [0.0], 0.001, done=[0.0008])
    assert pc.observer.e_out - out_before == pytest.approx(0.010)
