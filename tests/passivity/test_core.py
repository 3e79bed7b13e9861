"""Energy observers and passivity controllers against hand-worked sequences and properties."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.passivity.controller import TOLERANCE_J, MasterPassivity, SlavePassivity
from services.passivity.observer import EnergyObserver, RemoteEnergy, dot


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
    """The slave put 0.01 J in; the displayed force 10 N pushes the hand along at 0.5 m/s
    for 4 ms ticks: 0.02 J per tick wanted, so the first tick is cut to 0.01 J (β = 20
    N·s/m, f' = 10 − 20·0.5 = 0 N ... exactly what is left) and the next to zero."""
    pc = MasterPassivity()
    pc.remote.update(0, 0.01)
    f1 = pc.step([10.0], [0.5], 0.004)
    assert f1[0] == pytest.approx(5.0)  # 5 N × 0.5 m/s × 4 ms = 0.01 J
    assert pc.telemetry.last_gain == pytest.approx(10.0)
    assert pc.observer.e_out == pytest.approx(0.01)
    f2 = pc.step([10.0], [0.5], 0.004)
    assert f2[0] == pytest.approx(0.0, abs=1e-9)
    assert pc.telemetry.dissipated_j == pytest.approx(0.01 + 0.02)
    # Pushing against the force (input) is never changed and counts as input energy.
    f3 = pc.step([10.0], [-0.5], 0.004)
    assert f3 == [10.0]
    assert pc.observer.e_in == pytest.approx(0.02)


def test_master_controller_only_removes_the_component_along_the_velocity() -> None:
    pc = MasterPassivity()
    f = pc.step([3.0, 4.0, 0.0], [1.0, 0.0, 0.0], 0.001)
    assert f == pytest.approx([0.0, 4.0, 0.0])


def test_slave_controller_hand_worked() -> None:
    """The wall pushes back with 100 N (−x); the master commands 1 mm into it (0.1 J); the
    operator has put in 0.04 J: the step is cut to 0.4 mm (α = 6e-6 m/N)."""
    pc = SlavePassivity()
    pc.remote.update(0, 0.04)
    dx = pc.step([-100.0, 0.0, 0.0], [0.001, 0.0002, 0.0], 0.001)
    assert dx == pytest.approx([0.0004, 0.0002, 0.0])
    assert pc.telemetry.last_gain == pytest.approx(6e-6)
    assert pc.observer.e_out == pytest.approx(0.04)
    assert pc.offset == pytest.approx([-0.0006, 0.0, 0.0])
    # Retreating (the wall pushes along): input, never changed.
    back = pc.step([-100.0, 0.0, 0.0], [-0.001, 0.0, 0.0], 0.001)
    assert back == pytest.approx([-0.001, 0.0, 0.0])
    assert pc.observer.e_in == pytest.approx(0.1)


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
    controllers dissipate under 0.1 % of the energy exchanged and the slave drifts by µm."""
    k = 1000.0
    master, slave = MasterPassivity(), SlavePassivity()
    x, dt = 0.0, 0.001
    for i in range(2000):
        v = 0.05 * math.sin(2 * math.pi * i / 1000)  # in and out of a spring at x ≥ 0
        f_env = [-k * max(x, 0.0)]
        dx = slave.step(f_env, [v * dt], dt)
        x += dx[0]
        f_env = [-k * max(x, 0.0)]
        master.remote.update(0, slave.observer.e_in)
        master.step(f_env, [v], dt)
        slave.remote.update(0, master.observer.e_in)
    exchanged = master.observer.e_in
    assert exchanged > 0.2  # the spring was really worked
    assert master.telemetry.dissipated_j + slave.telemetry.dissipated_j < 1e-3 * exchanged
    assert abs(slave.offset[0]) < 1e-4


vec3 = st.lists(st.floats(-100.0, 100.0), min_size=3, max_size=3)


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(st.tuples(vec3, vec3, st.floats(0.0, 0.05)), min_size=1, max_size=60),
    delay=st.integers(0, 30),
)
def test_master_port_never_gives_more_than_it_received(
    steps: list[tuple[list[float], list[float], float]], delay: int
) -> None:
    pc = MasterPassivity()
    sent: list[float] = []
    total = 0.0
    for f, v, e_remote in steps:
        total += e_remote
        sent.append(total)
        if len(sent) > delay:
            pc.remote.update(0, sent[-1 - delay])
        f_out = pc.step(f, v, 0.001)
        # the controller only ever damps: it never adds power along the motion
        assert dot(f_out, v) <= max(dot(f, v), 0.0) + 1e-9
        assert pc.observer.e_out <= pc.remote.e_in + TOLERANCE_J * len(sent) + 1e-12


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(
        st.tuples(vec3, st.lists(st.floats(-0.01, 0.01), min_size=3, max_size=3), st.floats(0, 1)),
        min_size=1,
        max_size=60,
    ),
    delay=st.integers(0, 30),
    drift=st.floats(0.0, 1.0),
)
def test_slave_port_never_gives_more_than_it_received(
    steps: list[tuple[list[float], list[float], float]], delay: int, drift: float
) -> None:
    pc = SlavePassivity(drift_m_s=drift)
    sent: list[float] = []
    total = 0.0
    for f, dx, e_remote in steps:
        total += e_remote * 0.01
        sent.append(total)
        if len(sent) > delay:
            pc.remote.update(0, sent[-1 - delay])
        pc.step(f, dx, 0.001)
        assert pc.observer.e_out <= pc.remote.e_in + TOLERANCE_J * len(sent) + 1e-12
