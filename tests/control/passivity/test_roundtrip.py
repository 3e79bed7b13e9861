"""The round trip each port measures from the other's echoes (roundtrip.py), against
hand-worked stamps, and over any two clocks and delays."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus.messages import PassivityState
from services.control.passivity.roundtrip import MAX_RTT_NS, SAMPLE_NS, WINDOW_S, RoundTrip

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
    rt.heard(theirs(1, 123, None), 1 * MS, 10**12, 2 * MS)  # no echo in it: nothing measured
    assert rt.rtt_s(2 * MS) is None and rt.measured == 0


def test_the_echo_is_their_stamp_and_how_long_it_was_held() -> None:
    rt = RoundTrip()
    rt.heard(theirs(1, 777, None), 5 * MS, 10**12, 5 * MS)
    assert rt.echo(7 * MS) == (777, 2 * MS)
    assert rt.echo(4 * MS) == (777, 0)  # never a negative hold


def test_a_round_trip_is_the_time_since_we_sent_less_their_hold() -> None:
    """We sent at wall 10.000 s; they held our figures 3 ms; theirs arrived at monotonic
    50.0 s, read at monotonic 50.002 s when the wall said 10.205 s: it arrived at wall
    10.203 s, so 203 − 3 = 200 ms."""
    rt = RoundTrip()
    sent = 10_000 * MS
    rt.heard(theirs(1, 42, (sent, 3 * MS)), 50_000 * MS, 10_205 * MS, 50_002 * MS)
    assert rt.measured == 1
    assert rt.rtt_s(50_002 * MS) == pytest.approx(0.200)
    # The same message read again is not a second measurement.
    rt.heard(theirs(1, 42, (sent, 3 * MS)), 50_000 * MS, 10_300 * MS, 50_097 * MS)
    assert rt.measured == 1


@pytest.mark.parametrize(
    ("echo_t_ns", "now_wall_ns", "why"),
    [
        (20_000 * MS, 10_000 * MS, "a round trip below zero (their echo from our future)"),
        (1, 10**12 + MAX_RTT_NS, "longer than MAX_RTT_NS"),
    ],
)
def test_an_absurd_echo_is_ignored_and_counted(echo_t_ns: int, now_wall_ns: int, why: str) -> None:
    rt = RoundTrip()
    rt.heard(theirs(1, 42, (echo_t_ns, 0)), 50_000 * MS, now_wall_ns, 50_000 * MS)
    assert (rt.measured, rt.ignored) == (0, 1), why
    assert rt.rtt_s(50_000 * MS) is None


def test_the_estimate_is_the_median_of_the_window_one_sample_per_interval() -> None:
    """Round trips of 100, 300 and 200 ms, 20 ms apart: 200 ms. One 5 ms after the last,
    however long, is measured but not kept (SAMPLE_NS). Past the window, nothing."""
    rt = RoundTrip()
    wall0, mono0 = 100_000 * MS, 1_000 * MS
    for i, rtt_ms in enumerate((100, 300, 200)):
        arrival = mono0 + i * 20 * MS
        wall = wall0 + i * 20 * MS
        rt.heard(theirs(i + 1, 1, (wall - rtt_ms * MS, 0)), arrival, wall, arrival)
    assert rt.rtt_s(mono0 + 40 * MS) == pytest.approx(0.200)
    assert SAMPLE_NS > 5 * MS
    late = mono0 + 45 * MS
    rt.heard(theirs(9, 1, (wall0 + 45 * MS - 5_000 * MS, 0)), late, wall0 + 45 * MS, late)
    assert rt.measured == 4 and rt.rtt_s(late) == pytest.approx(0.200)
    # The first expires first: then the median of 300 and 200.
    assert rt.rtt_s(mono0 + int(WINDOW_S * 1e9) + 1 * MS) == pytest.approx(0.250)
    assert rt.rtt_s(mono0 + int(WINDOW_S * 1e9) + 100 * MS) is None


@given(
    offset_wall=st.integers(-(10**15), 10**15),
    offset_mono=st.integers(0, 10**15),
    down_ns=st.integers(0, 10**10),
    hold_ns=st.integers(0, 10**9),
    up_ns=st.integers(0, 10**10),
    read_after_ns=st.integers(0, 10**8),
)
def test_the_round_trip_is_the_two_delays_whatever_the_clocks(
    offset_wall: int, offset_mono: int, down_ns: int, hold_ns: int, up_ns: int, read_after_ns: int
) -> None:
    """Our message leaves at true time t0 (stamped on our wall clock), reaches the other
    side after `down_ns`, is held `hold_ns` (measured on their clock), and their echo
    reaches us after `up_ns`; we read it `read_after_ns` later. Our wall and monotonic
    clocks are offset from true time arbitrarily (and from each other): the round trip is
    down + up, to the nanosecond."""
    t0 = 10**12
    wall = lambda t: t + offset_wall  # noqa: E731
    mono = lambda t: t + offset_mono  # noqa: E731
    t3 = t0 + down_ns + hold_ns + up_ns
    rt = RoundTrip()
    msg = theirs(1, 5, (wall(t0), hold_ns))
    t4 = t3 + read_after_ns
    rt.heard(msg, mono(t3), wall(t4), mono(t4))
    got = rt.rtt_s(mono(t4))
    assert got is not None
    assert round(got * 1e9) == down_ns + up_ns


def test_a_message_without_an_echo_still_updates_what_we_echo() -> None:
    rt = RoundTrip()
    rt.heard(theirs(1, 100, None), 1 * MS, 10**12, 1 * MS)
    rt.heard(dataclasses.replace(theirs(2, 200, None)), 3 * MS, 10**12, 3 * MS)
    assert rt.echo(4 * MS) == (200, 1 * MS)
