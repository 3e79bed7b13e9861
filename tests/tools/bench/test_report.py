"""The JSON document and the table, built from phases reduced by the run's own functions."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from services.tools.bench import stats
from services.tools.bench.cpu_phases import cpu_figures
from services.tools.bench.force_phases import force_figures
from services.tools.bench.notes import force_note
from services.tools.bench.probes import FrameRecord
from services.tools.bench.report import (
    FIGURE_KEYS,
    PAPER,
    PHASE_KEYS,
    SPECS,
    TABLE_HEADER,
    TARGETS,
    Figure,
    document,
    figures,
    machine,
    table,
)
from services.tools.bench.video_phase import video_figures

MS = stats.NS_PER_MS
S = stats.NS_PER_S
T0 = 1_700_000_000 * S


def _force(rate_hz: float, latency_ms: float, lose: tuple[int, ...] = ()) -> dict[str, Any]:
    period = int(S / rate_hz)
    records = [
        (T0 + i * period + int(latency_ms * MS), (i + 1, T0 + i * period))
        for i in range(int(rate_hz))
        if i + 1 not in lose
    ]
    fig, _ = force_figures(records, T0, T0 + S)
    return fig


def _video(fps: float, w: int, h: int) -> tuple[dict[str, Any], list[tuple[int, int]]]:
    period = int(S / fps)
    frames = [
        FrameRecord(eye, i + 1, T0 + i * period, T0 + i * period + 5 * MS + d, T0 + i * period
                    + 8 * MS + d, 20_000, w, h)
        for i in range(int(fps))
        for eye, d in (("l", 0), ("r", MS // 2))
    ]  # fmt: skip
    return video_figures(frames, T0, T0 + S, w, h, fps)


def _summary(p50: float, p99: float) -> dict[str, Any]:
    return {"n": 100, "p50": p50, "p99": p99, "max": p99 * 2, "mean": p50, "min": p50 / 2}


def _cpu(**pct: float) -> dict[str, Any]:
    before = dict.fromkeys(pct, 10.0)
    after = {name: 10.0 + p / 100.0 * 5.0 for name, p in pct.items()}  # a 5 s window
    return cpu_figures(before, after, bench_s=0.25, wall_s=5.0)


IDLE = {"router": 3.0, "arm": 4.0, "force": 9.0, "decision": 2.0}
IDLE_SIM = {**IDLE, "vision": 1.0, "console": 6.0}  # the workcell's physics: in the arm


def full_phases() -> dict[str, Any]:
    vp, _ = _video(17.0, 360, 288)
    vv, _ = _video(30.0, 640, 480)
    with_video = _force(1000.0, 0.4)
    with_video["in_flight"] = {"count": 12, "covered_s": 0.2, "rate_hz": 60.0}
    alone = _force(1000.0, 0.2)
    alone["service_cpu_pct"] = 12.0
    return {
        "force_alone": alone,
        "force_stereo_paper": with_video,
        "force_stereo_vga": {**_force(500.0, 1.0, lose=(3, 4)), "in_flight": None},
        "video_paper": vp,
        "video_vga": vv,
        "commands_100hz": {
            "reached_rate_hz": 98.0,
            "arm_counter": {"commands": 490, "window_s": 5.0, "rate_hz": 98.0},
            "arm_ms": _summary(0.8, 2.0),
            "setpoint_ms": _summary(3.0, 6.0),
            "hops_ms": {
                "decision": _summary(0.4, 1.0),
                "to_arm": _summary(0.4, 1.0),
                "apply": _summary(2.2, 4.0),
            },
        },
        "commands_1000hz": {
            "reached_rate_hz": 480.0,
            "arm_counter": {"commands": 2500, "window_s": 5.0, "rate_hz": 500.0},
            "arm_ms": _summary(0.7, 2.5),
            "setpoint_ms": _summary(3.1, 7.0),
            "hops_ms": {
                "decision": _summary(0.3, 1.2),
                "to_arm": _summary(0.4, 1.3),
                "apply": _summary(2.4, 4.5),
            },
        },
        "busy_host": {"watchdog_holds": 0, "arm_cmd_max_gap_ms": 21.0, "sent_max_gap_ms": 15.0},
        "rpc_decision_status": _summary(2.0, 5.0),
        "rpc_decision_supervisor": _summary(0.6, 1.5),
        "rpc_arm_status": _summary(0.5, 1.2),
        "ik": {
            "n": 10.0,
            "analytic_ik_per_s": 3000.0,
            "dls_steps_per_s": 26000.0,
            "fr3_solve_per_s": 4000.0,
            "ur5e_solve_per_s": 6000.0,
        },
        "physics": {"sim_s": 5.0, "puma560_rtf": 2.1, "fr3_rtf": 3.4, "ur5e_rtf": 3.5},
        "baseline_tcp": {
            "rate_hz": 999.0,
            "latency_ms": _summary(0.06, 0.2),
            "loss": {"lost": 0},
        },
        "baseline_xmlrpc": {"latency_ms": _summary(0.35, 1.1), "calls": 100},
        "baseline_zenoh": {
            "rate_hz": 1000.0,
            "latency_ms": _summary(0.1, 0.4),
            "loss": {"lost": 0},
            "publisher_cpu_pct": 8.0,
        },
        "baseline_zenoh_query": {"latency_ms": _summary(0.25, 0.5), "calls": 100},
        "baseline_zenoh_relay_100hz": {"latency_ms": _summary(0.3, 0.8)},
        "baseline_zenoh_relay_1000hz": {"latency_ms": _summary(0.25, 0.7)},
        "cpu_idle": _cpu(**IDLE_SIM),
        "cpu_teleop": _cpu(**{k: 2 * v for k, v in IDLE_SIM.items()}),
        "teleop_floor": {"core_pct": 24.0, "services": {}, "na": {}},
    }


SETTINGS = {"quick": True, "phase_s": 5.0, "loadavg_start": "0.5", "loadavg_end": "0.7"}


def test_reducers_on_synthetic_streams() -> None:
    f = _force(1000.0, 0.25, lose=(10, 11))
    assert f["received"] == 998
    assert f["rate_hz"] == pytest.approx(998.0)
    assert f["produced_rate_hz"] == pytest.approx(1000.0, rel=1e-3)
    assert f["latency_ms"]["p50"] == pytest.approx(0.25)
    assert f["loss"]["lost"] == 2
    v, windows = _video(17.0, 360, 288)
    assert v["fps_l"] == pytest.approx(17.0, rel=1e-3) and v["fps_min"] == v["fps_r"]
    assert v["pairs_complete"] == 17 and v["pairs_missing"] == 0
    assert v["latency_ms"]["p50"] == pytest.approx(8.25)  # decoded 8 ms (l) / 8.5 ms (r)
    assert v["arrival_skew_ms"]["p50"] == pytest.approx(0.5)
    # a pair is in flight from its capture to the arrival of its later eye
    assert windows[0] == (T0, T0 + 5 * MS + MS // 2)


def test_document_has_every_figure_and_phase_and_is_strict_json() -> None:
    doc = document(full_phases(), machine(), SETTINGS, ["a note"])
    assert doc["schema"] == "telerobot-bench/2"
    assert list(doc["figures"]) == list(FIGURE_KEYS)
    assert len(set(FIGURE_KEYS)) == len(FIGURE_KEYS)
    assert set(PHASE_KEYS) <= set(doc["phases"])
    fields = {
        "key",
        "label",
        "unit",
        "ours",
        "better",
        "baseline",
        "baseline_name",
        "paper",
        "floor",
        "floor_name",
        "target",
        "target_name",
        "reason",
        "vs_paper",
        "vs_baseline",
        "vs_floor",
        "vs_target",
        "verdict",
        "target_verdict",
    }
    for key in FIGURE_KEYS:
        assert set(doc["figures"][key]) == fields
    assert set(doc["machine"]) >= {"nproc", "cpu_model", "python", "zenoh"}
    assert doc["paper"] == PAPER and doc["targets"] == TARGETS
    json.loads(json.dumps(doc, allow_nan=False))
    # every figure of a complete run has a value
    assert list(doc["not_measured"]) == ["force_rate_in_flight_vga"]  # None above
    assert "force_rate_in_flight_vga" in doc["target_misses"]


def test_every_target_of_issue_16_has_a_row() -> None:
    targeted = {f.key: f for f in figures(full_phases()) if f.target_name == "issue 16"}
    assert {f.target for f in targeted.values()} <= set(TARGETS.values())
    used = {s.target for s in SPECS if s.target is not None}
    assert used == set(TARGETS)
    assert {s.key for s in SPECS if s.target_run is not None} == {
        "rpc_decision_status_vs_xmlrpc",
        "rpc_arm_status_vs_xmlrpc",
    }


def test_figures_compare_with_paper_floor_baseline_and_target() -> None:
    rows = {f.key: f for f in figures(full_phases())}
    alone = rows["force_rate_alone"]
    assert alone.paper == 1000.0 and alone.baseline == 999.0 and alone.baseline_name == "raw TCP"
    assert alone.floor == 1000.0 and alone.floor_name == "bare Zenoh"
    assert alone.verdict == "meets" and alone.target == 995.0 and alone.target_verdict == "meets"
    assert rows["force_latency_alone_p50"].vs_floor == pytest.approx(0.2 / 0.1)
    assert rows["force_latency_alone_p99"].vs_floor == pytest.approx(0.2 / 0.4)
    assert rows["force_latency_alone_p99"].target_verdict == "meets"  # 0.2 ≤ 0.5
    assert rows["force_cpu_alone"].vs_floor == pytest.approx(12.0 / 8.0)
    assert rows["force_rate_in_flight_paper"].ours == 60.0
    assert rows["force_rate_in_flight_paper"].verdict == "MISSES"  # 60 < 76
    assert rows["force_rate_in_flight_paper"].target_verdict == "n/a"
    assert rows["force_rate_stereo_vga"].verdict == "meets"  # 998 Hz > 250
    assert rows["force_latency_stereo_vga_p99"].target_verdict == "meets"  # 1.0 ≤ 1 ms
    assert rows["force_lost_stereo_vga"].ours == 2.0
    assert rows["rpc_arm_status_p50"].vs_baseline == pytest.approx(0.5 / 0.35)
    assert rows["rpc_arm_status_p50"].vs_floor == pytest.approx(0.5 / 0.25)
    assert rows["rpc_arm_status_p50"].target_verdict == "MISSES"  # 0.5 > 0.4
    assert rows["rpc_arm_status_vs_xmlrpc"].target == 0.35
    assert rows["rpc_arm_status_vs_xmlrpc"].target_verdict == "MISSES"  # 0.5 > 0.35
    assert rows["rpc_decision_status_p50"].verdict == "MISSES"  # 2 ms > ~1 ms
    assert rows["rpc_decision_supervisor_p50"].verdict == "meets"
    assert rows["cmd_rate_100"].verdict == "meets"  # 98 ≥ 50
    assert rows["cmd_rate_100"].target_verdict == "n/a"  # the target is at 1 kHz
    assert rows["cmd_rate_1000"].target_verdict == "MISSES"  # 480 < 990
    assert rows["cmd_arm_counter_1000"].ours == 500.0
    assert rows["cmd_setpoint_1000_p99"].target == 3.0
    # commands against the two-hop relay at their own rate; the relay against one hop
    assert rows["cmd_setpoint_1000_p99"].vs_floor == pytest.approx(7.0 / 0.7)
    assert rows["cmd_setpoint_1000_p99"].floor_name == "bare Zenoh relay, 2 hops"
    assert rows["zenoh_relay_100_p50"].vs_baseline == pytest.approx(0.3 / 0.1)
    assert rows["zenoh_relay_1000_p99"].ours == pytest.approx(0.7)
    assert rows["video_latency_vga_p50"].target_verdict == "meets"  # 8.25 ms ≤ 15
    assert rows["ik_analytic_per_s"].verdict == "n/a"
    assert rows["ik_analytic_per_s"].target_verdict == "MISSES"  # 3000 < 20 000
    assert rows["cpu_idle_core"].ours == pytest.approx(18.0)
    assert rows["cpu_idle_core"].target_verdict == "meets"  # 18 ≤ 25
    assert rows["cpu_idle_sim"].ours == pytest.approx(25.0)
    assert rows["cpu_teleop_sim"].ours == pytest.approx(50.0)
    assert rows["cpu_teleop_sim"].target_verdict == "n/a"  # only idle is budgeted
    assert rows["cpu_teleop_core"].floor == pytest.approx(24.0)  # the same run's teleop floor
    assert rows["cpu_teleop_core"].floor_name == "bare Zenoh, the same 1 kHz streams"
    assert rows["cpu_idle_core"].floor is None
    assert rows["cpu_idle_console"].ours == pytest.approx(6.0)


def test_verdict_rules() -> None:
    hi = Figure("k", "rate", "Hz", 80.0, "higher", paper=76.0)
    lo = Figure("k", "latency", "ms", 1.2, "lower", paper=1.0)
    assert (hi.verdict, lo.verdict) == ("meets", "MISSES")
    assert hi.vs_paper == pytest.approx(80 / 76)
    assert Figure("k", "x", "", None, "higher", paper=1.0).verdict == "no data"
    assert Figure("k", "x", "", 3.0, "higher").verdict == "n/a"
    assert Figure("k", "x", "", 3.0, "lower", baseline=0.0).vs_baseline is None
    met = Figure("k", "x", "ms", 0.4, "lower", target=0.4, target_name="issue 16")
    assert met.target_verdict == "meets" and met.verdict == "n/a"
    assert Figure("k", "x", "ms", 0.41, "lower", target=0.4, target_name="t").target_verdict == (
        "MISSES"
    )
    # a same-run target that was not measured cannot be met
    assert Figure("k", "x", "ms", 0.1, "lower", target_name="XML-RPC").target_verdict == "no data"
    assert Figure("k", "x", "ms", 0.1, "lower").target_verdict == "n/a"


def test_table_lists_every_figure_and_says_plainly_what_misses() -> None:
    phases = full_phases()
    del phases["video_vga"]
    phases["commands_1000hz"]["na"] = {"setpoint_ms": "robot/state showed no setpoint_ns"}
    phases["commands_1000hz"]["setpoint_ms"] = _summary(math.nan, math.nan)
    phases["commands_1000hz"]["setpoint_ms"].update(p50=None, p99=None)
    phases["cpu_teleop"] = {"na": {"*": "cpu_teleop failed: no stereo frames from vision"}}
    phases["cpu_idle"] = _cpu(**IDLE)  # vision and console were not running
    doc = document(phases, machine(), SETTINGS, ["the note"])
    text = table(doc)
    for f in doc["figures"].values():
        assert f"| {f['label']} |" in text
    assert "eclipse-zenoh" in text and "CPUs" in text and "(--quick)" in text
    assert (
        "MISSES THE PAPER: call decision status p50: ours 2 vs the paper's 1 ms (2× the "
        "paper's)." in text
    )
    assert (
        "MISSES THE PAPER: force rate while a 360×288 pair is in flight: ours 60 vs the "
        "paper's 76 Hz (21 % short)." in text
    )
    assert (
        "MISSES THE TARGET: commands reaching the arm, sent at 1 kHz: ours 480 vs 990 Hz "
        "(issue 16; 52 % short)." in text
    )
    assert (
        "MISSES THE TARGET: call arm status p50, faster than XML-RPC: ours 0.5 vs 0.35 ms "
        "(XML-RPC p50, same run; 1.43× the target)." in text
    )
    assert (
        "NOT MEASURED: stereo fps per eye, 640×480 (30 asked): phase video_vga did not run "
        "(see the run's notes and logs)" in text
    )
    assert "NOT MEASURED: master→setpoint p50, 1 kHz: robot/state showed no setpoint_ns" in text
    assert (
        "NOT MEASURED: teleop CPU: console: cpu_teleop failed: no stereo frames from vision" in text
    )
    assert (
        "MISSES THE TARGET: IK solves/s, analytic (8 branches): ours 3000 vs 20,000 1/s "
        "(issue 16; 85 % short)." in text
    )
    assert (
        "NOT MEASURED: idle CPU: whole sim system (+ vision, console; physics in arm): not "
        "running through the whole window: vision, console" in text
    )
    assert "NOT MEASURED: idle CPU: console: console was not running through the whole window" in (
        text
    )
    assert "cpu_idle_sim" in doc["target_misses"] and "cpu_idle_core" not in doc["target_misses"]
    assert "Note: the note" in text
    assert "video_fps_vga" in doc["misses"] and "rpc_decision_status_p50" in doc["misses"]
    assert "force_rate_alone" not in doc["misses"]
    assert "cmd_setpoint_1000_p50" in doc["target_misses"]
    header = [line for line in text.splitlines() if line.startswith("| figure")]
    assert header == [TABLE_HEADER]
    row = next(line for line in text.splitlines() if line.startswith("| force latency p50, alone"))
    assert row == (
        "| force latency p50, alone | 0.20 ms | 0.10 (bare Zenoh) | 2× | 0.060 (raw TCP) | 3.3× "
        "|  |  |  |  |  |"
    )
    row = next(line for line in text.splitlines() if line.startswith("| idle CPU: router"))
    assert row == (
        "| idle CPU: router + arm + force + decision | 18.0 % |  |  |  |  |  |  |  | ≤ 25.0 "
        "| meets |"
    )


def test_a_run_that_meets_everything_says_so() -> None:
    phases = full_phases()
    phases["force_stereo_paper"]["in_flight"]["rate_hz"] = 500.0
    phases["force_stereo_vga"] = {**_force(1000.0, 0.3), "in_flight": {"rate_hz": 995.0}}
    phases["rpc_decision_status"] = _summary(0.3, 2.0)
    phases["rpc_arm_status"] = _summary(0.3, 1.0)
    phases["commands_1000hz"]["reached_rate_hz"] = 999.0
    phases["commands_1000hz"]["arm_ms"] = _summary(0.3, 0.9)
    phases["commands_1000hz"]["setpoint_ms"] = _summary(0.8, 2.5)
    phases["ik"]["analytic_ik_per_s"] = 25_000.0
    phases["ik"]["fr3_solve_per_s"] = 6_000.0
    text = table(document(phases, machine(), SETTINGS))
    assert "Every figure with a counterpart in the paper meets it." in text
    assert "Every figure with a target meets it." in text
    assert "MISSES" not in text and "NOT MEASURED" not in text


def test_force_note_tells_source_from_transport() -> None:
    phases = full_phases()
    note = force_note(phases)
    assert note.startswith("force produced by the sensor / received by the bench: alone ")
    assert "0 lost: every sample the sensor produced arrived." not in note  # 2 lost at VGA
    assert note.endswith("; with 640×480 2 missing.")
    phases["force_stereo_vga"]["service"] = {"drops": 2, "samples": 500}
    assert force_note(phases).endswith(
        "; with 640×480 2 missing (2 dropped inside the force service)."
    )
    phases["force_stereo_vga"] = _force(500.0, 1.0)
    assert force_note(phases).endswith("0 lost: every sample the sensor produced arrived.")
    assert "with 640×480 500/500 Hz" in force_note(phases)
