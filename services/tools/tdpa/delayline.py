"""A link emulator in userspace, for kernels without the netem qdisc: IPv4 packets routed
into a TUN device are read, held for their delay and written back to the same device when
due, where the kernel forwards them on (netem.py builds the namespaces and policy routes).

    python -m services.tools.tdpa.delayline --delay-ms 50 --jitter 0.1 --loss 0.01 \\
        --rate-mbit 0 --seed 0 --dev tl0 --robot-net 10.203.0.0/31

Each value applies to each direction on its own, as netem's on both ends of a veth would:
`--delay-ms` is the one-way delay; jitter is a fraction of it (normal, sigma = jitter ×
delay, clipped at ±2 sigma and at 0); loss is drawn per packet from a seeded
`random.Random` per direction (the same seed and traffic give the same drops); rate
serializes (a packet starts when the previous one of its direction has finished at
rate_mbit, then travels its delay). A packet's direction is its destination address:
inside `--robot-net` it goes to the robot, otherwise to the operator.

The one difference from netem's default: a direction never reorders. A packet whose drawn
delay would let it overtake the one before it leaves with that one instead, so TCP through
the line sees jitter as delay variation, never as reordering (netem reorders with jitter
unless given a rate or a FIFO child).

The process prints `ready` on stdout once the TUN is up, runs until SIGTERM or SIGINT, and
prints its counts as one JSON line on stderr when it exits. Memory is bounded by a queue cap
(packets and bytes held); a packet beyond it is dropped and counted.
"""

from __future__ import annotations

import argparse
import collections
import fcntl
import ipaddress
import json
import os
import random
import select
import signal
import socket
import struct
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from types import FrameType
from typing import Literal

Direction = Literal["to_robot", "to_operator"]
DIRECTIONS: tuple[Direction, Direction] = ("to_robot", "to_operator")

MAX_PACKETS = 10_000
MAX_BYTES = 16 * 1024 * 1024
READ_BURST = 64
"""Packets read per wake-up at most, so due packets are never held behind a flood."""

# linux/if_tun.h and linux/sockios.h
TUNSETIFF = 0x400454CA
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000
SIOCGIFFLAGS = 0x8913
SIOCSIFFLAGS = 0x8914
IFF_UP = 0x1


@dataclass(frozen=True, slots=True)
class DirectionShape:
    """One direction: delay_ms one way (0 … 5000), jitter as a fraction of it (0 … 1), loss
    per packet (0 … 1, excluded), rate_mbit (0: unlimited), queue_ms: with a rate, the
    bottleneck's buffer in time (0 … 10000; 0: unbounded but for the line's own cap): a
    packet that would wait longer than this for the link is dropped, as a router's full
    buffer drops it."""

    delay_ms: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0
    rate_mbit: float = 0.0
    queue_ms: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.delay_ms <= 5_000.0:
            raise ValueError("delay_ms must be within 0 … 5000")
        if not 0.0 <= self.jitter <= 1.0:
            raise ValueError("jitter must be within 0 … 1")
        if not 0.0 <= self.loss < 1.0:
            raise ValueError("loss must be within 0 … 1 (excluded)")
        if not 0.0 <= self.rate_mbit <= 100_000.0:
            raise ValueError("rate_mbit must be within 0 … 100000")
        if not 0.0 <= self.queue_ms <= 10_000.0:
            raise ValueError("queue_ms must be within 0 … 10000")


class _Lane:
    """One direction's draws and its serialization and ordering state (all times in ns)."""

    __slots__ = (
        "busy_until_ns",
        "delay_ns",
        "last_due_ns",
        "loss",
        "ns_per_byte",
        "queue_ns",
        "rng",
        "sigma_ns",
    )

    def __init__(self, shape: DirectionShape, rng: random.Random) -> None:
        self.delay_ns = shape.delay_ms * 1e6
        self.sigma_ns = shape.jitter * self.delay_ns
        self.loss = shape.loss
        self.ns_per_byte = 8_000.0 / shape.rate_mbit if shape.rate_mbit > 0.0 else 0.0
        self.queue_ns = shape.queue_ms * 1e6 if self.ns_per_byte > 0.0 else 0.0
        self.rng = rng
        self.busy_until_ns = 0
        self.last_due_ns = 0


class Schedule:
    """When each packet may leave, or that it is lost: the pure part of the delay line.

    `decide(t_ns, length, direction)` is called once per packet in arrival order, with
    `t_ns` from one monotonic clock. Directions are independent: each has its own seeded
    random stream, serialization and order.
    """

    def __init__(self, shapes: Mapping[Direction, DirectionShape], seed: int = 0) -> None:
        self._lanes = {d: _Lane(shapes[d], random.Random(f"{seed}/{d}")) for d in DIRECTIONS}

    def full(self, t_ns: int, direction: Direction) -> bool:
        """Whether the direction's bottleneck buffer is full at t_ns: a packet arriving now
        would wait more than its `queue_ms` before it starts onto the link."""
        lane = self._lanes[direction]
        return lane.queue_ns > 0.0 and lane.busy_until_ns - t_ns > lane.queue_ns

    def decide(self, t_ns: int, length: int, direction: Direction) -> int | None:
        """The due time (ns, same clock as t_ns) of a packet of `length` bytes arriving at
        t_ns, or None when it is lost; never earlier than the previous due time of its
        direction."""
        lane = self._lanes[direction]
        if lane.loss > 0.0 and lane.rng.random() < lane.loss:
            return None
        start_ns = max(t_ns, lane.busy_until_ns)
        lane.busy_until_ns = start_ns + round(length * lane.ns_per_byte)
        delay_ns = lane.delay_ns
        if lane.sigma_ns > 0.0:
            two_sigma = 2.0 * lane.sigma_ns
            delay_ns += min(two_sigma, max(-two_sigma, lane.rng.gauss(0.0, lane.sigma_ns)))
        due_ns = max(lane.busy_until_ns + max(0, round(delay_ns)), lane.last_due_ns)
        lane.last_due_ns = due_ns
        return due_ns


@dataclass(slots=True)
class Counts:
    forwarded: int = 0
    dropped_loss: int = 0
    dropped_queue: int = 0
    not_ipv4: int = 0
    write_errors: int = 0


class DelayLine:
    """The packets held, one FIFO per direction, bounded by `max_packets` and `max_bytes`
    together. A direction's due times never decrease (Schedule keeps its order), so each
    FIFO is already sorted and the next packet out is the earlier of the two heads."""

    def __init__(
        self,
        schedule: Schedule,
        max_packets: int = MAX_PACKETS,
        max_bytes: int = MAX_BYTES,
    ) -> None:
        self.schedule = schedule
        self.max_packets, self.max_bytes = max_packets, max_bytes
        self.counts = Counts()
        self._held: dict[Direction, collections.deque[tuple[int, bytes]]] = {
            d: collections.deque() for d in DIRECTIONS
        }
        self._packets = 0
        self._bytes = 0

    @property
    def held(self) -> tuple[int, int]:
        """(packets, bytes) in the line now."""
        return self._packets, self._bytes

    def offer(self, t_ns: int, packet: bytes, direction: Direction) -> int | None:
        """Take a packet that arrived at t_ns: its due time, or None when dropped (counted:
        for the queue when the line is full, which the schedule never sees, else for loss)."""
        if (
            self._packets >= self.max_packets
            or self._bytes + len(packet) > self.max_bytes
            or self.schedule.full(t_ns, direction)
        ):
            self.counts.dropped_queue += 1
            return None
        due_ns = self.schedule.decide(t_ns, len(packet), direction)
        if due_ns is None:
            self.counts.dropped_loss += 1
            return None
        self._held[direction].append((due_ns, packet))
        self._packets += 1
        self._bytes += len(packet)
        return due_ns

    def next_due_ns(self) -> int | None:
        """When the next packet is due, or None when the line is empty."""
        heads = [q[0][0] for q in self._held.values() if q]
        return min(heads) if heads else None

    def pop_due(self, now_ns: int) -> list[bytes]:
        """The packets due at now_ns, in due order (counted as forwarded)."""
        out: list[bytes] = []
        a, b = self._held["to_robot"], self._held["to_operator"]
        while True:
            if a and (not b or a[0][0] <= b[0][0]):
                q = a
            elif b:
                q = b
            else:
                break
            if q[0][0] > now_ns:
                break
            out.append(q.popleft()[1])
        self._packets -= len(out)
        self._bytes -= sum(map(len, out))
        self.counts.forwarded += len(out)
        return out


def classifier(robot_net: str) -> Callable[[bytes], Direction | None]:
    """The direction of an IPv4 packet from its destination (header bytes 16–20): to the
    robot inside robot_net, else to the operator; None when it is not IPv4."""
    net = ipaddress.IPv4Network(robot_net)
    base, mask = int(net.network_address), int(net.netmask)

    def direction(packet: bytes) -> Direction | None:
        if len(packet) < 20 or packet[0] >> 4 != 4:
            return None
        dst = int.from_bytes(packet[16:20], "big")
        return "to_robot" if dst & mask == base else "to_operator"

    return direction


def open_tun(name: str) -> int:
    """Attach to (or create) TUN device `name` without packet info, non-blocking, and set it
    up. Needs CAP_NET_ADMIN."""
    fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH22x", name.encode(), IFF_TUN | IFF_NO_PI))
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            ifr = fcntl.ioctl(s, SIOCGIFFLAGS, struct.pack("16sH22x", name.encode(), 0))
            flags = struct.unpack_from("16sH", ifr)[1]
            if not flags & IFF_UP:
                fcntl.ioctl(s, SIOCSIFFLAGS, struct.pack("16sH22x", name.encode(), flags | IFF_UP))
    except BaseException:
        os.close(fd)
        raise
    return fd


def run(
    line: DelayLine, fd: int, direction_of: Callable[[bytes], Direction | None], stop_fd: int
) -> None:
    """Forward until stop_fd becomes readable: one thread, select on the TUN and stop_fd
    with the time to the next due packet as timeout."""
    counts = line.counts
    while True:
        due_ns = line.next_due_ns()
        timeout_s = None if due_ns is None else max(0, due_ns - time.monotonic_ns()) / 1e9
        readable, _, _ = select.select([fd, stop_fd], [], [], timeout_s)
        if stop_fd in readable:
            return
        if readable:
            for _ in range(READ_BURST):
                try:
                    packet = os.read(fd, 65_536)
                except BlockingIOError:
                    break
                now_ns = time.monotonic_ns()
                direction = direction_of(packet)
                if direction is None:
                    counts.not_ipv4 += 1
                else:
                    line.offer(now_ns, packet, direction)
        for packet in line.pop_due(time.monotonic_ns()):
            try:
                os.write(fd, packet)
            except OSError:
                counts.write_errors += 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m services.tools.tdpa.delayline",
        description="A link emulator in userspace on a TUN device (see the module docstring).",
    )
    p.add_argument("--delay-ms", type=float, default=0.0, help="one-way delay, each direction")
    p.add_argument("--jitter", type=float, default=0.0, help="fraction of the delay (sigma)")
    p.add_argument("--loss", type=float, default=0.0, help="per packet, each direction")
    p.add_argument("--rate-mbit", type=float, default=0.0, help="0: unlimited")
    p.add_argument(
        "--queue-ms",
        type=float,
        default=0.0,
        help="with a rate: the bottleneck's buffer (0: unbounded)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dev", default="tl0", help="the TUN device")
    p.add_argument("--robot-net", default="10.203.0.0/31", help="destinations to the robot")
    p.add_argument("--max-packets", type=int, default=MAX_PACKETS)
    p.add_argument("--max-bytes", type=int, default=MAX_BYTES)
    args = p.parse_args(argv)
    try:
        shape = DirectionShape(args.delay_ms, args.jitter, args.loss, args.rate_mbit, args.queue_ms)
        direction_of = classifier(args.robot_net)
    except ValueError as e:
        p.error(str(e))
    line = DelayLine(
        Schedule(dict.fromkeys(DIRECTIONS, shape), args.seed), args.max_packets, args.max_bytes
    )

    stop_r, stop_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)

    def on_signal(signum: int, frame: FrameType | None) -> None:
        del signum, frame  # the wake-up fd stops the loop

    signal.set_wakeup_fd(stop_w)
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, on_signal)
    fd = open_tun(args.dev)
    try:
        print("ready", flush=True)
        run(line, fd, direction_of, stop_r)
    finally:
        os.close(fd)
        print(json.dumps(asdict(line.counts)), file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
