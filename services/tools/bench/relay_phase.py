"""The two-hop floor: the bench → router → a bare relay → router → the bench, at each command
rate, in the same run as the command phases.

master → puma crosses the router twice with a Python process between (the decision); the
one-hop floor (`baseline_zenoh`) is not its floor. Here a minimal relay process
(services.tools.bench.floor `relay`) puts each sample on again inline in Zenoh's callback, so
what master → puma costs above this is ours: the decision's and the puma's own Python.

The machine carries what it carries in the command phases: there the decision takes
robot/force (1 kHz through the router) while it follows, so here the bench takes it the way
the decision does (Zenoh keeps the newest in a ring of one, no Python per sample). Without
it the force service sends nothing (nobody subscribes) and the floor would be measured on a
quieter machine than the path it is set against.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import zenoh

from services.bus.keys import FORCE
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.tools.bench import floor, stats
from services.tools.bench.baselines import force_payload
from services.tools.bench.options import BenchOptions, RunResult, Say
from services.tools.bench.probes import StreamProbe
from services.tools.bench.procs import Children, wait_log
from services.tools.bench.report import ms_text

DRAIN_S = 2.0
ROUTE_PUT_S = 0.01
"""Before the timed run, one put per this until the first comes back (route set-up)."""

Record = tuple[int, tuple[Any, ...]]


def relay_key(rate_hz: float) -> str:
    return f"baseline_zenoh_relay_{rate_hz:.0f}hz"


def relay_figures(
    rate_hz: float, sent: int, first: int, records: Sequence[Record]
) -> dict[str, Any]:
    """The figures of one rate: samples `first`+1 … `first`+`sent` were timed; `records` are
    the probe's `(arrival_ns, (seq, t_ns))` (the route set-up's samples are left out)."""
    timed = [r for r in records if first < int(r[1][0]) <= first + sent]
    seqs = [int(r[1][0]) for r in timed]
    loss = stats.seq_loss(seqs)
    rx = np.array([r[0] for r in timed], dtype=np.int64)
    lat = stats.latencies_ms(rx, [int(r[1][1]) for r in timed])
    return {
        "sent_rate_hz": rate_hz,
        "sent": sent,
        "received": len(seqs),
        "rate_hz": stats.rate_from_times(rx),
        "latency_ms": stats.summarize(lat).as_dict(),
        "loss": {**loss.as_dict(), "lost": sent - loss.unique},
    }


def phase_relay_floor(
    kids: Children,
    node: Node,
    endpoint: str,
    rates_hz: Sequence[float],
    opts: BenchOptions,
    res: RunResult,
    say: Say,
) -> None:
    """At each rate, ForceSample bytes for `opts.phase_s` through the bare relay; one phase
    `baseline_zenoh_relay_<rate>hz` each."""
    probe = StreamProbe(node, floor.FLOOR_RELAY_OUT, lambda m: (m.seq, m.t_ns)).start()
    pub = floor.declare_floor_publisher(node.session, floor.FLOOR_RELAY_IN.key)
    force = node.latest(FORCE)  # robot/force flows, as while the decision follows
    try:
        relay = kids.spawn("zenoh-relay", floor.relay_argv(endpoint))
        wait_log(relay, floor.RELAYING, opts.startup_timeout_s)
        seq = _route(kids, pub, probe, opts.startup_timeout_s)
        deadline = time.monotonic() + opts.startup_timeout_s
        while force.read() is None:  # the force service starts sending on our subscription
            kids.check()
            if time.monotonic() > deadline:
                raise TimeoutError("robot/force never flowed to the bench")
            time.sleep(0.01)
        for rate in rates_hz:
            key = relay_key(rate)
            say(
                f"[{key}] the same bytes at {rate:g} Hz through a bare Zenoh relay (two hops "
                f"through the router) for {opts.phase_s:g} s …"
            )
            first = seq
            f0 = force.read()
            loop = RateLoop(rate)
            end = time.monotonic() + opts.phase_s
            while time.monotonic() < end:
                seq += 1
                pub.put(force_payload(seq, time.time_ns()))
                loop.sleep()
            _drain(probe, seq, DRAIN_S)
            fig = relay_figures(rate, seq - first, first, probe.snapshot())
            f1 = force.read()
            # robot/force's rate meanwhile (the sensor's seq), to show the load was there
            fig["force_rate_hz"] = (
                (f1[0].seq - f0[0].seq) / opts.phase_s
                if f0 is not None and f1 is not None
                else None
            )
            res.phases[key] = fig
            lat = fig["latency_ms"]
            flow = fig["force_rate_hz"]
            say(
                f"    {fig['received']} of {fig['sent']} back, one way p50 "
                f"{ms_text(lat['p50'])} p99 {ms_text(lat['p99'])}; robot/force meanwhile "
                + (f"{flow:.0f} Hz" if flow is not None else "not flowing")
            )
            kids.check("zenoh-relay")
    finally:
        force.watch(False)
        probe.stop()
        pub.undeclare()
        kids.stop("zenoh-relay")


def _route(kids: Children, pub: zenoh.Publisher, probe: StreamProbe[Any], timeout_s: float) -> int:
    """Put until a sample comes back (the routes through the relay exist); the last seq put."""
    deadline = time.monotonic() + timeout_s
    seq = 0
    while probe.count() == 0:
        kids.check("zenoh-relay")
        if time.monotonic() > deadline:
            raise TimeoutError(f"nothing came back through the relay within {timeout_s:g} s")
        seq += 1
        pub.put(force_payload(seq, time.time_ns()))
        probe.wait_count(1, ROUTE_PUT_S)
    return seq


def _drain(probe: StreamProbe[Any], last: int, timeout_s: float) -> None:
    """Until the sample `last` is back, or `timeout_s` (a lost one ends the wait there)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        newest = probe.newest()
        if newest is not None and int(newest[1][0]) >= last:
            return
        time.sleep(0.01)
