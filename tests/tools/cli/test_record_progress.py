"""`telerobot record` tells how it is going: samples per topic every few seconds (issue 23
item 10), in its log on stderr, while stdout keeps its one JSON summary at the end."""

from __future__ import annotations

import json
from pathlib import Path

from tests.bus.test_router import spawned, telerobot
from tests.conftest import Net
from tests.tools.cli.test_introspect import Streamer


def force_count(line: str) -> int:
    """The robot/force count of a progress line ("… s: robot/force N, …; W written …")."""
    return int(line.split("robot/force ", 1)[1].replace(";", ",").split(",")[0])


def test_record_logs_samples_per_topic(net: Net, tmp_path: Path) -> None:
    streamer = Streamer(net.node("force"))
    out = tmp_path / "session.mcap"
    argv = telerobot("record", "-o", str(out), "--progress-s", "0.5", "--connect", net.endpoint)
    try:
        with spawned(argv) as child:  # stderr merged: log lines and the summary, in order
            first = child.expect(lambda s: " s: robot/force " in s)
            later = child.expect(lambda s: " s: robot/force " in s and force_count(s) > 0)
            child.stop()
            lines = child.rest()
    finally:
        streamer.close()
    assert str(out) in first and "written" in later and "dropped" in later
    summary = [json.loads(s) for s in lines if s.startswith("{")]
    assert len(summary) == 1 and summary[0]["error"] == ""
    assert summary[0]["written"] >= force_count(later)
