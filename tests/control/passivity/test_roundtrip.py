"""The round trip each port measures from the other's echoes (roundtrip.py), against
hand-worked stamps, and over any two clocks and delays."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus.messages import PassivityState
from services.control.passivity.roundtrip import (
    ECHO_EVERY_NS,
    MAX_RTT_NS,
    SAMPLE_NS,
    WINDOW_S,
    RoundTrip,
)

MS = 1_000_000


def theirs(seq: int, t_ns: int, echo: tuple[int, int] | None) -> PassivityState:
    """The other side's figures, echoing (our t_ns, how long they held it)."""
    return PassivityState(
        seq=seq,
        t_ns=t_ns,
        master="m1",
        engage=1,
        side="master",
        enabled=True,
        e_in=0.0,
        e_out=0.0,
        dissipated_j=0.0,
        gain=0.0,
        active_steps=0,
        echo_t_ns=None if echo is None else echo[0],
        echo_age_ns=None if echo is None else echo[1],
    )


def test_nothing_heard_nothing_echoed_and_no_round_trip() -> None:
    rt = RoundTrip()
    assert rt.echo(5 * MS) is None and rt.rtt_s(5 * MS) is None
    rt.heard(theirs(1, 123, None), 10**12, 2 * MS)  # no echo in it: nothing measured
    assert rt.rtt_s(2 * MS) is None and rt.measured == 0


def test_the_echo_is_their_stamp_and_how_long_since_it_was_read() -> None:
    rt = RoundTrip()
    rt.heard(theirs(1, 777, None), 10**12, 5 * MS)
    assert rt.echo(7 * MS) == (777, 2 * MS)
    assert rt.echo(4 * MS) == (777, 0)  # never a negative hold
    rt.heard(theirs(2, 778, None), 10**12, 8 * MS)  # a new one arrives
    assert rt.echo(9 * MS) == (778, 1 * MS)


def test_a_round_trip_is_the_time_since_we_sent_less_their_hold() -> None:
    """We sent at wall 10.000 s; they held our figures 3 ms; we read theirs at wall
    10.203 s: 203 − 3 = 200 ms."""
    rt = RoundTrip()
    sent = 10_000 * MS
    rt.heard(theirs(1, 42, (sent, 3 * MS)), 10_203 * MS, 50_000 * MS)
    assert rt.measured == 1
    assert rt.rtt_s(50_000 * MS) == pytest.approx(0.200)


@pytest.mark.parametrize(
    ("echo_t_ns", "now_wall_ns", "why"),
    [
        (20_000 * MS, 10_000 * MS, "a round trip below zero (their echo from our future)"),
        (1, 10**12 + MAX_RTT_NS, "longer than MAX_RTT_NS"),
    ],
)
def test_an_absurd_echo_is_ignored_and_counted(echo_t_ns: int, now_wall_ns: int, why: str) -> None:
    rt = RoundTrip()
    rt.heard(theirs(1, 42, (echo_t_ns, 0)), now_wall_ns, 50_000 * MS)
    assert (rt.measured, rt.ignored) == (0, 1), why
    assert rt.rtt_s(50_000 * MS) is None


def test_the_estimate_is_the_median_of_the_window_one_sample_per_interval() -> None:
    """Round trips of 100, 300 and 200 ms, 20 ms apart: 200 ms. One 5 ms after the last,
    however long, is measured but not kept (SAMPLE_NS). Past the window, nothing."""
    rt = RoundTrip()
    wall0, mono0 = 100_000 * MS, 1_000 * MS
    for i, rtt_ms in enumerate((100, 300, 200)):
        wall = wall0 + i * 20 * MS
        rt.heard(theirs(i + 1, i + 1, (wall - rtt_ms * MS, 0)), wall, mono0 + i * 20 * MS)
    assert rt.rtt_s(mono0 + 40 * MS) == pytest.approx(0.200)
    assert SAMPLE_NS > 5 * MS
    late_wall = wall0 + 45 * MS
    rt.heard(theirs(9, 9, (late_wall - 5_000 * MS, 0)), late_wall, mono0 + 45 * MS)
    assert rt.measured == 4 and rt.rtt_s(mono0 + 45 * MS) == pytest.approx(0.200)
    # The first expires first: then the median of 300 and 200.
    assert rt.rtt_s(mono0 + int(WINDOW_S * 1e9) + 1 * MS) == pytest.approx(0.250)
    assert rt.rtt_s(mono0 + int(WINDOW_S * 1e9) + 100 * MS) is None


@given(
    offset_wall=st.integers(-(10**15), 10**15),
    offset_mono=st.integers(0, 10**15),
    down_ns=st.integers(0, 10**10),
    their_read_ns=st.integers(0, 10**7),
    hold_ns=st.integers(0, 10**9),
    up_ns=st.integers(0, 10**10),
    our_read_ns=st.integers(0, 10**7),
)
def test_the_round_trip_is_the_two_delays_and_the_reads_whatever_the_clocks(
    offset_wall: int,
    offset_mono: int,
    down_ns: int,
    their_read_ns: int,
    hold_ns: int,
    up_ns: int,
    our_read_ns: int,
) -> None:
    """Our message leaves at true time t0 (stamped on our wall clock); it reaches the other
    side after `down_ns`, which reads it `their_read_ns` later and sends its echo
    `hold_ns` after that (their own RoundTrip, on a clock of their own); the echo reaches
    us after `up_ns` and we read it `our_read_ns` later. Our wall and monotonic clocks are
    offset from true time arbitrarily: the round trip is the two delays and the two reads'
    lateness, to the nanosecond, never less than the link's."""
    t0 = 10**12
    mine = RoundTrip()
    other = RoundTrip()
    ours = theirs(1, t0 + offset_wall, None)
    t_read = t0 + down_ns + their_read_ns
    other.heard(ours, 0, t_read + 7)  # their monotonic clock: any offset of its own
    echo = other.echo(t_read + 7 + hold_ns)
    assert echo is not None and echo == (t0 + offset_wall, hold_ns)
    t_back = t_read + hold_ns + up_ns + our_read_ns
    mine.heard(theirs(1, 5, echo), t_back + offset_wall, t_back + offset_mono)
    got = mine.rtt_s(t_back + offset_mono)
    assert got is not None
    assert round(got * 1e9) == down_ns + their_read_ns + up_ns + our_read_ns


def test_a_message_without_an_echo_still_updates_what_we_echo() -> None:
    rt = RoundTrip()
    rt.heard(theirs(1, 100, None), 10**12, 1 * MS)
    rt.heard(dataclasses.replace(theirs(2, 200, None)), 10**12, 3 * MS)
    assert rt.echo(4 * MS) == (200, 1 * MS)


def test_the_echo_and_the_round_trip_ride_on_one_message_in_each_interval() -> None:
    """52 bytes a message: carried at most every ECHO_EVERY_NS, not on every one."""
    rt = RoundTrip()
    assert rt.carry(0) == (None, None)  # nothing heard yet: nothing to carry
    sent = 10_000 * MS
    rt.heard(theirs(1, 42, (sent, 0)), sent + 100 * MS, 1_000 * MS)
    echo, rtt = rt.carry(1_001 * MS)
    assert echo == (42, 1 * MS) and rtt == pytest.approx(0.100)
    assert rt.carry(1_001 * MS + ECHO_EVERY_NS - 1) == (None, None)
    echo, rtt = rt.carry(1_001 * MS + ECHO_EVERY_NS)
    assert echo == (42, 1 * MS + ECHO_EVERY_NS) and rtt == pytest.approx(0.100)
