"""The JSON document and the table, built from phases reduced by the run's own functions."""

from __future__ import annotations

import json
from typing import Any

import pytest

from services.bench import stats
from services.bench.probes import FrameRecord
from services.bench.report import (
    FIGURE_KEYS,
    PAPER,
    PHASE_KEYS,
    Figure,
    document,
    figures,
    machine,
    table,
)
from services.bench.run import force_figures, force_note, video_figures

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


def full_phases() -> dict[str, Any]:
    vp, _ = _video(17.0, 360, 288)
    vv, _ = _video(30.0, 640, 480)
    with_video = _force(1000.0, 0.4)
    with_video["in_flight"] = {"count": 12, "covered_s": 0.2, "rate_hz": 60.0}
    return {
        "force_alone": _force(1000.0, 0.2),
        "force_stereo_paper": with_video,
        "force_stereo_vga": {**_force(500.0, 1.0, lose=(3, 4)), "in_flight": None},
        "video_paper": vp,
        "video_vga": vv,
        "commands_100hz": {
            "forwarded_rate_hz": 98.0,
            "forward_ms": _summary(0.8, 2.0),
            "applied_ms": _summary(3.0, 6.0),
        },
        "commands_1000hz": {
            "forwarded_rate_hz": 480.0,
            "forward_ms": _summary(0.7, 2.5),
            "applied_ms": _summary(3.1, 7.0),
        },
        "rpc_decision_status": _summary(2.0, 5.0),
        "rpc_decision_supervisor": _summary(0.6, 1.5),
        "rpc_puma_status": _summary(0.5, 1.2),
        "ik": {"n": 10.0, "analytic_ik_per_s": 3000.0, "dls_steps_per_s": 26000.0},
        "baseline_tcp": {
            "rate_hz": 999.0,
            "latency_ms": _summary(0.06, 0.2),
            "loss": {"lost": 0},
        },
        "baseline_xmlrpc": {"latency_ms": _summary(0.35, 1.1), "calls": 100},
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
    assert doc["schema"] == "telerobot-bench/1"
    assert set(FIGURE_KEYS) <= set(doc["figures"])
    assert list(doc["figures"]) == list(FIGURE_KEYS)
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
        "vs_paper",
        "vs_baseline",
        "verdict",
    }
    for key in FIGURE_KEYS:
        assert set(doc["figures"][key]) == fields
    assert set(doc["machine"]) >= {"nproc", "cpu_model", "python", "zenoh"}
    assert doc["paper"] == PAPER
    json.loads(json.dumps(doc, allow_nan=False))
    # every figure of a complete run has a value
    assert [k for k in FIGURE_KEYS if doc["figures"][k]["ours"] is None] == [
        "force_rate_in_flight_vga"  # set to None above: no pair was in flight
    ]


def test_figures_compare_with_paper_and_baseline() -> None:
    rows = {f.key: f for f in figures(full_phases())}
    alone = rows["force_rate_alone"]
    assert alone.paper == 1000.0 and alone.baseline == 999.0 and alone.baseline_name == "raw TCP"
    assert alone.verdict == "meets"
    assert rows["force_rate_in_flight_paper"].ours == 60.0
    assert rows["force_rate_in_flight_paper"].verdict == "MISSES"  # 60 < 76
    assert rows["force_rate_stereo_vga"].verdict == "meets"  # 998 Hz > 250
    assert rows["force_lost_stereo_vga"].ours == 2.0
    assert rows["rpc_puma_status_p50"].vs_baseline == pytest.approx(0.5 / 0.35)
    assert rows["rpc_decision_status_p50"].verdict == "MISSES"  # 2 ms > ~1 ms
    assert rows["rpc_decision_supervisor_p50"].verdict == "meets"
    assert rows["cmd_rate_100"].verdict == "meets"  # 98 ≥ 50
    assert rows["ik_analytic_per_s"].verdict == "n/a"


def test_verdict_rules() -> None:
    hi = Figure("k", "rate", "Hz", 80.0, "higher", paper=76.0)
    lo = Figure("k", "latency", "ms", 1.2, "lower", paper=1.0)
    assert (hi.verdict, lo.verdict) == ("meets", "MISSES")
    assert hi.vs_paper == pytest.approx(80 / 76)
    assert Figure("k", "x", "", None, "higher", paper=1.0).verdict == "no data"
    assert Figure("k", "x", "", 3.0, "higher").verdict == "n/a"
    assert Figure("k", "x", "", 3.0, "lower", baseline=0.0).vs_baseline is None


def test_table_lists_every_figure_and_says_plainly_what_misses() -> None:
    phases = full_phases()
    del phases["video_vga"]
    doc = document(phases, machine(), SETTINGS, ["the note"])
    text = table(doc)
    for f in doc["figures"].values():
        assert f"| {f['label']} |" in text
    assert "eclipse-zenoh" in text and "CPUs" in text and "(--quick)" in text
    assert (
        "MISSES THE PAPER: call decision status p50 (2 nested calls): ours 2 vs the paper's "
        "1 ms (2× the paper's)." in text
    )
    assert (
        "MISSES THE PAPER: force rate while a 360×288 pair is in flight: ours 60 vs the "
        "paper's 76 Hz (21 % short)." in text
    )
    assert "NOT MEASURED: stereo fps per eye, 640×480 (30 asked)" in text
    assert "Note: the note" in text
    assert "video_fps_vga" in doc["misses"] and "rpc_decision_status_p50" in doc["misses"]
    assert "force_rate_alone" not in doc["misses"]
    header = [line for line in text.splitlines() if line.startswith("| figure")]
    assert header == [
        "| figure | ours | baseline (same run) | ours/baseline | paper | ours/paper | verdict |"
    ]


def test_a_run_that_meets_everything_says_so() -> None:
    phases = full_phases()
    phases["force_stereo_paper"]["in_flight"]["rate_hz"] = 500.0
    phases["force_stereo_vga"]["in_flight"] = {"rate_hz": 400.0}
    phases["rpc_decision_status"] = _summary(0.9, 2.0)
    text = table(document(phases, machine(), SETTINGS))
    assert "Every figure with a counterpart in the paper meets it." in text
    assert "MISSES" not in text


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
