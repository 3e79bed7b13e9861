"""`telerobot bench --arm libfranka [--robot-ip HOST]`: the FR3 through libfranka, measured.

Starts the router, the arm (`--driver libfranka --model fr3`), the force service and the
decision as separate processes (as deployed), and franky-sim on a loopback address when no
`--robot-ip` is given. Then, at each command rate, the bench streams `robot/cmd` as a master
for `phase_s` (services.tools.bench.commands) and reports:

- master→setpoint (the arm's setpoint for the command, its `setpoint_ns`) and master→arm,
  as the main bench does;
- setpoint→robot: from the arm writing a setpoint into the real-time process's block to that
  process's 1 kHz loop first aiming at it (both `time.monotonic_ns`, one clock), sampled;
- the control callback's cycle: the wall-clock period between two of its `readOnce` (p50,
  p99, max), and the cycles libfranka counts as lost (a `readOnce` duration above 1 ms), and
  the robot's clock against the wall's (franky-sim runs slower than real time when loaded).

The block is read from this process (services/control/arm/franka/shm.py, by the robot's
address): the arm's own numbers, no extra wire. Figures from franky-sim say what this
machine and the simulator do; a real FR3 on an RT kernel is what the numbers are for.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from services.bus.config import NodeConfig
from services.bus.node import Node
from services.control.arm.franka.frankysim import FrankySim, start_franky_sim
from services.control.arm.franka.shm import (
    C_SP_SEQ,
    C_SP_T,
    RING,
    S_RING,
    S_RING_I,
    S_SP_SEQ,
    S_SP_T,
    Shared,
    state_path,
)
from services.tools.bench import stats
from services.tools.bench.commands import phase_commands
from services.tools.bench.options import BenchOptions, Say
from services.tools.bench.probes import CommandDriver
from services.tools.bench.procs import wait_arm_ready
from services.tools.cell.ports import free_port
from services.tools.cell.procs import Children, telerobot_argv, wait_alive, wait_log

MASTER_ID = "bench"
SAMPLE_S = 0.002


class BlockWatch:
    """Reads the arm's block while a phase runs: every cycle period the loop wrote, and
    setpoint→robot samples."""

    def __init__(self, path: Path) -> None:
        self.shm = Shared.attach(path)
        self.periods: list[float] = []
        self.handoff_ms: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-franka", daemon=True)
        self.start_snap = self.shm.snapshot()
        self.end_snap = self.start_snap
        self.t0 = time.monotonic()
        self.t1 = self.t0

    def __enter__(self) -> BlockWatch:
        self._ring_i = int(self.shm.a[S_RING_I])
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.end_snap = self.shm.snapshot()
        self.t1 = time.monotonic()
        self.shm.close()

    def _run(self) -> None:
        a = self.shm.a
        last_seq = -1
        while not self._stop.wait(SAMPLE_S):
            k = int(a[S_RING_I])
            if k - self._ring_i > RING:  # fell behind a full ring: keep the newest
                self._ring_i = k - RING
            for i in range(self._ring_i, k):
                self.periods.append(float(a[S_RING + i % RING]))
            self._ring_i = k
            sp_seq, taken_seq = int(a[C_SP_SEQ]), int(a[S_SP_SEQ])
            if sp_seq == taken_seq and sp_seq != last_seq and sp_seq > 0:
                written, taken = float(a[C_SP_T]), float(a[S_SP_T])
                if taken >= written and int(a[C_SP_SEQ]) == sp_seq:
                    self.handoff_ms.append((taken - written) / 1e6)
                    last_seq = sp_seq

    def figures(self) -> dict[str, Any]:
        p = np.array(self.periods[1:]) * 1e3 if len(self.periods) > 1 else np.zeros(0)
        s0, s1 = self.start_snap, self.end_snap
        wall_s = self.t1 - self.t0
        robot_s = s1.t_robot_s - s0.t_robot_s
        return {
            "cycle_ms": stats.summarize(p).as_dict(),
            "cycles": s1.cycles - s0.cycles,
            "lost_cycles": s1.lost - s0.lost,
            "robot_s_per_wall_s": round(robot_s / wall_s, 3) if wall_s > 0 else None,
            "setpoint_to_robot_ms": stats.summarize(np.array(self.handoff_ms)).as_dict(),
        }


def run_franka(opts: BenchOptions, say: Say = print) -> dict[str, Any]:
    """The libfranka run (see the module docstring); every child is stopped on return."""
    sim: FrankySim | None = None
    host = opts.robot_ip
    if not host:
        say("starting franky-sim (MuJoCo) on a loopback address …")
        sim = start_franky_sim()
        host = sim.host
    out: dict[str, Any] = {
        "settings": {
            "robot_ip": host,
            "robot": "franky-sim" if sim is not None else "robot",
            "phase_s": opts.phase_s,
            "command_rates_hz": list(opts.command_rates_hz),
        },
        "phases": {},
        "notes": [],
    }
    try:
        endpoint = f"tcp/127.0.0.1:{opts.port or free_port()}"
        zargs = ["--mode", "client", "--connect", endpoint]
        with Children(opts.logs_dir) as kids:
            router = kids.spawn("router", telerobot_argv("router", "--listen", endpoint))
            wait_log(router, "router up", opts.startup_timeout_s)
            node = Node(
                "master", NodeConfig(mode="client", connect=(endpoint,)), instance=MASTER_ID
            )
            try:
                node.announce()
                arm_args = ["--autostart", "--model", "fr3", "--driver", "libfranka"]
                kids.spawn("arm", telerobot_argv("arm", *arm_args, "--robot-ip", host, *zargs))
                kids.spawn("force", telerobot_argv("force", *zargs))
                kids.spawn("decision", telerobot_argv("decision", *zargs))
                for name in ("arm", "force", "decision"):
                    wait_alive(kids, node.alive.wait, name, opts.startup_timeout_s)
                wait_arm_ready(kids, node, opts.startup_timeout_s)
                say(f"arm ready on {host} (libfranka); force and decision up")
                driver = CommandDriver(node, MASTER_ID)
                for i, rate in enumerate(opts.command_rates_hz):
                    key = f"libfranka_{rate:.0f}hz"
                    with BlockWatch(state_path(host)) as watch:
                        sign = -1.0 if i % 2 else 1.0
                        fig, notes = phase_commands(node, driver, rate, sign, opts.phase_s, say)
                    fig["callback"] = watch.figures()
                    out["phases"][key] = fig
                    out["notes"].extend(notes)
                    cb = fig["callback"]
                    say(
                        f"    callback: cycle p50 {cb['cycle_ms']['p50']:.3f} ms p99 "
                        f"{cb['cycle_ms']['p99']:.3f} max {cb['cycle_ms']['max']:.3f}; "
                        f"{cb['lost_cycles']} lost of {cb['cycles']}; robot clock "
                        f"{cb['robot_s_per_wall_s']}× the wall's; setpoint→robot p50 "
                        f"{cb['setpoint_to_robot_ms']['p50']:.3f} ms"
                    )
                    kids.check()
            finally:
                node.close()
    finally:
        if sim is not None:
            sim.close()
    return out


def table(out: dict[str, Any]) -> str:
    """The figures as a Markdown table."""
    rows = [
        "| rate | reached | master→setpoint p50 / p99 | setpoint→robot p50 / p99 | "
        "cycle p50 / p99 / max | lost cycles | robot clock |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key, fig in out["phases"].items():
        cb = fig["callback"]
        sp, hand, cyc = fig["setpoint_ms"], cb["setpoint_to_robot_ms"], cb["cycle_ms"]
        rows.append(
            f"| {key.split('_')[1]} | {fig['reached_rate_hz']:.0f} Hz | {_ms(sp, 'p50')} / "
            f"{_ms(sp, 'p99')} | {_ms(hand, 'p50')} / {_ms(hand, 'p99')} | {_ms(cyc, 'p50')} / "
            f"{_ms(cyc, 'p99')} / {_ms(cyc, 'max')} | {cb['lost_cycles']} of {cb['cycles']} | "
            f"{cb['robot_s_per_wall_s']}× |"
        )
    return "\n".join(rows)


def _ms(d: dict[str, Any], k: str) -> str:
    v = d.get(k)
    return "n/a" if v is None or v != v else f"{v:.3f} ms"
