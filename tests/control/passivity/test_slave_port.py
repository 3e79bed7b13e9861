"""The slave port on measured, timestamped motion (services/control/passivity/slave.py): pairing,
target correction, energy reflection, the supervisor's exclusion, and properties."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.passivity.controller import TOLERANCE_J
from services.control.passivity.slave import MAX_BACKOFF_M, MIN_FORCE_N, SlavePort, TimedHistory

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
    assert sp.offset[2] == pytest.approx(off - 0.001)  # free: 1 cm/s


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
            # Within the budget; an overdrawn one backs out at most MAX_BACKOFF_M.
            backed_out = -committed / norm >= MAX_BACKOFF_M - 1e-9
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
