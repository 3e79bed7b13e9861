"""The bench's output: the comparison figures, the JSON document and the text table.

Every figure is read from the run's measured `phases` (see `services.tools.bench.run`); the only
constants are the paper's own figures (§3, quoted in `PAPER`) which the table sets beside
ours. A figure that misses the paper's is flagged `MISSES` in the table and listed after it.
"""

from __future__ import annotations

import importlib.metadata
import math
import os
import platform
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

SCHEMA = "telerobot-bench/2"

#: The paper's §3 figures (2.0 GHz P-IV server, 100 Mbps LAN, .NET Remoting).
PAPER: dict[str, float] = {
    "force_alone_hz": 1000.0,  # "streaming only force packets is about 1 KHz"
    "force_with_video_hz": 250.0,  # "Multi-streaming of Force and video … 250 Hz"
    "force_active_video_hz": 76.0,  # "… which drops to 76 Hz during active video intervals"
    # "a throughput of 58.94 ms per stereo frame rate (17 fps)", 288×360×3 B per picture:
    # the measured period, 16.97 fps, which the paper rounds to 17.
    "stereo_fps": 1000.0 / 58.94,
    "stereo_frame_ms": 58.94,
    "command_rate_hz": 50.0,  # "50 Hz for operator commands"
    "command_round_trip_ms": 1.0,  # "a command takes … around 1 ms in our case"
}
PAPER_SIZE = (360, 288)
"""The paper's "288×360 pixels" per picture, rows × columns: 360 px wide, 288 high — half a
PAL frame (720×576), the capture cards of the time. Either reading gives its 0.6 MB pair."""

#: Issue 16's "Done when" (on a quiet machine, through the router, separate processes).
TARGETS: dict[str, float] = {
    "idle_core_pct": 25.0,  # router + arm + force + decision, % of one core
    "idle_sim_pct": 60.0,  # the whole sim system without a browser
    "force_alone_hz": 995.0,
    "force_alone_lost": 0.0,
    "force_alone_p99_ms": 0.5,
    "force_in_flight_vga_hz": 990.0,  # while a VGA pair is in flight
    "force_vga_p99_ms": 1.0,  # with VGA stereo at 30 fps
    "cmd_1khz_reach_hz": 990.0,
    "cmd_1khz_arm_p50_ms": 0.5,
    "cmd_1khz_setpoint_p50_ms": 1.0,
    "cmd_1khz_setpoint_p99_ms": 3.0,
    "arm_status_p50_ms": 0.4,
    "decision_status_p50_ms": 1.0,
    "ik_per_s": 20_000.0,  # all 8 analytic branches per pose
    "ik_numerical_per_s": 5_000.0,  # the FR3 from a warm seed
    "physics_rtf": 1.0,  # the MuJoCo cell with the arm and five objects keeps real time
    "stereo_vga_p50_ms": 15.0,  # capture → decoded at 640×480
    "busy_host_holds": 0.0,  # issue 42: a 100 Hz master beside two nice-19 busy loops
    "busy_host_gap_ms": 50.0,
}

#: The processes of the sim profile (deploy/sim.toml) whose CPU the bench reports, and the
#: two sums the issue budgets. The workcell's physics runs in the arm's process
#: (`sim_physics = "embedded"`): its CPU is in the arm's figure (since 2026-12-03).
CORE_SERVICES: tuple[str, ...] = ("router", "arm", "force", "decision")
SIM_SERVICES: tuple[str, ...] = (*CORE_SERVICES, "vision", "console")

Better = Literal["higher", "lower"]
Verdict = Literal["meets", "MISSES", "n/a", "no data"]


def _verdict(ours: float | None, other: float | None, better: Better) -> Verdict:
    if ours is None:
        return "no data"
    if other is None:
        return "n/a"
    ok = ours >= other if better == "higher" else ours <= other
    return "meets" if ok else "MISSES"


@dataclass(frozen=True, slots=True)
class Figure:
    """One row of the comparison: our measured value beside the bare-Zenoh floor's and a
    baseline's of the same run, the paper's figure and issue 16's target.

    `better` says which direction wins; ratios are ours / other. `verdict` is "meets" or
    "MISSES" against the paper's figure, "n/a" when the paper gives none, and "no data" when
    the run measured nothing; `target_verdict` the same against the target. `reason` says
    why a figure has no data.
    """

    key: str
    label: str
    unit: str
    ours: float | None
    better: Better
    baseline: float | None = None
    baseline_name: str | None = None
    paper: float | None = None
    floor: float | None = None
    floor_name: str | None = None
    target: float | None = None
    target_name: str | None = None
    reason: str | None = None

    @property
    def vs_paper(self) -> float | None:
        return _ratio(self.ours, self.paper)

    @property
    def vs_baseline(self) -> float | None:
        return _ratio(self.ours, self.baseline)

    @property
    def vs_floor(self) -> float | None:
        return _ratio(self.ours, self.floor)

    @property
    def vs_target(self) -> float | None:
        return _ratio(self.ours, self.target)

    @property
    def verdict(self) -> Verdict:
        return _verdict(self.ours, self.paper, self.better)

    @property
    def target_verdict(self) -> Verdict:
        if self.target_name is not None and self.target is None:
            return "no data"  # a same-run target that was not measured cannot be met
        return _verdict(self.ours, self.target, self.better)

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out.update(
            vs_paper=self.vs_paper,
            vs_baseline=self.vs_baseline,
            vs_floor=self.vs_floor,
            vs_target=self.vs_target,
            verdict=self.verdict,
            target_verdict=self.target_verdict,
        )
        return out


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or b == 0 or not (math.isfinite(a) and math.isfinite(b)):
        return None
    return a / b


def _get(d: Mapping[str, Any], path: str) -> float | None:
    """`d["a"]["b"]…` for path "a.b…", as a float; None when any step is missing or None."""
    cur: Any = d
    for part in path.split("."):
        if not isinstance(cur, Mapping) or cur.get(part) is None:
            return None
        cur = cur[part]
    if isinstance(cur, bool) or not isinstance(cur, int | float):
        return None
    return float(cur) if math.isfinite(float(cur)) else None


def _reason(phases: Mapping[str, Any], path: str) -> str:
    """Why `path` has no value: the phase's own `na` entry for a part of the path (e.g.
    `setpoint_ms` of `commands_1000hz.setpoint_ms.p50`, `console` of
    `cpu_idle.services.console`) or for the whole phase (`"*"`), else that the phase did
    not run."""
    parts = path.split(".")
    phase = phases.get(parts[0])
    if not isinstance(phase, Mapping):
        return f"phase {parts[0]} did not run (see the run's notes and logs)"
    na = phase.get("na")
    if isinstance(na, Mapping):
        for key in (*parts[1:], "*"):
            if isinstance(na.get(key), str):
                return str(na[key])
    return "nothing was measured (see the run's notes and logs)"


@dataclass(frozen=True, slots=True)
class Spec:
    """Where one row's figures come from: `path` into the phases for ours; `baseline` and
    `floor` as (path, name) of same-run measurements; `paper` a PAPER key; `target` a
    TARGETS key or `target_run` a same-run (path, name) to beat."""

    key: str
    label: str
    unit: str
    path: str
    better: Better
    baseline: tuple[str, str] | None = None
    floor: tuple[str, str] | None = None
    paper: str | None = None
    target: str | None = None
    target_run: tuple[str, str] | None = None


TCP = "raw TCP"
XMLRPC = "XML-RPC"
ZENOH = "bare Zenoh"
ZENOH_GET = "bare Zenoh get"
ZENOH_RELAY = "bare Zenoh relay, 2 hops"


def _floor(stat: str) -> tuple[str, str]:
    """The pub/sub floor's `stat` (p50, p99, max) of one-way latency."""
    return (f"baseline_zenoh.latency_ms.{stat}", ZENOH)


def _relay_floor(rate: int, stat: str) -> tuple[str, str]:
    """The two-hop relay floor's `stat` of one-way latency at `rate` Hz (relay_phase)."""
    return (f"baseline_zenoh_relay_{rate}hz.latency_ms.{stat}", ZENOH_RELAY)


def _get_floor(stat: str) -> tuple[str, str]:
    """The get→reply floor's `stat` of round-trip time."""
    return (f"baseline_zenoh_query.latency_ms.{stat}", ZENOH_GET)


TELEOP_FLOOR = ("teleop_floor.core_pct", "bare Zenoh, the same 1 kHz streams")
"""The teleop floor (teleop_floor.py): the router and three bare processes carrying what
the router, the decision, the arm and the force service carry during 1 kHz teleop."""


def _cpu_specs(phase: str, what: str, targets: bool) -> list[Spec]:
    specs = [
        Spec(f"{phase}_core", f"{what} CPU: router + arm + force + decision", "%",
             f"{phase}.core_pct", "lower", target="idle_core_pct" if targets else None,
             floor=None if targets else TELEOP_FLOOR),
        Spec(f"{phase}_sim", f"{what} CPU: whole sim system (+ vision, console; physics in arm)",
             "%",
             f"{phase}.sim_pct", "lower", target="idle_sim_pct" if targets else None),
    ]  # fmt: skip
    specs += [
        Spec(f"{phase}_{name}", f"{what} CPU: {name}", "%", f"{phase}.services.{name}", "lower")
        for name in SIM_SERVICES
    ]
    return specs


def _stereo_specs(key: str, w: int, h: int, fps: int, vga: bool) -> list[Spec]:
    size = f"{w}×{h}"
    phase = f"force_stereo_{key}"
    return [
        Spec(f"force_rate_stereo_{key}", f"force rate, with stereo {size}@{fps}", "Hz",
             f"{phase}.rate_hz", "higher", paper="force_with_video_hz"),
        Spec(f"force_rate_in_flight_{key}", f"force rate while a {size} pair is in flight", "Hz",
             f"{phase}.in_flight.rate_hz", "higher", paper="force_active_video_hz",
             target="force_in_flight_vga_hz" if vga else None),
        Spec(f"force_latency_stereo_{key}_p50", f"force latency p50, with stereo {size}@{fps}",
             "ms", f"{phase}.latency_ms.p50", "lower", floor=_floor("p50")),
        Spec(f"force_latency_stereo_{key}_p99", f"force latency p99, with stereo {size}@{fps}",
             "ms", f"{phase}.latency_ms.p99", "lower", floor=_floor("p99"),
             target="force_vga_p99_ms" if vga else None),
        Spec(f"force_lost_stereo_{key}", f"force samples lost, with stereo {size}@{fps}", "",
             f"{phase}.loss.lost", "lower"),
    ]  # fmt: skip


def _video_specs(key: str, w: int, h: int, fps: int, vga: bool) -> list[Spec]:
    size = f"{w}×{h}"
    phase = f"video_{key}"
    return [
        Spec(f"video_fps_{key}", f"stereo fps per eye, {size} ({fps} asked)", "fps",
             f"{phase}.fps_min", "higher", paper="stereo_fps"),
        Spec(f"video_latency_{key}_p50", f"stereo capture→decoded p50, {size}", "ms",
             f"{phase}.latency_ms.p50", "lower", floor=_floor("p50"),
             target="stereo_vga_p50_ms" if vga else None),
        Spec(f"video_latency_{key}_p99", f"stereo capture→decoded p99, {size}", "ms",
             f"{phase}.latency_ms.p99", "lower", floor=_floor("p99")),
        Spec(f"video_skew_{key}_p99", f"stereo pair arrival skew p99, {size}", "ms",
             f"{phase}.arrival_skew_ms.p99", "lower"),
    ]  # fmt: skip


def _command_specs(rate: int) -> list[Spec]:
    name = "1 kHz" if rate == 1000 else f"{rate} Hz"
    phase = f"commands_{rate}hz"
    fast = rate == 1000
    return [
        Spec(f"cmd_rate_{rate}", f"commands reaching the arm, sent at {name}", "Hz",
             f"{phase}.reached_rate_hz", "higher", paper="command_rate_hz",
             target="cmd_1khz_reach_hz" if fast else None),
        Spec(f"cmd_arm_counter_{rate}",
             f"commands the arm counted per s, sent at {name} (holds included)", "Hz",
             f"{phase}.arm_counter.rate_hz", "higher"),
        Spec(f"cmd_forward_{rate}_p50", f"master→arm p50, {name}", "ms", f"{phase}.arm_ms.p50",
             "lower", floor=_relay_floor(rate, "p50"),
             target="cmd_1khz_arm_p50_ms" if fast else None),
        Spec(f"cmd_forward_{rate}_p99", f"master→arm p99, {name}", "ms", f"{phase}.arm_ms.p99",
             "lower", floor=_relay_floor(rate, "p99")),
        Spec(f"cmd_setpoint_{rate}_p50", f"master→setpoint p50, {name}", "ms",
             f"{phase}.setpoint_ms.p50", "lower", floor=_relay_floor(rate, "p50"),
             target="cmd_1khz_setpoint_p50_ms" if fast else None),
        Spec(f"cmd_setpoint_{rate}_p99", f"master→setpoint p99, {name}", "ms",
             f"{phase}.setpoint_ms.p99", "lower", floor=_relay_floor(rate, "p99"),
             target="cmd_1khz_setpoint_p99_ms" if fast else None),
        Spec(f"cmd_hop_decision_{rate}_p50", f"hop: master→decision's tick p50, {name}", "ms",
             f"{phase}.hops_ms.decision.p50", "lower"),
        Spec(f"cmd_hop_to_arm_{rate}_p50", f"hop: decision's tick→arm p50, {name}", "ms",
             f"{phase}.hops_ms.to_arm.p50", "lower"),
        Spec(f"cmd_hop_apply_{rate}_p50", f"hop: arm→setpoint p50, {name}", "ms",
             f"{phase}.hops_ms.apply.p50", "lower"),
    ]  # fmt: skip


XMLRPC_P50 = ("baseline_xmlrpc.latency_ms.p50", "XML-RPC p50, same run")

#: Every row of the comparison, in table order.
SPECS: tuple[Spec, ...] = (
    *_cpu_specs("cpu_idle", "idle", targets=True),
    *_cpu_specs("cpu_teleop", "teleop", targets=False),
    Spec("zenoh_floor_rate", "bare Zenoh pub/sub rate (1 kHz sent)", "Hz",
         "baseline_zenoh.rate_hz", "higher", baseline=("baseline_tcp.rate_hz", TCP)),
    Spec("zenoh_floor_p50", "bare Zenoh pub/sub latency p50", "ms",
         "baseline_zenoh.latency_ms.p50", "lower", baseline=("baseline_tcp.latency_ms.p50", TCP)),
    Spec("zenoh_floor_p99", "bare Zenoh pub/sub latency p99", "ms",
         "baseline_zenoh.latency_ms.p99", "lower", baseline=("baseline_tcp.latency_ms.p99", TCP)),
    Spec("zenoh_floor_lost", "bare Zenoh pub/sub samples lost", "", "baseline_zenoh.loss.lost",
         "lower", baseline=("baseline_tcp.loss.lost", TCP)),
    Spec("zenoh_floor_pub_cpu", "bare Zenoh publisher CPU at 1 kHz", "%",
         "baseline_zenoh.publisher_cpu_pct", "lower"),
    Spec("zenoh_floor_get_p50", "bare Zenoh get→reply p50", "ms",
         "baseline_zenoh_query.latency_ms.p50", "lower",
         baseline=("baseline_xmlrpc.latency_ms.p50", XMLRPC)),
    Spec("zenoh_floor_get_p99", "bare Zenoh get→reply p99", "ms",
         "baseline_zenoh_query.latency_ms.p99", "lower",
         baseline=("baseline_xmlrpc.latency_ms.p99", XMLRPC)),
    *(
        Spec(f"zenoh_relay_{rate}_{stat}", f"bare Zenoh relay, 2 hops, {stat} at {name}", "ms",
             f"baseline_zenoh_relay_{rate}hz.latency_ms.{stat}", "lower",
             baseline=(f"baseline_zenoh.latency_ms.{stat}", "bare Zenoh, 1 hop at 1 kHz"))
        for rate, name in ((100, "100 Hz"), (1000, "1 kHz"))
        for stat in ("p50", "p99")
    ),
    Spec("force_rate_alone", "force rate, alone", "Hz", "force_alone.rate_hz", "higher",
         baseline=("baseline_tcp.rate_hz", TCP), floor=("baseline_zenoh.rate_hz", ZENOH),
         paper="force_alone_hz", target="force_alone_hz"),
    Spec("force_latency_alone_p50", "force latency p50, alone", "ms",
         "force_alone.latency_ms.p50", "lower", baseline=("baseline_tcp.latency_ms.p50", TCP),
         floor=_floor("p50")),
    Spec("force_latency_alone_p99", "force latency p99, alone", "ms",
         "force_alone.latency_ms.p99", "lower", baseline=("baseline_tcp.latency_ms.p99", TCP),
         floor=_floor("p99"), target="force_alone_p99_ms"),
    Spec("force_latency_alone_max", "force latency max, alone", "ms",
         "force_alone.latency_ms.max", "lower", baseline=("baseline_tcp.latency_ms.max", TCP),
         floor=_floor("max")),
    Spec("force_lost_alone", "force samples lost, alone", "", "force_alone.loss.lost", "lower",
         baseline=("baseline_tcp.loss.lost", TCP), floor=("baseline_zenoh.loss.lost", ZENOH),
         target="force_alone_lost"),
    Spec("force_cpu_alone", "force service CPU, force alone (1 kHz)", "%",
         "force_alone.service_cpu_pct", "lower",
         floor=("baseline_zenoh.publisher_cpu_pct", ZENOH)),
    *_stereo_specs("paper", *PAPER_SIZE, 17, vga=False),
    *_stereo_specs("vga", 640, 480, 30, vga=True),
    *_video_specs("paper", *PAPER_SIZE, 17, vga=False),
    *_video_specs("vga", 640, 480, 30, vga=True),
    *_command_specs(100),
    *_command_specs(1000),
    Spec("busy_host_holds", "watchdog holds, 100 Hz master beside 2 nice-19 busy loops", "",
         "busy_host.watchdog_holds", "lower", target="busy_host_holds"),
    Spec("busy_host_gap", "longest gap of targets at the arm, beside the busy loops", "ms",
         "busy_host.arm_cmd_max_gap_ms", "lower", target="busy_host_gap_ms"),
    Spec("busy_host_sent_gap", "longest gap of the master's sending, beside the busy loops",
         "ms", "busy_host.sent_max_gap_ms", "lower"),
    Spec("rpc_decision_status_p50", "call decision status p50", "ms",
         "rpc_decision_status.p50", "lower", baseline=("baseline_xmlrpc.latency_ms.p50", XMLRPC),
         floor=_get_floor("p50"), paper="command_round_trip_ms", target="decision_status_p50_ms"),
    Spec("rpc_decision_status_p99", "call decision status p99", "ms", "rpc_decision_status.p99",
         "lower", baseline=("baseline_xmlrpc.latency_ms.p99", XMLRPC), floor=_get_floor("p99")),
    Spec("rpc_decision_status_vs_xmlrpc", "call decision status p50, faster than XML-RPC", "ms",
         "rpc_decision_status.p50", "lower", target_run=XMLRPC_P50),
    Spec("rpc_decision_supervisor_p50", "call decision supervisor p50", "ms",
         "rpc_decision_supervisor.p50", "lower",
         baseline=("baseline_xmlrpc.latency_ms.p50", XMLRPC), floor=_get_floor("p50"),
         paper="command_round_trip_ms"),
    Spec("rpc_decision_supervisor_p99", "call decision supervisor p99", "ms",
         "rpc_decision_supervisor.p99", "lower",
         baseline=("baseline_xmlrpc.latency_ms.p99", XMLRPC), floor=_get_floor("p99")),
    Spec("rpc_arm_status_p50", "call arm status p50 (direct)", "ms", "rpc_arm_status.p50",
         "lower", baseline=("baseline_xmlrpc.latency_ms.p50", XMLRPC), floor=_get_floor("p50"),
         paper="command_round_trip_ms", target="arm_status_p50_ms"),
    Spec("rpc_arm_status_p99", "call arm status p99 (direct)", "ms", "rpc_arm_status.p99",
         "lower", baseline=("baseline_xmlrpc.latency_ms.p99", XMLRPC), floor=_get_floor("p99")),
    Spec("rpc_arm_status_vs_xmlrpc", "call arm status p50, faster than XML-RPC", "ms",
         "rpc_arm_status.p50", "lower", target_run=XMLRPC_P50),
    Spec("ik_analytic_per_s", "IK solves/s, analytic (8 branches)", "1/s",
         "ik.analytic_ik_per_s", "higher", target="ik_per_s"),
    Spec("ik_dls_per_s", "IK steps/s, damped least squares", "1/s", "ik.dls_steps_per_s",
         "higher"),
    Spec("ik_fr3_per_s", "IK solves/s, FR3 numerical, warm seed", "1/s",
         "ik.fr3_solve_per_s", "higher", target="ik_numerical_per_s"),
    Spec("ik_ur5e_per_s", "IK solves/s, UR5e numerical, warm seed", "1/s",
         "ik.ur5e_solve_per_s", "higher"),
    Spec("physics_puma560_rtf", "physics real-time factor, PUMA 560 + 5 objects", "×",
         "physics.puma560_rtf", "higher", target="physics_rtf"),
    Spec("physics_fr3_rtf", "physics real-time factor, FR3 + 5 objects", "×",
         "physics.fr3_rtf", "higher", target="physics_rtf"),
    Spec("physics_ur5e_rtf", "physics real-time factor, UR5e + 5 objects", "×",
         "physics.ur5e_rtf", "higher", target="physics_rtf"),
)  # fmt: skip

FIGURE_KEYS: tuple[str, ...] = tuple(s.key for s in SPECS)

#: the phases a complete run measures (keys of `phases`)
PHASE_KEYS: tuple[str, ...] = (
    "force_alone",
    "force_stereo_paper",
    "force_stereo_vga",
    "video_paper",
    "video_vga",
    "commands_100hz",
    "commands_1000hz",
    "busy_host",
    "rpc_decision_status",
    "rpc_decision_supervisor",
    "rpc_arm_status",
    "ik",
    "physics",
    "baseline_tcp",
    "baseline_xmlrpc",
    "baseline_zenoh",
    "baseline_zenoh_query",
    "cpu_idle",
    "cpu_teleop",
    "teleop_floor",
)


def figures(phases: Mapping[str, Any]) -> list[Figure]:
    """The comparison rows, each read from the measured phases."""
    out = []
    for s in SPECS:
        ours = _get(phases, s.path)
        target, target_name = None, None
        if s.target is not None:
            target = TARGETS[s.target]
            target_name = "issue 42" if s.target.startswith("busy_host") else "issue 16"
        elif s.target_run is not None:
            target, target_name = _get(phases, s.target_run[0]), s.target_run[1]
        out.append(
            Figure(
                key=s.key,
                label=s.label,
                unit=s.unit,
                ours=ours,
                better=s.better,
                baseline=_get(phases, s.baseline[0]) if s.baseline else None,
                baseline_name=s.baseline[1] if s.baseline else None,
                paper=PAPER[s.paper] if s.paper else None,
                floor=_get(phases, s.floor[0]) if s.floor else None,
                floor_name=s.floor[1] if s.floor else None,
                target=target,
                target_name=target_name,
                reason=None if ours is not None else _reason(phases, s.path),
            )
        )
    return out


def machine() -> dict[str, Any]:
    """Where the run happened: CPUs, CPU model, Python, Zenoh, kernel, load."""
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        zenoh_version = importlib.metadata.version("eclipse-zenoh")
    except importlib.metadata.PackageNotFoundError:
        zenoh_version = "unknown"
    return {
        "nproc": os.cpu_count(),
        "cpu_model": model,
        "python": sys.version.split()[0],
        "zenoh": zenoh_version,
        "platform": platform.platform(),
    }


def document(
    phases: Mapping[str, Any],
    machine_info: Mapping[str, Any],
    settings: Mapping[str, Any],
    notes: Sequence[str] = (),
) -> dict[str, Any]:
    """The JSON document of a run: schema, machine, settings, measured phases, the paper's
    figures and issue 16's targets, the comparison rows, what misses and what has no data."""
    rows = figures(phases)
    return {
        "schema": SCHEMA,
        "machine": dict(machine_info),
        "settings": dict(settings),
        "phases": dict(phases),
        "paper": dict(PAPER),
        "targets": dict(TARGETS),
        "figures": {f.key: f.as_dict() for f in rows},
        "misses": [f.key for f in rows if f.verdict in ("MISSES", "no data")],
        "target_misses": [
            f.key for f in rows if f.target_name is not None and f.target_verdict != "meets"
        ],
        "not_measured": {f.key: f.reason for f in rows if f.ours is None},
        "notes": list(notes),
    }


def ms_text(x: float | None) -> str:
    """A latency for the progress lines: "0.123 ms", or "n/a"."""
    return "n/a" if x is None else f"{x:.3f} ms"


def _fmt(x: float | None, unit: str = "") -> str:
    if x is None:
        return "n/a"
    if unit == "%":
        return f"{x:.1f}"
    if unit == "1/s" or abs(x) >= 1000:
        return f"{x:,.0f}"
    if abs(x) >= 100:
        return f"{x:.0f}"
    if abs(x) >= 10:
        return f"{x:.1f}"
    if x == int(x) and unit == "":
        return f"{int(x)}"
    return f"{x:.2f}" if abs(x) >= 0.1 else f"{x:.3f}"


def _fmt_ratio(r: float | None) -> str:
    if r is None:
        return ""
    return f"{r:.2g}×" if r < 10 else f"{r:.0f}×"


def _sig(x: float) -> str:
    """4 significant digits, so a near miss never prints as "17.0 vs 17.0"; thousands
    grouped rather than in exponent form."""
    return f"{x:,.0f}" if abs(x) >= 10_000 else f"{x:.4g}"


def _shortfall(ours: float, other: float, better: str, whose: str) -> str:
    """How far a missed figure is from `other`, in the direction that counts."""
    if better == "higher":
        return f"{(1.0 - ours / other) * 100:.2g} % short" if other else "short"
    return f"{ours / other:.3g}× {whose}" if other else "over"


PAPERS = "the paper's"
TABLE_HEADER = (
    "| figure | ours | floor (same run) | ours/floor | baseline (same run) | ours/baseline "
    "| paper | ours/paper | vs paper | target | vs target |"
)


def _cell(value: float | None, name: str | None, unit: str) -> str:
    return f"{_fmt(value, unit)} ({name})" if name else ""


def table(doc: Mapping[str, Any]) -> str:
    """A Markdown table of the comparison, headed by the machine, followed by what misses
    issue 16's targets, what misses the paper and what was not measured (with why)."""
    m = doc["machine"]
    s = doc["settings"]
    run_cpu = (s.get("cpu") or {}).get("run")
    shared = (
        f"other processes took {run_cpu['others_share']:.0%} of the CPUs during the run "
        f"(the bench and its services {run_cpu['bench_share']:.0%})"
        if run_cpu
        else f"load average {s.get('loadavg_start', 'n/a')} before the run"
    )
    lines = [
        f"Machine: {m['nproc']} CPUs, {m['cpu_model']}, Python {m['python']}, "
        f"eclipse-zenoh {m['zenoh']}; {shared}; phases of {s.get('phase_s', 'n/a')} s"
        f"{' (--quick)' if s.get('quick') else ''}; arm model {s.get('model', 'puma560')}.",
        "",
        TABLE_HEADER,
        "|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---|",
    ]
    for f in doc["figures"].values():
        unit = f["unit"]
        suffix = f" {unit}" if unit and f["ours"] is not None else ""
        paper = _fmt(f["paper"], unit) if f["paper"] is not None else ""
        target = ""
        if f["target_name"] is not None:
            sign = "≥" if f["better"] == "higher" else "≤"
            value = _fmt(f["target"], unit) if f["target"] is not None else "n/a"
            run = f["target_name"] != "issue 16"
            target = f"{sign} {value}" + (f" ({f['target_name']})" if run else "")
        lines.append(
            f"| {f['label']} | {_fmt(f['ours'], unit)}{suffix} "
            f"| {_cell(f['floor'], f['floor_name'], unit)} | {_fmt_ratio(f['vs_floor'])} "
            f"| {_cell(f['baseline'], f['baseline_name'], unit)} "
            f"| {_fmt_ratio(f['vs_baseline'])} "
            f"| {paper} | {_fmt_ratio(f['vs_paper'])} | {paper and f['verdict']} "
            f"| {target} | {target and f['target_verdict']} |"
        )
    lines.append("")
    rows = doc["figures"]
    measured = [rows[k] for k in doc.get("target_misses", [])]
    for f in (f for f in measured if f["ours"] is not None and f["target"] is not None):
        lines.append(
            f"MISSES THE TARGET: {f['label']}: ours {_sig(f['ours'])} vs {_sig(f['target'])} "
            f"{f['unit']}".rstrip()
            + f" ({f['target_name']}; "
            + f"{_shortfall(f['ours'], f['target'], f['better'], 'the target')})."
        )
    if not doc.get("target_misses"):
        lines.append("Every figure with a target meets it.")
    paper_misses = [rows[k] for k in doc["misses"] if rows[k]["verdict"] == "MISSES"]
    for f in paper_misses:
        lines.append(
            f"MISSES THE PAPER: {f['label']}: ours {_sig(f['ours'])} vs the paper's "
            f"{_sig(f['paper'])} {f['unit']}".rstrip()
            + f" ({_shortfall(f['ours'], f['paper'], f['better'], PAPERS)})."
        )
    if not paper_misses:
        lines.append("Every figure with a counterpart in the paper meets it.")
    for key, reason in doc.get("not_measured", {}).items():
        lines.append(f"NOT MEASURED: {rows[key]['label']}: {reason}")
    for note in doc.get("notes", []):
        lines.append(f"Note: {note}")
    return "\n".join(lines)
