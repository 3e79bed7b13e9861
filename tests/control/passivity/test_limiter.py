"""The master port's energy-bounding force limiter against hand-worked sequences, and the
property that the master port never gives the hand more than it received (plus the
reserve), whatever the hand does within its force rate (hypothesis over reversals)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.master.passivity import master_port
from services.control.passivity.controller import TOLERANCE_J, MasterPassivity
from services.control.passivity.dynamics import Device


def test_without_a_mass_model_the_limit_uses_the_current_velocity() -> None:
    """0.03 J received; 10 N pushing the hand along at 0.5 m/s in 4 ms ticks (0.02 J a
    tick). Tick 2 sees 0.02 J out, 0.01 J left: the largest force whose work at 0.5 m/s fits
    is 5 N. Tick 3 sees 0.01 J more: nothing left, 0 N. The output is exactly what came in
    (the limiter alone, damper off)."""
    pc = MasterPassivity(limit=True, damp=False, reserve_j=0.0, hand_rate_n_s=0.0)
    pc.remote.update(0, 0.03)
    assert pc.step([10.0], [0.0], 0.004) == [10.0]
    assert pc.step([10.0], [0.002], 0.004) == pytest.approx([5.0])
    assert pc.step([10.0], [0.004], 0.004) == pytest.approx([0.0], abs=1e-9)
    assert pc.observer.e_out == pytest.approx(0.03)
    assert pc.limited_steps == 2
    assert pc.telemetry.dissipated_j == 0.0


def test_a_force_step_on_a_still_hand_is_bounded_by_its_own_work() -> None:
    """1 mJ received; the device (0.5 kg) at rest, 10 N asked, 10 ms ticks. The force alone
    would move the device by k·f/m·dt² and do W(k) = k²·f²·dt²/m = 0.02·k² J: the limit is
    k = √(0.001/0.02) = 0.2236, 2.236 N. Carried out on the device, that is exactly 1 mJ."""
    dt = 0.01
    pc = MasterPassivity(limit=True, damp=False, mass_kg=0.5, reserve_j=0.0, hand_rate_n_s=0.0)
    pc.remote.update(0, 0.001)
    dev = Device(mass_kg=0.5, damping_ns_m=0.0, x=[0.0], v=[0.0])
    assert pc.step([0.0], dev.x, dt) == [0.0]
    dev.step([0.0], dt)
    f = pc.step([10.0], dev.x, dt)
    assert f == pytest.approx([10.0 * math.sqrt(0.05)])
    dev.step(f, dt)
    assert pc.step([0.0], dev.x, dt) == [0.0]
    assert pc.observer.e_out == pytest.approx(0.001)
    assert pc.budget_j == pytest.approx(0.0, abs=1e-12)


def test_a_hand_pushing_in_holds_the_force_its_input_pays_for() -> None:
    """Nothing received, the device 0.5 kg, 10 ms ticks. Tick 1: the device still, a force
    would push it back (work k²·f²·dt²/m > 0): 0 N. Tick 2: the hand moves in at 0.1 m/s;
    10 N asked: W(k) = k·10·(−0.1)·0.01 + k²·100·1e-4/0.5 = −0.01·k + 0.02·k², root k = 0.5:
    5 N, the force that just stops it. Tick 3: still 0.1 m/s in against 5 N (the hand's own
    5 N keeps it going); 20 N asked: w = −0.1 − 5/0.5·0.01 = −0.2, W(k) = −0.04·k + 0.08·k²,
    k = 0.5: 10 N, again v⁺ = −0.1 + (10 − 5)/0.5·0.01 = 0. Nothing is ever given out."""
    dt = 0.01
    pc = MasterPassivity(limit=True, damp=False, mass_kg=0.5, reserve_j=0.0, hand_rate_n_s=0.0)
    assert pc.step([10.0], [0.0], dt) == [0.0]
    assert pc.step([10.0], [-0.001], dt) == pytest.approx([5.0])
    assert pc.step([20.0], [-0.002], dt) == pytest.approx([10.0])
    assert pc.observer.e_in == pytest.approx(0.005)  # 5 N × 1 mm pushed in
    assert pc.observer.e_out == 0.0


def test_the_reserve_is_spent_once_and_comes_back_only_with_slave_energy() -> None:
    """reserve 1 mJ, nothing received: the hand moving along at 0.5 m/s, 4 ms ticks. The
    first limited tick shows 0.5 N (0.5 × 0.5 × 0.004 = 1 mJ), then nothing until the slave
    sends energy."""
    pc = MasterPassivity(limit=True, damp=False, reserve_j=0.001, hand_rate_n_s=0.0)
    pc.step([10.0], [0.0], 0.004)
    # 10 N × 2 mm = 20 mJ out, unforeseen (no velocity known at the first tick): overdrawn.
    assert pc.step([10.0], [0.002], 0.004) == [0.0]
    assert pc.budget_j == pytest.approx(-0.02)
    assert pc.step([10.0], [0.004], 0.004) == [0.0]
    pc.remote.update(0, pc.observer.e_out)  # the slave pays it all back
    assert pc.step([10.0], [0.006], 0.004) == pytest.approx([0.5])


def test_a_held_back_force_rises_towards_the_bound_by_a_fraction_of_the_gap() -> None:
    """rise 0.3; the hand pushing in as in the test above (tick 2's bound 5 N): from 0 N
    held, the force shown is 0 + 0.3 × (5 − 0) = 1.5 N. Tick 3, the hand still moving in at
    0.1 m/s against 1.5 N: w = −0.1 − 1.5/0.5·0.01 = −0.13, W(k) = k·10·(−0.13)·0.01 +
    k²·0.02 → bound k = 0.65 (6.5 N), shown 1.5 + 0.3 × (6.5 − 1.5) = 3 N."""
    dt = 0.01
    pc = MasterPassivity(
        limit=True, damp=False, mass_kg=0.5, reserve_j=0.0, hand_rate_n_s=0.0, rise=0.3
    )
    assert pc.step([10.0], [0.0], dt) == [0.0]
    assert pc.step([10.0], [-0.001], dt) == pytest.approx([1.5])
    assert pc.step([10.0], [-0.002], dt) == pytest.approx([3.0])
    assert pc.limited_steps == 3


def test_an_unbounded_force_passes_at_once_whatever_rise() -> None:
    """Energy to spare (the slave sent 1 J): 8 N asked on a still hand is shown at once,
    so `rise` costs nothing while the loop is passive (a fast link, free space)."""
    pc = MasterPassivity(limit=True, mass_kg=0.5, reserve_j=1e-4, hand_rate_n_s=0.0, rise=0.3)
    pc.remote.update(0, 1.0)
    assert pc.step([0.0], [0.0], 0.01) == [0.0]
    assert pc.step([8.0], [0.0], 0.01) == [8.0]
    assert pc.limited_steps == 0


@settings(max_examples=80, deadline=None)
@given(
    asked=st.lists(st.floats(-40.0, 40.0), min_size=30, max_size=120),
    hand=st.lists(st.floats(-1.0, 1.0), min_size=30, max_size=120),
    credit=st.lists(st.floats(0.0, 2e-3), min_size=30, max_size=120),
    dofs=st.sampled_from([1, 3]),
    reserve=st.sampled_from([0.0, 1e-4]),
    rise=st.sampled_from([1.0, 0.3, 0.05]),
)
def test_the_master_port_never_gives_more_than_it_received(
    asked: list[float],
    hand: list[float],
    credit: list[float],
    dofs: int,
    reserve: float,
    rise: float,
) -> None:
    """A device of 0.5 kg, the hand's force changing by at most `rate`·dt a tick in any
    direction (the fractions in `hand` pick the change: reversals, pushes, release), the
    force asked anything up to 40 N and the slave's energy arriving in random amounts:
    after every tick the master's output ≤ what it received + the reserve, whether the
    force goes to the bound at once or rises towards it (`rise`)."""
    dt, rate, mass = 0.001, 200.0, 0.5
    pc = MasterPassivity(limit=True, mass_kg=mass, reserve_j=reserve, hand_rate_n_s=rate, rise=rise)
    dev = Device(mass_kg=mass, damping_ns_m=0.0, x=[0.0] * dofs, v=[0.0] * dofs)
    h = [0.0] * dofs
    received = 0.0
    n = min(len(asked), len(hand), len(credit))
    for k in range(n):
        received += credit[k]
        pc.remote.update(0, received)
        axis = k % dofs
        f_ask = [0.0] * dofs
        f_ask[axis] = asked[k]
        f_ask[(axis + 1) % dofs] += 0.5 * asked[(k + 1) % n]
        f = pc.step(f_ask, dev.x, dt)
        if k >= 2:  # the hand takes hold of a device at rest, then changes its force
            h[(k // 7) % dofs] += rate * dt * hand[k]
        dev.step([a + b for a, b in zip(f, h, strict=True)], dt)
        assert pc.observer.e_out <= received + reserve + TOLERANCE_J + 1e-12


@settings(max_examples=80, deadline=None)
@given(
    asked=st.lists(st.floats(-40.0, 40.0), min_size=30, max_size=150),
    credit=st.lists(st.floats(0.0, 2e-3), min_size=30, max_size=150),
    grips=st.lists(st.floats(-20.0, 20.0), min_size=1, max_size=6),
    dofs=st.sampled_from([1, 3]),
    reserve=st.sampled_from([0.0, 1e-4]),
    rise=st.sampled_from([1.0, 0.3]),
)
def test_the_services_setting_gives_no_more_than_it_received_but_a_grip_change(
    asked: list[float],
    credit: list[float],
    grips: list[float],
    dofs: int,
    reserve: float,
    rise: float,
) -> None:
    """The master service's controller (`master_port`: the limiter, the damper's gain
    bounded, no bound at the current velocity, the hand's force assumed held over the tick),
    its reserve and rise varied. The hand grips the 0.5 kg device with a force that changes,
    now and then, to any value up to 20 N (`grips`, one every 25 ticks). A change shows as
    that tick's misprediction, at most |f|·|Δ|·dt²/m; after every tick the master's output
    never exceeds what it received + the reserve + those."""
    dt, mass = 0.002, 0.5
    pc = replace(master_port(mass), reserve_j=reserve, rise=rise)
    dev = Device(mass_kg=mass, damping_ns_m=0.0, x=[0.0] * dofs, v=[0.0] * dofs)
    hand = [0.0] * dofs
    received = 0.0
    allowance = 0.0
    n = min(len(asked), len(credit))
    for k in range(n):
        received += credit[k]
        pc.remote.update(0, received)
        f_ask = [0.0] * dofs
        f_ask[k % dofs] = asked[k]
        f = pc.step(f_ask, dev.x, dt)
        if k % 25 == 2:  # the hand changes its grip (from rest at k = 2)
            new = [0.0] * dofs
            new[(k // 25) % dofs] = grips[(k // 25) % len(grips)]
            change = math.sqrt(sum((a - b) ** 2 for a, b in zip(new, hand, strict=True)))
            allowance += math.sqrt(sum(x * x for x in f)) * change * dt * dt / mass
            hand = new
        dev.step([a + b for a, b in zip(f, hand, strict=True)], dt)
        assert pc.observer.e_out <= received + reserve + allowance + TOLERANCE_J + 1e-12


@pytest.mark.parametrize(
    ("damp", "beta_max", "bound_current", "lowest"),
    [
        (False, math.inf, False, 3.99),
        (True, 20.0, False, 3.99),  # the master service's setting
        (True, math.inf, False, 0.0),
        (False, math.inf, True, 0.0),
    ],
)
def test_a_hand_holding_still_is_not_dropped_when_it_moves_out_by_micrometres(
    damp: bool, beta_max: float, bound_current: bool, lowest: float
) -> None:
    """The collapse traced over the link (docs/passivity.md, 2026-11-26): a hand pressing
    with 4 N holds the 0.5 kg device still against a display of 4 N (6 N asked, no energy
    from the slave). A nudge outward of 8 µm/s: the damper, and the bound at the current
    velocity, each see a force pushing the hand out with nothing to pay it and cut it to 0
    for a tick — then the hand lunges in and the full 6 N kicks it back. The prediction
    with the hand's own force sees that the hand stops the device within the tick: the
    display stays at 4 N, also with the damper's gain bounded to 20 N·s/m (β·v = 0.16 mN).
    The energy given out is the same 63 nJ either way."""
    pc = MasterPassivity(
        limit=True,
        damp=damp,
        beta_max=beta_max,
        bound_current=bound_current,
        mass_kg=0.5,
        reserve_j=0.0,
        hand_rate_n_s=0.0,
        rise=0.3,
    )
    dev = Device(mass_kg=0.5, damping_ns_m=2.0, x=[0.0], v=[0.0])
    shown = []
    for k in range(300):
        f = pc.step([6.0], dev.x, 0.002)
        dev.step([f[0] - 4.0], 0.002)
        if k == 200:
            dev.v[0] += 8e-6
        shown.append(f[0])
    assert shown[190:201] == pytest.approx([4.0] * 11, abs=1e-3)  # held at the hand's 4 N
    assert min(shown[201:]) == pytest.approx(lowest, abs=0.01)
    assert max(shown[201:]) == pytest.approx(4.0 if lowest else 6.0, abs=0.01)
    assert pc.observer.e_out == pytest.approx(6.35e-8, rel=0.01)
