"""The bilateral loop over a bad link in simulation: unstable without TDPA, bounded with it.

Assertions are on forces, penetration and energies of seeded simulations, never on time.
"""

from __future__ import annotations

import math
from functools import cache

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.passivity.dynamics import Wall
from services.tools.tdpa.loop import (
    Link,
    LinkSpec,
    LoopResult,
    LoopSpec,
    Twist,
    contact_metrics,
    held,
    simulate,
    swing_rms,
    trend_n_s,
    twist_metrics,
)

THREE_DOF = {"dofs": 3, "target_m": (0.02, 0.0, 0.08), "wall": Wall(normal=(0.0, 0.0, 1.0))}


@cache
def run(rtt_s: float, tdpa: bool, dofs: int = 1, ramp_n_s: float = 0.0) -> LoopResult:
    extra = THREE_DOF if dofs == 3 else {}
    spec = LoopSpec(
        round_trip_s=rtt_s, jitter=0.1, loss=0.01, tdpa=tdpa, ramp_n_s=ramp_n_s, **extra
    )
    return simulate(spec)


def test_link_delays_drops_and_keeps_the_newest() -> None:
    import random

    link = Link(LinkSpec(delay_s=0.1, jitter=0.5, loss=0.0), random.Random(3))
    for k in range(10):
        link.send(k * 0.01, k)
    assert link.receive(0.04) is None  # nothing can arrive before 50 ms
    got = [link.receive(0.05 + k * 0.01) for k in range(20)]
    seen = [g for g in got if g is not None]
    assert seen == sorted(seen)  # latest-wins: never goes back to an older packet
    assert got[-1] == 9
    lossy = Link(LinkSpec(loss=0.5), random.Random(1))
    for k in range(1000):
        lossy.send(0.0, k)
    assert 400 < lossy.lost < 600
    with pytest.raises(ValueError):
        LinkSpec(loss=1.0)


@pytest.mark.parametrize("dofs", [1, 3])
def test_without_delay_tdpa_changes_nothing_the_operator_feels(dofs: int) -> None:
    off, on = contact_metrics(run(0.0, False, dofs)), contact_metrics(run(0.0, True, dofs))
    assert off["stable"] and on["stable"]
    assert on["steady_force_n"] == pytest.approx(off["steady_force_n"], rel=0.05)
    # 8.4 N against 8.6 N in 1-DoF (10.0 N at the release while the drift was 1 cm/s).
    assert on["peak_force_n"] == pytest.approx(off["peak_force_n"], rel=0.2)


@pytest.mark.parametrize(("seed", "loss"), [(0, 0.0)] + [(seed, 0.01) for seed in range(1, 7)])
def test_without_delay_the_force_felt_is_the_same_whatever_the_link_drops(
    seed: int, loss: float
) -> None:
    """Issue 18's "at 0 ms within 5 %", on what the operator feels, for every seed and with
    no loss at all. With the offset given back at 1 cm/s (before 2026-11-26 evening) the
    slave's correction at the impact was never repaid while the simulated operator pressed:
    felt 5.8-6.0 N against 8.2 N in every run without loss and in seeds 3-6 (seeds 1-2 only
    because a dropped packet happened to break the cycle)."""
    results = []
    for tdpa in (False, True):
        spec = LoopSpec(round_trip_s=0.0, jitter=0.1, loss=loss, tdpa=tdpa, seed=seed)
        results.append(contact_metrics(simulate(spec)))
    off, on = results
    assert on["stable"]
    assert on["felt_force_n"] == pytest.approx(off["felt_force_n"], rel=0.05)
    assert on["steady_force_n"] == pytest.approx(off["steady_force_n"], rel=0.05)


@pytest.mark.parametrize("dofs", [1, 3])
@pytest.mark.parametrize("rtt_s", [0.1, 0.2])
def test_without_tdpa_contact_goes_unstable(dofs: int, rtt_s: float) -> None:
    ref = contact_metrics(run(0.0, False, dofs))
    m = contact_metrics(run(rtt_s, False, dofs))
    assert not m["stable"]
    assert m["peak_force_n"] > 10 * ref["peak_force_n"]
    assert m["oscillation_rms_n"] > 0.5 * m["steady_force_n"]
    assert m["penetration_mm"] > 10 * ref["penetration_mm"]


@pytest.mark.parametrize("dofs", [1, 3])
@pytest.mark.parametrize("rtt_s", [0.1, 0.2])
def test_with_tdpa_contact_stays_bounded_and_calm(dofs: int, rtt_s: float) -> None:
    ref = contact_metrics(run(0.0, True, dofs))
    m = contact_metrics(run(rtt_s, True, dofs))
    assert m["peak_force_n"] < 1.5 * ref["peak_force_n"]
    assert m["penetration_mm"] < 1.5 * ref["penetration_mm"]
    assert m["steady_force_n"] > 0.6 * ref["steady_force_n"]  # still in contact, pressing
    assert m["stable"]
    assert m["swing_rms_n"] < 0.05 * m["steady_force_n"]


@pytest.mark.parametrize("dofs", [1, 3])
@pytest.mark.parametrize("rtt_s", [0.2, 0.7])
def test_with_tdpa_no_seed_oscillates_though_some_step_late(dofs: int, rtt_s: float) -> None:
    """Six seeds: with TDPA the contact never swings back and forth (below 3 % of the steady
    force about its best monotone fit; 36-178 % without TDPA), but in some seeds it steps up
    late in the hold: the simulated operator still pressing towards its 8 N at the rate its
    model allows (0.3 N/s per N it misses), the display following the hand's push while the
    master's reservoir is empty (docs/passivity.md, "Late steps"). The RMS about the mean
    counts such a step; the swing does not, and never exceeds that RMS."""
    extra: dict[str, object] = dict(THREE_DOF) if dofs == 3 else {}
    for seed in range(1, 7):
        spec = LoopSpec(round_trip_s=rtt_s, jitter=0.1, loss=0.01, tdpa=True, seed=seed, **extra)
        m = contact_metrics(simulate(spec))
        assert m["stable"], (seed, m)
        assert m["swing_rms_n"] < 0.03 * m["steady_force_n"], seed
        assert m["swing_rms_n"] <= m["oscillation_rms_n"] + 1e-12
        if not m["settled"]:
            assert m["creep_n_s"] > 0.0  # a step up, not down: the operator pressing on


def test_with_tdpa_a_700ms_round_trip_stays_bounded() -> None:
    ref = contact_metrics(run(0.0, True))
    off, on = contact_metrics(run(0.7, False)), contact_metrics(run(0.7, True))
    assert on["peak_force_n"] < 2 * ref["peak_force_n"] < off["peak_force_n"] / 5
    assert on["penetration_mm"] < 2 * ref["penetration_mm"]
    assert on["steady_force_n"] > 0.3 * ref["steady_force_n"]


def _overdrafts(res: LoopResult) -> tuple[float, float, float]:
    exchanged = res.master_in[-1] + res.slave_in[-1]
    master = max(o - i for o, i in zip(res.master_out, res.slave_in, strict=True))
    slave = max(o - i for o, i in zip(res.slave_out, res.master_in, strict=True))
    return exchanged, master, slave


@pytest.mark.parametrize("rtt_s", [0.1, 0.7])
def test_slave_port_gives_the_environment_no_more_than_the_operator_put_in(rtt_s: float) -> None:
    off_exchanged, _, off_slave = _overdrafts(run(rtt_s, False))
    exchanged, _, slave = _overdrafts(run(rtt_s, True))
    # Without TDPA the channel creates energy: the bound below is broken by far (joules).
    assert off_slave > 5 * max(0.1 * off_exchanged, 0.002)
    # With it: only one-tick prediction errors, ~1 mJ at 700 ms. (With the master's
    # limiter the contact no longer bounces, so far less is exchanged: 10 mJ at 700 ms.)
    assert slave < max(0.1 * exchanged, 0.002)


@pytest.mark.parametrize("rtt_s", [0.1, 0.7])
def test_master_ramp_keeps_the_master_port_balanced(rtt_s: float) -> None:
    exchanged, master, slave = _overdrafts(run(rtt_s, True, 1, ramp_n_s=200.0))
    assert master < 0.02 * exchanged
    assert slave < 0.1 * exchanged
    assert contact_metrics(run(rtt_s, True, 1, ramp_n_s=200.0))["penetration_mm"] < 5.0


def test_with_the_master_limiter_700ms_settles_and_the_master_port_balances() -> None:
    """The energy-bounding force limiter at the master (on by default in the simulation):
    at 700 ms round trip (10 % jitter, 1 % loss, seed 1) the contact settles, and the
    master port gives the hand no more than the slave sent, beyond its 0.1 mJ reserve, than
    the one-tick prediction errors (≤ 1 mJ; 23 mJ without the limiter)."""
    ref = contact_metrics(run(0.0, True))
    m = contact_metrics(run(0.7, True))
    assert m["stable"]
    assert m["oscillation_rms_n"] < 0.1 * m["steady_force_n"]
    assert m["steady_force_n"] > 0.6 * ref["steady_force_n"]
    assert m["penetration_mm"] < 1.5 * ref["penetration_mm"]
    _, master, _ = _overdrafts(run(0.7, True))
    assert master < 0.001
    without = simulate(LoopSpec(round_trip_s=0.7, jitter=0.1, loss=0.01, tdpa=True, limit=False))
    assert not contact_metrics(without)["stable"]  # the damper alone: still hunting
    assert _overdrafts(without)[1] > 10 * master


def test_trend_is_the_least_squares_slope() -> None:
    ramp = [(0.1 * i, 5.0 + 2.0 * 0.1 * i) for i in range(30)]  # 2 N/s
    assert trend_n_s(ramp) == pytest.approx(2.0)
    wobble = [(0.01 * i, 8.0 + (1.0 if i % 2 else -1.0)) for i in range(200)]
    assert abs(trend_n_s(wobble)) < 0.1  # an oscillation has no trend
    assert trend_n_s([]) == 0.0 and trend_n_s([(1.0, 3.0), (1.0, 4.0)]) == 0.0


def test_swing_counts_back_and_forth_not_steps() -> None:
    assert swing_rms([]) == 0.0
    assert swing_rms([5.0, 5.0, 5.0, 7.2, 7.2, 7.2]) == 0.0  # a late step of the contact
    assert swing_rms([9.0, 8.0, 8.0, 6.5]) == 0.0  # sinking
    # Rising fit 0, 0, 0, 0 (residuals ±1: 1); falling fit 1, 0, 0, -1 (0, -1, 1, 0).
    assert swing_rms([1.0, -1.0, 1.0, -1.0]) == pytest.approx(math.sqrt(0.5))
    # Rising fit 0, 1.5, 1.5, 3: residuals 0, ±0.5, 0 -> sqrt(0.5 / 4); falling: 1.12.
    assert swing_rms([0.0, 2.0, 1.0, 3.0]) == pytest.approx(math.sqrt(0.125))
    # Rising fit 2, 6, 6, 6 (residuals 0, 2, 0, -2 -> sqrt(2)); falling 16/3 x 3, 4 (2.16).
    assert swing_rms([2.0, 8.0, 6.0, 4.0]) == pytest.approx(math.sqrt(2.0))


def test_a_contact_lost_in_the_window_did_not_hold() -> None:
    assert held([5.0, 5.0, 7.2, 7.2], 6.1)  # a late step: held
    assert not held([0.0, 0.0, 42.0, 42.0], 21.0)  # left the surface, hit it again
    assert not held([], 0.0)
    # Without TDPA at 700 ms the sim's contact leaves the surface in the window too.
    off = contact_metrics(run(0.7, False))
    assert not off["stable"] and not off["settled"]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), max_size=40), st.floats(-1e3, 1e3))
def test_swing_never_exceeds_the_rms_about_the_mean(values: list[float], shift: float) -> None:
    swing = swing_rms(values)
    mean = sum(values) / len(values) if values else 0.0
    rms = math.sqrt(sum((v - mean) ** 2 for v in values) / len(values)) if values else 0.0
    assert 0.0 <= swing <= rms + 1e-9 * (1.0 + rms)
    assert swing_rms([v + shift for v in values]) == pytest.approx(swing, abs=1e-6)
    assert swing_rms(sorted(values)) == pytest.approx(0.0, abs=1e-9)
    assert swing_rms(sorted(values, reverse=True)) == pytest.approx(0.0, abs=1e-9)


def _slave_speeds(res: LoopResult) -> list[float]:
    dt = res.spec.dt_s
    return [abs(b - a) / dt for a, b in zip(res.x_slave, res.x_slave[1:], strict=False)]


@pytest.mark.parametrize("seed", range(1, 7))
def test_the_slave_arm_chases_its_target_within_its_speed_and_creates_no_energy(
    seed: int,
) -> None:
    """The simulated slave moves as the PUMA's safety filter lets it (0.5 m/s at the tool,
    ArmConfig.max_tool_speed_m_s). At 700 ms with 10 % jitter the latest-wins link delivers
    the master's positions in bunches: a slave that jumps to each one steps over a
    millisecond's worth of the wall (seed 4: 1.7 mm in one tick, 9 mJ out of a channel
    that had been given none). Chasing it at the arm's speed, every impact is a few ticks
    the controller sees: the channel never shows more than 2 mJ generated, in every seed."""
    spec = LoopSpec(round_trip_s=0.7, jitter=0.1, loss=0.01, tdpa=True, seed=seed)
    res = simulate(spec)
    assert max(_slave_speeds(res)) <= spec.slave_speed_m_s * (1 + 1e-9)
    m = contact_metrics(res)
    assert m["energy_generated_j"] < 0.002
    assert m["peak_force_n"] < 15.0 and m["penetration_mm"] < 3.0


def test_a_slave_without_a_speed_limit_jumps_with_the_bunched_packets() -> None:
    """Why the speed limit is modelled: without it the same run steps the tool by more than
    a millimetre in one tick into the wall (1.7 m/s), and the channel shows 9 mJ created."""
    spec = LoopSpec(round_trip_s=0.7, jitter=0.1, loss=0.01, tdpa=True, seed=4, slave_speed_m_s=0.0)
    res = simulate(spec)
    assert max(_slave_speeds(res)) > 1.0
    assert contact_metrics(res)["energy_generated_j"] > 0.005


@pytest.mark.parametrize(("rtt_s", "dofs"), [(0.2, 1), (0.7, 1), (0.2, 3), (0.7, 3)])
def test_the_services_slave_port_presses_and_holds_with_nothing_slowing_the_approach(
    rtt_s: float, dofs: int
) -> None:
    """The decision's own port on the slave side, no guarded approach: the first impact
    at the arm's 0.5 m/s overdraws the budget, and what the wall kept of it is forgiven
    once the tool is out of contact. Left owing (before 2026-11-27) the budget stayed below
    zero, every re-entry overdrew again and the master was sent nothing: at 700 ms the tool
    grazed the wall (0.02–0.7 N in six seeds of six) while the operator pushed 6 cm past
    it. In 3-DoF at 200 ms the contact also came and went (3 seeds of 6) while the target
    backed out past where the contact began. Every seed now presses and holds, the impacts'
    energy bounded by a few ticks', and once the operator has let go the tool is back where
    the master says (3-DoF at 700 ms, seed 1, it stayed 38 mm off, owing)."""
    extra: dict[str, object] = dict(THREE_DOF) if dofs == 3 else {}
    for seed in range(1, 7):
        spec = LoopSpec(
            round_trip_s=rtt_s,
            jitter=0.1,
            loss=0.01,
            tdpa=True,
            seed=seed,
            slave_port=True,
            **extra,
        )
        res = simulate(spec)
        m = contact_metrics(res)
        assert m["stable"] and m["steady_force_n"] > 3.0, (seed, m)
        assert abs(res.x_slave[-1] - res.x_master[-1]) < 1e-4, seed
        assert m["penetration_mm"] < 3.0 and m["peak_force_n"] < 15.0, seed
        assert m["energy_generated_j"] < 0.005, seed


def test_the_services_slave_port_needs_an_arm_that_chases_its_target() -> None:
    with pytest.raises(ValueError, match="slave_port"):
        simulate(LoopSpec(slave_port=True, slave_speed_m_s=0.0))


@pytest.mark.parametrize("speed", [-0.1, math.nan, math.inf])
def test_a_bad_slave_speed_is_refused(speed: float) -> None:
    with pytest.raises(ValueError, match="slave_speed_m_s"):
        simulate(LoopSpec(slave_speed_m_s=speed))


TWIST: dict[str, object] = {**THREE_DOF, "slave_port": True, "twist": Twist()}


@pytest.mark.parametrize("rtt_s", [0.2, 0.7])
def test_a_turn_against_a_stop_holds_with_a_rotational_port_at_each_end(rtt_s: float) -> None:
    """The press with a turn against a torsional stop, the master showing the moment: a
    rotational port at each end beside the force's. Both contacts press and hold in every
    seed, neither oscillates, the channel creates no more than an impact's energy, and the
    turn is let go at the release. (One port for the whole wrench lost both contacts at
    200 ms, 0.05 N·m held for 0.5 N·m: docs/passivity.md, "Rotations".)"""
    for seed in range(1, 4):
        res = simulate(
            LoopSpec(round_trip_s=rtt_s, jitter=0.1, loss=0.01, tdpa=True, seed=seed, **TWIST)
        )  # type: ignore[arg-type]
        force, moment = contact_metrics(res), twist_metrics(res)
        assert force["stable"] and force["steady_force_n"] > 3.0, (seed, force)
        assert moment["stable"] and moment["steady_force_n"] > 0.2, (seed, moment)
        assert moment["peak_force_n"] < 1.0 and moment["penetration_mm"] < 40.0, seed
        assert force["energy_generated_j"] < 0.005, seed
        assert res.m_contact[-1] == 0.0 and res.f_contact[-1] == 0.0, seed


def test_without_tdpa_the_turn_against_the_stop_bounces() -> None:
    res = simulate(LoopSpec(round_trip_s=0.2, jitter=0.1, loss=0.01, tdpa=False, **TWIST))  # type: ignore[arg-type]
    moment = twist_metrics(res)
    assert not moment["stable"] and moment["peak_force_n"] > 3.0
    assert moment["energy_generated_j"] > 1.0


def test_without_delay_the_rotational_port_changes_nothing_the_operator_feels() -> None:
    """At 0 ms the moment felt with both rotational ports is the moment felt without them,
    within 5 %, and it is the stop's."""
    on, off = (
        twist_metrics(simulate(LoopSpec(tdpa=tdpa, **TWIST)))  # type: ignore[arg-type]
        for tdpa in (True, False)
    )
    assert off["felt_force_n"] > 0.3
    assert abs(on["felt_force_n"] - off["felt_force_n"]) < 0.05 * off["felt_force_n"]
    assert on["felt_force_n"] == pytest.approx(on["steady_force_n"], rel=0.05)


def test_the_twist_needs_the_services_ports_in_three_dofs() -> None:
    with pytest.raises(ValueError, match="twist"):
        simulate(LoopSpec(twist=Twist()))
    with pytest.raises(ValueError, match="twist"):
        simulate(LoopSpec(twist=Twist(), slave_port=True))
