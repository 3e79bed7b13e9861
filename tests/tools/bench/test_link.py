"""`telerobot bench link` (issue 41): the figures and the table from a run's records (pure),
the command line's refusals, and one short condition for real over QUIC with mixed
reliability through the emulated link (root and /dev/net/tun or netem). The transports'
endpoints and TLS files: tests/tools/tdpa/test_transports.py."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from services.tools.bench import link, link_floor
from services.tools.tdpa.netem import unavailable


def record(rtt_ms: float) -> tuple[dict[str, Any], dict[str, list[int]]]:
    """A station's record of 1 s: 100 commands (every 10 ms), 10 of them not arriving, 5
    more not forwarded; force at 1 kHz with 10 lost; 10 pairs, the level going 0 → 1."""
    t0 = 1_000_000_000_000
    sent = [t0 + i * 10_000_000 for i in range(100)]
    one_way = int(rtt_ms / 2 * 1e6)
    force = [(t0 + i * 1_000_000 + one_way, i, t0 + i * 1_000_000) for i in range(1000) if i % 100]
    frames = [(t0 + i * 100_000_000 + one_way + 20_000_000, i, t0 + i * 100_000_000, 320, 240,
               9000) for i in range(10)]  # fmt: skip
    op = {
        "t0_ns": t0,
        "t1_ns": t0 + 1_000_000_000,
        "sent_t_ns": sent,
        "commands": {
            "arm_ms": {"n": 50, "p50": rtt_ms / 2 + 2, "p99": rtt_ms / 2 + 9},
            "engagements": 1,
        },
        "round_trip_ms": [rtt_ms + 5.0] * 99 + [rtt_ms + 50.0],
        "force": force,
        "frames": frames,
        "levels": [(t0, 0), (t0 + 500_000_000, 1)],
        "events": [(t0, "vision", "status", "video_level"), (t0, "decision", "watchdog", "")],
    }
    robot = {"arrived": sent[:90], "forwarded": [*sent[:85], 12345]}
    return op, robot


def test_figures_from_a_record() -> None:
    op, robot = record(200.0)
    f = link.figures(link.Condition("quic-mixed", 200.0, 2.0), op, robot)
    assert f["cmds_sent"] == 100 and f["cmds_arrived"] == 90 and f["cmds_reached"] == 85
    assert f["cmds_arrived_pct"] == pytest.approx(90.0)
    assert f["round_trip_ms"]["p50"] == pytest.approx(205.0)
    assert f["round_trip_p50_ratio"] == pytest.approx(205.0 / 200.0)
    assert f["cmd_age_p99_over_one_way_ms"] == pytest.approx(9.0)
    assert f["force_rate_hz"] == pytest.approx(990.0)
    assert f["force_lost_pct"] == pytest.approx(100 * 9 / 999)
    assert f["force_age_ms"]["p50"] == pytest.approx(100.0)
    assert f["video_fps"] == pytest.approx(10.0) and f["video_size"] == "320x240"
    assert f["video_age_ms"]["p50"] == pytest.approx(120.0)
    assert (f["video_level_final"], f["video_level_max"], f["video_level_changes"]) == (1, 1, 1)
    assert f["watchdog_holds"] == 1 and f["rate_mbit"] == 2.0
    text = link.table({"quic-mixed_200ms_2mbit": f, "tcp_700ms": {"error": "boom"}})
    lines = text.splitlines()
    assert lines[0].split()[:3] == ["condition", "rt", "p50"]
    row = lines[2].split()
    assert row[0] == "quic-mixed_200ms_2mbit" and row[1] == "205" and row[3] == "1.02"
    assert "320x240" in row and lines[3].startswith("tcp_700ms") and "failed: boom" in lines[3]


def test_zero_round_trip_has_no_ratio() -> None:
    op, robot = record(0.0)
    f = link.figures(link.Condition("tcp", 0.0), op, robot)
    assert f["round_trip_p50_ratio"] is None and f["round_trip_p99_ratio"] is None


def test_the_sweep_and_its_keys() -> None:
    conds = link.conditions(("tcp", "quic-mixed"), (0.0, 700.0), 2.0, 0.01, 0.1, video=False)
    assert [c.key for c in conds] == [
        "tcp_0ms_2mbit_novideo",
        "tcp_700ms_2mbit_novideo",
        "quic-mixed_0ms_2mbit_novideo",
        "quic-mixed_700ms_2mbit_novideo",
    ]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--transports", "tcp,sctp"], "--transports"),
        (["--rtt-ms", "50,fast"], "--rtt-ms takes numbers"),
        (["--rtt-ms", "20000"], "--rtt-ms: each within"),
        (["--loss", "1.0"], "--loss in"),
        (["--duration-s", "0"], "--duration-s in"),
    ],
)
def test_bad_options_are_refused_by_name(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as done:
        link.main(argv)
    assert done.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.system
@pytest.mark.timeout(300)
@pytest.mark.skipif(unavailable() is not None, reason=f"no emulated link: {unavailable()}")
def test_one_short_condition_over_quic_with_mixed_reliability(tmp_path: Path) -> None:
    """The whole path for real: the robot host's processes and the station in their
    namespaces, QUIC datagrams through the delay line (or netem), 1 % loss. Counts only:
    the figures themselves are the bench's, on a quiet machine."""
    out = tmp_path / "link.json"
    argv = ["--transports", "quic-mixed", "--rtt-ms", "0", "--duration-s", "3", "--floor-s", "1"]
    code = link.main([*argv, "--json", str(out), "--logs", str(tmp_path / "logs")])
    doc = json.loads(out.read_text())
    f = doc["conditions"]["quic-mixed_0ms"]
    assert code == 0, f
    assert f["cmds_sent"] > 0 and f["cmds_arrived"] > 0 and f["cmds_reached"] > 0
    assert f["cmds_arrived"] <= f["cmds_sent"]
    assert f["force_age_ms"]["n"] > 0 and f["round_trip_ms"]["n"] > 0
    assert f["video_fps"] > 0 and f["video_level_final"] is not None
    if f["emulator"] == "delayline":
        assert f["emulator_counts"]["forwarded"] > 0
    assert doc["settings"]["transports"] == ["quic-mixed"]
    # the bare-Zenoh floor over its own link of the same shape: 1 s each way, counted
    floor = f["floor"]
    assert "error" not in floor, floor
    assert floor["down"]["sent"] == 1000 and floor["up"]["sent"] == 500
    assert 0 < floor["down"]["received"] <= 1000 and 0 < floor["up"]["received"] <= 500
    assert floor["down"]["age_p50_ms"] >= 0.0 and floor["down"]["age_p99_ms"] >= 0.0


def test_the_floor_summary_counts_and_orders_and_the_table_shows_it() -> None:
    s = link_floor.summary([5.0, 1.0, 3.0, 2.0], sent=8)
    assert s == {
        "sent": 8,
        "received": 4,
        "delivered_pct": 50.0,
        "age_p50_ms": pytest.approx(2.5),  # numpy's linear percentiles, as the bench's
        "age_p99_ms": pytest.approx(4.94),
    }
    empty = link_floor.summary([], sent=10)
    assert empty["received"] == 0 and empty["delivered_pct"] == 0.0
    assert empty["age_p50_ms"] is None and empty["age_p99_ms"] is None
    assert link_floor.summary([], sent=0)["delivered_pct"] is None
    op, robot = record(200.0)
    f = link.figures(link.Condition("quic-mixed", 200.0, 2.0), op, robot)
    f["floor"] = {"down": {**s, "delivered_pct": 73.8, "age_p50_ms": 269.6, "age_p99_ms": 3646.3}}
    line = link.table({"quic-mixed_200ms_2mbit": f}).splitlines()[-1]
    assert line.split()[-3:] == ["73.8", "269.6", "3646.3"]
    f["floor"] = {"error": "the robot side did not start"}
    assert link.table({"x": f}).splitlines()[-1].split()[-3:] == ["–", "–", "–"]
