"""The bench's statistics on hand-worked inputs, and properties against brute-force references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.tools.bench import stats

MS = stats.NS_PER_MS


def test_percentile_interpolates_like_numpy() -> None:
    assert stats.percentile([1, 2, 3, 4], 50) == 2.5
    assert stats.percentile([5.0], 99) == 5.0
    # 101 values 0…100: the q-th percentile is q itself
    assert stats.percentile(list(range(101)), 99) == pytest.approx(99.0)
    assert math.isnan(stats.percentile([], 50))
    with pytest.raises(ValueError):
        stats.percentile([1.0], 101)


def test_summarize_values_and_empty() -> None:
    s = stats.summarize([4.0, 1.0, 3.0, 2.0])
    assert (s.n, s.p50, s.max, s.mean, s.min) == (4, 2.5, 4.0, 2.5, 1.0)
    assert s.p99 == pytest.approx(3.97)
    empty = stats.summarize([])
    assert empty.n == 0
    assert empty.as_dict() == {
        "n": 0,
        "p50": None,
        "p99": None,
        "max": None,
        "mean": None,
        "min": None,
    }


def test_latencies_ms_is_arrival_minus_stamp() -> None:
    got = stats.latencies_ms([3 * MS, 10 * MS], [1 * MS, 9_500_000])
    assert got.tolist() == [2.0, 0.5]
    with pytest.raises(ValueError):
        stats.latencies_ms([1, 2], [1])


def test_seq_loss_counts_gaps_duplicates_and_reordering() -> None:
    loss = stats.seq_loss([10, 11, 13, 12, 12, 16])
    assert loss.received == 6
    assert loss.unique == 5
    assert (loss.first, loss.last, loss.expected) == (10, 16, 7)
    assert loss.lost == 2  # 14 and 15
    assert loss.duplicates == 1
    assert loss.reordered == 2  # 12 after 13, and its duplicate
    assert loss.loss_ratio == pytest.approx(2 / 7)


def test_seq_loss_of_nothing_and_of_a_clean_stream() -> None:
    assert stats.seq_loss([]).as_dict()["expected"] == 0
    assert stats.seq_loss([]).loss_ratio == 0.0
    clean = stats.seq_loss(list(range(1, 1001)))
    assert (clean.lost, clean.duplicates, clean.reordered, clean.expected) == (0, 0, 0, 1000)


@settings(deadline=None)  # a loaded CI host must not turn a slow example into a failure
@given(st.lists(st.integers(0, 300), min_size=1, max_size=200))
def test_seq_loss_matches_a_set_count(seqs: list[int]) -> None:
    loss = stats.seq_loss(seqs)
    distinct = set(seqs)
    assert loss.unique == len(distinct)
    assert loss.lost == max(distinct) - min(distinct) + 1 - len(distinct)
    assert loss.duplicates == len(seqs) - len(distinct)
    assert loss.lost >= 0 and 0.0 <= loss.loss_ratio < 1.0


def test_rates() -> None:
    assert stats.rate_hz(500, 0.5) == 1000.0
    assert stats.rate_hz(3, 0.0) == 0.0
    with pytest.raises(ValueError):
        stats.rate_hz(-1, 1.0)
    # 11 events 1 ms apart: 10 intervals over 10 ms
    assert stats.rate_from_times([i * MS for i in range(11)]) == pytest.approx(1000.0)
    assert stats.rate_from_times([5]) == 0.0
    assert stats.rate_from_times([5, 5]) == 0.0


def test_merge_windows() -> None:
    assert stats.merge_windows([(5, 7), (1, 3), (2, 4), (7, 9), (20, 10)]) == [
        (1, 4),
        (5, 9),
        (10, 20),
    ]
    assert stats.merge_windows([]) == []


def test_rate_in_windows_counts_only_inside_the_union() -> None:
    s = stats.NS_PER_S
    times = [0, s // 2, s, 3 * s // 2, 2 * s, 5 * s]
    # windows [0, 1 s] and [0.5 s, 2 s] merge into [0, 2 s]: 5 events in 2 s
    wr = stats.rate_in_windows(times, [(0, s), (s // 2, 2 * s)])
    assert (wr.count, wr.covered_s, wr.rate_hz) == (5, 2.0, 2.5)
    assert stats.rate_in_windows(times, []).rate_hz == 0.0


@settings(deadline=None)
@given(
    st.lists(st.integers(0, 1000), max_size=60),
    st.lists(st.tuples(st.integers(0, 1000), st.integers(0, 1000)), max_size=8),
)
def test_rate_in_windows_agrees_with_brute_force(
    times: list[int], windows: list[tuple[int, int]]
) -> None:
    wr = stats.rate_in_windows(times, windows)
    inside = sum(1 for t in times if any(min(a, b) <= t <= max(a, b) for a, b in windows))
    assert wr.count == inside


def test_pair_skew_only_for_complete_pairs() -> None:
    left = {1: 10 * MS, 2: 20 * MS, 3: 30 * MS}
    right = {1: 11 * MS, 3: 29 * MS, 4: 40 * MS}
    assert stats.pair_skew_ms(left, right) == [1.0, 1.0]


def _ms(x: float) -> int:
    return int(x * MS)


def test_first_carriers_keeps_the_lowest_seq_per_origin() -> None:
    cmds = [(12, 500), (10, 500), (11, None), (13, 700), (14, 700)]
    assert stats.first_carriers(cmds) == {500: 10, 700: 13}
    assert stats.first_carriers([]) == {}


def test_stamped_commands_hand_worked() -> None:
    sent = [_ms(1), _ms(2), _ms(3), _ms(4)]
    # Puma commands (seq, origin): 20 carries 1 ms, 21 carries 2 ms, 22 re-sends 2 ms, 23 is a
    # hold, 24 carries 4 ms; 3 ms was superseded before the decision sent it; 9 ms is not ours.
    arm = [(20, _ms(1)), (21, _ms(2)), (22, _ms(2)), (23, None), (24, _ms(4)), (25, _ms(9))]
    states = [
        (20, _ms(1.3), None, _ms(1)),  # received, no setpoint yet
        (20, _ms(1.3), _ms(1.9), _ms(1)),  # its setpoint, one state later
        (22, _ms(2.9), _ms(3.1), _ms(2)),  # a re-send of 2 ms: its times overstate the path
        (23, _ms(3.2), _ms(3.3), None),  # a hold
        (24, _ms(4.2), _ms(4.6), _ms(4)),
        (25, _ms(9.2), _ms(9.5), _ms(9)),  # another master's
    ]
    # The decision's ticks: 20 at 1.1 ms, 21 at 2.1, 22 at 2.6 (the re-send), 24 at 4.05.
    ticks = {20: _ms(1.1), 21: _ms(2.1), 22: _ms(2.6), 24: _ms(4.05), 25: _ms(9.1)}
    got = stats.stamped_commands(sent, arm, states, ticks)
    assert got.reached == 3  # 1, 2 and 4 ms
    assert got.sampled == 2  # 1 and 4 ms: 2 ms was only shown through its re-send
    np.testing.assert_allclose(got.arm_ms, [0.3, 0.2])
    np.testing.assert_allclose(got.setpoint_ms, [0.9, 0.6])
    # hops: master → tick for the three reached (through each one's first carrier), tick →
    # receipt and receipt → setpoint for the two shown
    np.testing.assert_allclose(got.decision_ms, [0.1, 0.1, 0.05])
    np.testing.assert_allclose(got.to_arm_ms, [0.2, 0.15])
    np.testing.assert_allclose(got.apply_ms, [0.6, 0.4])
    without = stats.stamped_commands(sent, arm, states)  # no send stamps: no hops
    assert without.decision_ms.size == without.to_arm_ms.size == 0
    np.testing.assert_allclose(without.apply_ms, [0.6, 0.4])


def test_stamped_commands_without_the_arm_stream_takes_each_origins_first_state() -> None:
    states = [(5, _ms(1.5), None, _ms(1)), (6, _ms(1.8), _ms(2.0), _ms(1)), (7, None, None, None)]
    got = stats.stamped_commands([_ms(1)], [], states)
    assert (got.reached, got.sampled) == (0, 1)
    np.testing.assert_allclose(got.arm_ms, [0.5])  # seq 5, the first to show it
    assert got.setpoint_ms.size == 0  # seq 5 never showed a setpoint; 6 is a later carrier


def test_stamped_commands_of_services_without_the_fields_is_empty() -> None:
    got = stats.stamped_commands([1, 2], [(1, None)], [(1, None, None, None)])
    assert (got.reached, got.sampled, got.arm_ms.size, got.setpoint_ms.size) == (0, 0, 0, 0)


def test_sent_stream_counts_only_the_timed_samples_and_their_loss() -> None:
    # seqs 1–3 were a route set-up; 4–13 timed (10 sent), 7 lost; each back 2 ms after its stamp
    records = [(t * 1_000_000 + 2_000_000, (s, t * 1_000_000)) for t, s in enumerate(range(1, 14))]
    records = [r for r in records if r[1][0] != 7]
    fig = stats.sent_stream(10, records, first=3)
    assert fig["sent"] == 10 and fig["received"] == 9
    assert fig["loss"]["lost"] == 1
    assert fig["latency_ms"]["p50"] == pytest.approx(2.0)
    assert fig["latency_ms"]["max"] == pytest.approx(2.0)
    assert fig["rate_hz"] == pytest.approx(8 / 0.009)  # 9 arrivals over 9 ms


def test_sent_stream_with_nothing_back_is_all_lost() -> None:
    fig = stats.sent_stream(5, [])
    assert fig["received"] == 0 and fig["loss"]["lost"] == 5


def test_counters_delta_keeps_every_counter_read_both_times() -> None:
    before = {"samples": 10, "overruns": 2, "gone": 1}
    after = {"samples": 1010, "overruns": 2, "new": 5}
    assert stats.counters_delta(before, after) == {"samples": 1000, "overruns": 0}
    assert stats.counters_delta(None, after) is None
    assert stats.counters_delta(before, None) is None
