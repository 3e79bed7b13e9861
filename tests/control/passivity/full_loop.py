"""The whole bilateral loop through the real services, in-process on loopback (a helper for
the system tests and for measuring; not a test module).

puma (SimArm), force (sim wrist in the sim workcell), decision (`passivity` on or off) and,
when asked, a master with the simulated haptic operator (`SimHapticMaster`, `passivity` on
or off), each on a node of its own. The arm is first moved (through the decision server)
to `start_gap_m` above the table, then the operator presses down onto it, holds and
releases. A console node records the wrist force (world frame, with the tool pose of the
robot/state nearest in time), the robot states and both sides' passivity figures.
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from services.bus import keys
from services.bus.messages import Event, ForceSample, OperatorCommand, PassivityState, RobotState
from services.control.decision.config import DecisionConfig
from services.control.decision.service import DecisionService
from services.control.force.config import ForceConfig
from services.control.force.service import ForceService
from services.control.master.config import MasterConfig
from services.control.master.haptic_sim import SimHapticMaster
from services.control.master.service import MasterService
from services.control.puma.config import HOME_Q_RAD, PumaConfig
from services.control.puma.service import PumaService
from services.control.puma.sim_arm import SimArm
from services.world.workcell.scene import TABLE
from tests.conftest import Net, wait_until

__all__ = ["Loop", "Trace", "build", "metrics", "start_master", "wait_until"]

TOP_Z = TABLE.top_z


@dataclass
class Trace:
    """What the console saw, in arrival order (guarded by `lock`)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    forces: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, world f_z up)
    force_norms: list[float] = field(default_factory=list)
    states: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, tool z)
    slave: list[PassivityState] = field(default_factory=list)
    master: list[PassivityState] = field(default_factory=list)
    puma_cmds: int = 0
    events: list[str] = field(default_factory=list)
    _R: np.ndarray = field(default_factory=lambda: np.eye(3))

    def on_state(self, s: RobotState) -> None:
        with self.lock:
            self._R = np.asarray(s.tool_R).reshape(3, 3)
            self.states.append((s.t_ns, float(s.tool_p[2])))

    def on_force(self, f: ForceSample) -> None:
        with self.lock:
            fw = self._R @ np.asarray(f.f, dtype=float)
            self.forces.append((f.t_ns, float(fw[2])))
            self.force_norms.append(float(np.linalg.norm(fw)))

    def on_passivity(self, m: PassivityState) -> None:
        with self.lock:
            (self.slave if m.side == "slave" else self.master).append(m)

    def on_event(self, e: Event) -> None:
        with self.lock:
            self.events.append(f"{e.source}/{e.kind}: {e.message[:80]}")

    def on_cmd(self, c: OperatorCommand) -> None:
        with self.lock:
            self.puma_cmds += 1

    def force_between(self, t0_ns: int, t1_ns: int) -> list[float]:
        with self.lock:
            ts = [t for t, _ in self.forces]
            i, j = bisect.bisect_left(ts, t0_ns), bisect.bisect_left(ts, t1_ns)
            return [f for _, f in self.forces[i:j]]

    def z_between(self, t0_ns: int, t1_ns: int) -> list[float]:
        with self.lock:
            return [z for t, z in self.states if t0_ns <= t < t1_ns]


@dataclass
class Loop:
    net: Net
    decision: DecisionService
    trace: Trace
    closers: list = field(default_factory=list)  # type: ignore[type-arg]
    master: MasterService | None = None
    t_start_ns: int = 0

    def close(self) -> None:
        for c in reversed(self.closers):
            c()


def build(net: Net, passivity: bool = True, start_gap_m: float = 0.04, **decision: float) -> Loop:
    """The robot side, the arm `start_gap_m` above the table, recording; no master yet."""
    puma = PumaService(
        net.node("puma"),
        PumaConfig(sim_calibration_s=0.05),
        arm=SimArm(HOME_Q_RAD, calibration_s=0.05),
    )
    force = ForceService(net.node("force"), ForceConfig(seed=7, period_ms=2.0))
    cfg = DecisionConfig(passivity=passivity, **decision)  # type: ignore[arg-type]
    dec = DecisionService(net.node("decision"), cfg)
    console = net.node("console")
    trace = Trace()
    loop = Loop(net, dec, trace, [puma.close, force.close, dec.close])
    console.subscribe(keys.STATE, trace.on_state)
    console.subscribe(keys.FORCE, trace.on_force)
    console.subscribe(keys.PASSIVITY_SLAVE, trace.on_passivity)
    console.subscribe(keys.PASSIVITY_MASTER, trace.on_passivity)
    console.subscribe(keys.PUMA_CMD, trace.on_cmd)
    console.subscribe(keys.EVENTS, trace.on_event)
    state = console.latest(keys.STATE)
    console.call("decision", "connect", {}, 5.0)
    console.call("decision", "initialize", {}, 5.0)

    def status() -> str:
        got = state.read()
        return "" if got is None else got[0].status

    assert wait_until(lambda: status() == "ready", 10.0)
    got = state.read()
    assert got is not None
    p = list(got[0].tool_p)
    p[2] = TOP_Z + start_gap_m
    console.call("decision", "move_pose", {"p": p, "R": list(got[0].tool_R), "wait": True}, 30.0)
    return loop


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
    """Peak |f| over the run; steady f and oscillation RMS over [hold_from, hold_to) after
    the master started; tool z range there; final energies of both ports."""
    t0 = loop.t_start_ns
    tr = loop.trace
    window = tr.force_between(t0 + int(hold_from_s * 1e9), t0 + int(hold_to_s * 1e9))
    steady = sum(window) / len(window) if window else 0.0
    rms = math.sqrt(sum((f - steady) ** 2 for f in window) / len(window)) if window else 0.0
    zs = tr.z_between(t0 + int(hold_from_s * 1e9), t0 + int(hold_to_s * 1e9))
    with tr.lock:
        slave = tr.slave[-1] if tr.slave else None
        master = tr.master[-1] if tr.master else None
        peak = max(tr.force_norms, default=0.0)
    out = {
        "peak_n": peak,
        "steady_n": steady,
        "rms_n": rms,
        "z_min_mm": 1e3 * (min(zs, default=math.nan) - TOP_Z),
        "z_max_mm": 1e3 * (max(zs, default=math.nan) - TOP_Z),
    }
    for name, m in (("slave", slave), ("master", master)):
        out[f"{name}_in_j"] = m.e_in if m else math.nan
        out[f"{name}_out_j"] = m.e_out if m else math.nan
        out[f"{name}_active"] = float(m.active_steps) if m else math.nan
    return out
