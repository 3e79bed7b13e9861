"""The paper's three tasks end to end over Zenoh, headless.

Each test runs on a private network: the arm (simulated arm at home), the force service
(simulated wrist), the decision server and the workcell simulation, each on a node of its
own, and the operator's station (a master service on a virtual device, id `operator`)
with the scripted person, who drives the arm only through that master. Assertions are on
the task's measures, as the operator sees them, and on the supervisor's counters.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest

from services.tools.cell.sim import SimCell, light_cell
from services.tools.tasks.metrics import TaskReport
from services.tools.tasks.system import Station, run_task
from tests.conftest import Net

pytestmark = pytest.mark.system


@pytest.fixture(params=["puma560"])
def station(net: Net, request: pytest.FixtureRequest) -> Iterator[Station]:
    cell: SimCell = light_cell(net.node, request.param)
    st: Station | None = None
    try:
        cell.start()
        st = Station(net.node)
        yield st
    finally:
        if st is not None:
            st.close()
        cell.close()


def common_checks(report: TaskReport) -> None:
    assert report.error is None, "\n".join([report.error or "", *report.log])
    assert report.success, report.table()
    # the palm never touched anything, nothing was pushed into anything, no e-stop
    assert report.interventions["contact"] == 0, report.table()
    assert report.interventions["estop"] == 0
    assert report.workcell["collisions"] == 0
    assert report.workcell["missed"] == 0
    # the arm was driven through the master, with the master-shift and the scale knobs
    assert report.operator["clutches"] >= 1
    assert report.operator["scale_changes"] >= 1
    assert report.events.get("decision:lease", 0) >= 1
    # printed both ways
    assert json.loads(report.to_json())["success"] is True
    assert "SUCCESS" in report.table()


@pytest.mark.parametrize("station", ["puma560", "fr3"], indirect=True)
def test_task1_tool_pose_within_2_mm_and_1_degree(station: Station) -> None:
    report = run_task(1, station)
    common_checks(report)
    assert report.measures["position_error_mm"] < 2.0
    assert report.measures["orientation_error_deg"] < 1.0
    assert report.operator["frame_changes"] >= 1


def test_task2_three_blocks_stacked(station: Station) -> None:
    report = run_task(2, station)
    common_checks(report)
    assert report.measures["blocks_stacked"] == 3
    assert report.measures["column"] == ["block0", "block1", "block2"]
    # stacked by physics: where the fingers let go, nothing snaps it into place
    assert report.measures["misalignment_mm"] < 5.0
    assert report.workcell["grasps"] == 2 and report.workcell["releases"] == 2


def test_task3_bottle_never_tilts_past_15_degrees_and_spills_nothing(station: Station) -> None:
    report = run_task(3, station)
    common_checks(report)
    assert report.measures["max_tilt_deg"] < 15.0
    assert report.measures["spilled_ml"] == 0.0
    assert report.measures["place_error_mm"] < 10.0
    assert report.measures["turned_deg"] == pytest.approx(90.0, abs=1.0)
    assert report.workcell["toppled"] == 0
