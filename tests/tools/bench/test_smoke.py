"""The whole `telerobot bench --quick` against the real services (slow: opt-in)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from services.tools.bench.report import FIGURE_KEYS, PHASE_KEYS
from services.tools.cli.bench import main

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        os.environ.get("TELEROBOT_BENCH_SMOKE") != "1",
        reason="the full bench run takes about two minutes: set TELEROBOT_BENCH_SMOKE=1",
    ),
]


@pytest.mark.timeout(600)
def test_quick_run_writes_every_figure(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    plot = tmp_path / "plot.png"
    code = main(
        ["--quick", "--json", str(out), "--plot", str(plot), "--logs", str(tmp_path / "logs")]
    )
    assert code == 0
    doc = json.loads(out.read_text())
    assert set(FIGURE_KEYS) <= set(doc["figures"])
    assert set(PHASE_KEYS) <= set(doc["phases"])
    assert plot.is_file()
    assert doc["phases"]["force_alone"]["received"] > 0
    assert doc["phases"]["video_paper"]["frames_l"] > 0
    assert doc["phases"]["commands_100hz"]["reached_distinct"] > 0
    assert doc["phases"]["commands_100hz"]["arm_ms"]["n"] > 0
    assert doc["phases"]["baseline_zenoh"]["received"] > 0
    assert doc["phases"]["baseline_zenoh_query"]["latency_ms"]["n"] > 0
    for key in ("cpu_idle", "cpu_teleop"):
        assert set(doc["phases"][key]["services"]) >= {"router", "arm", "force", "console"}
        assert doc["phases"][key]["sim_pct"] is not None
    assert doc["phases"]["cpu_teleop"]["video"]["frames_l"] > 0
    floor = doc["phases"]["teleop_floor"]
    assert floor["na"] == {} and floor["core_pct"] == pytest.approx(sum(floor["services"].values()))
