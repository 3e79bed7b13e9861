"""The userspace delay line: its schedule and queue (pure), and, as root, the link it makes.

The unit tests drive `Schedule` and `DelayLine` with made-up arrival times. The system tests
build the three-namespace link of `netem_link(..., emulator="delayline")` and measure it from
inside the namespaces with a small UDP echo and a TCP transfer; the delay they check is the
link's own, the thing under test.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import random
import statistics
import subprocess
import sys

import pytest

from services.tools.tdpa.delayline import (
    DIRECTIONS,
    DelayLine,
    Direction,
    DirectionShape,
    Schedule,
    classifier,
)
from services.tools.tdpa.netem import (
    ROBOT_IP,
    LinkShape,
    in_ns,
    netem_link,
    shape,
    tun_refusal,
    unavailable,
)
from tests.bus.test_router import ChildProcess, spawned
from tests.conftest import free_port

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


def test_a_link_shape_gives_the_delay_line_half_its_round_trip() -> None:
    args = LinkShape(round_trip_ms=100.0, jitter=0.1, loss=0.01, rate_mbit=5.0, seed=3)
    assert args.delayline_args() == [
        "--delay-ms=50.0",
        "--jitter=0.1",
        "--loss=0.01",
        "--rate-mbit=5.0",
        "--seed=3",
    ]


# ---- the link, for real (root) ----------------------------------------------------------

ECHO = r"""
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind((sys.argv[1], int(sys.argv[2])))
print("ready", flush=True)
while True:
    data, peer = s.recvfrom(2048)
    s.sendto(data, peer)
"""

PING = r"""
import json, socket, sys, time
host, port, n, gap_s = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.settimeout(5.0)
rtts = []
for k in range(n):
    t = time.monotonic_ns()
    s.sendto(b"%d" % k, (host, port))
    while s.recv(2048) != b"%d" % k:
        pass
    rtts.append((time.monotonic_ns() - t) / 1e6)
    time.sleep(gap_s)
print(json.dumps(rtts), flush=True)
"""

SINK = r"""
import hashlib, socket, sys
srv = socket.create_server((sys.argv[1], int(sys.argv[2])))
print("ready", flush=True)
conn, _ = srv.accept()
h, n = hashlib.sha256(), 0
while chunk := conn.recv(65536):
    h.update(chunk)
    n += len(chunk)
print(n, h.hexdigest(), flush=True)
"""

SEND = r"""
import random, socket, sys
data = random.Random(int(sys.argv[3])).randbytes(int(sys.argv[4]))
with socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=30) as s:
    s.sendall(data)
"""


def _skip_reason() -> str | None:
    return unavailable() or tun_refusal()


def _ready(proc: ChildProcess) -> None:
    assert proc.expect(lambda _: True).strip() == "ready", proc.argv


def _ping(ns: str, port: int, n: int) -> list[float]:
    done = subprocess.run(
        in_ns(ns, sys.executable, "-c", PING, ROBOT_IP, str(port), str(n), "0.05"),
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    rtts: list[float] = json.loads(done.stdout)
    return rtts


@pytest.mark.system
@pytest.mark.timeout(120)
def test_the_delay_line_delays_a_round_trip_by_its_shape() -> None:
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    port = free_port()
    with netem_link(LinkShape(round_trip_ms=100.0), emulator="delayline") as link:
        assert link.emulator == "delayline" and link.delayline is not None
        argv = in_ns(link.robot, sys.executable, "-c", ECHO, ROBOT_IP, str(port))
        with spawned(argv, merge_stderr=False) as echo:
            _ready(echo)
            slow = _ping(link.operator, port, 20)
            shape(link, LinkShape(round_trip_ms=0.0))
            fast = _ping(link.operator, port, 20)
        runs = link.delayline.runs
    assert len(slow) == 20 and len(fast) == 20
    # Never sooner than the shape (the property); the upper bounds only catch a delay applied
    # twice or a reshape not taken, with room for a loaded machine.
    assert min(slow) >= 95.0, slow
    assert statistics.median(slow) < 2 * 100.0, slow
    assert statistics.median(fast) < min(slow) / 2, fast
    # every datagram of each run went through the line, both ways, and nothing else did
    assert [r["forwarded"] for r in runs] == [40, 40], runs
    assert all(r["dropped_loss"] == r["dropped_queue"] == r["not_ipv4"] == 0 for r in runs)


@pytest.mark.system
@pytest.mark.timeout(120)
def test_tcp_through_a_lossy_delay_line_arrives_intact() -> None:
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    port, size, seed = free_port(), 1_000_000, 11
    how = LinkShape(round_trip_ms=20.0, jitter=0.1, loss=0.01, seed=seed)
    with netem_link(how, emulator="delayline") as link:
        assert link.delayline is not None
        argv = in_ns(link.robot, sys.executable, "-c", SINK, ROBOT_IP, str(port))
        with spawned(argv, merge_stderr=False) as sink:
            _ready(sink)
            sent = subprocess.run(
                in_ns(
                    link.operator,
                    sys.executable,
                    "-c",
                    SEND,
                    ROBOT_IP,
                    str(port),
                    str(seed),
                    str(size),
                ),
                capture_output=True,
                text=True,
                timeout=90,
                check=False,
            )
            assert sent.returncode == 0, sent.stderr[-2000:]
            got = "\n".join(sink.rest(60.0)[1:])
        link.delayline.stop()
        counts = link.delayline.runs[-1]
    want = hashlib.sha256(random.Random(seed).randbytes(size)).hexdigest()
    assert got.split() == [str(size), want]
    assert counts["dropped_loss"] >= 1, counts  # the loss was there and TCP recovered
    assert counts["dropped_queue"] == 0 and counts["write_errors"] == 0, counts


@pytest.mark.parametrize(
    ("kwargs", "named"),
    [
        ({"round_trip_ms": -1.0}, "round_trip_ms"),
        ({"round_trip_ms": 20_000.0}, "round_trip_ms"),
        ({"jitter": 1.5}, "jitter"),
        ({"loss": 1.0}, "loss"),
        ({"rate_mbit": -1.0}, "rate_mbit"),
        ({"jitter": float("nan")}, "jitter"),
    ],
)
def test_link_shape_refuses_absurd_values_by_name(kwargs: dict[str, float], named: str) -> None:
    with pytest.raises(ValueError, match=named):
        LinkShape(**kwargs)  # type: ignore[arg-type]


def test_link_shape_netem_arguments() -> None:
    how = LinkShape(round_trip_ms=200.0, jitter=0.1, loss=0.01, rate_mbit=10.0)
    # each end delays what it sends by half the round trip, jitter 10 % of that
    expected = "delay 100.000ms 10.000ms distribution normal loss 1.0000% rate 10mbit"
    assert how.netem_args() == expected.split()


def test_a_rate_capped_direction_drops_what_would_wait_longer_than_its_buffer() -> None:
    """`queue_ms` (issue 41): a thin link's buffer is finite, as a router's is; without it a
    2 Mbit/s cap held up to the line's own cap (seconds) of packets behind the video."""
    shape = DirectionShape(rate_mbit=1.0, queue_ms=10.0)  # 125 B/ms: 1000 B take 8 ms
    line = DelayLine(Schedule(dict.fromkeys(("to_robot", "to_operator"), shape)))
    pkt = bytes(1000)
    assert line.offer(0, pkt, "to_robot") == 8_000_000  # on the link at once
    assert line.offer(0, pkt, "to_robot") == 16_000_000  # waits 8 ms ≤ 10
    assert line.offer(0, pkt, "to_robot") is None  # would wait 16 ms: the buffer is full
    assert line.offer(0, pkt, "to_operator") == 8_000_000  # the other direction is its own
    assert line.offer(7_000_000, pkt, "to_robot") == 24_000_000  # waits 9 ms
    assert line.counts.dropped_queue == 1 and line.counts.dropped_loss == 0
    unbounded = DelayLine(Schedule(dict.fromkeys(("to_robot", "to_operator"),
                                                 DirectionShape(rate_mbit=1.0))))  # fmt: skip
    assert [unbounded.offer(0, pkt, "to_robot") for _ in range(3)][-1] == 24_000_000
    with pytest.raises(ValueError, match="queue_ms"):
        DirectionShape(queue_ms=-1.0)
    args = LinkShape(rate_mbit=2.0, queue_ms=200.0).delayline_args()
    assert args[-1] == "--queue-ms=200.0"
    assert LinkShape(rate_mbit=2.0, queue_ms=200.0).netem_args()[-2:] == ["limit", "33"]
