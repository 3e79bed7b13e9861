"""A rogue peer for the flood test: robot/cmd at a fixed rate for a bounded time.

`python -m tests.faults.rogue --connect tcp/127.0.0.1:PORT --rate-hz 10000 --seconds 3`

It waits for the decision server's liveliness token (and `--settle-s` for the peers to
mesh with it: samples published before a subscriber is known have no route), then
publishes OperatorCommands of its own master id ("rogue": active, dp = 0, dR = I, so even
a command that were followed would hold the arm still) with strictly increasing seq, and
every `--garbage-every`-th payload random bytes instead. Then it prints one JSON line on
stdout (what it sent and when, in `time.time_ns()`) and keeps its session open until
SIGTERM (at most `--linger-s`): closing a session discards what is still queued for a slow
receiver, so it must not end before the receivers have drained the flood.
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import time

from services.bus import codec, keys
from services.bus.config import NodeConfig
from services.bus.lifecycle import Shutdown
from services.bus.messages import IDENTITY_R
from services.bus.node import Node
from tests.faults.procs import LOOPBACK_LISTEN

MARK = "rogue-result "


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="rogue", description=__doc__)
    p.add_argument("--connect", required=True)
    p.add_argument("--rate-hz", type=float, default=10_000.0)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--garbage-every", type=int, default=10, help="0: none")
    p.add_argument("--master", default="rogue")
    p.add_argument("--linger-s", type=float, default=30.0)
    p.add_argument(
        "--settle-s",
        type=float,
        default=1.0,
        help="after the decision server is seen, time for the peers to mesh with the rogue",
    )
    args = p.parse_args(argv)
    if not 0 < args.seconds <= 30:
        p.error("--seconds must be within (0, 30]: a flood is always bounded")
    stop = Shutdown()
    rng = random.Random(11)
    cfg = NodeConfig(mode="peer", connect=(args.connect,), listen=(LOOPBACK_LISTEN,))
    with Node("rogue", cfg) as node:
        pub = node.publisher(keys.CMD)
        if not node.alive.wait("decision", 15.0):
            print("rogue: no decision server", file=sys.stderr)
            return 2
        time.sleep(args.settle_s)
        fields = {
            "seq": 0,
            "t_ns": 0,
            "master": args.master,
            "engage": 1,
            "active": True,
            "frame": "world",
            "dp": [0.0, 0.0, 0.0],
            "dR": list(IDENTITY_R),
        }
        sent = valid = garbage = 0
        put_s = 0.0
        t0_ns = time.time_ns()
        start = time.perf_counter()
        end = start + args.seconds
        while True:
            now = time.perf_counter()
            if now >= end:
                break
            due = int((now - start) * args.rate_hz) + 1
            t_put = time.perf_counter()
            while sent < due:
                sent += 1
                if args.garbage_every and sent % args.garbage_every == 0:
                    pub.put_bytes(rng.randbytes(rng.randint(0, 64)))
                    garbage += 1
                else:
                    fields["seq"] = sent
                    fields["t_ns"] = time.time_ns()
                    pub.put_bytes(codec.pack(fields))
                    valid += 1
            put_s += time.perf_counter() - t_put
            time.sleep(0.0005)
        t1_ns = time.time_ns()
        result = {
            "sent": sent,
            "valid": valid,
            "garbage": garbage,
            "t0_ns": t0_ns,
            "t1_ns": t1_ns,
            "rate_hz": sent / ((t1_ns - t0_ns) / 1e9),
            "put_s": put_s,
        }
        print(MARK + json.dumps(result), flush=True)
        stop.wait(args.linger_s)
    return 0


if __name__ == "__main__":
    sys.exit(main())
