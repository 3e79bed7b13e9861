"""`telerobot bench passivity --link`: the contact task through the real services over a real
bad link, TDPA off and on.

The robot side (arm with the simulated arm, force with the simulated wrist at 500 Hz in the
simulated workcell, decision, a recording console) runs in one network namespace, the master
station with the simulated haptic operator (`device = "haptic_sim"`, 100 Hz) in another,
each a process of its own, Zenoh peers over TCP across `services.tools.tdpa.netem`'s link
(the kernel's netem, or the userspace delay line). The operator presses the gripper's
fingertips onto the MuJoCo table for 8 N, holds, releases. Per run the same measures as the
simulated bench (`services.tools.tdpa.sim_bench`), keys `passivity_<delay_ms>_<on|off>_<measure>`
in their own JSON, and one plot per delay. docs/passivity.md, "The whole loop over the link".

    python -m services.tools.tdpa.link_bench robot ENDPOINT PASSIVITY WATCHDOG_MS
    python -m services.tools.tdpa.link_bench operator ENDPOINT PASSIVITY RATE_HZ

are the two sides (`run_over_link` starts them): the robot side listens on ENDPOINT, puts
the arm `START_GAP_M` above the table and prints `ready`, then reads `start T_NS` (when the
operator began) and `stop` on its standard input and prints the run as one JSON line; the
operator side connects, prints `start T_NS`, runs the press–hold–release and prints its
port's figures as one JSON line.
"""

from __future__ import annotations

import bisect
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.messages import Event, ForceSample, MasterFeedback, PassivityState, RobotState
from services.bus.node import Node
from services.bus.peers import Clients, Peers
from services.control.arm.model import DEFAULT_MODEL
from services.control.decision.config import DecisionConfig
from services.control.master.config import MasterConfig
from services.control.master.haptic_sim import SimHapticMaster
from services.control.master.service import MasterService
from services.tools.cell.ports import free_port
from services.tools.cell.sim import LIGHT_FORCE, NodeFactory, SimCell, light_arm
from services.tools.cell.wait import wait_until
from services.tools.tdpa.loop import held, swing_rms, trend_n_s
from services.tools.tdpa.netem import ROBOT_IP, LinkShape, in_ns, netem_link, unavailable
from services.tools.tdpa.results import off_on_plot, put_measures
from services.tools.tdpa.transports import endpoint as link_endpoint
from services.tools.tdpa.transports import secure, write_tls_configs
from services.world.workcell.mujoco_model import PhysicsParams
from services.world.workcell.scene import TABLE, Scene

TOUCH_Z = TABLE.top_z + PhysicsParams().finger_length_m
"""The tool point's height when the gripper's fingertips touch the table (m)."""
TOUCH_BAND_M = 0.005
"""A force counts as the touch only with the tool point this close above `TOUCH_Z` (m)."""
FLOOR_BELOW_TOUCH_M = 0.005
"""The decision's workspace floor in the link bench: this far below the touch (m). The arm's
own box has its floor at the table top, where the tool point is; the fingertips reach 35 mm
below it, so there the guarded approach (`APPROACH_ZONE_M` above the floor) began 15 mm
under the touch and the operator's 7–8 cm/s met the table at full speed: 31–53 N at the
touch, the slave port overdrawn, the overdraw forgiven and the tool held clear of the table
for the rest of the run (0.0 N held, 2026-12-02). 5 mm below the touch is where the removed
probe touched above the old floor: the zone starts 15 mm above the touch again, and the
floor bounds the press at 5 mm × the cell's ≈ 5 kN/m, below the supervisor's limit."""

APPROACH_S, HOLD_S, RELEASE_S = 2.0, 8.0, 1.0
"""The operator's path: down over APPROACH_S, hold HOLD_S (`--hold-s`), up over RELEASE_S."""
DEPTH_M = 0.1
START_GAP_M = 0.04
MEASURE_S = 3.0
"""The hold is measured over its last MEASURE_S: "after settling". The simulated operator
presses until it feels 8 N, at 1 mm/s per newton short; with a passive display that shows
what the hand pushes with, that takes it some 5 s after the touch (measured in-process at
0 ms: the force's slope 2.0, 0.26, 0.12 N/s over 3–5, 5–7, 7–12 s). Before 2026-11-26 11:00
UTC the hold was 4 s, measured from 1 s after the approach: the operator's transient."""
CONTACT_N = 1.0
"""The touch: the first wrist force at or above this (the slave port's dead band)."""
LEASE_MS = 2000
"""The longest link lease the contract allows (PROTOCOL.md §5). The default 1 s does not
outlast a TCP retransmission at 700 ms round trip: the master's liveliness token lapses and
the decision holds (measured)."""
MODULE = "services.tools.tdpa.link_bench"
APPROACH_ZONE_M = 0.02
"""The decision's guarded approach (`approach_zone_m`) in the link bench: within 2 cm of
the floor the tool goes down at `APPROACH_SPEED_M_S` at most. Without it the
operator's 7–8 cm/s approach reaches the table at that speed and the arm's braking lets
the tool run 2–3 mm into the old 20 kN/m probe: a 60–100 N impact that overdraws the slave port
before any energy came from the master (docs/passivity.md). `--approach-zone 0`: off."""
APPROACH_SPEED_M_S = 0.005
"""The guarded approach's speed in the link bench (m/s; the decision's default 0.02 was set
against the removed 20 kN/m probe). On the MuJoCo table at 200 ms (2026-12-02, one run each,
the floor `FLOOR_BELOW_TOUCH_M` in place): 20 mm/s touched at 38 N, 10 mm/s at 23 N, both
overdrawing the slave port before the master had sent any energy; at 5 mm/s the first touch
rises to 1.5–2 N and holds (the contact's damping keeps an impact's energy, which the
workcell then never gives back)."""
MASTER_RATE_HZ = 500.0
"""The master station's loop rate over the link (`--master-rate-hz`): a haptic device's.
At 100 Hz the force limiter lets the display rise only while the hand sinks at
Ḟ·h²/(rise·m), 25 times faster than at 500 Hz, and the contact creeps on (docs/passivity.md)."""
CONTACT_DAMPING_NS_M = 250.0
"""The operator's master damps the hand in contact (`[master] contact_damping_ns_m`, N·s/m).
The MuJoCo table (≈ 5 kN/m with the arm's servo at the PUMA's tool) shown to the softly held
device (0.5 kg, 2 N·s/m; hand 300 N/m, 10 N·s/m) bounced at 0 ms with TDPA off: every
displayed newton lifts the hand 3.3 mm against a penetration of 0.2 mm, and the loop's own
delay (master tick, bus, decision, servo, sensor) needs about k·τ of damping, far above the
hand's 12 (docs/passivity.md, "On the MuJoCo cell")."""
QUIET_S = 0.5
"""The robot side measures once the master's figures have not arrived for this long."""
TWIST_RAD = 0.15
"""`--twist`: how far the operator turns the handle about the master's z once the press has
seated the tool (rad, over TWIST_S from TWIST_AFTER_S; `SimHapticMaster.twist_rad`), and on
until it feels 0.5 N·m."""
TWIST_AFTER_S, TWIST_S = APPROACH_S + 1.0, 1.5
TORSION_NM_RAD = 30.0
"""`--twist`: the contact's resistance to a turn about its normal (`[force]
torsion_nm_rad`), the simulated bench's stop (`loop.Twist`)."""

ZENOH_CONFIG_ENV = "TELEROBOT_LINK_ZENOH_CONFIG"
"""Over TLS or QUIC: each side's Zenoh file (the router's certificate, the client's CA),
handed to the two processes in their environment."""

YIELD_DEFAULT = DecisionConfig().passivity_yield_m_s_n
"""The decision's yield to the hand unless `--yield` says otherwise (docs/passivity.md)."""


def watchdog_ms(rtt_ms: float) -> float:
    """The decision's watchdogs over a lossy link. A lost TCP segment stalls the stream for
    a retransmission timeout (Linux: the smoothed round trip + 4 × its variation, at least
    200 ms) plus the one-way delay: a watchdog shorter than that holds the arm at every
    loss (at 700 ms with a 1 s watchdog, measured: the first loss lost the master). The
    master holds the last wrist force as long (`[master] force_stale_ms`): at 100 ms every
    such stall dropped the display to zero and back, the hand lunging in at each."""
    return 1000.0 + 2.0 * rtt_ms


@dataclass
class Trace:
    """What the console saw, in arrival order (guarded by `lock`)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    forces: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, world f_z up)
    force_norms: list[float] = field(default_factory=list)
    states: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, tool z)
    slave: list[PassivityState] = field(default_factory=list)
    master: list[PassivityState] = field(default_factory=list)
    felt: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, shown f_z up)
    moments: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, world c_z)
    felt_moments: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, shown c_z)
    uplink: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, ms on the way)
    targets: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, target z sent)
    tangential: list[tuple[int, float]] = field(default_factory=list)  # (t_ns, world |f_xy|)
    arm_cmds: int = 0
    events: list[tuple[float, str]] = field(default_factory=list)  # (arrival, monotonic s; text)
    master_rx_s: float = 0.0
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
            self.tangential.append((f.t_ns, float(math.hypot(fw[0], fw[1]))))
            self.moments.append((f.t_ns, float((self._R @ np.asarray(f.c, dtype=float))[2])))

    def on_passivity(self, m: PassivityState) -> None:
        with self.lock:
            (self.slave if m.side == "slave" else self.master).append(m)
            if m.side == "master":
                self.master_rx_s = time.monotonic()
                # One clock for both namespaces: the master's figures' time on the way.
                self.uplink.append((m.t_ns, (time.time_ns() - m.t_ns) / 1e6))

    def on_feedback(self, m: MasterFeedback) -> None:
        """The force the master displayed on the hand (master frame: its z is the press)."""
        with self.lock:
            self.felt.append((m.t_ns, float(m.f[2])))
            self.felt_moments.append((m.t_ns, float(m.c[2])))

    def master_quiet_s(self) -> float:
        """Seconds since the master's last passivity figures arrived (inf: none yet)."""
        with self.lock:
            return time.monotonic() - self.master_rx_s if self.master_rx_s else math.inf

    def on_event(self, e: Event) -> None:
        with self.lock:
            self.events.append((time.monotonic(), f"{e.source}/{e.kind}: {e.message[:80]}"))

    def events_split(self) -> tuple[list[str], list[str]]:
        """The events up to the master's last figures (the run), and after them: the
        operator's end (its liveliness lost, the decision holding), not the run's."""
        with self.lock:
            end = self.master_rx_s or math.inf
            return (
                [text for t, text in self.events if t <= end],
                [text for t, text in self.events if t > end],
            )

    def on_cmd(self, m: object) -> None:
        with self.lock:
            self.arm_cmds += 1
            p, t_ns = getattr(m, "p", None), getattr(m, "t_ns", None)
            if p is not None and t_ns is not None and not getattr(m, "hold", False):
                self.targets.append((int(t_ns), float(p[2])))

    def force_between(self, t0_ns: int, t1_ns: int) -> list[tuple[int, float]]:
        """(t_ns, world f_z) of the forces received in [t0_ns, t1_ns)."""
        with self.lock:
            ts = [t for t, _ in self.forces]
            i, j = bisect.bisect_left(ts, t0_ns), bisect.bisect_left(ts, t1_ns)
            return self.forces[i:j]

    def z_between(self, t0_ns: int, t1_ns: int) -> list[float]:
        with self.lock:
            return [z for t, z in self.states if t0_ns <= t < t1_ns]

    def touch(self, since_ns: int = 0) -> tuple[int, float] | None:
        """(t_ns, tool z) of the first force at or above CONTACT_N from `since_ns` on (the
        operator's start) with the tool point within TOUCH_BAND_M of the touch height, or
        None: the arm's own moves before the start, and the tool's inertia on the wrist
        in the air (1–5 N where the link delivers the commands in bursts), reach 1 N too
        (the penetration read 30–190 mm)."""
        with self.lock:
            if not self.states:
                return None
            ts = [s for s, _ in self.states]
            for t, f in self.forces:
                if t < since_ns or abs(f) < CONTACT_N:
                    continue
                z = self.states[min(bisect.bisect_left(ts, t), len(ts) - 1)][1]
                if z <= TOUCH_Z + TOUCH_BAND_M:
                    return t, z
            return None


def build_robot(
    node: NodeFactory,
    passivity: bool = True,
    start_gap_m: float = START_GAP_M,
    torsion_nm_rad: float = 0.0,
    model: str = DEFAULT_MODEL,
    **decision: float,
) -> tuple[SimCell, Trace]:
    """The cell layer's `SimCell` (the sim arm `model` on the workcell's physics, `light_arm`; the
    MuJoCo cell of the table: the contact, and its friction resisting a turn, are its
    solver's; the sim wrist, 500 Hz, `LIGHT_FORCE`; the decision with `passivity` and the
    `decision` settings) and a recording console, each on a node from `node(name,
    instance)`; the arm connected, initialized and moved through the decision server to
    `start_gap_m` above the touch (the gripper's fingertips on the table), the decision's
    workspace floor `FLOOR_BELOW_TOUCH_M` below the touch (unless `decision` sets it).
    Returns the cell (closed by the caller) and the trace. `torsion_nm_rad` is kept for the
    command line's `--twist`; the cell's friction is what resists the turn."""
    del torsion_nm_rad
    box = DecisionConfig()
    floor = (*box.workspace_min[:2], TOUCH_Z - FLOOR_BELOW_TOUCH_M)
    settings: dict[str, Any] = {
        "workspace_from_arm": False,
        "workspace_min": floor,
        "approach_speed_m_s": APPROACH_SPEED_M_S,
    } | decision
    cell = SimCell(
        node,
        arm=light_arm(model),
        force=LIGHT_FORCE,
        decision=DecisionConfig(passivity=passivity, **settings),
        scene=Scene(boxes=(TABLE,)),
    )
    try:
        console = node("console", None)
        trace = Trace()
        console.subscribe(keys.STATE, trace.on_state)
        console.subscribe(keys.FORCE, trace.on_force)
        console.subscribe(keys.PASSIVITY_SLAVE, trace.on_passivity)
        console.subscribe(keys.PASSIVITY_MASTER, trace.on_passivity)
        console.subscribe(keys.MASTER_FEEDBACK, trace.on_feedback)
        console.subscribe(keys.ARM_TARGET, trace.on_cmd)
        console.subscribe(keys.EVENTS, trace.on_event)
        state = console.latest(keys.STATE)
        console.call("decision", "connect", {}, 5.0)
        console.call("decision", "initialize", {}, 5.0)

        def status() -> str:
            got = state.read()
            return "" if got is None else got[0].status

        if not wait_until(lambda: status() == "ready", 10.0):
            raise RuntimeError(f"the arm did not become ready (status {status()!r})")
        got = state.read()
        assert got is not None
        p = list(got[0].tool_p)
        p[2] = TOUCH_Z + start_gap_m
        console.call(
            "decision", "move_pose", {"p": p, "R": list(got[0].tool_R), "wait": True}, 30.0
        )
    except BaseException:
        cell.close()
        raise
    return cell, trace


def metrics(
    trace: Trace, t_start_ns: int, hold_from_s: float, hold_to_s: float
) -> dict[str, float]:
    """Peak |f| over the run; steady f, the mean force felt (shown on the hand,
    `master/feedback`), oscillation RMS, swing (`swing_rms`), whether the contact `held`
    and creep (N/s, `trend_n_s`) over [hold_from, hold_to) after the master started; tool
    z range there (mm above the table top);
    penetration (mm below the tool's height at the touch, over the whole run); final
    energies of both ports."""
    t0 = t_start_ns
    lo_ns, hi_ns = t0 + int(hold_from_s * 1e9), t0 + int(hold_to_s * 1e9)
    points = [((t - t0) / 1e9, f) for t, f in trace.force_between(lo_ns, hi_ns)]
    window = [f for _, f in points]
    steady = sum(window) / len(window) if window else 0.0
    rms = math.sqrt(sum((f - steady) ** 2 for f in window) / len(window)) if window else 0.0
    zs = trace.z_between(lo_ns, hi_ns)
    touch = trace.touch(t0)
    with trace.lock:
        felt = [f for t, f in trace.felt if lo_ns <= t < hi_ns]
        slave = trace.slave[-1] if trace.slave else None
        master = trace.master[-1] if trace.master else None
        peak = max(trace.force_norms, default=0.0)
        z_all = [z for t, z in trace.states if touch is not None and t >= touch[0]]
    top = TOUCH_Z  # the z range is the tool point's above the touch
    out = {
        "peak_n": peak,
        "steady_n": steady,
        "felt_n": sum(felt) / len(felt) if felt else 0.0,
        "rms_n": rms,
        "swing_n": swing_rms(window),
        "held": held(window, steady),
        "creep_n_s": trend_n_s(points),
        "z_min_mm": 1e3 * (min(zs, default=math.nan) - top),
        "z_max_mm": 1e3 * (max(zs, default=math.nan) - top),
        "penetration_mm": (
            1e3 * max(touch[1] - min(z_all, default=touch[1]), 0.0) if touch else math.nan
        ),
    }
    with trace.lock:
        moments = [((t - t0) / 1e9, c) for t, c in trace.moments if lo_ns <= t < hi_ns]
        felt_c = [c for t, c in trace.felt_moments if lo_ns <= t < hi_ns]
        peak_c = max((abs(c) for _, c in trace.moments), default=0.0)
    # Against the turn: each with the sign it holds over the window (its median's; the
    # moment at the tool about the world's z, the one shown about the hand's).
    sign, felt_sign = _median_sign([c for _, c in moments]), _median_sign(felt_c)
    cw = [sign * c for _, c in moments]
    c_steady = sum(cw) / len(cw) if cw else 0.0
    out |= {
        "moment_peak_nm": peak_c,
        "moment_steady_nm": c_steady,
        "moment_felt_nm": felt_sign * sum(felt_c) / len(felt_c) if felt_c else 0.0,
        "moment_rms_nm": (math.sqrt(sum((c - c_steady) ** 2 for c in cw) / len(cw)) if cw else 0.0),
        "moment_swing_nm": swing_rms(cw),
        "moment_held": held(cw, c_steady),
        "moment_creep_nm_s": trend_n_s([(t, sign * c) for t, c in moments]),
    }
    with trace.lock:
        rtts = {
            side: sorted(x.rtt_ms for x in seen if x.rtt_ms is not None and lo_ns <= x.t_ns < hi_ns)
            for side, seen in (("slave", trace.slave), ("master", trace.master))
        }
        up = sorted(ms for t, ms in trace.uplink if lo_ns <= t < hi_ns)
    for side, xs in rtts.items():
        # The round trip each port measured from the other's echoes, over the window.
        out[f"{side}_rtt_ms"] = xs[len(xs) // 2] if xs else math.nan
    # The master's figures from its put to the robot side (median, p90): the link's one
    # way and what queued ahead of them.
    out["uplink_ms"] = up[len(up) // 2] if up else math.nan
    out["uplink_p90_ms"] = up[int(len(up) * 0.9)] if up else math.nan
    for name, m in (("slave", slave), ("master", master)):
        out[f"{name}_in_j"] = m.e_in if m else math.nan
        out[f"{name}_out_j"] = m.e_out if m else math.nan
        out[f"{name}_dissipated_j"] = m.dissipated_j if m else math.nan
        out[f"{name}_active"] = float(m.active_steps) if m else math.nan
        rot_in = m.rot_e_in if m is not None else None
        rot_out = m.rot_e_out if m is not None else None
        out[f"{name}_rot_in_j"] = rot_in if rot_in is not None else math.nan
        out[f"{name}_rot_out_j"] = rot_out if rot_out is not None else math.nan
    return out


def _median_sign(xs: list[float]) -> float:
    """−1 if the median of `xs` is negative, else 1."""
    ordered = sorted(xs)
    return -1.0 if ordered and ordered[len(ordered) // 2] < 0.0 else 1.0


class RouterSide(Clients):
    """Over UDP, TLS or QUIC: a router listens on the link's `endpoint` (and on loopback),
    the robot's services are its clients on loopback, so the operator's one session to the
    robot host is the one over the link (peers would also open direct TCP sessions to each
    other's listeners). `zenoh_config`: the router's TLS block (TLS and QUIC)."""

    def __init__(self, endpoint: str, zenoh_config: str = "") -> None:
        from services.bus.router import open_router

        local = f"tcp/127.0.0.1:{free_port()}"
        self.router = open_router(
            NodeConfig(
                mode="router",
                listen=(endpoint, local),
                lease_ms=LEASE_MS,
                zenoh_config=zenoh_config,
            )
        )
        super().__init__(local, NodeConfig(lease_ms=LEASE_MS))

    def close(self) -> None:
        super().close()
        self.router.close()


def robot(
    endpoint: str,
    passivity: bool,
    watchdog: float,
    zone_m: float,
    hold_s: float,
    yield_m_s_n: float = YIELD_DEFAULT,
    torsion_nm_rad: float = 0.0,
    model: str = DEFAULT_MODEL,
) -> None:
    peers: Peers | RouterSide = (
        RouterSide(endpoint, os.environ.get(ZENOH_CONFIG_ENV, ""))
        if not endpoint.startswith("tcp/")
        else Peers(endpoint, NodeConfig(lease_ms=LEASE_MS))
    )
    cell: SimCell | None = None
    try:
        cell, trace = build_robot(
            peers.node,
            passivity=passivity,
            watchdog_ms=watchdog,
            state_stale_ms=watchdog,
            torsion_nm_rad=torsion_nm_rad,
            model=model,
            approach_zone_m=zone_m,
            passivity_yield_m_s_n=yield_m_s_n,
        )
        print("ready", flush=True)
        start = sys.stdin.readline().split()
        if not start or start[0] != "start":
            raise SystemExit(f"expected `start T_NS`, got {start[:2]!r}")
        t0 = int(start[1])
        stop = sys.stdin.readline().split()
        if not stop or stop[0] != "stop":
            raise SystemExit(f"expected `stop`, got {stop[:1]!r}")
        # The operator has ended; its last figures may still be on the link (one-way delay,
        # a retransmission): measure once they have stopped coming.
        wait_until(lambda: trace.master_quiet_s() > QUIET_S, watchdog / 1e3 + 2.0)
        m = metrics(trace, t0, APPROACH_S + max(hold_s - MEASURE_S, 0.0), APPROACH_S + hold_s)
        tdpa = cell.decision.passivity
        if tdpa is not None:
            m["slave_recovered_j"] = tdpa.pc.recovered_j
            m["slave_clipped_j"] = tdpa.pc.clipped_j
            m["slave_excluded_j"] = tdpa.pc.excluded_j
            m["slave_forgiven_j"] = tdpa.pc.forgiven_j
            m["slave_yielded_mm"] = tdpa.pc.yielded_m * 1e3
            if tdpa.rot is not None:
                m["slave_rot_recovered_j"] = tdpa.rot.recovered_j
        events, after = trace.events_split()
        with trace.lock:
            m["arm_cmds"] = float(trace.arm_cmds)
            series = [((t - t0) / 1e9, f) for t, f in trace.forces if t >= t0]
            turn = [((t - t0) / 1e9, c) for t, c in trace.moments if t >= t0]
            heights = [((t - t0) / 1e9, z - TOUCH_Z) for t, z in trace.states if t >= t0]
            shown = [((t - t0) / 1e9, f) for t, f in trace.felt if t >= t0]
            sent = [((t - t0) / 1e9, z - TOUCH_Z) for t, z in trace.targets if t >= t0]
            side = [((t - t0) / 1e9, f) for t, f in trace.tangential if t >= t0]
        doc = {
            "metrics": m,
            "events": events[-20:],
            "events_after": after[-5:],
            "force": series[::2],
            "z": heights[::2],
            "felt": shown[::2],
            "target": sent[::2],
            "tangential": side[::2],
        }
        if torsion_nm_rad > 0.0:
            doc["moment"] = turn[::2]
        print(json.dumps(doc), flush=True)
    finally:
        if cell is not None:
            cell.close()
        peers.close()


def operator(
    endpoint: str,
    passivity: bool,
    rate_hz: float,
    stale_ms: float,
    hold_s: float,
    twist_rad: float = 0.0,
    tangential_gain: float = 1.0,
) -> None:
    routed = not endpoint.startswith("tcp/")  # a client of the robot host's router: RouterSide
    cfg = NodeConfig(
        mode="client" if routed else "peer",
        connect=(endpoint,),
        lease_ms=LEASE_MS,
        zenoh_config=os.environ.get(ZENOH_CONFIG_ENV, ""),
    )
    node = Node("master", cfg, instance="op")
    try:
        if not node.alive.wait("decision", 30.0):
            raise SystemExit(f"no decision server over the link (alive: {node.alive.names()})")
        mcfg = MasterConfig(
            master_id="op",
            device="haptic_sim",
            passivity=passivity,
            rate_hz=rate_hz,
            force_stale_ms=stale_ms,
            passivity_moments=twist_rad != 0.0,
            contact_damping_ns_m=CONTACT_DAMPING_NS_M,
            contact_tangential_gain=tangential_gain,
        )
        device = SimHapticMaster(
            depth_m=DEPTH_M,
            approach_s=APPROACH_S,
            hold_s=hold_s,
            release_s=RELEASE_S,
            twist_rad=twist_rad,
            twist_after_s=TWIST_AFTER_S,
            twist_s=TWIST_S,
        )
        t0 = time.time_ns()
        station = MasterService(node, mcfg, device=device)
        print(f"start {t0}", flush=True)
        try:
            end = t0 + int((APPROACH_S + hold_s + RELEASE_S + 0.5) * 1e9)
            wait_until(lambda: time.time_ns() >= end, APPROACH_S + hold_s + RELEASE_S + 5.0)
            out: dict[str, float] = {"master_ticks": float(station.ticks)}
            tdpa = station.passivity
            if tdpa is not None:
                out |= {
                    "master_in_j": tdpa.pc.observer.e_in,
                    "master_out_j": tdpa.pc.observer.e_out,
                    "slave_in_seen_j": tdpa.pc.remote.e_in,
                }
                if tdpa.rot is not None:
                    out |= {
                        "master_rot_in_j": tdpa.rot.observer.e_in,
                        "master_rot_out_j": tdpa.rot.observer.e_out,
                        "slave_rot_in_seen_j": tdpa.rot.remote.e_in,
                        "master_rot_limited": float(tdpa.rot.limited_steps),
                    }
            print(json.dumps(out), flush=True)
        finally:
            station.close()
    finally:
        node.close()


def run_over_link(
    rtt_ms: float,
    passivity: bool,
    jitter: float = 0.1,
    loss: float = 0.01,
    rate_hz: float = MASTER_RATE_HZ,
    transport: str = "tcp",
    approach_zone_m: float = APPROACH_ZONE_M,
    rate_mbit: float = 0.0,
    hold_s: float = HOLD_S,
    yield_m_s_n: float = YIELD_DEFAULT,
    twist: bool = False,
    model: str = DEFAULT_MODEL,
    tangential_gain: float = 1.0,
) -> dict[str, Any]:
    """One press–hold–release of arm `model` over a fresh link (with `twist`, a turn
    against the contact too: `TWIST_RAD`; the master showing the contact's friction ×
    `tangential_gain`, its `contact_tangential_gain`) (`rate_mbit` > 0: its bandwidth each
    way, a link the streams can saturate; the hold `hold_s` long; `yield_m_s_n`: the decision's
    `passivity_yield_m_s_n`): the robot side's metrics, the operator's own figures (keys
    `op_…`), the link's emulator, the last events and the series, each (s since the
    operator started, value): `force` (world f_z), `z` (the tool point above the touch, m),
    `target` (the target z the decision sent, above the touch, m), `tangential` (the
    world force's size across z, N) and `felt` (the force
    shown on the hand, N, the master's z). Raises RuntimeError when the link cannot be made
    (`unavailable()` says why beforehand) or a side fails."""
    endpoint = link_endpoint(transport, ROBOT_IP, free_port())
    env_robot, env_op = dict(os.environ), dict(os.environ)
    certs = tempfile.TemporaryDirectory(prefix="passivity-link-")
    if secure(transport):  # the cell's CA and the router's certificate for ROBOT_IP
        router_cfg, client_cfg = write_tls_configs(Path(certs.name), ROBOT_IP)
        env_robot[ZENOH_CONFIG_ENV], env_op[ZENOH_CONFIG_ENV] = str(router_cfg), str(client_cfg)
    flag = "1" if passivity else "0"
    wd = str(watchdog_ms(rtt_ms))
    shape = LinkShape(round_trip_ms=rtt_ms, jitter=jitter, loss=loss, rate_mbit=rate_mbit)
    with netem_link(shape) as link:
        with subprocess.Popen(
            in_ns(
                link.robot,
                sys.executable,
                "-m",
                MODULE,
                "robot",
                endpoint,
                flag,
                wd,
                str(approach_zone_m),
                str(hold_s),
                str(yield_m_s_n),
                str(TORSION_NM_RAD if twist else 0.0),
                model,
            ),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env_robot,
        ) as robot_side:
            try:
                assert robot_side.stdout is not None
                ready = robot_side.stdout.readline().strip()
                if ready != "ready":
                    raise RuntimeError(f"robot side did not start: {ready[:200]!r}")
                op = subprocess.run(
                    in_ns(
                        link.operator,
                        sys.executable,
                        "-m",
                        MODULE,
                        "operator",
                        endpoint,
                        flag,
                        str(rate_hz),
                        wd,
                        str(hold_s),
                        str(TWIST_RAD if twist else 0.0),
                        str(tangential_gain),
                    ),
                    capture_output=True,
                    text=True,
                    timeout=90 + hold_s,
                    check=False,
                    env=env_op,
                )
                if op.returncode != 0:
                    raise RuntimeError(f"operator side failed: {op.stderr[-1500:]}")
                lines = op.stdout.strip().splitlines()
                start = next(x for x in lines if x.startswith("start "))
                op_figures = json.loads(lines[-1])
                got, err = robot_side.communicate(f"{start}\nstop\n", timeout=60)
                if robot_side.returncode != 0:
                    raise RuntimeError(f"robot side failed: {err[-1500:]}")
                out = json.loads(got.strip().splitlines()[-1])
            finally:
                if robot_side.poll() is None:
                    robot_side.kill()
        emulator = link.emulator
    certs.cleanup()
    m: dict[str, Any] = dict(out["metrics"])
    m |= {f"op_{k}": v for k, v in op_figures.items()}
    m |= {"rtt_ms": rtt_ms, "passivity": passivity, "rate_hz": rate_hz, "hold_s": hold_s}
    m |= {"load1": os.getloadavg()[0], "emulator": emulator, "transport": transport}
    m["approach_zone_m"], m["rate_mbit"] = approach_zone_m, rate_mbit
    m["yield_m_s_n"] = yield_m_s_n
    m["twist"] = twist
    m["model"] = model
    m["tangential_gain"] = tangential_gain
    m["events"] = out["events"]
    m["events_after"] = out.get("events_after", [])
    m["force"] = out["force"]
    for key in ("z", "felt", "target", "tangential"):
        m[key] = out[key]
    if "moment" in out:
        m["moment"] = out["moment"]
    return m


SUPERVISOR_LIMIT_N = DecisionConfig().max_force_n
"""The decision's contact filter (40 N): a force resting at 95 % of it or above is the
supervisor holding the tool against its limit, not a contact the loop settled: not stable,
however calm (one run without TDPA at 700 ms, 2026-11-26, rested at 42 N, RMS 0.02 N)."""


def model_line(doc: dict[str, Any]) -> str:
    """What `--link`'s table is of, in one paragraph (the simulated loop's is
    `sim_bench.model_line`)."""
    st = doc["settings"]
    return (
        "Model: the real services over a real link — the robot side (the arm "
        f"({st.get('model', DEFAULT_MODEL)}) on the MuJoCo cell, the force service, the "
        "decision with the guarded approach of "
        f"{st.get('approach_zone_m')} m) and the master station (a simulated 0.5 kg device "
        f"held by a simulated hand, {st.get('master_rate_hz'):g} Hz, contact damping "
        f"{st.get('contact_damping_ns_m'):g} N·s/m, the contact's friction shown × "
        f"{st.get('tangential_gain', 1.0):g}) in two network namespaces joined by "
        f"{st.get('emulator', 'the link')} over {st.get('transport')}; round trips "
        f"{st.get('delays_ms')} ms, jitter {st.get('jitter')}, loss {st.get('loss')}; the "
        f"fingertips pressed onto the table, {st.get('hold_s'):g} s hold measured over its last "
        f"{st.get('measured_s'):g} s (docs/passivity.md). Forces in N along the world's z."
    )


def bench_measures(m: dict[str, Any]) -> dict[str, float | bool]:
    """The simulated bench's measures (`passivity.MEASURES`) from one run over the link.
    energy_generated_j: the channel's output beyond its input at the end, counting what the
    workcell gave back to repay an impact as input (0 with TDPA off: nothing observed).
    stable: the contact held through the window (`held`) and a swing (`swing_rms`: RMS
    about the best monotone fit) below 10 % of a steady force above 1 N and below 95 % of
    the supervisor's contact limit (`SUPERVISOR_LIMIT_N`); settled: an RMS about the mean
    below 10 % of such a force (a step inside the window counts)."""
    steady, rms, swing = float(m["steady_n"]), float(m["rms_n"]), float(m["swing_n"])
    resting = 1.0 < steady < 0.95 * SUPERVISOR_LIMIT_N
    nan = math.nan
    if m["passivity"]:
        out_j = m["master_out_j"] + m["slave_out_j"]
        in_j = m["master_in_j"] + m["slave_in_j"] + m.get("slave_recovered_j", 0.0)
        generated = max(out_j - in_j, 0.0)
    else:
        generated = nan
    return {
        "peak_force_n": float(m["peak_n"]),
        "steady_force_n": steady,
        "felt_force_n": float(m.get("felt_n", nan)),
        "oscillation_rms_n": rms,
        "swing_rms_n": swing,
        "creep_n_s": float(m.get("creep_n_s", nan)),
        "penetration_mm": float(m["penetration_mm"]),
        "energy_generated_j": generated,
        "master_dissipated_j": float(m.get("master_dissipated_j", nan)),
        "slave_dissipated_j": float(m.get("slave_dissipated_j", nan)),
        "stable": resting and bool(m["held"]) and swing < 0.1 * steady,
        "settled": resting and rms < 0.1 * steady,
    }


def moment_measures(m: dict[str, Any]) -> dict[str, float | bool]:
    """`bench_measures` of the turn's moment (`--twist`; N·m for N, no penetration): the
    energy balance counts both ports; stable: the contact held and a swing below 10 % of
    a steady moment above 0.1 N·m (the rotational port's dead band)."""
    steady, rms = float(m["moment_steady_nm"]), float(m["moment_rms_nm"])
    swing = float(m["moment_swing_nm"])
    resting = steady > 0.1
    nan = math.nan
    if m["passivity"]:
        out_j = sum(float(m.get(k, 0.0)) for k in ("master_rot_out_j", "slave_rot_out_j"))
        in_j = sum(float(m.get(k, 0.0)) for k in ("master_rot_in_j", "slave_rot_in_j"))
        in_j += float(m.get("slave_rot_recovered_j", 0.0))
        generated = max(out_j - in_j, 0.0) if math.isfinite(out_j - in_j) else nan
    else:
        generated = nan
    return {
        "peak_force_n": float(m["moment_peak_nm"]),
        "steady_force_n": steady,
        "felt_force_n": float(m["moment_felt_nm"]),
        "oscillation_rms_n": rms,
        "swing_rms_n": swing,
        "creep_n_s": float(m["moment_creep_nm_s"]),
        "penetration_mm": nan,
        "energy_generated_j": generated,
        "master_dissipated_j": nan,
        "slave_dissipated_j": nan,
        "stable": resting and bool(m["moment_held"]) and swing < 0.1 * steady,
        "settled": resting and rms < 0.1 * steady,
    }


def run_matrix(
    delays_ms: tuple[int, ...],
    jitter: float,
    loss: float,
    say: Callable[[str], None] = print,
    transport: str = "tcp",
    approach_zone_m: float = APPROACH_ZONE_M,
    rate_mbit: float = 0.0,
    master_rate_hz: float = MASTER_RATE_HZ,
    hold_s: float = HOLD_S,
    yield_m_s_n: float = YIELD_DEFAULT,
    twist: bool = False,
    model: str = DEFAULT_MODEL,
    tangential_gain: float = 1.0,
) -> tuple[dict[str, Any], dict[tuple[int, bool], dict[str, Any]]]:
    """Every delay, TDPA off then on, over a fresh link each: (the JSON document with the
    simulated bench's keys, the runs). `twist`: the turn too, its moment under
    `passivity_<delay>_<on|off>_moment_<measure>`."""
    doc: dict[str, Any] = {
        "settings": {
            "delays_ms": list(delays_ms),
            "jitter": jitter,
            "loss": loss,
            "link": "real services over network namespaces",
            "transport": transport,
            "approach_zone_m": approach_zone_m,
            "rate_mbit": rate_mbit,
            "master_rate_hz": master_rate_hz,
            "hold_s": hold_s,
            "measured_s": min(MEASURE_S, hold_s),
            "yield_m_s_n": yield_m_s_n,
            "contact_damping_ns_m": CONTACT_DAMPING_NS_M,
            "twist": twist,
            "model": model,
            "tangential_gain": tangential_gain,
        },
    }
    runs: dict[tuple[int, bool], dict[str, Any]] = {}
    for delay in delays_ms:
        for on in (False, True):
            say(f"  {delay} ms, TDPA {'on' if on else 'off'} …")
            m = run_over_link(
                float(delay),
                on,
                jitter,
                loss,
                transport=transport,
                approach_zone_m=approach_zone_m,
                rate_mbit=rate_mbit,
                rate_hz=master_rate_hz,
                hold_s=hold_s,
                yield_m_s_n=yield_m_s_n,
                twist=twist,
                model=model,
                tangential_gain=tangential_gain,
            )
            runs[(delay, on)] = m
            if on:
                say(
                    f"    round trip measured by the ports: decision {m['slave_rtt_ms']:.1f} ms, "
                    f"master {m['master_rtt_ms']:.1f} ms; the master's figures on the way "
                    f"{m['uplink_ms']:.1f} ms (p90 {m['uplink_p90_ms']:.1f})"
                )
            doc["settings"]["emulator"] = m["emulator"]
            parts = [("", bench_measures(m))]
            if twist:
                parts.append(("moment_", moment_measures(m)))
            # Not measured (TDPA off: no energies) is null, not NaN.
            put_measures(doc, delay, on, parts)
    # What happened in each run, for when a figure needs explaining: the last events the
    # console saw (interventions, holds, the arm's motions) and the slave port's figures.
    doc["runs"] = {
        f"{delay}_{'on' if on else 'off'}": {
            "events": list(m.get("events", []))[-20:],
            "arm_cmds": m.get("arm_cmds"),
            "slave_recovered_j": m.get("slave_recovered_j"),
            "slave_excluded_j": m.get("slave_excluded_j"),
            "slave_forgiven_j": m.get("slave_forgiven_j"),
            "slave_yielded_mm": m.get("slave_yielded_mm"),
            "master_out_j": m.get("op_master_out_j"),
            "master_in_j": m.get("op_master_in_j"),
            "measured_rtt_ms": {
                side: None if math.isnan(m.get(f"{key}_rtt_ms", math.nan)) else m[f"{key}_rtt_ms"]
                for side, key in (("decision", "slave"), ("master", "master"))
            },
            "rotation": {
                k: m.get(k)
                for k in (
                    "op_master_rot_in_j",
                    "op_master_rot_out_j",
                    "op_slave_rot_in_seen_j",
                    "op_master_rot_limited",
                    "slave_rot_in_j",
                    "slave_rot_out_j",
                    "slave_rot_recovered_j",
                )
                if k in m
            },
            "load1": m.get("load1"),
        }
        for (delay, on), m in runs.items()
    }
    doc["load1_end"] = round(os.getloadavg()[0], 2)
    return doc, runs


def plots(runs: dict[tuple[int, bool], dict[str, Any]], out_dir: Path) -> list[Path]:
    """One PNG per delay: the wrist force (world z, up) against time, TDPA off and on;
    with the turn (`--twist`), one of the moment at the tool (its size) too."""
    paths = []
    for delay in sorted({d for d, _ in runs}):
        transport = str(runs[(delay, True)].get("transport", "tcp")).upper()
        kinds = [("force", "wrist force", 120.0, "force (N)", "")]
        if all("moment" in runs[(delay, on)] for on in (False, True)):
            kinds.append(("moment", "moment at the tool (size)", 3.0, "moment (N·m)", "_moment"))
        for key, what, clip, y_label, suffix in kinds:
            curves = {}
            for on in (False, True):
                pts = runs[(delay, on)][key]
                ys = [p[1] if key == "force" else abs(p[1]) for p in pts]
                curves[on] = ([p[0] for p in pts], ys)
            paths.append(
                off_on_plot(
                    curves,
                    f"{what} over the link, {delay} ms round trip (real services, {transport})",
                    "time since the operator started (s)",
                    clip,
                    out_dir / f"passivity_link_{delay}ms{suffix}.png",
                    y_label,
                )
            )
    return paths


def main(argv: list[str]) -> None:
    role, endpoint, passivity = argv[0], argv[1], argv[2] == "1"
    if role == "robot":
        robot(
            endpoint,
            passivity,
            float(argv[3]),
            float(argv[4]),
            float(argv[5]),
            float(argv[6]),
            float(argv[7]) if len(argv) > 7 else 0.0,
            argv[8] if len(argv) > 8 else DEFAULT_MODEL,
        )
    elif role == "operator":
        operator(
            endpoint,
            passivity,
            float(argv[3]),
            float(argv[4]),
            float(argv[5]),
            float(argv[6]) if len(argv) > 6 else 0.0,
            float(argv[7]) if len(argv) > 7 else 1.0,
        )
    else:
        raise SystemExit(f"unknown role {role!r}")


if __name__ == "__main__":
    main(sys.argv[1:])


__all__ = [
    "bench_measures",
    "build_robot",
    "metrics",
    "plots",
    "run_matrix",
    "run_over_link",
    "unavailable",
]
