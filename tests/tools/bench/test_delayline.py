"""The userspace delay line's schedule and queue (pure), driven with made-up arrival times."""

from __future__ import annotations

import itertools
import math
import statistics

import pytest

from services.tools.bench.delayline import (
    DIRECTIONS,
    DelayLine,
    Direction,
    DirectionShape,
    Schedule,
    classifier,
)

MS = 1_000_000


def schedule(seed: int = 0, **shape: float) -> Schedule:
    return Schedule(dict.fromkeys(DIRECTIONS, DirectionShape(**shape)), seed)


def delays_ms(s: Schedule, n: int, gap_ms: float, direction: Direction = "to_robot") -> list[float]:
    """The delays of n packets of 100 B arriving gap_ms apart (None for a lost one)."""
    out = []
    for k in range(n):
        t = round(k * gap_ms * MS)
        due = s.decide(t, 100, direction)
        out.append(math.nan if due is None else (due - t) / MS)
    return out


def test_a_constant_delay_is_exact() -> None:
    s = schedule(delay_ms=50.0)
    for t in (0, 3, 7 * MS, 1_000 * MS + 1):
        assert s.decide(t, 1500, "to_robot") == t + 50 * MS
        assert s.decide(t, 60, "to_operator") == t + 50 * MS


def test_jitter_is_bounded_at_two_sigma_and_centred_on_the_delay() -> None:
    # 1 s apart: the order rule never binds, each delay is its own draw
    d = delays_ms(schedule(seed=3, delay_ms=50.0, jitter=0.1), 10_000, 1_000.0)
    assert min(d) >= 40.0 and max(d) <= 60.0  # sigma 5 ms, clipped at ±10 ms
    assert abs(statistics.fmean(d) - 50.0) < 0.25  # 5 standard errors (0.05 ms)
    assert 4.0 < statistics.stdev(d) < 5.0  # a normal clipped at ±2 sigma: 0.88 sigma
    assert sum(1 for x in d if x in (40.0, 60.0)) > 100  # 4.6 % sit on the clip


def test_jitter_never_makes_a_delay_negative() -> None:
    d = delays_ms(schedule(seed=1, delay_ms=10.0, jitter=1.0), 5_000, 1_000.0)
    assert min(d) == 0.0 and max(d) <= 30.0
    assert sum(1 for x in d if x == 0.0) > 500  # the draws below -1 sigma (16 %)


def test_a_direction_keeps_its_order_under_jitter() -> None:
    s = schedule(seed=5, delay_ms=50.0, jitter=0.5)
    dues = [s.decide(k * MS, 100, "to_robot") or 0 for k in range(2_000)]
    assert all(dues)
    assert dues == sorted(dues)
    # the rule bound: with 1 ms between packets and 25 ms of sigma, many would have overtaken
    assert sum(1 for a, b in itertools.pairwise(dues) if a == b) > 500


@pytest.mark.parametrize("seed", [0, 1, 2024])
def test_loss_is_within_binomial_bounds_and_reproducible(seed: int) -> None:
    n, p = 20_000, 0.05
    lost = [math.isnan(x) for x in delays_ms(schedule(seed, loss=p), n, 1.0)]
    sd = math.sqrt(n * p * (1 - p))
    assert abs(sum(lost) - n * p) < 5 * sd
    again = [math.isnan(x) for x in delays_ms(schedule(seed, loss=p), n, 1.0)]
    other = [math.isnan(x) for x in delays_ms(schedule(seed + 1, loss=p), n, 1.0)]
    assert lost == again
    assert lost != other


def test_rate_serializes_a_direction() -> None:
    n, length, rate_mbit = 50, 1250, 10.0  # 1 ms per packet
    s = schedule(delay_ms=5.0, rate_mbit=rate_mbit)
    dues = [s.decide(0, length, "to_robot") for _ in range(n)]
    tx_ns = length * 8 * 1_000 / rate_mbit
    assert dues == [round((k + 1) * tx_ns) + 5 * MS for k in range(n)]
    assert dues[-1] is not None and dues[-1] >= n * length * 8 / (rate_mbit * 1e6) * 1e9
    # an idle link does not delay the next packet beyond its own transmission
    t = 200 * MS
    assert s.decide(t, length, "to_robot") == t + round(tx_ns) + 5 * MS


def test_directions_are_independent() -> None:
    slow = schedule(seed=9, delay_ms=20.0, jitter=0.2, loss=0.1, rate_mbit=1.0)
    quiet = schedule(seed=9, delay_ms=20.0, jitter=0.2, loss=0.1, rate_mbit=1.0)
    mixed, alone = [], []
    for k in range(2_000):
        t = k * 3 * MS
        slow.decide(t, 1500, "to_robot")  # a flood one way: 12 ms per packet, every 3 ms
        mixed.append(slow.decide(t, 100, "to_operator"))
        alone.append(quiet.decide(t, 100, "to_operator"))
    assert mixed == alone  # same draws, same serialization, same due times the other way


def test_per_direction_shapes() -> None:
    s = Schedule({"to_robot": DirectionShape(10.0), "to_operator": DirectionShape(30.0)})
    assert s.decide(0, 100, "to_robot") == 10 * MS
    assert s.decide(0, 100, "to_operator") == 30 * MS


def test_the_line_releases_packets_when_due_in_due_order() -> None:
    line = DelayLine(
        Schedule({"to_robot": DirectionShape(10.0), "to_operator": DirectionShape(4.0)})
    )
    assert line.next_due_ns() is None
    assert line.offer(0, b"r1", "to_robot") == 10 * MS
    assert line.offer(1 * MS, b"o1", "to_operator") == 5 * MS
    assert line.offer(2 * MS, b"r2", "to_robot") == 12 * MS
    assert line.offer(7 * MS, b"o2", "to_operator") == 11 * MS
    assert line.next_due_ns() == 5 * MS
    assert line.pop_due(5 * MS - 1) == []
    assert line.pop_due(5 * MS) == [b"o1"]
    assert line.next_due_ns() == 10 * MS
    assert line.pop_due(100 * MS) == [b"r1", b"o2", b"r2"]
    assert line.held == (0, 0)
    assert line.counts.forwarded == 4


def test_the_queue_cap_drops_and_counts() -> None:
    line = DelayLine(schedule(delay_ms=10.0), max_packets=5, max_bytes=1_000_000)
    accepted = [line.offer(k, bytes(100), "to_robot") for k in range(8)]
    assert [d is not None for d in accepted] == [True] * 5 + [False] * 3
    assert line.counts.dropped_queue == 3 and line.held == (5, 500)
    assert len(line.pop_due(10 * MS + 4)) == 5
    assert line.offer(20 * MS, bytes(100), "to_operator") is not None  # room again

    by_bytes = DelayLine(schedule(delay_ms=10.0), max_packets=100, max_bytes=1_000)
    accepted = [by_bytes.offer(k, bytes(400), "to_operator") for k in range(4)]
    assert [d is not None for d in accepted] == [True, True, False, False]
    assert by_bytes.counts.dropped_queue == 2 and by_bytes.held == (2, 800)
    assert by_bytes.counts.dropped_loss == 0


def test_a_lost_packet_is_counted_and_not_held() -> None:
    line = DelayLine(schedule(seed=0, loss=0.5))
    kept = [line.offer(k, bytes(10), "to_robot") for k in range(1_000)]
    n_kept = sum(1 for d in kept if d is not None)
    assert line.counts.dropped_loss == 1_000 - n_kept
    assert line.held == (n_kept, 10 * n_kept)


def ipv4(dst: str) -> bytes:
    header = bytearray(20)
    header[0] = 0x45
    header[16:20] = bytes(int(x) for x in dst.split("."))
    return bytes(header)


def test_the_direction_is_the_destination_address() -> None:
    direction_of = classifier("10.203.0.0/31")
    assert direction_of(ipv4("10.203.0.1")) == "to_robot"
    assert direction_of(ipv4("10.203.0.0")) == "to_robot"
    assert direction_of(ipv4("10.203.0.2")) == "to_operator"
    assert direction_of(ipv4("192.0.2.1")) == "to_operator"
    assert direction_of(b"\x60" + bytes(39)) is None  # IPv6
    assert direction_of(b"\x45" + bytes(10)) is None  # shorter than a header


def test_shapes_outside_their_bounds_are_refused() -> None:
    for bad in ({"delay_ms": -1.0}, {"delay_ms": 5_001.0}, {"jitter": 1.5}, {"loss": 1.0}):
        with pytest.raises(ValueError):
            DirectionShape(**bad)
