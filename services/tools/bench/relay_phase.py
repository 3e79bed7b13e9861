"""The two-hop floor: the bench → router → a bare relay → router → the bench, at each command
rate, in the same run as the command phases.

master → arm crosses the router twice with a Python process between (the decision); the
one-hop floor (`baseline_zenoh`) is not its floor. Here a minimal relay process
(services.tools.bench.floor `relay`) puts each sample on again inline in Zenoh's callback, so
what master → arm costs above this is ours: the decision's and the arm's own Python.

The relay takes robot/force and robot/state the way the decision does while it follows
(Zenoh keeps the newest in a ring of one, no Python per sample): its link carries what the
decision's carries, and the force service sends its 1 kHz through the router as in the
command phases. Without that the force service sends nothing (nobody subscribes) and the
floor would be measured on a quieter machine than the path it is set against.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import zenoh

from services.bus.keys import FORCE, STATE
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.tools.bench import floor, stats
from services.tools.bench.baselines import force_payload
from services.tools.bench.force_phases import force_counters
from services.tools.bench.options import BenchOptions, RunResult, Say
from services.tools.bench.probes import StreamProbe
from services.tools.bench.report import ms_text
from services.tools.cell.procs import Children, wait_log

DRAIN_S = 2.0
ROUTE_PUT_S = 0.01
"""Before the timed run, one put per this until the first comes back (route set-up)."""


def relay_key(rate_hz: float) -> str:
    return f"baseline_zenoh_relay_{rate_hz:.0f}hz"


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
    try:
        relay = kids.spawn("zenoh-relay", floor.relay_argv(endpoint, take=(FORCE.key, STATE.key)))
        wait_log(relay, floor.RELAYING, opts.startup_timeout_s)
        seq = _route(kids, pub, probe, opts.startup_timeout_s)
        _wait_force_flowing(kids, node, opts.startup_timeout_s)
        for rate in rates_hz:
            key = relay_key(rate)
            say(
                f"[{key}] the same bytes at {rate:g} Hz through a bare Zenoh relay (two hops "
                f"through the router) for {opts.phase_s:g} s …"
            )
            first = seq
            f0, t0 = force_counters(node), time.monotonic()
            loop = RateLoop(rate)
            end = time.monotonic() + opts.phase_s
            while time.monotonic() < end:
                seq += 1
                pub.put(force_payload(seq, time.time_ns()))
                loop.sleep()
            _drain(probe, seq, DRAIN_S)
            fig = {"sent_rate_hz": rate, **stats.sent_stream(seq - first, probe.snapshot(), first)}
            # robot/force's rate meanwhile (samples the service handed to the bus)
            force_sent = stats.counters_delta(f0, force_counters(node))
            fig["force_rate_hz"] = (
                force_sent["published"] / (time.monotonic() - t0)
                if force_sent and "published" in force_sent
                else None
            )
            res.phases[key] = fig
            lat = fig["latency_ms"]
            flow = fig["force_rate_hz"]
            say(
                f"    {fig['received']} of {fig['sent']} back, one way p50 "
                f"{ms_text(lat['p50'])} p99 {ms_text(lat['p99'])}; robot/force meanwhile "
                + (f"{flow:.0f} Hz" if flow is not None else "unknown")
            )
            kids.check("zenoh-relay")
    finally:
        probe.stop()
        pub.undeclare()
        kids.stop("zenoh-relay")


def _wait_force_flowing(kids: Children, node: Node, timeout_s: float) -> None:
    """Until the force service hands samples to the bus (it starts on the relay's
    subscription, as on the decision's)."""
    deadline = time.monotonic() + timeout_s
    first = force_counters(node)
    while True:
        kids.check()
        now = force_counters(node)
        sent = stats.counters_delta(first, now)
        if sent is not None and sent.get("published", 0) > 0:
            return
        if time.monotonic() > deadline:
            raise TimeoutError("the force service never sent on the relay's subscription")
        time.sleep(0.05)


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
