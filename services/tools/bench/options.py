"""What a bench run is asked to do (`BenchOptions`) and what it returns (`RunResult`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.control.force.priority import PriorityLevel
from services.tools.bench.report import PAPER_SIZE

Say = Callable[[str], None]
Trace = tuple[np.ndarray, np.ndarray]


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
    model: str = "puma560"
    """The arm model the arm service runs (`telerobot arm --model`)."""
    busy_s: float = 60.0
    """The busy-host phase: a 100 Hz master this long beside two nice-19 busy loops in a
    session of their own (0: skip it)."""
    arm: str = "sim"
    """`libfranka`: the FR3 through libfranka instead (services.tools.bench.franka_phase)."""
    robot_ip: str = ""
    """With `arm = libfranka`: the robot's address ("": franky-sim, started by the bench)."""

    @staticmethod
    def quick_options(**overrides: Any) -> BenchOptions:
        """`--quick`: 5 s phases, fewer calls and IK poses (under 2 min on 2 cores)."""
        base: dict[str, Any] = {
            "phase_s": 5.0,
            "quick": True,
            "rpc_calls": 200,
            "ik_n": 2000,
            "cpu_settle_s": 3.0,
            "busy_s": 10.0,
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
