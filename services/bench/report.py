"""The bench's output: the comparison figures, the JSON document and the text table.

Every figure is read from the run's measured `phases` (see `services.bench.run`); the only
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

SCHEMA = "telerobot-bench/1"

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

Better = Literal["higher", "lower"]


@dataclass(frozen=True, slots=True)
class Figure:
    """One row of the comparison: our measured value, the same-run baseline's, the paper's.

    `better` says which direction wins; ratios are ours / other. The verdict is "meets" or
    "MISSES" against the paper's figure, "n/a" when the paper gives none, and "no data" when
    the run measured nothing (which is reported as a miss as well).
    """

    key: str
    label: str
    unit: str
    ours: float | None
    better: Better
    baseline: float | None = None
    baseline_name: str | None = None
    paper: float | None = None

    @property
    def vs_paper(self) -> float | None:
        return _ratio(self.ours, self.paper)

    @property
    def vs_baseline(self) -> float | None:
        return _ratio(self.ours, self.baseline)

    @property
    def verdict(self) -> str:
        if self.ours is None:
            return "no data"
        if self.paper is None:
            return "n/a"
        ok = self.ours >= self.paper if self.better == "higher" else self.ours <= self.paper
        return "meets" if ok else "MISSES"

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out.update(vs_paper=self.vs_paper, vs_baseline=self.vs_baseline, verdict=self.verdict)
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


#: Every figure of the comparison, in table order: (key, label, unit, phase path, better,
#: baseline path or None, baseline name, paper key or None).
FIGURE_SPECS: tuple[tuple[str, str, str, str, Better, str | None, str | None, str | None], ...] = (
    ("force_rate_alone", "force rate, alone", "Hz", "force_alone.rate_hz", "higher",
     "baseline_tcp.rate_hz", "raw TCP", "force_alone_hz"),
    ("force_latency_alone_p50", "force latency p50, alone", "ms", "force_alone.latency_ms.p50",
     "lower", "baseline_tcp.latency_ms.p50", "raw TCP", None),
    ("force_latency_alone_p99", "force latency p99, alone", "ms", "force_alone.latency_ms.p99",
     "lower", "baseline_tcp.latency_ms.p99", "raw TCP", None),
    ("force_latency_alone_max", "force latency max, alone", "ms", "force_alone.latency_ms.max",
     "lower", "baseline_tcp.latency_ms.max", "raw TCP", None),
    ("force_lost_alone", "force samples lost, alone", "", "force_alone.loss.lost", "lower",
     "baseline_tcp.loss.lost", "raw TCP", None),
    ("force_rate_stereo_paper", "force rate, with stereo 360×288@17", "Hz",
     "force_stereo_paper.rate_hz", "higher", None, None, "force_with_video_hz"),
    ("force_rate_in_flight_paper", "force rate while a 360×288 pair is in flight", "Hz",
     "force_stereo_paper.in_flight.rate_hz", "higher", None, None, "force_active_video_hz"),
    ("force_latency_stereo_paper_p50", "force latency p50, with stereo 360×288@17", "ms",
     "force_stereo_paper.latency_ms.p50", "lower", None, None, None),
    ("force_latency_stereo_paper_p99", "force latency p99, with stereo 360×288@17", "ms",
     "force_stereo_paper.latency_ms.p99", "lower", None, None, None),
    ("force_lost_stereo_paper", "force samples lost, with stereo 360×288@17", "",
     "force_stereo_paper.loss.lost", "lower", None, None, None),
    ("force_rate_stereo_vga", "force rate, with stereo 640×480@30", "Hz",
     "force_stereo_vga.rate_hz", "higher", None, None, "force_with_video_hz"),
    ("force_rate_in_flight_vga", "force rate while a 640×480 pair is in flight", "Hz",
     "force_stereo_vga.in_flight.rate_hz", "higher", None, None, "force_active_video_hz"),
    ("force_latency_stereo_vga_p50", "force latency p50, with stereo 640×480@30", "ms",
     "force_stereo_vga.latency_ms.p50", "lower", None, None, None),
    ("force_latency_stereo_vga_p99", "force latency p99, with stereo 640×480@30", "ms",
     "force_stereo_vga.latency_ms.p99", "lower", None, None, None),
    ("force_lost_stereo_vga", "force samples lost, with stereo 640×480@30", "",
     "force_stereo_vga.loss.lost", "lower", None, None, None),
    ("video_fps_paper", "stereo fps per eye, 360×288 (17 asked)", "fps", "video_paper.fps_min",
     "higher", None, None, "stereo_fps"),
    ("video_latency_paper_p50", "stereo capture→decoded p50, 360×288", "ms",
     "video_paper.latency_ms.p50", "lower", None, None, None),
    ("video_latency_paper_p99", "stereo capture→decoded p99, 360×288", "ms",
     "video_paper.latency_ms.p99", "lower", None, None, None),
    ("video_skew_paper_p99", "stereo pair arrival skew p99, 360×288", "ms",
     "video_paper.arrival_skew_ms.p99", "lower", None, None, None),
    ("video_fps_vga", "stereo fps per eye, 640×480 (30 asked)", "fps", "video_vga.fps_min",
     "higher", None, None, "stereo_fps"),
    ("video_latency_vga_p50", "stereo capture→decoded p50, 640×480", "ms",
     "video_vga.latency_ms.p50", "lower", None, None, None),
    ("video_latency_vga_p99", "stereo capture→decoded p99, 640×480", "ms",
     "video_vga.latency_ms.p99", "lower", None, None, None),
    ("video_skew_vga_p99", "stereo pair arrival skew p99, 640×480", "ms",
     "video_vga.arrival_skew_ms.p99", "lower", None, None, None),
    ("cmd_rate_100", "commands reaching the arm, sent at 100 Hz", "Hz",
     "commands_100hz.forwarded_rate_hz", "higher", None, None, "command_rate_hz"),
    ("cmd_forward_100_p50", "master→puma command p50, 100 Hz", "ms",
     "commands_100hz.forward_ms.p50", "lower", None, None, None),
    ("cmd_forward_100_p99", "master→puma command p99, 100 Hz", "ms",
     "commands_100hz.forward_ms.p99", "lower", None, None, None),
    ("cmd_applied_100_p50", "master→arm applied p50, 100 Hz", "ms",
     "commands_100hz.applied_ms.p50", "lower", None, None, None),
    ("cmd_applied_100_p99", "master→arm applied p99, 100 Hz", "ms",
     "commands_100hz.applied_ms.p99", "lower", None, None, None),
    ("cmd_rate_1000", "commands reaching the arm, sent at 1 kHz", "Hz",
     "commands_1000hz.forwarded_rate_hz", "higher", None, None, "command_rate_hz"),
    ("cmd_forward_1000_p50", "master→puma command p50, 1 kHz", "ms",
     "commands_1000hz.forward_ms.p50", "lower", None, None, None),
    ("cmd_forward_1000_p99", "master→puma command p99, 1 kHz", "ms",
     "commands_1000hz.forward_ms.p99", "lower", None, None, None),
    ("cmd_applied_1000_p50", "master→arm applied p50, 1 kHz", "ms",
     "commands_1000hz.applied_ms.p50", "lower", None, None, None),
    ("cmd_applied_1000_p99", "master→arm applied p99, 1 kHz", "ms",
     "commands_1000hz.applied_ms.p99", "lower", None, None, None),
    ("rpc_decision_status_p50", "call decision status p50 (2 nested calls)", "ms",
     "rpc_decision_status.p50", "lower", "baseline_xmlrpc.latency_ms.p50", "XML-RPC",
     "command_round_trip_ms"),
    ("rpc_decision_status_p99", "call decision status p99", "ms", "rpc_decision_status.p99",
     "lower", "baseline_xmlrpc.latency_ms.p99", "XML-RPC", None),
    ("rpc_decision_supervisor_p50", "call decision supervisor p50", "ms",
     "rpc_decision_supervisor.p50", "lower", "baseline_xmlrpc.latency_ms.p50", "XML-RPC",
     "command_round_trip_ms"),
    ("rpc_decision_supervisor_p99", "call decision supervisor p99", "ms",
     "rpc_decision_supervisor.p99", "lower", "baseline_xmlrpc.latency_ms.p99", "XML-RPC", None),
    ("rpc_puma_status_p50", "call puma status p50 (direct)", "ms", "rpc_puma_status.p50",
     "lower", "baseline_xmlrpc.latency_ms.p50", "XML-RPC", "command_round_trip_ms"),
    ("rpc_puma_status_p99", "call puma status p99 (direct)", "ms", "rpc_puma_status.p99",
     "lower", "baseline_xmlrpc.latency_ms.p99", "XML-RPC", None),
    ("ik_analytic_per_s", "IK solves/s, analytic (8 branches)", "1/s", "ik.analytic_ik_per_s",
     "higher", None, None, None),
    ("ik_dls_per_s", "IK steps/s, damped least squares", "1/s", "ik.dls_steps_per_s",
     "higher", None, None, None),
)  # fmt: skip

FIGURE_KEYS: tuple[str, ...] = tuple(s[0] for s in FIGURE_SPECS)

#: the phases a complete run measures (keys of `phases`)
PHASE_KEYS: tuple[str, ...] = (
    "force_alone",
    "force_stereo_paper",
    "force_stereo_vga",
    "video_paper",
    "video_vga",
    "commands_100hz",
    "commands_1000hz",
    "rpc_decision_status",
    "rpc_decision_supervisor",
    "rpc_puma_status",
    "ik",
    "baseline_tcp",
    "baseline_xmlrpc",
)


def figures(phases: Mapping[str, Any]) -> list[Figure]:
    """The comparison rows, each read from the measured phases."""
    out = []
    for key, label, unit, path, better, base_path, base_name, paper_key in FIGURE_SPECS:
        out.append(
            Figure(
                key=key,
                label=label,
                unit=unit,
                ours=_get(phases, path),
                better=better,
                baseline=_get(phases, base_path) if base_path else None,
                baseline_name=base_name if base_path else None,
                paper=PAPER[paper_key] if paper_key else None,
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
    figures, the comparison rows and the list of misses."""
    rows = figures(phases)
    return {
        "schema": SCHEMA,
        "machine": dict(machine_info),
        "settings": dict(settings),
        "phases": dict(phases),
        "paper": dict(PAPER),
        "figures": {f.key: f.as_dict() for f in rows},
        "misses": [f.key for f in rows if f.verdict in ("MISSES", "no data")],
        "notes": list(notes),
    }


def _fmt(x: float | None, unit: str = "") -> str:
    if x is None:
        return "n/a"
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


def _shortfall(f: Mapping[str, Any]) -> str:
    """How far a missed figure is from the paper's, in the direction that counts."""
    ours, paper = float(f["ours"]), float(f["paper"])
    if f["better"] == "higher":
        return f"{(1.0 - ours / paper) * 100:.2g} % short" if paper else "short"
    return f"{ours / paper:.3g}× the paper's" if paper else "over"


def table(doc: Mapping[str, Any]) -> str:
    """A Markdown table of the comparison, headed by the machine, followed by the misses."""
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
        f"{' (--quick)' if s.get('quick') else ''}.",
        "",
        "| figure | ours | baseline (same run) | ours/baseline | paper | ours/paper | verdict |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for f in doc["figures"].values():
        unit = f["unit"]
        suffix = f" {unit}" if unit else ""
        base = f"{_fmt(f['baseline'], unit)} ({f['baseline_name']})" if f["baseline_name"] else ""
        paper = f"{_fmt(f['paper'], unit)}" if f["paper"] is not None else ""
        lines.append(
            f"| {f['label']} | {_fmt(f['ours'], unit)}{suffix if f['ours'] is not None else ''} "
            f"| {base} | {_fmt_ratio(f['vs_baseline'])} | {paper} "
            f"| {_fmt_ratio(f['vs_paper'])} | {f['verdict']} |"
        )
    lines.append("")
    misses = [doc["figures"][k] for k in doc["misses"]]
    if misses:
        for f in misses:
            if f["verdict"] == "no data":
                lines.append(f"NOT MEASURED: {f['label']} (see the run's notes and logs).")
            else:
                # 4 significant digits: a near miss must not print as "17.0 vs 17.0".
                lines.append(
                    f"MISSES THE PAPER: {f['label']}: ours {f['ours']:.4g} vs the paper's "
                    f"{f['paper']:.4g} {f['unit']}".rstrip()
                    + f" ({_shortfall(f)})."
                )
    else:
        lines.append("Every figure with a counterpart in the paper meets it.")
    for note in doc.get("notes", []):
        lines.append(f"Note: {note}")
    return "\n".join(lines)
