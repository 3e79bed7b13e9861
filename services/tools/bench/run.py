"""One bench run: start the deployed topology, measure each phase, stop everything.

Topology (as deploy/robot.toml runs it): the embedded router on 127.0.0.1:PORT, and arm
(sim arm, autostart), force (sim sensor, 1 kHz), decision, a master station (virtual
device, not engaged) and, in the video phases, vision — each a separate process in client
mode connected to the router. The bench itself is one more client: the operator's side.
The CPU phases at the end run the sim profile's set instead (services.tools.bench.cpu_phases).

Phases, in order (each `phase_s` long): IK throughput (in the bench process, before any
child runs); force alone; the raw-TCP floor; the bare-Zenoh floor; the two-hop bare-Zenoh
relay at each command rate (services.tools.bench.relay_phase); commands at 100 Hz and at 1 kHz
(services.tools.bench.commands); method calls, the bare-Zenoh get→reply floor and the
XML-RPC baseline; force + stereo at the paper's setting; force + stereo at 640×480@30; CPU
per service idle, then during 1 kHz teleop with VGA stereo.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from services.bus.config import NodeConfig
from services.bus.errors import RpcError, Unavailable
from services.bus.node import Node
from services.tools.bench import cpu, cpu_phases
from services.tools.bench.commands import CALL_TIMEOUT_S, phase_busy_host, phase_commands
from services.tools.bench.force_phases import phase_force, phase_tcp, phase_zenoh_floor
from services.tools.bench.notes import busy_note, force_note
from services.tools.bench.options import BenchOptions, RunResult, Say
from services.tools.bench.probes import CommandDriver
from services.tools.bench.procs import children_cpu_s, cpu_by_child, wait_arm_ready
from services.tools.bench.relay_phase import phase_relay_floor
from services.tools.bench.rpc_phase import phase_rpc
from services.tools.bench.teleop_floor import phase_teleop_floor
from services.tools.bench.video_phase import phase_video
from services.tools.cell.ports import free_port
from services.tools.cell.procs import ChildFailed, Children, telerobot_argv, wait_alive, wait_log

MASTER_ID = "bench"
STATION_ID = "station"


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
        return cpu.sample(children_cpu_s(self.kids) if self.kids is not None else 0.0)

    def _by_child(self) -> dict[str, float]:
        return cpu_by_child(self.kids) if self.kids is not None else {}

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
        "model": opts.model,
        "busy_s": opts.busy_s,
        "loadavg_start": _loadavg(),
    }

    log = CpuLog()
    say(f"IK throughput over {opts.ik_n} poses …")
    from services.tools.bench.ik_phase import bench_ik

    with log.phase("ik"):
        res.phases["ik"] = bench_ik(opts.ik_n)
    say("physics real-time factor of the MuJoCo cell, every model …")
    from services.tools.bench.physics_phase import bench_physics

    with log.phase("physics"):
        res.phases["physics"] = bench_physics(min(opts.phase_s, 10.0))

    zargs = ["--mode", "client", "--connect", endpoint]
    with Children(opts.logs_dir) as kids:
        log.kids = kids
        router = kids.spawn("router", telerobot_argv("router", "--listen", endpoint))
        wait_log(router, "router up", opts.startup_timeout_s)
        with log.phase("teleop_floor"):
            res.phases["teleop_floor"] = _teleop_floor(kids, endpoint, opts, say)
        say(f"router up on {endpoint}; starting arm, force, decision, master …")
        node = Node("master", NodeConfig(mode="client", connect=(endpoint,)), instance=MASTER_ID)
        try:
            node.announce()  # alive/master/bench: the bench commands as a master
            _start_services(kids, node, zargs, opts, say)
            res.settings["force_priority_applied"] = _force_priority(node)
            # Start-up transients (the last imports, the first states, the sensor's bias)
            # are not what an operator works with.
            time.sleep(opts.settle_s)
            with log.phase("force_alone"):
                phase_force(kids, node, opts, res, "force_alone", say)
            kids.check()
            with log.phase("baseline_tcp"):
                phase_tcp(opts, res, say)
            with log.phase("baseline_zenoh"):
                phase_zenoh_floor(kids, node, endpoint, opts, res, say)
            with log.phase("baseline_zenoh_relay"):
                phase_relay_floor(kids, node, endpoint, opts.command_rates_hz, opts, res, say)
            driver = CommandDriver(node, MASTER_ID)
            for i, rate in enumerate(opts.command_rates_hz):
                with log.phase(f"commands_{rate:.0f}hz"):
                    sign = -1.0 if i % 2 else 1.0
                    fig, notes = phase_commands(node, driver, rate, sign, opts.phase_s, say)
                    res.phases[f"commands_{rate:.0f}hz"] = fig
                    res.notes.extend(notes)
                kids.check()
            if opts.busy_s > 0:
                with log.phase("busy_host"):
                    fig, notes = phase_busy_host(node, driver, opts.busy_s, say)
                    res.phases["busy_host"] = fig
                    res.notes.extend(notes)
                kids.check()
            with log.phase("rpc"):
                phase_rpc(kids, node, endpoint, opts, res, say)
            for key, size, fps in (
                ("paper", opts.paper_size, opts.paper_fps),
                ("vga", opts.vga_size, opts.vga_fps),
            ):
                with log.phase(f"video_{key}"):
                    phase_video(kids, node, zargs, key, size, fps, opts, res, say)
                kids.check()
            sim = cpu_phases.SimRun(
                kids,
                node,
                driver,
                zargs,
                opts.vga_size,
                opts.vga_fps,
                opts.startup_timeout_s,
                say,
                model=opts.model,
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
    kids.spawn("arm", telerobot_argv("arm", "--autostart", "--model", opts.model, *zargs))
    kids.spawn("force", telerobot_argv("force", "--priority", opts.force_priority, *zargs))
    kids.spawn("decision", telerobot_argv("decision", *zargs))
    kids.spawn("master", telerobot_argv("master", "--config", str(station), *zargs))
    for name in ("arm", "force", "decision", f"master/{STATION_ID}"):
        wait_alive(kids, node.alive.wait, name, opts.startup_timeout_s)
    wait_arm_ready(kids, node, opts.startup_timeout_s)
    say("arm ready, force streaming, decision and master up")


def _teleop_floor(kids: Children, endpoint: str, opts: BenchOptions, say: Say) -> dict[str, Any]:
    """The teleop floor (teleop_floor.py), first: nothing but the router runs yet."""
    try:
        return phase_teleop_floor(
            kids, endpoint, opts.cpu_settle_s, opts.phase_s, opts.startup_timeout_s, say
        )
    except (ChildFailed, TimeoutError) as e:
        why = f"not measured: {(str(e).splitlines() or [type(e).__name__])[0]}"
        say(f"    teleop floor {why}")
        return {"na": {"*": why}}


def _force_priority(node: Node) -> dict[str, Any] | None:
    """What the kernel granted the force sampler's thread (its `sensor_status`)."""
    try:
        got = node.call("force", "sensor_status", {}, CALL_TIMEOUT_S).get("priority_applied")
    except (Unavailable, RpcError):
        return None
    return dict(got) if isinstance(got, dict) else None
