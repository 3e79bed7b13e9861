"""`telerobot bench passivity` on a short grid: the JSON keys, the table, the plots."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.tools.bench.passivity import MEASURES, main, run, table


def test_run_names_every_measure_and_shows_the_instability_it_prevents() -> None:
    doc, results = run((0, 200))
    for delay in (0, 200):
        for on in ("on", "off"):
            for m in MEASURES:
                assert f"passivity_{delay}_{on}_{m}" in doc
    assert doc["passivity_200_off_stable"] is False
    assert doc["passivity_200_on_peak_force_n"] < doc["passivity_200_off_peak_force_n"] / 10
    # The transparency criterion, in the simulation: at 0 ms the operator feels
    # with TDPA what it feels without, within 5 %, and what it feels is the tool's force.
    felt_on, felt_off = doc["passivity_0_on_felt_force_n"], doc["passivity_0_off_felt_force_n"]
    assert felt_off > 5.0 and abs(felt_on - felt_off) < 0.05 * felt_off
    assert felt_on == pytest.approx(doc["passivity_0_on_steady_force_n"], rel=0.05)
    assert set(results) == {(0, False), (0, True), (200, False), (200, True)}
    rows = table(doc).splitlines()
    assert len(rows) == 2 + 4 and "NO" in rows[4]  # 200 ms, off


def test_cli_writes_json_and_plots(tmp_path: Path) -> None:
    out = tmp_path / "b.json"
    assert main(["--delays-ms", "50", "--json", str(out), "--plots", str(tmp_path)]) == 0
    doc = json.loads(out.read_text())
    assert doc["settings"]["delays_ms"] == [50]
    assert (tmp_path / "passivity_50ms.png").stat().st_size > 1000


def test_at_700ms_the_master_limiter_is_what_settles_the_contact() -> None:
    with_limit, _ = run((700,))
    damper_only, _ = run((700,), master_limit=False)
    assert with_limit["settings"]["master_limit"] is True
    assert with_limit["passivity_700_on_stable"] is True
    assert damper_only["passivity_700_on_stable"] is False
    assert (
        with_limit["passivity_700_on_oscillation_rms_n"]
        < damper_only["passivity_700_on_oscillation_rms_n"] / 10
    )
