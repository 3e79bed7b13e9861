"""`telerobot bench passivity` on a short grid: the JSON keys, the table, the plots."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.tools.tdpa.sim_bench import (
    MEASURES,
    SEED_FIGURES,
    main,
    run,
    seed_figures,
    seeds,
    seeds_table,
    table,
)


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


def test_cli_writes_json_and_plots(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "b.json"
    assert main(["--delays-ms", "50", "--json", str(out), "--plots", str(tmp_path)]) == 0
    doc = json.loads(out.read_text())
    assert doc["settings"]["delays_ms"] == [50]
    assert (tmp_path / "passivity_50ms.png").stat().st_size > 1000
    # each run: contact, felt and intended force over the two ports' reservoirs
    import cv2

    for on in ("on", "off"):
        img = cv2.imread(str(tmp_path / f"passivity_50ms_{on}.png"))
        assert img is not None and img.shape[0] > 500  # two panels stacked
    # the table says what it is of
    said = capsys.readouterr().out
    assert said.startswith("Model: a simulated 1-DoF teleoperation loop at 1000 Hz")
    assert "5000 N/m wall" in said and "0.5 kg master device" in said


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


def test_cli_slave_port_runs_the_services_port_in_the_simulation(tmp_path: Path) -> None:
    for bad in (["--slave-port", "--link"], ["--slave-port", "--slave-speed", "0"]):
        with pytest.raises(SystemExit):
            main(bad)
    out = tmp_path / "p.json"
    assert main(["--delays-ms", "700", "--slave-port", "--json", str(out), "--plots", ""]) == 0
    doc = json.loads(out.read_text())
    assert doc["settings"]["slave_port"] is True
    # The service's port presses and holds at 700 ms (it grazed the wall, owing, before
    # the forgiveness), and differs from the reference controller's run.
    assert doc["passivity_700_on_stable"] is True
    assert doc["passivity_700_on_steady_force_n"] > 3.0
    ref, _ = run((700,))
    assert ref["settings"]["slave_port"] is False
    assert ref["passivity_700_on_steady_force_n"] != doc["passivity_700_on_steady_force_n"]


def test_seeds_sum_up_each_seeds_run() -> None:
    summary = seeds(2, (200,))
    docs = [run((200,), seed=seed)[0] for seed in (1, 2)]
    for on in ("off", "on"):
        k = f"passivity_200_{on}_"
        assert summary[k + "seeds_stable"] == sum(d[k + "stable"] for d in docs)
        assert summary[k + "seeds_settled"] == sum(d[k + "settled"] for d in docs)
        swings = [100 * d[k + "swing_rms_n"] / d[k + "steady_force_n"] for d in docs]
        assert summary[k + "seeds_swing_max_pct"] == pytest.approx(max(swings), abs=1e-3)
        felt = [100 * d[k + "felt_force_n"] / d[k + "steady_force_n"] for d in docs]
        assert summary[k + "seeds_felt_min_pct"] == pytest.approx(min(felt), abs=1e-3)
        gen = max(d[k + "energy_generated_j"] for d in docs)
        assert summary[k + "seeds_generated_max_j"] == gen
    assert summary["passivity_200_off_seeds_stable"] == 0  # bounces in both seeds
    assert summary["passivity_200_on_seeds_stable"] == 2
    assert len(summary) == 2 * len(SEED_FIGURES)
    rows = seeds_table(summary, (200,), 2).splitlines()
    assert rows[0] == "seeds 1 … 2:" and len(rows) == 3 + 2
    assert "0 / 2" in rows[3] and "2 / 2" in rows[4]


def test_cli_model_and_tangential_gain_are_the_links(capsys: pytest.CaptureFixture[str]) -> None:
    """`--model` picks the arm of `--link`'s robot side, `--tangential-gain` its master's
    friction shown; the simulation has neither, and a model not shipped or a gain outside
    0 … 1 is refused before anything runs."""
    for bad in (["--model", "fr3"], ["--link", "--model", "kuka"]):
        with pytest.raises(SystemExit):
            main(bad)
        assert "--model" in capsys.readouterr().err
    for bad in (["--tangential-gain", "0"], ["--link", "--tangential-gain", "1.5"]):
        with pytest.raises(SystemExit):
            main(bad)
        assert "--tangential-gain" in capsys.readouterr().err


def test_cli_seeds_is_the_simulations(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["--seeds", "3", "--link"])
    assert "--seeds" in capsys.readouterr().err
    out = tmp_path / "s.json"
    assert main(["--delays-ms", "0", "--seeds", "2", "--json", str(out), "--plots", ""]) == 0
    doc = json.loads(out.read_text())
    assert doc["settings"]["seeds"] == 2
    assert doc["passivity_0_on_seeds_settled"] == 2
    assert "seeds 1 … 2:" in capsys.readouterr().out


def test_a_run_without_a_steady_force_is_left_out_of_the_percentages() -> None:
    def one(steady: float, swing: float, felt: float) -> dict[str, object]:
        return {
            "steady_force_n": steady,
            "swing_rms_n": swing,
            "oscillation_rms_n": 2 * swing,
            "felt_force_n": felt,
            "energy_generated_j": 0.001,
            "stable": steady > 0.0,
            "settled": False,
        }

    got = seed_figures([one(8.0, 0.4, 6.0), one(0.0, 0.0, 0.0), one(4.0, 0.4, 4.0)])
    assert got["stable"] == 2 and got["settled"] == 0
    assert got["swing_max_pct"] == 10.0 and got["rms_max_pct"] == 20.0  # 0.4 of 4 N
    assert (got["felt_min_pct"], got["felt_max_pct"]) == (75.0, 100.0)
    none = seed_figures([one(0.0, 0.0, 0.0)])
    assert none["swing_max_pct"] is None and none["felt_min_pct"] is None
    json.dumps(none, allow_nan=False)  # no infinity in the document
    summary = {f"passivity_0_{on}_seeds_{f}": v for on in ("off", "on") for f, v in none.items()}
    row = seeds_table(summary, (0,), 1).splitlines()[-1]
    assert row.split()[:2] == ["0", "on"] and row.count("–") == 3  # swing, RMS, felt


def test_cli_twist_measures_the_moment_too(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        main(["--twist", "--slave-speed", "0"])
    out = tmp_path / "t.json"
    assert (
        main(["--delays-ms", "200", "--twist", "--json", str(out), "--plots", str(tmp_path)]) == 0
    )
    doc = json.loads(out.read_text())
    assert doc["settings"]["twist"] is True and doc["settings"]["dofs"] == 3
    for on in ("on", "off"):
        for m in MEASURES:
            assert f"passivity_200_{on}_moment_{m}" in doc
    assert doc["passivity_200_on_moment_stable"] is True
    assert doc["passivity_200_off_moment_stable"] is False
    assert doc["passivity_200_on_stable"] is True  # the press holds beside the turn
    assert (tmp_path / "passivity_200ms_moment.png").stat().st_size > 1000
    assert "the moment (N·m" in capsys.readouterr().out
