"""The bare-Zenoh floor: the least a Python process can do on our bus, in the same run.

- pub/sub: a minimal publisher process — plain zenoh-python, one session, one publisher with
  `robot/force`'s QoS (REAL_TIME, express, block on congestion) and no code of our services —
  sends the very bytes of a ForceSample at 1 kHz on `FLOOR_TOPIC` through the bench's router.
  The bench receives them with the probe it uses on `robot/force` (stamp first, decode,
  validate, append), so whatever our force path costs above this is ours, not Zenoh's.
- relay: a minimal process takes the same bytes on `FLOOR_RELAY_IN` and puts them, untouched
  and inline in Zenoh's callback, on `FLOOR_RELAY_OUT` (robot/force's QoS both ways). The
  bench sends at 100 Hz and 1 kHz and receives them back: two hops through the router, as
  master → decision → arm, and the floor under that path's latency.
- get→reply: a minimal queryable in a process of the same kind replies inline in Zenoh's
  callback with a fixed msgpack map (arm's own `status` map) to plain `get`s from the bench's
  session: the floor under every method call.

The publisher waits until Zenoh reports a matching subscriber before its first sample (no
sample is lost to route set-up), then reports on stdout what it sent and the CPU it used
while sending: `time.process_time()` over the send loop, every thread of the process (Zenoh's
own included).

Run as `python -m services.tools.bench.floor pub|serve …` (the bench spawns it like a service).
"""

from __future__ import annotations

import argparse
import re
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import zenoh

from services.bus import codec
from services.bus.config import NodeConfig
from services.bus.keys import ENCODING, QoS, Topic
from services.bus.messages import ForceSample
from services.bus.rate import RateLoop
from services.tools.bench.baselines import force_payload

FLOOR_TOPIC = Topic("bench/floor/force", ForceSample, QoS.CONTROL, latest_wins=True)
"""Where the floor publisher sends: a key of the bench's own, so no service receives it."""
FLOOR_RELAY_IN = Topic("bench/floor/relay/in", ForceSample, QoS.CONTROL, latest_wins=True)
FLOOR_RELAY_OUT = Topic("bench/floor/relay/out", ForceSample, QoS.CONTROL, latest_wins=True)
"""The relay's two keys: the bench puts on the first, the relay puts on the second."""
RELAYING = "floor relaying"
FLOOR_RPC_KEY = "bench/floor/rpc/status"
MATCH_TIMEOUT_S = 20.0
SERVING = "floor serving"

#: robot/force's delivery, as services.bus.node declares QoS.CONTROL (tests hold them equal)
FLOOR_PRIORITY = zenoh.Priority.REAL_TIME
FLOOR_EXPRESS = True
FLOOR_CONGESTION = zenoh.CongestionControl.BLOCK


def floor_session(endpoint: str, mode: str) -> zenoh.Session:
    """A bare session of a floor process: `mode` peer or (anything else) client, to
    `endpoint`."""
    cfg = NodeConfig(mode="peer" if mode == "peer" else "client", connect=(endpoint,))
    return zenoh.open(cfg.to_zenoh())


def _matching(pub: zenoh.Publisher) -> bool:
    """Whether a subscriber matches. The 1.10 stub types `matching_status` as a bool; the
    library returns a MatchingStatus, whose `matching` says it (either is read right)."""
    status: object = pub.matching_status
    return bool(getattr(status, "matching", status))


# --- the processes ---------------------------------------------------------------------------


def publish(endpoint: str, mode: str, rate_hz: float, duration_s: float) -> FloorSent:
    """The publisher: once a subscriber matches, one ForceSample per tick for `duration_s`."""
    with floor_session(endpoint, mode) as session:
        pub = declare_floor_publisher(session, FLOOR_TOPIC.key)
        deadline = time.monotonic() + MATCH_TIMEOUT_S
        while not _matching(pub):
            if time.monotonic() > deadline:
                raise TimeoutError(f"no subscriber on {FLOOR_TOPIC.key} in {MATCH_TIMEOUT_S} s")
            time.sleep(0.005)
        sent = 0
        loop = RateLoop(rate_hz)
        cpu0, wall0 = time.process_time(), time.monotonic()
        end = wall0 + duration_s
        while time.monotonic() < end:
            sent += 1
            pub.put(force_payload(sent, time.time_ns()))
            loop.sleep()
        report = FloorSent(sent, time.process_time() - cpu0, time.monotonic() - wall0)
        pub.undeclare()
    return report


def declare_floor_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """A publisher with robot/force's delivery (`FLOOR_*`)."""
    return session.declare_publisher(
        key,
        encoding=zenoh.Encoding(ENCODING),
        priority=FLOOR_PRIORITY,
        express=FLOOR_EXPRESS,
        congestion_control=FLOOR_CONGESTION,
    )


def relay(endpoint: str, mode: str, stop: threading.Event, take: Sequence[str] = ()) -> int:
    """The relay: every sample on FLOOR_RELAY_IN is put on FLOOR_RELAY_OUT at once, in Zenoh's
    callback, until `stop`; how many it relayed. It also takes the keys `take` the way the
    decision takes robot/force and robot/state (Zenoh keeps the newest in a ring of one; no
    Python per sample), so its link carries what the decision's does."""
    relayed = 0
    with floor_session(endpoint, mode) as session:
        taken = [session.declare_subscriber(k, zenoh.handlers.RingChannel(1)) for k in take]
        pub = declare_floor_publisher(session, FLOOR_RELAY_OUT.key)

        def on_sample(sample: zenoh.Sample) -> None:
            nonlocal relayed
            pub.put(sample.payload)
            relayed += 1

        sub = session.declare_subscriber(FLOOR_RELAY_IN.key, on_sample)
        print(f"{RELAYING} {FLOOR_RELAY_IN.key} -> {FLOOR_RELAY_OUT.key}", flush=True)
        while not stop.wait(0.2):
            pass
        sub.undeclare()
        pub.undeclare()
        for t in taken:
            t.undeclare()
    return relayed


def serve(endpoint: str, mode: str, reply: bytes, stop: threading.Event) -> None:
    """The queryable: reply `reply` to every get, inline in the callback, until `stop`."""
    encoding = zenoh.Encoding(ENCODING)

    def on_query(query: zenoh.Query) -> None:
        try:
            query.reply(query.key_expr, reply, encoding=encoding)
        finally:
            query.drop()

    with floor_session(endpoint, mode) as session:
        queryable = session.declare_queryable(FLOOR_RPC_KEY, on_query)
        print(f"{SERVING} {FLOOR_RPC_KEY}", flush=True)
        while not stop.wait(0.2):
            pass
        queryable.undeclare()


# --- the bench's side ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FloorSent:
    """What the floor publisher reports: samples sent, CPU (s) and wall time (s) of its send
    loop."""

    sent: int
    cpu_s: float
    wall_s: float

    @property
    def cpu_pct(self) -> float:
        """% of one core over the send loop."""
        return self.cpu_s / self.wall_s * 100.0 if self.wall_s > 0 else 0.0

    def line(self) -> str:
        return f"floor sent {self.sent} cpu_s {self.cpu_s:.6f} wall_s {self.wall_s:.6f}"


_SENT = re.compile(r"floor sent (\d+) cpu_s ([0-9.eE+-]+) wall_s ([0-9.eE+-]+)")


def parse_sent(output: str) -> FloorSent:
    """The publisher's report from its output (ValueError when it printed none)."""
    found = _SENT.findall(output)
    if not found:
        raise ValueError("the floor publisher printed no report")
    sent, cpu_s, wall_s = found[-1]
    return FloorSent(int(sent), float(cpu_s), float(wall_s))


def pub_argv(endpoint: str, rate_hz: float, duration_s: float, mode: str = "client") -> list[str]:
    return [
        sys.executable,
        "-m",
        "services.tools.bench.floor",
        "pub",
        "--connect",
        endpoint,
        "--mode",
        mode,
        "--rate-hz",
        f"{rate_hz:g}",
        "--duration-s",
        f"{duration_s:g}",
    ]


def relay_argv(endpoint: str, mode: str = "client", take: Sequence[str] = ()) -> list[str]:
    argv = [
        sys.executable,
        "-m",
        "services.tools.bench.floor",
        "relay",
        "--connect",
        endpoint,
        "--mode",
        mode,
    ]
    for key in take:
        argv += ["--take", key]
    return argv


def serve_argv(endpoint: str, reply_file: Path, mode: str = "client") -> list[str]:
    return [
        sys.executable,
        "-m",
        "services.tools.bench.floor",
        "serve",
        "--connect",
        endpoint,
        "--mode",
        mode,
        "--reply",
        str(reply_file),
    ]


@dataclass(frozen=True, slots=True)
class GetTimes:
    """Round trips (ms) of the gets that got a reply map, and how many did not."""

    ms: list[float]
    failures: int


def time_gets(
    session: zenoh.Session, n: int, timeout_s: float = 5.0, startup_s: float = 20.0
) -> GetTimes:
    """`n` sequential plain `get`s of the floor's queryable, each reply unpacked as a map
    (what `Node.call` does, without its liveliness check). Gets are retried until the first
    reply (route set-up, ZENOH_NOTES pitfall 5) within `startup_s`; that one is not timed."""
    payload = codec.pack({})
    encoding = zenoh.Encoding(ENCODING)

    def once() -> bool:
        replies = list(session.get(FLOOR_RPC_KEY, payload=payload, encoding=encoding,
                                   timeout=timeout_s))  # fmt: skip
        if not replies or replies[0].ok is None:
            return False
        return isinstance(codec.unpack(replies[0].ok.payload.to_bytes()), dict)

    deadline = time.monotonic() + startup_s
    while not once():
        if time.monotonic() > deadline:
            raise TimeoutError(f"no reply from {FLOOR_RPC_KEY} within {startup_s:g} s")
        time.sleep(0.02)
    out: list[float] = []
    failures = 0
    for _ in range(n):
        t0 = time.perf_counter()
        ok = once()
        dt_ms = (time.perf_counter() - t0) * 1e3
        if ok:
            out.append(dt_ms)
        else:
            failures += 1
    return GetTimes(out, failures)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m services.tools.bench.floor", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    for name, text in (
        ("pub", "the floor publisher"),
        ("relay", "the floor relay"),
        ("serve", "the floor queryable"),
    ):
        s = sub.add_parser(name, help=text)
        s.add_argument("--connect", required=True, metavar="ENDPOINT")
        s.add_argument("--mode", choices=["client", "peer"], default="client")
        if name == "pub":
            s.add_argument("--rate-hz", type=float, default=1000.0)
            s.add_argument("--duration-s", type=float, default=5.0)
        elif name == "relay":
            s.add_argument("--take", action="append", default=[], metavar="KEY",
                           help="also take KEY, newest kept (repeatable)")  # fmt: skip
        elif name == "serve":
            s.add_argument("--reply", required=True, metavar="FILE", help="msgpack map to reply")
    args = p.parse_args(argv)
    if args.cmd == "pub":
        print(publish(args.connect, args.mode, args.rate_hz, args.duration_s).line(), flush=True)
        return 0
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    if args.cmd == "relay":
        print(f"relayed {relay(args.connect, args.mode, stop, args.take)}", flush=True)
        return 0
    serve(args.connect, args.mode, Path(args.reply).read_bytes(), stop)
    return 0


if __name__ == "__main__":
    sys.exit(main())
