"""The CPU phases: what each service of the sim profile costs, idle and during teleoperation.

They run last, on the set `telerobot up sim` runs (deploy/sim.toml): router, arm (sim,
autostart, with the workcell's MuJoCo cell in its process: `sim_physics = "embedded"`),
force (sim), decision, vision (sim camera, 640×480 at 30 fps) and the console with its
in-process virtual master and no browser. The bench's own master station (which the sim
profile does not have) is stopped first, and its arm, alone in a physics of its own for the
other phases, is started again with the cell as the profile runs it, and so is the force
service, at the profile's priority (the other phases ask for `highest`, as robot.toml does);
nothing is measured after these phases, so restarting them and starting the console cannot
disturb another phase. The arm's figure holds the physics. The services stay the bench's
clients (robot.toml's mode); the profile runs them as peers of its router (docs/bench.md
has both). The same run's teleop floor (teleop_floor.py) is the least the router and the
three 1 kHz services can cost.

- `cpu_idle`: after `settle_s`, a window in which nobody operates and nobody subscribes to
  video (the bench holds no subscription but its liveliness one);
- `cpu_teleop`: the same processes while the bench streams `robot/cmd` at 1 kHz (as a master,
  services.tools.bench.commands) and subscribes to both eyes, decoding every frame.

Per service: the CPU its process group used over the window (/proc utime + stime,
services.tools.bench.cpu) in % of one core; and the two sums issue 16 budgets. The bench's own
process is reported beside them (`bench_pct`), never in the sums.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Any

from services.bus.node import Node
from services.tools.bench import commands, cpu, stats
from services.tools.bench.probes import CommandDriver, VideoProbe
from services.tools.bench.procs import cpu_by_child, wait_arm_ready
from services.tools.bench.report import CORE_SERVICES, SIM_SERVICES
from services.tools.cell.procs import ChildFailed, Children, telerobot_argv, wait_alive

Say = Callable[[str], None]
PhaseLog = Callable[[str], AbstractContextManager[None]]

EXTRA_SERVICES = ("vision", "console")
"""Started for the CPU phases only (in this order, the arm again with the workcell in it;
stopped in reverse)."""
CONSOLE_MASTER = "master/console"
"""The console's in-process virtual master (its default id): `up sim` has no other."""
VIDEO_WARMUP_S = 1.0
VIDEO_FRAMES_FIRST = 3


def cpu_figures(
    before: Mapping[str, float], after: Mapping[str, float], bench_s: float, wall_s: float
) -> dict[str, Any]:
    """One CPU window's figures from the per-service CPU seconds at both ends: each
    service's % of one core (`services`), the budgeted sums (`core_pct`: router + arm +
    force + decision; `sim_pct`: the whole sim profile), the bench process's own %
    (`bench_pct`, from its CPU seconds `bench_s` over the window) and, for a sum that could
    not be made, why (`na`)."""
    pct = cpu.percent_of_core(before, after, wall_s)
    fig: dict[str, Any] = {
        "window_s": wall_s,
        "services": pct,
        "core_pct": cpu.budget_sum(pct, CORE_SERVICES),
        "sim_pct": cpu.budget_sum(pct, SIM_SERVICES),
        "bench_pct": bench_s / wall_s * 100.0 if wall_s > 0 else None,
        "na": {},
    }
    for key, names in (("core_pct", CORE_SERVICES), ("sim_pct", SIM_SERVICES)):
        missing = [n for n in names if n not in pct]
        if missing:
            fig["na"][key] = f"not running through the whole window: {', '.join(missing)}"
    for name in SIM_SERVICES:
        if name not in pct:
            fig["na"][name] = f"{name} was not running through the whole window"
    return fig


@dataclass(frozen=True, slots=True)
class CpuMark:
    """CPU readings at one instant: per service, the bench's own, both clocks."""

    services: dict[str, float]
    bench_s: float
    mono_s: float
    wall_ns: int


@dataclass
class SimRun:
    """The CPU phases over the running bench topology; `run()` fills `phases` (`cpu_idle`,
    `cpu_teleop`) and returns notes. Every child it starts is stopped before `run` returns."""

    kids: Children
    node: Node
    driver: CommandDriver
    zargs: list[str]
    vga_size: tuple[int, int]
    vga_fps: float
    startup_timeout_s: float
    say: Say
    model: str = "puma560"
    phases: dict[str, Any] = field(default_factory=dict)

    def mark(self) -> CpuMark:
        return CpuMark(
            cpu_by_child(self.kids),
            cpu.process_cpu_s(os.getpid()),
            time.monotonic(),
            time.time_ns(),
        )

    def run(
        self, settle_s: float, window_s: float, teleop_rate_hz: float, log: PhaseLog
    ) -> list[str]:
        """Start the sim profile's extra services, measure both windows, stop them. A
        failure here (a service that does not come up, or dies) leaves the phases not
        measured, with the reason, and the rest of the run intact."""
        w, h = self.vga_size
        notes = [
            "CPU phases: the sim profile's processes (router, arm, force, decision, vision "
            f"{w}×{h}@{self.vga_fps:g}, console without a browser, with its virtual "
            "master; the workcell's physics in the arm's process), run after every other "
            "phase with the "
            "bench's station master stopped; "
            f"{settle_s:g} s to settle, then {window_s:g} s idle (nobody operating, nobody "
            f"subscribed to video), then {window_s:g} s while the bench streams robot/cmd at "
            f"{teleop_rate_hz:g} Hz and decodes both eyes. % of one core per process group "
            "(/proc utime + stime); the bench's own process is not in the sums."
        ]
        pending = ["cpu_idle", "cpu_teleop"]
        try:
            self._start()
            # Start-up (imports, the first frames, the console's scene) is not idling.
            time.sleep(settle_s)
            with log("cpu_idle"):
                self.phases["cpu_idle"] = self._idle(window_s)
            pending.remove("cpu_idle")
            self.kids.check()
            with log("cpu_teleop"):
                self.phases["cpu_teleop"] = self._teleop(window_s, teleop_rate_hz)
            pending.remove("cpu_teleop")
        except (ChildFailed, TimeoutError) as e:
            reason = f"{pending[0]} failed: {str(e).splitlines()[0]}"
            for key in pending:
                self.phases[key] = {"na": {"*": reason}}
            notes.append(reason + " (see the children's logs).")
        finally:
            for name in reversed(EXTRA_SERVICES):
                self.kids.stop(name)
        for key in ("cpu_idle", "cpu_teleop"):
            fig = self.phases[key]
            if fig.get("core_pct") is not None:
                self.say(
                    f"    {key}: core {fig['core_pct']:.1f} %, whole sim "
                    + (f"{fig['sim_pct']:.1f} %" if fig["sim_pct"] is not None else "n/a")
                    + " of one core; "
                    + ", ".join(f"{k} {v:.1f}" for k, v in fig["services"].items())
                )
        return notes

    def _start(self) -> None:
        self.say(
            "[cpu] stopping the station master; starting vision, the arm with the workcell's "
            "physics in its process, the force service at the profile's priority, console …"
        )
        self.kids.stop("master")
        self.kids.stop("arm")
        # The force service as the profile runs it: deploy/sim.toml leaves its priority at
        # the default (`normal`); at `highest`, as the other phases ask for, its sampler
        # spins the last 100 µs of every period under SCHED_FIFO (6–9 % of a core here).
        self.kids.stop("force")
        w, h = self.vga_size
        argv = {
            "vision": ("vision", "--size", f"{w}x{h}", "--fps", f"{self.vga_fps:g}"),
            "arm": ("arm", "--autostart", "--model", self.model, "--sim-physics", "embedded"),
            "console": ("console", "--port", "0"),
            "force": ("force",),
        }
        for name in ("vision", "arm", "force", "console"):
            self.kids.spawn(name, telerobot_argv(*argv[name], *self.zargs))
        for name in (*EXTRA_SERVICES, "workcell", "arm", "force", CONSOLE_MASTER):
            wait_alive(self.kids, self.node.alive.wait, name, self.startup_timeout_s)
        wait_arm_ready(self.kids, self.node, self.startup_timeout_s)

    def _idle(self, window_s: float) -> dict[str, Any]:
        self.say(f"[cpu_idle] the sim profile idle for {window_s:g} s …")
        a = self.mark()
        # The window's length is the measurement itself, not a wait for a condition.
        time.sleep(window_s)
        b = self.mark()
        return cpu_figures(a.services, b.services, b.bench_s - a.bench_s, b.mono_s - a.mono_s)

    def _teleop(self, window_s: float, rate_hz: float) -> dict[str, Any]:
        self.say(f"[cpu_teleop] robot/cmd at {rate_hz:g} Hz + stereo decoded for {window_s:g} s …")
        marks: dict[str, CpuMark] = {}
        video = VideoProbe(self.node).start()
        t0 = time.monotonic()
        try:
            if not video.wait_frames(VIDEO_FRAMES_FIRST, self.startup_timeout_s):
                raise TimeoutError("no stereo frames from vision")
            time.sleep(VIDEO_WARMUP_S)  # the subscriber's first frames: vision resuming
            self.say(f"    stereo decoded after {time.monotonic() - t0:.1f} s; streaming commands")

            def mark(what: str) -> None:
                marks[what] = self.mark()

            s = commands.stream(self.node, self.driver, rate_hz, window_s, 1.0, mark=mark)
        finally:
            frames = video.stop()
        a, b = marks["start"], marks["end"]
        fig = cpu_figures(a.services, b.services, b.bench_s - a.bench_s, b.mono_s - a.mono_s)
        cmd = commands.command_figures(rate_hz, s.run, s.step_m, s.fwd_rec, s.st_rec)
        fig["commands"] = {
            k: cmd[k] for k in ("sent", "sent_rate_hz", "engagements", "reached_rate_hz")
        }
        inside = [f for f in frames if a.wall_ns <= f.rx_ns <= b.wall_ns]
        fig["video"] = {
            "frames_l": sum(1 for f in inside if f.eye == "l"),
            "frames_r": sum(1 for f in inside if f.eye == "r"),
            "fps_l": stats.rate_from_times([f.t_ns for f in inside if f.eye == "l"]),
            "fps_r": stats.rate_from_times([f.t_ns for f in inside if f.eye == "r"]),
            "decode_errors": video.decode_errors,
        }
        return fig
