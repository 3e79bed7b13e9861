"""One bench run: start the deployed topology, measure each phase, stop everything.

Topology (as deploy/robot.toml runs it): the embedded router on 127.0.0.1:PORT, and puma
(sim arm, autostart), force (sim sensor, 1 kHz), decision, a master station (virtual
device, not engaged) and, in the video phases, vision — each a separate process in client
mode connected to the router. The bench itself is one more client: the operator's side.
The CPU phases at the end run the sim profile's set instead (services.tools.bench.system).

Phases, in order (each `phase_s` long): IK throughput (in the bench process, before any
child runs); force alone; the raw-TCP floor; the bare-Zenoh floor; commands at 100 Hz and at
1 kHz (services.tools.bench.commands); method calls, the bare-Zenoh get→reply floor and the
XML-RPC baseline; force + stereo at the paper's setting; force + stereo at 640×480@30; CPU
per service idle, then during 1 kHz teleop with VGA stereo.
"""

from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.bus import codec
from services.bus.config import NodeConfig
from services.bus.errors import RpcError, Unavailable
from services.bus.keys import FORCE, STATE, VISION_STATS
from services.bus.messages import ForceSample, VisionStats
from services.bus.node import Node
from services.control.force.priority import PriorityLevel
from services.tools.bench import cpu, floor, stats, system
from services.tools.bench.baselines import force_payload, tcp_floor, xmlrpc_round_trips
from services.tools.bench.commands import CALL_TIMEOUT_S, phase_commands
from services.tools.bench.probes import (
    CommandDriver,
    FrameRecord,
    StreamProbe,
    VideoProbe,
    time_calls,
)
from services.tools.bench.procs import (
    ChildFailed,
    Children,
    free_port,
    telerobot_argv,
    wait_alive,
    wait_log,
)
from services.tools.bench.report import PAPER_SIZE, ms_text

Say = Callable[[str], None]
Trace = tuple[np.ndarray, np.ndarray]

MASTER_ID = "bench"
STATION_ID = "station"
VIDEO_WARMUP_S = 1.0
FLOOR_DRAIN_S = 2.0


@dataclass(frozen=True, slots=True)
class BenchOptions:
    """What to run. `phase_s`: length of every measuring phase (s); `rpc_calls`: calls per
    method; `ik_n`: poses for the IK throughput; `port`: the router's TCP port on
    127.0.0.1 (0: a free one); `logs_dir`: the children's logs; `force_priority`: the
    force service's `--priority` (what the kernel granted is recorded in the settings)."""

    phase_s: float = 20.0
    quick: bool = False
    rpc_calls: int = 1000
    ik_n: int = 10_000
    port: int = 0
    logs_dir: Path = Path("artifacts/bench-logs")
    command_rates_hz: tuple[float, ...] = (100.0, 1000.0)
    paper_size: tuple[int, int] = PAPER_SIZE
    paper_fps: float = 17.0
    vga_size: tuple[int, int] = (640, 480)
    vga_fps: float = 30.0
    startup_timeout_s: float = 90.0
    settle_s: float = 1.0
    force_priority: PriorityLevel = "highest"
    """The force sampler's thread priority, as deploy/robot.toml runs it."""
    cpu_settle_s: float = 5.0
    """After the sim profile's services are up, before the idle CPU window (s)."""
    teleop_rate_hz: float = 1000.0

    @staticmethod
    def quick_options(**overrides: Any) -> BenchOptions:
        """`--quick`: 5 s phases, fewer calls and IK poses (under 2 min on 2 cores)."""
        base: dict[str, Any] = {
            "phase_s": 5.0,
            "quick": True,
            "rpc_calls": 200,
            "ik_n": 2000,
            "cpu_settle_s": 3.0,
        }
        base.update(overrides)
        return BenchOptions(**base)


@dataclass
class RunResult:
    """What `run_bench` returns: the measured phases, the settings, notes for people, and
    the force-latency traces for the plot."""

    phases: dict[str, Any] = field(default_factory=dict)
    settings: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    traces: dict[str, Trace] = field(default_factory=dict)


class CpuLog:
    """CPU use of the whole run and of each phase: the bench's processes vs the others
    (services.tools.bench.cpu), and each running service's share of one core (`services_pct`).
    `kids` is set once the children exist."""

    def __init__(self) -> None:
        self.kids: Children | None = None
        self.cpus = os.cpu_count() or 1
        self.start = self._now()
        self.phases: dict[str, dict[str, Any]] = {}

    def _now(self) -> cpu.CpuSample | None:
        return cpu.sample(self.kids.cpu_s() if self.kids is not None else 0.0)

    def _by_child(self) -> dict[str, float]:
        return self.kids.cpu_by_child() if self.kids is not None else {}

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        a, kids_a, t_a = self._now(), self._by_child(), time.monotonic()
        yield
        b, kids_b, t_b = self._now(), self._by_child(), time.monotonic()
        if a is not None and b is not None:
            use: dict[str, Any] = dict(cpu.usage(a, b, self.cpus).as_dict())
            use["services_pct"] = cpu.percent_of_core(kids_a, kids_b, t_b - t_a)
            self.phases[name] = use

    def total(self) -> dict[str, float | int] | None:
        b = self._now()
        if self.start is None or b is None:
            return None
        return cpu.usage(self.start, b, self.cpus).as_dict()


def _loadavg() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def run_bench(opts: BenchOptions, say: Say = print) -> RunResult:
    """Run every phase; every child is stopped before this returns or raises."""
    port = opts.port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    res = RunResult()
    res.settings = {
        "quick": opts.quick,
        "phase_s": opts.phase_s,
        "rpc_calls": opts.rpc_calls,
        "ik_n": opts.ik_n,
        "router": endpoint,
        "mode": "client",
        "paper_size": f"{opts.paper_size[0]}x{opts.paper_size[1]}",
        "paper_fps": opts.paper_fps,
        "vga_size": f"{opts.vga_size[0]}x{opts.vga_size[1]}",
        "vga_fps": opts.vga_fps,
        "command_rates_hz": list(opts.command_rates_hz),
        "force_priority": opts.force_priority,
        "cpu_settle_s": opts.cpu_settle_s,
        "teleop_rate_hz": opts.teleop_rate_hz,
        "loadavg_start": _loadavg(),
    }

    log = CpuLog()
    say(f"IK throughput over {opts.ik_n} poses …")
    from services.control.puma.kinematics import bench_ik

    with log.phase("ik"):
        res.phases["ik"] = bench_ik(opts.ik_n)

    zargs = ["--mode", "client", "--connect", endpoint]
    with Children(opts.logs_dir) as kids:
        log.kids = kids
        router = kids.spawn("router", telerobot_argv("router", "--listen", endpoint))
        wait_log(router, "router up", opts.startup_timeout_s)
        say(f"router up on {endpoint}; starting puma, force, decision, master …")
        node = Node("master", NodeConfig(mode="client", connect=(endpoint,)), instance=MASTER_ID)
        try:
            node.announce()  # alive/master/bench: the bench commands as a master
            _start_services(kids, node, zargs, opts, say)
            res.settings["force_priority_applied"] = _force_priority(node)
            # Start-up transients (the last imports, the first states, the sensor's bias)
            # are not what an operator works with.
            time.sleep(opts.settle_s)
            with log.phase("force_alone"):
                _phase_force(kids, node, opts, res, "force_alone", say)
            kids.check()
            with log.phase("baseline_tcp"):
                _phase_tcp(opts, res, say)
            with log.phase("baseline_zenoh"):
                _phase_zenoh_floor(kids, node, endpoint, opts, res, say)
            driver = CommandDriver(node, MASTER_ID)
            for i, rate in enumerate(opts.command_rates_hz):
                with log.phase(f"commands_{rate:.0f}hz"):
                    sign = -1.0 if i % 2 else 1.0
                    fig, notes = phase_commands(node, driver, rate, sign, opts.phase_s, say)
                    res.phases[f"commands_{rate:.0f}hz"] = fig
                    res.notes.extend(notes)
                kids.check()
            with log.phase("rpc"):
                _phase_rpc(kids, node, endpoint, opts, res, say)
            for key, size, fps in (
                ("paper", opts.paper_size, opts.paper_fps),
                ("vga", opts.vga_size, opts.vga_fps),
            ):
                with log.phase(f"video_{key}"):
                    _phase_video(kids, node, zargs, key, size, fps, opts, res, say)
                kids.check()
            sim = system.SimRun(
                kids, node, driver, zargs, opts.vga_size, opts.vga_fps, opts.startup_timeout_s, say
            )
            res.notes.extend(
                sim.run(opts.cpu_settle_s, opts.phase_s, opts.teleop_rate_hz, log.phase)
            )
            res.phases.update(sim.phases)
        finally:
            node.close()
    log.kids = None  # every child is reaped: its time is in getrusage(RUSAGE_CHILDREN)
    res.settings["loadavg_end"] = _loadavg()
    res.settings["cpu"] = {"run": log.total(), "phases": log.phases}
    res.notes.append(force_note(res.phases))
    busy = busy_note(res.settings["cpu"])
    if busy:
        res.notes.append(busy)
    return res


def force_note(phases: dict[str, Any]) -> str:
    """Where force samples went missing: the sensor's own rate beside the delivered one, and
    the missing seqs beside those the force service itself dropped (0 with its default
    inline publishing; its optional hand-off queue keeps the newest when its publisher
    falls behind)."""
    parts, missing = [], []
    for key, name in (
        ("force_alone", "alone"),
        ("force_stereo_paper", "with 360×288"),
        ("force_stereo_vga", "with 640×480"),
    ):
        f = phases.get(key)
        if f is None:
            continue
        parts.append(f"{name} {f['produced_rate_hz']:.0f}/{f['rate_hz']:.0f} Hz")
        lost = int(f["loss"]["lost"])
        if lost:
            drops = (f.get("service") or {}).get("drops")
            inside = f" ({drops} dropped inside the force service)" if drops is not None else ""
            missing.append(f"{name} {lost} missing{inside}")
    text = "force produced by the sensor / received by the bench: " + ", ".join(parts)
    if parts and not missing:
        return text + "; 0 lost: every sample the sensor produced arrived."
    return text + "; " + ", ".join(missing) + "."


BUSY_SHARE = 0.15
"""Above this share of the CPUs taken by other processes, a phase is reported as contended."""


def busy_note(cpu_use: dict[str, Any]) -> str | None:
    """A plain warning naming the phases during which other processes took more than
    BUSY_SHARE of the CPUs (their figures include that contention)."""
    run = cpu_use.get("run")
    phases = cpu_use.get("phases", {})
    busy = {k: v["others_share"] for k, v in phases.items() if v["others_share"] > BUSY_SHARE}
    if run is None or not busy:
        return None
    listed = ", ".join(f"{k} {share:.0%}" for k, share in busy.items())
    return (
        f"the machine was shared: other processes took {run['others_share']:.0%} of the "
        f"{run['cpus']} CPUs over the run, and more than {BUSY_SHARE:.0%} during: {listed}; "
        "those figures include that contention."
    )


# --- start-up -----------------------------------------------------------------------------


def _start_services(
    kids: Children, node: Node, zargs: list[str], opts: BenchOptions, say: Say
) -> None:
    station = opts.logs_dir / "bench-master.toml"
    # The station's virtual master must not engage at start (its default): it would hold
    # the decision's lease and the bench's commands would be refused.
    station.write_text(
        f'[master]\ndevice = "virtual"\nmaster_id = "{STATION_ID}"\nengage_on_start = false\n'
    )
    kids.spawn("puma", telerobot_argv("puma", "--autostart", *zargs))
    kids.spawn("force", telerobot_argv("force", "--priority", opts.force_priority, *zargs))
    kids.spawn("decision", telerobot_argv("decision", *zargs))
    kids.spawn("master", telerobot_argv("master", "--config", str(station), *zargs))
    for name in ("puma", "force", "decision", f"master/{STATION_ID}"):
        wait_alive(kids, node.alive.wait, name, opts.startup_timeout_s)
    status = StreamProbe(node, STATE, lambda m: (m.status,)).start()
    try:
        deadline = time.monotonic() + opts.startup_timeout_s
        while (newest := status.newest()) is None or newest[1][0] != "ready":
            kids.check()
            if time.monotonic() > deadline:
                raise TimeoutError("the puma never reported ready on robot/state")
            time.sleep(0.05)
    finally:
        # Undeclared at once: a subscriber left running would load the bench all along.
        status.stop()
    say("puma ready, force streaming, decision and master up")


def _force_priority(node: Node) -> dict[str, Any] | None:
    """What the kernel granted the force sampler's thread (its `sensor_status`)."""
    try:
        got = node.call("force", "sensor_status", {}, CALL_TIMEOUT_S).get("priority_applied")
    except (Unavailable, RpcError):
        return None
    return dict(got) if isinstance(got, dict) else None


# --- force --------------------------------------------------------------------------------


def _force_probe(node: Node) -> StreamProbe[ForceSample]:
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


def _measure_window(probe_ready: Callable[[], bool], phase_s: float) -> tuple[int, int]:
    """The measuring window: from when the probe has its first sample, for phase_s."""
    if not probe_ready():
        raise TimeoutError("no sample arrived on the probed stream")
    t0 = time.time_ns()
    # The phase's length is the measurement itself, not a wait for a condition.
    time.sleep(phase_s)
    return t0, time.time_ns()


FORCE_COUNTERS = ("samples", "published", "drops", "overruns")
"""The force sampler's counters (its `sensor_status`): samples taken, handed to the bus,
dropped from its hand-off queue when the publisher fell behind, periods skipped late."""


def _force_counters(node: Node) -> dict[str, int] | None:
    try:
        got = node.call("force", "sensor_status", {}, CALL_TIMEOUT_S)
    except (Unavailable, RpcError):
        return None
    return {k: int(got[k]) for k in FORCE_COUNTERS if isinstance(got.get(k), int)}


def _delta(a: dict[str, int] | None, b: dict[str, int] | None) -> dict[str, int] | None:
    """b − a per counter, around a measuring window (None if either call failed)."""
    if a is None or b is None:
        return None
    return {k: b[k] - a[k] for k in b if k in a}


def _phase_force(
    kids: Children, node: Node, opts: BenchOptions, res: RunResult, key: str, say: Say
) -> None:
    say(f"[{key}] force stream alone for {opts.phase_s:g} s …")
    probe = _force_probe(node)
    before = _force_counters(node)
    if not probe.wait_count(1, 10.0):
        raise TimeoutError("no sample arrived on robot/force")
    cpu_a, t0 = kids.cpu_by_child(), time.time_ns()
    # The phase's length is the measurement itself, not a wait for a condition.
    time.sleep(opts.phase_s)
    cpu_b, t1 = kids.cpu_by_child(), time.time_ns()
    after = _force_counters(node)
    fig, trace = force_figures(probe.stop(), t0, t1)
    fig["rejected"] = probe.rejected
    fig["service"] = _delta(before, after)
    pct = cpu.percent_of_core(cpu_a, cpu_b, (t1 - t0) / stats.NS_PER_S)
    fig["service_cpu_pct"] = pct.get("force")
    fig["router_cpu_pct"] = pct.get("router")
    res.phases[key] = fig
    res.traces["force alone"] = trace
    cpu_text = f", force service {pct['force']:.1f} % of a core" if "force" in pct else ""
    say(_force_line(fig) + cpu_text)


def _force_line(fig: dict[str, Any]) -> str:
    lat = fig["latency_ms"]
    return (
        f"    {fig['rate_hz']:.0f} Hz received, latency p50 {ms_text(lat['p50'])} p99 "
        f"{ms_text(lat['p99'])} max {ms_text(lat['max'])}, lost {fig['loss']['lost']}"
    )


# --- TCP floor ----------------------------------------------------------------------------


def _phase_tcp(opts: BenchOptions, res: RunResult, say: Say) -> None:
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
    say(_force_line(res.phases["baseline_tcp"]))


# --- bare-Zenoh floor -------------------------------------------------------------------


def _phase_zenoh_floor(
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
        own_a, cpu_a, t_a = cpu.process_cpu_s(os.getpid()), kids.cpu_by_child(), time.monotonic()
        try:
            code = pub.proc.wait(timeout=opts.phase_s + opts.startup_timeout_s)
        except subprocess.TimeoutExpired:
            raise TimeoutError("the bare Zenoh publisher did not finish") from None
        own_b, cpu_b, t_b = cpu.process_cpu_s(os.getpid()), kids.cpu_by_child(), time.monotonic()
        if code != 0:
            raise ChildFailed(f"the bare Zenoh publisher exited with {code}:\n{pub.tail()}")
        sent = floor.parse_sent(pub.output())
        probe.wait_count(sent.sent, FLOOR_DRAIN_S)
    finally:
        records = probe.stop()
        kids.stop("zenoh-floor")
    rx = np.array([r[0] for r in records], dtype=np.int64)
    seqs = [int(r[1][0]) for r in records]
    lat = stats.latencies_ms(rx, [r[1][1] for r in records])
    loss = stats.seq_loss(seqs)
    wall_s = t_b - t_a
    router = cpu.percent_of_core(cpu_a, cpu_b, wall_s).get("router")
    res.phases["baseline_zenoh"] = {
        "duration_s": sent.wall_s,
        "sent": sent.sent,
        "received": len(seqs),
        "rate_hz": stats.rate_from_times(rx),
        "payload_bytes": len(force_payload(max(seqs, default=1), time.time_ns())),
        "latency_ms": stats.summarize(lat).as_dict(),
        "loss": {**loss.as_dict(), "lost": sent.sent - loss.unique},
        "rejected": probe.rejected,
        "publisher_cpu_pct": sent.cpu_pct,
        "subscriber_cpu_pct": (own_b - own_a) / wall_s * 100.0 if wall_s > 0 else None,
        "router_cpu_pct": router,
    }
    f = res.phases["baseline_zenoh"]
    say(_force_line(f) + f"; publisher {f['publisher_cpu_pct']:.1f} % of a core")


def _puma_status(node: Node, attempts: int = 3) -> dict[str, Any]:
    """Puma's status map (the XML-RPC baseline replies with it), retried on a lost reply."""
    lost = Unavailable("puma status: no attempt made")
    for _ in range(attempts):
        try:
            return node.call("puma", "status", {}, CALL_TIMEOUT_S)
        except Unavailable as e:
            lost = e
    raise lost


# --- method calls -------------------------------------------------------------------------


def _phase_rpc(
    kids: Children, node: Node, endpoint: str, opts: BenchOptions, res: RunResult, say: Say
) -> None:
    n = opts.rpc_calls
    for key, service, method in (
        ("rpc_decision_status", "decision", "status"),
        ("rpc_decision_supervisor", "decision", "supervisor"),
        ("rpc_puma_status", "puma", "status"),
    ):
        say(f"[{key}] {n} calls of robot/{service}/rpc/{method} …")
        times = time_calls(node, service, method, n)
        res.phases[key] = {**stats.summarize(times.ms).as_dict(), "failures": times.failures}
        failed = sum(times.failures.values())
        say(
            f"    p50 {ms_text(res.phases[key]['p50'])} p99 {ms_text(res.phases[key]['p99'])}"
            + (f", {failed} failed: {times.failures}" if failed else "")
        )
        if failed:
            res.notes.append(
                f"{key}: {failed} of {n} calls failed ({times.failures}); only the answered "
                "ones are timed."
            )
    reply = _puma_status(node)
    say(f"[baseline_zenoh_query] {n} bare-Zenoh gets of a queryable replying puma's status map …")
    reply_file = opts.logs_dir / "floor-reply.msgpack"
    reply_file.write_bytes(codec.pack(reply))
    server = kids.spawn("zenoh-floor-rpc", floor.serve_argv(endpoint, reply_file))
    try:
        wait_log(server, floor.SERVING, opts.startup_timeout_s)
        got = floor.time_gets(node.session, n)
    finally:
        kids.stop("zenoh-floor-rpc")
    res.phases["baseline_zenoh_query"] = {
        "latency_ms": stats.summarize(got.ms).as_dict(),
        "calls": n,
        "failures": got.failures,
        "reply_bytes": len(codec.pack(reply)),
    }
    lat = res.phases["baseline_zenoh_query"]["latency_ms"]
    say(f"    p50 {ms_text(lat['p50'])} p99 {ms_text(lat['p99'])}")
    say(f"[baseline_xmlrpc] {n} XML-RPC calls returning puma's status map …")
    rtt = xmlrpc_round_trips(reply, n)
    res.phases["baseline_xmlrpc"] = {"latency_ms": stats.summarize(rtt).as_dict(), "calls": n}
    lat = res.phases["baseline_xmlrpc"]["latency_ms"]
    say(f"    p50 {ms_text(lat['p50'])} p99 {ms_text(lat['p99'])}")


# --- video --------------------------------------------------------------------------------


def _phase_video(
    kids: Children,
    node: Node,
    zargs: list[str],
    key: str,
    size: tuple[int, int],
    fps: float,
    opts: BenchOptions,
    res: RunResult,
    say: Say,
) -> None:
    w, h = size
    say(f"[video_{key}] starting vision at {w}x{h} @ {fps:g} fps …")
    kids.spawn(
        "vision", telerobot_argv("vision", "--size", f"{w}x{h}", "--fps", f"{fps:g}", *zargs)
    )
    try:
        wait_alive(kids, node.alive.wait, "vision", opts.startup_timeout_s)
        video = VideoProbe(node).start()
        vstats = StreamProbe(node, VISION_STATS, lambda m: (m,)).start()
        if not video.wait_frames(3, opts.startup_timeout_s):
            kids.check("vision")
            raise TimeoutError(f"no stereo frames at {w}x{h} within {opts.startup_timeout_s} s")
        # The renderer's first frames come while its caches fill: not what an operator sees.
        time.sleep(VIDEO_WARMUP_S)
        say(f"[force_stereo_{key}] force + stereo {w}x{h}@{fps:g} for {opts.phase_s:g} s …")
        probe = _force_probe(node)
        before = _force_counters(node)
        t0, t1 = _measure_window(lambda: probe.wait_count(1, 10.0), opts.phase_s)
        after = _force_counters(node)
        force_rec = probe.stop()
        frames = video.stop()
        newest_stats = vstats.stop()
        last_stats: VisionStats | None = newest_stats[-1][1][0] if newest_stats else None
    finally:
        kids.stop("vision")
    frames = [f for f in frames if t0 <= f.rx_ns <= t1]
    vfig, windows = video_figures(frames, t0, t1, w, h, fps)
    vfig["decode_errors"] = video.decode_errors
    if last_stats is not None:
        vfig["vision_stats"] = {
            "fps": last_stats.fps,
            "encode_ms": last_stats.encode_ms,
            "dropped": last_stats.dropped,
            "capture_skew_ms": last_stats.skew_ms,
        }
    ffig, trace = force_figures(force_rec, t0, t1)
    ffig["service"] = _delta(before, after)
    inflight = stats.rate_in_windows([r[0] for r in force_rec if t0 <= r[0] <= t1], windows)
    ffig["in_flight"] = {
        "count": inflight.count,
        "covered_s": inflight.covered_s,
        "rate_hz": inflight.rate_hz if inflight.covered_s > 0 else None,
    }
    if inflight.covered_s <= 0:
        ffig["na"] = {"in_flight": "no stereo pair was complete inside the window"}
    res.phases[f"video_{key}"] = vfig
    res.phases[f"force_stereo_{key}"] = ffig
    res.traces[f"with stereo {w}x{h}@{fps:g}"] = trace
    say(_force_line(ffig) + f"; {inflight.rate_hz:.0f} Hz while a pair is in flight")
    lat = vfig["latency_ms"]
    say(
        f"    video {vfig['fps_l']:.1f}/{vfig['fps_r']:.1f} fps (l/r), capture→decoded p50 "
        f"{ms_text(lat['p50'])} p99 {ms_text(lat['p99'])}, {vfig['mbit_s']:.1f} Mbit/s"
    )


def video_figures(
    frames: Sequence[FrameRecord], t0: int, t1: int, w: int, h: int, fps: float
) -> tuple[dict[str, Any], list[tuple[int, int]]]:
    """The video phase's figures from the decoded frames (already cut to the window
    [t0, t1]): fps per eye, capture→decoded latency, arrival skew, missing pairs, bit rate;
    and each complete pair's in-flight window (capture t_ns, arrival of its later eye)."""
    duration_s = (t1 - t0) / stats.NS_PER_S
    eyes = {e: [f for f in frames if f.eye == e] for e in ("l", "r")}
    # From the delivered frames' own capture stamps: (n − 1) periods over their span, free of
    # where the window happened to cut the frame train.
    fps_l = stats.rate_from_times([f.t_ns for f in eyes["l"]])
    fps_r = stats.rate_from_times([f.t_ns for f in eyes["r"]])
    lat = [(f.decoded_ns - f.t_ns) / stats.NS_PER_MS for f in frames]
    left = {f.seq: f.rx_ns for f in eyes["l"]}
    right = {f.seq: f.rx_ns for f in eyes["r"]}
    both = sorted(set(left) & set(right))
    t_of = {f.seq: f.t_ns for f in frames}
    windows = [(t_of[s], max(left[s], right[s])) for s in both]
    pair_loss = stats.seq_loss(sorted(set(left) | set(right)))
    fig = {
        "width": w,
        "height": h,
        "fps_target": fps,
        "duration_s": duration_s,
        "frames_l": len(eyes["l"]),
        "frames_r": len(eyes["r"]),
        "fps_l": fps_l,
        "fps_r": fps_r,
        "fps_min": min(fps_l, fps_r),
        "pairs_complete": len(both),
        "pairs_missing": pair_loss.lost,
        "latency_ms": stats.summarize(lat).as_dict(),
        "arrival_skew_ms": stats.summarize(stats.pair_skew_ms(left, right)).as_dict(),
        "bytes_per_pair": (sum(f.nbytes for f in frames) / len(both)) if both else None,
        "mbit_s": sum(f.nbytes for f in frames) * 8 / 1e6 / duration_s if duration_s else 0.0,
    }
    return fig, windows


__all__ = [
    "BenchOptions",
    "RunResult",
    "force_figures",
    "force_note",
    "run_bench",
    "video_figures",
]
