"""The whole bilateral loop through the real services, in-process on loopback (a helper for
the system tests and for measuring; not a test module).

arm (SimArm), force (sim wrist in the sim workcell), decision (`passivity` on or off) and,
when asked, a master with the simulated haptic operator (`SimHapticMaster`, `passivity` on
or off), each on a node of its own. The arm is first moved (through the decision server)
to `start_gap_m` above the table, then the operator presses down onto it, holds and
releases. A console node records the wrist force (world frame, with the tool pose of the
robot/state nearest in time), the robot states and both sides' passivity figures. The robot
side, the trace and the measures are the link bench's (`services.tools.tdpa.link_bench`,
which runs the same loop split over a bad link).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from services.control.decision.service import DecisionService
from services.control.master.config import MasterConfig
from services.control.master.haptic_sim import SimHapticMaster
from services.control.master.service import MasterService
from services.tools.tdpa import link_bench as pl
from services.tools.tdpa.link_bench import Trace
from tests.conftest import Net, wait_until

__all__ = ["Loop", "Trace", "build", "metrics", "start_master", "wait_until"]

TOP_Z = pl.TOUCH_Z  # the tool point when the fingertips touch the table


@dataclass
class Loop:
    net: Net
    decision: DecisionService
    trace: Trace
    closers: list[Callable[[], None]] = field(default_factory=list)
    master: MasterService | None = None
    t_start_ns: int = 0

    def close(self) -> None:
        for c in reversed(self.closers):
            c()


def build(net: Net, passivity: bool = True, start_gap_m: float = 0.04, **decision: float) -> Loop:
    """The robot side, the arm `start_gap_m` above the table, recording; no master yet."""
    cell, trace = pl.build_robot(net.node, passivity, start_gap_m, **decision)
    return Loop(net, cell.decision, trace, [cell.close])


def start_master(
    loop: Loop, passivity: bool = True, rate_hz: float = 100.0, **sim: float
) -> MasterService:
    """The simulated operator on a master station (100 Hz), engaged at once."""
    cfg = MasterConfig(master_id="op", device="haptic_sim", passivity=passivity, rate_hz=rate_hz)
    station = MasterService(
        loop.net.node("master", instance="op"), cfg, device=SimHapticMaster(**sim)
    )
    loop.master = station
    loop.t_start_ns = time.time_ns()
    loop.closers.append(station.close)
    return station


def metrics(loop: Loop, hold_from_s: float, hold_to_s: float) -> dict[str, float]:
    """`link_bench.metrics` of the loop's trace since the master started."""
    return pl.metrics(loop.trace, loop.t_start_ns, hold_from_s, hold_to_s)
