"""The slave port on measured, timestamped motion (services/control/passivity/slave.py): pairing,
target correction, energy reflection, the supervisor's exclusion, and properties."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.passivity.controller import TOLERANCE_J
from services.control.passivity.slave import (
    DRIFT_CONTACT_M_S,
    MAX_BACKOFF_M,
    MIN_FORCE_N,
    OWING_CLEAR_M,
    YIELD_MAX_M_S,
    YIELD_MIN_N,
    SlavePort,
    TimedHistory,
)

UP = (0.0, 0.0, 1.0)


def test_history_interpolates_at_a_time_and_clamps_to_the_ends() -> None:
    h = TimedHistory(maxlen=4)
    assert h.at(0) is None and h.newest_ns is None
    assert h.add(1_000, (0.0, 0.0, 0.0))
    assert h.add(2_000, (0.0, 0.0, -1.0))
    assert not h.add(2_000, (9.0, 9.0, 9.0))  # not newer: ignored
    assert not h.add(1_500, (9.0, 9.0, 9.0))  # reordered: ignored
    assert h.at(1_250) == pytest.approx((0.0, 0.0, -0.25))
    assert h.at(500) == (0.0, 0.0, 0.0)  # before the oldest: the oldest
    assert h.at(9_000) == (0.0, 0.0, -1.0)  # never extrapolated
    for k in range(3, 8):
        h.add(k * 1_000, (float(k), 0.0, 0.0))
    assert h.at(1_000) == (4.0, 0.0, 0.0)  # only the newest 4 kept
    assert h.newest_ns == 7_000


def test_observe_pairs_the_mean_force_with_the_measured_step() -> None:
    sp = SlavePort()
    assert sp.observe((0.0, 0.0, 10.0), (0.0, 0.0, 0.0)) == 0.0  # the starting point
    # The tool moved 1 cm down into a force growing 10 → 30 N: 0.2 J out of the channel.
    assert sp.observe((0.0, 0.0, 30.0), (0.0, 0.0, -0.01)) == pytest.approx(-0.2)
    assert sp.observer.e_out == pytest.approx(0.2) and sp.observer.e_in == 0.0
    sp.restart()  # a hold: the next sample only sets the starting point
    assert sp.observe((0.0, 0.0, 30.0), (0.0, 0.0, 0.5)) == 0.0


def test_workcell_energy_first_repays_an_overdraw_and_is_never_credited_beyond_it() -> None:
    sp = SlavePort()
    sp.remote.update(0, 0.05)
    sp.observe((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    sp.observe((0.0, 0.0, 20.0), (0.0, 0.0, -0.01))  # 0.1 J out, 0.05 paid: 0.05 overdrawn
    assert sp.budget_j == pytest.approx(-0.05)
    sp.observe((0.0, 0.0, 0.0), (0.0, 0.0, -0.005))  # the workcell gives 0.05 J back
    assert sp.recovered_j == pytest.approx(0.05) and sp.observer.e_in == 0.0
    assert sp.budget_j == pytest.approx(0.0)
    # A sensing lag makes the workcell look active (0.06 J back for 0.1 J in, 0.05 of it
    # already recovered): only what it was given is credited to the channel.
    sp.observe((0.0, 0.0, 24.0), (0.0, 0.0, -0.005))
    sp.observe((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert sp.observer.e_in == pytest.approx(0.05)
    assert sp.clipped_j == pytest.approx(0.01)
    assert sp.observer.e_in + sp.recovered_j <= sp.observer.e_out + 1e-12


def test_the_supervisors_retraction_is_not_the_channels_energy() -> None:
    sp = SlavePort()
    sp.remote.update(0, 1.0)
    sp.observe((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    sp.observe((0.0, 0.0, 60.0), (0.0, 0.0, -0.004))  # pressed in: 0.12 J out, paid
    sp.observe((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), supervised=True)  # retracted: 0.12 J back
    assert sp.observer.e_in == 0.0
    assert sp.excluded_j == pytest.approx(0.12)


def test_correct_stops_at_the_first_touch_without_energy_and_passes_free_motion() -> None:
    sp = SlavePort(drift_m_s=0.0)
    # Free space: the target passes unchanged whatever the budget.
    assert sp.correct((0.0, 0.0, -0.05), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.01) == [
        0.0,
        0.0,
        -0.05,
    ]
    # Touching (5 N up) with a target 2 cm deeper and no energy: the target is the tool.
    out = sp.correct((0.0, 0.0, -0.05), (0.0, 0.0, -0.03), (0.0, 0.0, 5.0), 0.01)
    assert out == pytest.approx([0.0, 0.0, -0.03])
    assert sp.offset == pytest.approx([0.0, 0.0, 0.02])
    assert sp.telemetry.active_steps == 1
    # Sideways motion along the surface costs nothing: it passes.
    out = sp.correct((0.01, 0.0, -0.03), (0.0, 0.0, -0.03), (0.0, 0.0, 5.0), 0.01)
    assert out[0] == pytest.approx(0.01) and out[2] == pytest.approx(-0.01)
    # With 0.05 J from the master the target may go 1 cm deeper against 5 N, no more.
    paid = SlavePort(drift_m_s=0.0)
    paid.remote.update(0, 0.05)
    out = paid.correct((0.0, 0.0, -0.05), (0.0, 0.0, -0.03), (0.0, 0.0, 5.0), 0.01)
    assert out[2] == pytest.approx(-0.04)


def test_an_overdrawn_budget_backs_the_target_out_along_the_force() -> None:
    sp = SlavePort(drift_m_s=0.0)
    sp.correct((0.0, 0.0, -0.01), (0.0, 0.0, 0.0), (0.0, 0.0, 20.0), 0.01)  # the touch at 0
    sp.offset = [0.0, 0.0, 0.0]
    sp.observe((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    sp.observe((0.0, 0.0, 20.0), (0.0, 0.0, -0.002))  # 0.02 J out, none paid
    out = sp.correct((0.0, 0.0, -0.01), (0.0, 0.0, -0.002), (0.0, 0.0, 20.0), 0.01)
    assert out[2] == pytest.approx(-0.002 + 0.02 / 20.0)


def test_drift_is_given_back_only_with_energy_to_spare() -> None:
    sp = SlavePort(drift_m_s=0.01)
    sp.correct((0.0, 0.0, -0.05), (0.0, 0.0, -0.03), (0.0, 0.0, 5.0), 0.01)
    off = sp.offset[2]
    sp.correct((0.0, 0.0, -0.05), (0.0, 0.0, -0.03), (0.0, 0.0, 5.0), 0.01)
    assert sp.offset[2] == pytest.approx(off)  # in contact, no energy: kept
    sp.correct((0.0, 0.0, -0.05), (0.0, 0.0, -0.03), (0.0, 0.0, 0.0), 0.1)
    off -= DRIFT_CONTACT_M_S * 0.1
    assert sp.offset[2] == pytest.approx(off)  # free, towards the surface just left: slowly
    sp.correct((0.0, 0.0, -0.01), (0.0, 0.0, -0.03), (0.0, 0.0, 0.0), 0.1)
    assert sp.offset[2] == pytest.approx(off - 0.001)  # free, clear of it: 1 cm/s


def test_the_target_backs_out_no_further_than_where_the_contact_began() -> None:
    """Overdrawn, the target backs out along the force, at most 2 mm past the tool and
    never past the point where this contact began: past it the tool leaves the surface,
    the display goes blank a round trip later and the hand sinks (the simulated loop with
    the service's port, 3-DoF at 200 ms: the contact came and went in 3 seeds of 6)."""
    sp = SlavePort(drift_m_s=0.0)
    sp.correct((0.0, 0.0, -0.001), (0.0, 0.0, 0.0), (0.0, 0.0, 2.0), 0.01)  # felt at z = 0
    sp.observer.record(-0.05)  # 50 mJ overdrawn
    for tool_z, want_z in [
        (-0.001, 0.0),  # the tool 1 mm in: back to where the contact began, not 2 mm out
        (-0.005, -0.005 + MAX_BACKOFF_M),  # 5 mm in: 2 mm past the tool
        (0.0005, 0.0005),  # above where it began: held at the tool
    ]:
        sp.offset = [0.0, 0.0, 0.0]
        out = sp.correct((0.0, 0.0, -0.003), (0.0, 0.0, tool_z), (0.0, 0.0, 20.0), 0.01)
        assert out[2] == pytest.approx(want_z), tool_z
    sp.correct((0.0, 0.0, -0.003), (0.0, 0.0, -0.001), (0.0, 0.0, 0.0), 0.01)  # contact lost
    sp.offset = [0.0, 0.0, 0.0]
    out = sp.correct((0.0, 0.0, -0.003), (0.0, 0.0, -0.002), (0.0, 0.0, 20.0), 0.01)
    assert out[2] == pytest.approx(-0.002)  # a new contact, felt here: held at the tool
    sp.offset = [0.0, 0.0, 0.0]
    out = sp.correct((0.0, 0.0, -0.003), (0.0, 0.0, -0.0035), (0.0, 0.0, 20.0), 0.01)
    assert out[2] == pytest.approx(-0.002)  # the arm ran on 1.5 mm: backed out to the touch
    sp.reset(1)
    assert sp.backoff_m((0.0, 0.0, 20.0), (0.0, 0.0, -0.002)) == MAX_BACKOFF_M  # none known


def test_an_overdraw_the_workcell_keeps_is_forgiven_once_out_of_contact() -> None:
    """What the workcell gives back repays an impact's overdraw; what it keeps (its
    damping) is forgiven only out of contact, and counted: left owing, the port held the
    budget below zero for good and the operator pushed 6 cm past a wall the tool grazed."""
    sp = SlavePort(drift_m_s=0.03)
    sp.correct((0.0, 0.0, -0.002), (0.0, 0.0, 0.0), (0.0, 0.0, 20.0), 0.01)  # felt at z = 0
    sp.observe((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    sp.observe((0.0, 0.0, 20.0), (0.0, 0.0, -0.002))  # the impact: 10 N × 2 mm, none paid
    assert sp.budget_j == pytest.approx(-0.02)
    sp.observe((0.0, 0.0, 10.0), (0.0, 0.0, -0.001))  # 15 N × 1 mm back: repays, in contact
    assert sp.recovered_j == pytest.approx(0.015) and sp.observer.e_in == 0.0
    assert sp.forgiven_j == 0.0 and sp.budget_j == pytest.approx(-0.005)
    sp.observe((0.0, 0.0, 0.0), (0.0, 0.0, -0.0005))  # 5 N × 0.5 mm back, and out of contact
    assert sp.recovered_j == pytest.approx(0.0175)
    assert sp.forgiven_j == pytest.approx(0.0025) and sp.budget_j == pytest.approx(0.0)
    sp.offset = [0.0, 0.0, 0.001]  # out of contact near it: back into it only slowly
    out = sp.correct((0.0, 0.0, -0.01), (0.0, 0.0, -0.0005), (0.0, 0.0, 0.0), 0.01)
    assert out[2] == pytest.approx(-0.009 - DRIFT_CONTACT_M_S * 0.01)
    sp.remote.update(0, 0.01)  # the next contact, paid for: the offset goes back again
    sp.correct((0.0, 0.0, -0.01), (0.0, 0.0, -0.0005), (0.0, 0.0, 2.0), 0.01)
    before = sp.offset[2]
    assert before > 0.03 * 0.01
    # Out of it again, near its surface: slowly; clear of it (the operator let go): at speed.
    out = sp.correct((0.0, 0.0, -0.01), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.01)
    assert out[2] == pytest.approx(-0.01 + before - DRIFT_CONTACT_M_S * 0.01)
    before = sp.offset[2]
    out = sp.correct((0.0, 0.0, 0.01), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.01)
    assert out[2] == pytest.approx(0.01 + before - 0.03 * 0.01)
    sp.reset(1)
    assert sp.forgiven_j == 0.0


def test_out_of_contact_the_offset_goes_back_fast_only_away_from_the_surface_or_clear_of_it() -> (
    None
):
    """After a contact (here one forgiven), the offset is given back towards its surface
    near it only at DRIFT_CONTACT_M_S (a second touch that slow is no impact: held back
    altogether, the tool hovered above the MuJoCo table for good while the operator pressed
    on; at the drift's speed, it struck the table again), at the drift's speed away from it,
    and towards it while the target stays OWING_CLEAR_M out (the operator let go)."""
    sp = SlavePort(drift_m_s=0.03)
    sp.correct((0.0, 0.0, -0.003), (0.0, 0.0, 0.0), (0.0, 0.0, 20.0), 0.01)  # felt at z = 0
    sp.observe((0.0, 0.0, 20.0), (0.0, 0.0, 0.0))
    sp.observe((0.0, 0.0, 20.0), (0.0, 0.0, -0.001))  # 20 mJ out, none paid
    sp.observe((0.0, 0.0, 0.0), (0.0, 0.0, 0.0004))  # 10 N × 1.4 mm back: 6 mJ forgiven
    assert sp.forgiven_j == pytest.approx(0.006)
    tool, free, step = (0.0, 0.0, 0.0004), (0.0, 0.0, 0.0), 0.03 * 0.01
    for master_z, offset_z, out_z in [
        (0.004, 0.003, 0.007 - step),  # towards it, the target 6.7 mm out: given back
        (0.001, 0.003, 0.004 - DRIFT_CONTACT_M_S * 0.01),  # towards it, 3.7 mm out: slowly
        (0.004, -0.002, 0.002 + step),  # away from it: given back
    ]:
        sp.offset = [0.0, 0.0, offset_z]
        out = sp.correct((0.0, 0.0, master_z), tool, free, 0.01)
        assert out[2] == pytest.approx(out_z), (master_z, offset_z)
    assert 0.0067 >= OWING_CLEAR_M > 0.0037


# --- yielding to the hand -------------------------------------------------------------------


def test_withheld_is_the_force_now_beyond_what_the_hand_feels() -> None:
    sp = SlavePort(yield_m_s_n=5e-5)
    assert sp.withheld_n(13.0) == 0.0  # no figures from the master: nothing known
    sp.asked_n, sp.shown_n = 10.0, 7.5
    assert sp.withheld_n(8.0) == pytest.approx(0.5)  # the force now, not the one asked
    # A force the master could not show anyway (its own limit: asked 10 N of 13) is not
    # the controller's: only what it withheld of the 10 N.
    assert sp.withheld_n(13.0) == pytest.approx(2.5)
    assert sp.withheld_n(7.0) == 0.0  # the tool presses less than the hand feels


def test_the_target_yields_along_the_force_at_the_rate_and_stops_past_the_bound() -> None:
    """A tool at 12 N where the hand feels 8 (master asked 12): 4 N withheld, out along the
    force (+z) at 5e-5 m/(N·s) × 4 N = 0.2 mm/s, never more than MAX_BACKOFF_M past the tool."""
    sp = SlavePort(drift_m_s=0.0, yield_m_s_n=5e-5)
    sp.remote.update(0, 1.0)  # energy to spare: the energy controller leaves it alone
    sp.asked_n, sp.shown_n = 12.0, 8.0
    tool, f = (0.0, 0.0, -0.001), (0.0, 0.0, 12.0)
    out = sp.correct(tool, tool, f, 0.01)
    assert sp.yielding
    assert out == pytest.approx((0.0, 0.0, -0.001 + 5e-5 * 4.0 * 0.01))
    assert sp.offset[2] == pytest.approx(2e-6) and sp.yielded_m == pytest.approx(2e-6)
    # A huge excess: at YIELD_MAX_M_S; the arm not following: never past the bound.
    sp.asked_n, sp.shown_n = 1000.0, 0.0
    f = (0.0, 0.0, 1000.0)
    out = sp.correct(tool, tool, f, 0.01)
    assert out[2] - tool[2] == pytest.approx(2e-6 + YIELD_MAX_M_S * 0.01)
    for _ in range(200):
        out = sp.correct(tool, tool, f, 0.01)
    assert out[2] - tool[2] == pytest.approx(MAX_BACKOFF_M)
    # Below YIELD_MIN_N of excess, or off, or in free space: nothing.
    for port, asked, shown, force in (
        (SlavePort(drift_m_s=0.0, yield_m_s_n=5e-5), 12.0, 12.0 - 0.9 * YIELD_MIN_N, 12.0),
        (SlavePort(drift_m_s=0.0), 12.0, 8.0, 12.0),
        (SlavePort(drift_m_s=0.0, yield_m_s_n=5e-5), 12.0, 8.0, 0.0),
    ):
        port.remote.update(0, 1.0)
        port.asked_n, port.shown_n = asked, shown
        assert port.correct(tool, tool, (0.0, 0.0, force), 0.01) == pytest.approx(tool)
        assert not port.yielding


def test_what_the_workcell_gives_back_while_yielding_is_not_the_channels() -> None:
    """The tool backs out 0.1 mm under 12 N while yielding: 1.2 mJ the workcell gives back,
    excluded (not for the master); the same motion without a yield is credited."""
    for yielding in (True, False):
        sp = SlavePort(drift_m_s=0.0, yield_m_s_n=5e-5)
        sp.observe((0.0, 0.0, 12.0), (0.0, 0.0, -0.001))
        sp.observe((0.0, 0.0, 12.0), (0.0, 0.0, -0.002))  # 1 mm in under 12 N: 12 mJ out
        sp.remote.update(0, 1.0)
        sp.asked_n, sp.shown_n = (12.0, 8.0) if yielding else (12.0, 12.0)
        sp.correct((0.0, 0.0, -0.002), (0.0, 0.0, -0.002), (0.0, 0.0, 12.0), 0.01)
        assert sp.yielding is yielding
        e = sp.observe((0.0, 0.0, 12.0), (0.0, 0.0, -0.0019))
        if yielding:
            assert e == 0.0 and sp.excluded_j == pytest.approx(12.0 * 1e-4)
            assert sp.observer.e_in == 0.0
        else:
            assert e == pytest.approx(12.0 * 1e-4) and sp.excluded_j == 0.0


def test_with_the_yield_on_the_offset_returns_into_a_contact_slowly_and_not_past_the_hand() -> None:
    sp = SlavePort(drift_m_s=0.03, yield_m_s_n=5e-5)
    sp.remote.update(0, 1.0)
    sp.offset = [0.0, 0.0, 0.001]  # the slave 1 mm out of where the master says
    tool, target = (0.0, 0.0, -0.001), (0.0, 0.0, -0.002)
    sp.asked_n, sp.shown_n = 8.0, 8.0  # the hand feels all of the 8 N: given back, slowly
    out = sp.correct(target, tool, (0.0, 0.0, 8.0), 0.01)
    assert out[2] == pytest.approx(-0.001 - DRIFT_CONTACT_M_S * 0.01)
    sp.offset = [0.0, 0.0, 0.001]
    sp.shown_n = 8.0 - 1.5 * YIELD_MIN_N  # the tool presses harder than the hand feels
    sp.asked_n = 8.0 - 1.5 * YIELD_MIN_N  # (and was never asked more: no yield either)
    out = sp.correct(target, tool, (0.0, 0.0, 8.0), 0.01)
    assert not sp.yielding and out[2] == pytest.approx(-0.001)
    sp.offset = [0.0, 0.0, 0.001]  # in free space near the surface just left: slowly
    out = sp.correct(target, tool, (0.0, 0.0, 0.0), 0.01)
    assert out[2] == pytest.approx(-0.001 - DRIFT_CONTACT_M_S * 0.01)
    sp.offset = [0.0, 0.0, 0.001]  # and clear of it: at drift_m_s
    out = sp.correct((0.0, 0.0, 0.01), tool, (0.0, 0.0, 0.0), 0.01)
    assert out[2] == pytest.approx(0.011 - 0.03 * 0.01)
    # With the yield off, the contact is as before: at drift_m_s when the energy pays,
    # whatever the hand feels (held back, the offset built at the touch came back at once
    # when the force dipped under the dead band: impacts of 49–71 N at 200 ms).
    off = SlavePort(drift_m_s=0.03)
    off.remote.update(0, 1.0)
    off.offset = [0.0, 0.0, 0.001]
    off.asked_n, off.shown_n = 8.0, 2.0
    out = off.correct(target, tool, (0.0, 0.0, 8.0), 0.01)
    assert out[2] == pytest.approx(-0.001 - 0.03 * 0.01)


@settings(max_examples=80, deadline=None)
@given(
    steps=st.lists(
        st.tuples(
            st.tuples(*[st.floats(-0.1, 0.1, allow_nan=False)] * 3),
            st.tuples(*[st.floats(-0.1, 0.1, allow_nan=False)] * 3),
            st.tuples(*[st.floats(-100.0, 100.0, allow_nan=False)] * 3),
            st.floats(0.0, 200.0),
            st.floats(0.0, 200.0),
        ),
        min_size=1,
        max_size=20,
    ),
    remote=st.floats(0.0, 1.0),
)
def test_the_yield_only_ever_backs_the_target_out(
    steps: list[tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...], float, float]],
    remote: float,
) -> None:
    """Whatever the master reports, the yield moves the target along the contact force
    (out of it, never in), by at most YIELD_MAX_M_S × dt, and never further than
    MAX_BACKOFF_M past the tool unless the target was already there."""
    with_y = SlavePort(drift_m_s=0.0, yield_m_s_n=5e-5)
    without = SlavePort(drift_m_s=0.0)
    for port in (with_y, without):
        port.remote.update(0, remote)
    for target, p_now, f, asked, shown in steps:
        with_y.asked_n, with_y.shown_n = asked, shown
        with_y.offset = list(without.offset)  # the same start, the yield alone differs
        a = with_y.correct(target, p_now, f, 0.01)
        b = without.correct(target, p_now, f, 0.01)
        d = [x - y for x, y in zip(a, b, strict=True)]
        norm = math.sqrt(sum(x * x for x in f))
        moved = math.sqrt(sum(x * x for x in d))
        assert moved <= YIELD_MAX_M_S * 0.01 + 1e-12
        if moved > 0.0:
            assert sum(x * y for x, y in zip(d, f, strict=True)) == pytest.approx(moved * norm)
            out_m = sum(fi * (x - p) for fi, x, p in zip(f, a, p_now, strict=True)) / norm
            assert out_m <= MAX_BACKOFF_M + 1e-12


vec3 = st.tuples(*[st.floats(-0.1, 0.1, allow_nan=False)] * 3)
force3 = st.tuples(*[st.floats(-100.0, 100.0, allow_nan=False)] * 3)


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(st.tuples(vec3, vec3, force3), min_size=1, max_size=30),
    remote=st.floats(0.0, 1.0),
)
def test_correct_never_commits_more_than_the_budget(
    steps: list[tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]], remote: float
) -> None:
    """Whatever the master asks, the energy the target would put into the workcell from
    the measured tool never exceeds what is left of the master's, and the workcell is never
    credited with more than it was given."""
    sp = SlavePort()
    sp.remote.update(0, remote)
    for target, p_now, f in steps:
        out = sp.correct(target, p_now, f, 0.01)
        assert all(math.isfinite(x) for x in out)
        committed = -sum(fi * (o - p) for fi, o, p in zip(f, out, p_now, strict=True))
        norm = math.sqrt(sum(x * x for x in f))
        if norm >= MIN_FORCE_N:
            # Within the budget; an overdrawn one backs out at most MAX_BACKOFF_M, and not
            # past where the contact began.
            bound = sp.backoff_m(f, p_now)
            assert 0.0 <= bound <= MAX_BACKOFF_M
            backed_out = -committed / norm >= bound - 1e-9
            assert committed <= sp.budget_j + 1e-9 or (sp.budget_j < 0.0 and backed_out)
        sp.observe(f, out)  # the arm got there
        assert sp.observer.e_in + sp.recovered_j <= sp.observer.e_out + TOLERANCE_J + 1e-12


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(st.tuples(vec3, vec3, force3), min_size=1, max_size=20),
    remote=st.floats(0.0, 1.0),
)
def test_the_sent_target_never_jumps_at_a_rebase(
    steps: list[tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]], remote: float
) -> None:
    """After a hold the arm re-engages from where it is: the new start pose contains the
    offset, so the first target of the new engagement is the old target (no jump)."""
    sp = SlavePort(drift_m_s=0.0)
    sp.remote.update(0, remote)
    target, p_now, f = steps[0]
    for target, p_now, f in steps:
        sent = sp.correct(target, p_now, f, 0.01)
    # The supervisor re-engages with p0 = the tool, which is where the last target took it;
    # the master's displacement restarts at zero from there.
    sp.rebase()
    assert sp.offset == [0.0, 0.0, 0.0]
    again = sp.correct(sent, sent, (0.0, 0.0, 0.0), 0.01)
    assert again == pytest.approx(sent)


def test_the_yield_runs_only_for_a_contact_begun_on_a_short_round_trip() -> None:
    """yield_max_rtt_s = 0.25: decided out of contact, kept through the contact."""
    tool, free, press = (0.0, 0.0, -0.001), (0.0, 0.0, 0.0), (0.0, 0.0, 12.0)

    def port(rtt_s: float | None) -> SlavePort:
        sp = SlavePort(drift_m_s=0.0, yield_m_s_n=5e-5, yield_max_rtt_s=0.25, rtt_s=rtt_s)
        sp.remote.update(0, 1.0)
        sp.asked_n, sp.shown_n = 12.0, 8.0
        return sp

    unknown = port(None)  # nothing measured yet: no yield
    unknown.correct(tool, tool, press, 0.01)
    assert unknown.yield_on is False and not unknown.yielding
    slow = port(0.4)
    slow.correct(tool, tool, free, 0.01)
    slow.correct(tool, tool, press, 0.01)
    assert not slow.yielding and slow.yielded_m == 0.0
    fast = port(0.2)
    fast.correct(tool, tool, free, 0.01)  # out of contact: decided, on
    assert fast.yield_on is True
    fast.correct(tool, tool, press, 0.01)
    assert fast.yielding
    fast.rtt_s = 3.0  # the link slows mid-contact: nothing switches
    fast.correct(tool, tool, press, 0.01)
    assert fast.yielding
    fast.correct(tool, tool, free, 0.01)  # out of contact: decided again, off
    fast.correct(tool, tool, press, 0.01)
    assert fast.yield_on is False and not fast.yielding
    # Without a bound (inf, the port's default) it yields whatever the link.
    anyway = SlavePort(drift_m_s=0.0, yield_m_s_n=5e-5)
    anyway.remote.update(0, 1.0)
    anyway.asked_n, anyway.shown_n = 12.0, 8.0
    anyway.correct(tool, tool, press, 0.01)
    assert anyway.yielding and anyway.yield_max_rtt_s == math.inf


def test_a_new_engagement_decides_the_yield_afresh() -> None:
    tool, press = (0.0, 0.0, -0.001), (0.0, 0.0, 12.0)
    sp = SlavePort(drift_m_s=0.0, yield_m_s_n=5e-5, yield_max_rtt_s=0.25, rtt_s=0.1)
    sp.remote.update(0, 1.0)
    sp.asked_n, sp.shown_n = 12.0, 8.0
    sp.correct(tool, tool, press, 0.01)  # begins in contact, the round trip short: on
    assert sp.yielding
    sp.reset(1)
    assert sp.yield_on is None
    sp.rtt_s = 0.5
    sp.remote.update(1, 1.0)
    sp.asked_n, sp.shown_n = 12.0, 8.0
    sp.correct(tool, tool, press, 0.01)
    assert sp.yield_on is False and not sp.yielding
