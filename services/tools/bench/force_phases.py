"""The force phases: the force stream alone, its raw-TCP floor and its bare-Zenoh floor,
and the figures of a force window (rate, the sensor's own rate, latency, loss)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from services.bus.errors import RpcError, Unavailable
from services.bus.keys import FORCE
from services.bus.messages import ForceSample
from services.bus.node import Node
from services.tools.bench import cpu, floor, stats
from services.tools.bench.baselines import force_payload, tcp_floor
from services.tools.bench.commands import CALL_TIMEOUT_S
from services.tools.bench.options import BenchOptions, RunResult, Say, Trace
from services.tools.bench.probes import StreamProbe
from services.tools.bench.procs import cpu_by_child
from services.tools.bench.report import ms_text
from services.tools.cell.procs import ChildFailed, Children

FLOOR_DRAIN_S = 2.0

# --- force --------------------------------------------------------------------------------


def force_probe(node: Node) -> StreamProbe[ForceSample]:
    return StreamProbe(node, FORCE, lambda m: (m.seq, m.t_ns)).start()


def force_figures(
    records: Sequence[tuple[int, tuple[Any, ...]]], t0_ns: int, t1_ns: int
) -> tuple[dict[str, Any], Trace]:
    """The force phase's figures from probe records `(rx_ns, (seq, t_ns))` that arrived in
    [t0_ns, t1_ns]: rate, the sensor's own rate, latency summary, seq loss; and the trace
    (s since t0, latency ms) for the plot."""
    rows = [r for r in records if t0_ns <= r[0] <= t1_ns]
    rx = np.array([r[0] for r in rows], dtype=np.int64)
    seq = [int(r[1][0]) for r in rows]
    tx = np.array([r[1][1] for r in rows], dtype=np.int64)
    lat = stats.latencies_ms(rx, tx)
    loss = stats.seq_loss(seq)
    duration_s = (t1_ns - t0_ns) / stats.NS_PER_S
    produced = 0.0
    if len(seq) >= 2 and tx.max() > tx.min():
        # The sensor's own rate, from its seq and t_ns: counts what was lost on the way too.
        produced = (max(seq) - min(seq)) * stats.NS_PER_S / float(tx.max() - tx.min())
    fig = {
        "duration_s": duration_s,
        "received": len(rows),
        "rate_hz": stats.rate_hz(len(rows), duration_s),
        "produced_rate_hz": produced,
        "latency_ms": stats.summarize(lat).as_dict(),
        "loss": loss.as_dict(),
    }
    t_s = (rx - t0_ns).astype(float) / stats.NS_PER_S
    return fig, (t_s, lat)


def measure_window(probe_ready: Callable[[], bool], phase_s: float) -> tuple[int, int]:
    """The measuring window: from when the probe has its first sample, for phase_s."""
    if not probe_ready():
        raise TimeoutError("no sample arrived on the probed stream")
    t0 = time.time_ns()
    # The phase's length is the measurement itself, not a wait for a condition.
    time.sleep(phase_s)
    return t0, time.time_ns()


FORCE_COUNTERS = ("samples", "published", "drops", "overruns", "caught_up")
"""The force sampler's counters (its `sensor_status`): samples taken, handed to the bus,
dropped from its hand-off queue when the publisher fell behind, periods skipped late,
periods sampled at once after a short stall."""


def force_counters(node: Node) -> dict[str, int] | None:
    try:
        got = node.call("force", "sensor_status", {}, CALL_TIMEOUT_S)
    except (Unavailable, RpcError):
        return None
    return {k: int(got[k]) for k in FORCE_COUNTERS if isinstance(got.get(k), int)}


def phase_force(
    kids: Children, node: Node, opts: BenchOptions, res: RunResult, key: str, say: Say
) -> None:
    say(f"[{key}] force stream alone for {opts.phase_s:g} s …")
    probe = force_probe(node)
    before = force_counters(node)
    if not probe.wait_count(1, 10.0):
        raise TimeoutError("no sample arrived on robot/force")
    cpu_a, t0 = cpu_by_child(kids), time.time_ns()
    # The phase's length is the measurement itself, not a wait for a condition.
    time.sleep(opts.phase_s)
    cpu_b, t1 = cpu_by_child(kids), time.time_ns()
    after = force_counters(node)
    fig, trace = force_figures(probe.stop(), t0, t1)
    fig["rejected"] = probe.rejected
    fig["service"] = stats.counters_delta(before, after)
    pct = cpu.percent_of_core(cpu_a, cpu_b, (t1 - t0) / stats.NS_PER_S)
    fig["service_cpu_pct"] = pct.get("force")
    fig["router_cpu_pct"] = pct.get("router")
    res.phases[key] = fig
    res.traces["force alone"] = trace
    cpu_text = f", force service {pct['force']:.1f} % of a core" if "force" in pct else ""
    say(force_line(fig) + cpu_text)


def force_line(fig: dict[str, Any]) -> str:
    lat = fig["latency_ms"]
    return (
        f"    {fig['rate_hz']:.0f} Hz received, latency p50 {ms_text(lat['p50'])} p99 "
        f"{ms_text(lat['p99'])} max {ms_text(lat['max'])}, lost {fig['loss']['lost']}"
    )


# --- TCP floor ----------------------------------------------------------------------------


def phase_tcp(opts: BenchOptions, res: RunResult, say: Say) -> None:
    say(f"[baseline_tcp] the same force packets over raw TCP at 1 kHz for {opts.phase_s:g} s …")
    run = tcp_floor(1000.0, opts.phase_s)
    lat = stats.latencies_ms(run.rx_ns, run.t_ns)
    loss = stats.seq_loss(run.seq)
    span_s = (
        float(run.rx_ns.max() - run.rx_ns.min()) / stats.NS_PER_S if run.rx_ns.size > 1 else 0.0
    )
    res.phases["baseline_tcp"] = {
        "duration_s": span_s,
        "sent": run.sent,
        "received": len(run.seq),
        "rate_hz": stats.rate_from_times(run.rx_ns),
        "payload_bytes": run.payload_bytes,
        "latency_ms": stats.summarize(lat).as_dict(),
        "loss": {**loss.as_dict(), "lost": run.sent - loss.unique},
    }
    say(force_line(res.phases["baseline_tcp"]))


# --- bare-Zenoh floor -------------------------------------------------------------------


def phase_zenoh_floor(
    kids: Children, node: Node, endpoint: str, opts: BenchOptions, res: RunResult, say: Say
) -> None:
    """The same ForceSample bytes from a minimal zenoh-python publisher at 1 kHz through the
    router to the bench's force probe (services.tools.bench.floor)."""
    say(
        f"[baseline_zenoh] the same force packets from a bare Zenoh publisher at 1 kHz for "
        f"{opts.phase_s:g} s …"
    )
    probe = StreamProbe(node, floor.FLOOR_TOPIC, lambda m: (m.seq, m.t_ns)).start()
    try:
        pub = kids.spawn("zenoh-floor", floor.pub_argv(endpoint, 1000.0, opts.phase_s))
        deadline = time.monotonic() + opts.startup_timeout_s
        while not probe.wait_count(1, 0.1):
            kids.check("zenoh-floor")
            if time.monotonic() > deadline:
                raise TimeoutError("no sample from the bare Zenoh publisher")
        # The bench's own CPU while it receives: the subscriber's side of the floor.
        own_a, cpu_a, t_a = cpu.process_cpu_s(os.getpid()), cpu_by_child(kids), time.monotonic()
        code = pub.wait(opts.phase_s + opts.startup_timeout_s)
        if code is None:
            raise TimeoutError("the bare Zenoh publisher did not finish")
        own_b, cpu_b, t_b = cpu.process_cpu_s(os.getpid()), cpu_by_child(kids), time.monotonic()
        if code != 0:
            raise ChildFailed(f"the bare Zenoh publisher exited with {code}:\n{pub.tail()}")
        sent = floor.parse_sent(pub.output())
        probe.wait_count(sent.sent, FLOOR_DRAIN_S)
    finally:
        records = probe.stop()
        kids.stop("zenoh-floor")
    wall_s = t_b - t_a
    router = cpu.percent_of_core(cpu_a, cpu_b, wall_s).get("router")
    res.phases["baseline_zenoh"] = {
        "duration_s": sent.wall_s,
        **stats.sent_stream(sent.sent, records),
        "payload_bytes": len(force_payload(sent.sent, time.time_ns())),
        "rejected": probe.rejected,
        "publisher_cpu_pct": sent.cpu_pct,
        "subscriber_cpu_pct": (own_b - own_a) / wall_s * 100.0 if wall_s > 0 else None,
        "router_cpu_pct": router,
    }
    f = res.phases["baseline_zenoh"]
    say(force_line(f) + f"; publisher {f['publisher_cpu_pct']:.1f} % of a core")
