"""Recording a Franka FR3 (7 joints, mounted, with its hand): the arm's description gives
the file its model and frames, whatever the recorder started before or after the arm."""

from __future__ import annotations

import io
import json
from collections import defaultdict
from collections.abc import Iterator
from contextlib import redirect_stdout
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from mcap.reader import make_reader

from services.bus import keys
from services.control.arm.config import ArmConfig
from services.control.arm.links import urdf_tree, urdf_with_tool
from services.control.arm.model import load_model
from services.control.arm.service import ArmService
from services.geometry import rot_z
from services.tools.cli.main import main as telerobot
from services.tools.record import foxglove3d
from services.tools.record.archive import Recording
from services.tools.record.recorder import Recorder, RecorderConfig, RecorderStats
from services.tools.record.report import analyze
from tests.conftest import Net, wait_until

from .test_foxglove3d import _compose

pytestmark = pytest.mark.system

FR3 = load_model("fr3")
DESC = keys.ARM_DESCRIPTION.key
NEW_TOOL_P = (0.0, 0.02, 0.15)
NEW_TOOL_R = tuple(float(x) for x in rot_z(0.3).reshape(9))


@dataclass(frozen=True)
class Files:
    early: Path
    """Recorder started before the arm: the description comes live."""
    late: Path
    """Recorder started after the arm: the description comes from the arm's cache."""
    stats: dict[str, RecorderStats]


def _wait_models(recorders: dict[str, Recorder], n: int) -> None:
    """Until every recorder has drawn the arm of n descriptions."""
    for name, rec in recorders.items():
        assert wait_until(
            lambda rec=rec: rec.stats().robot_models >= n,  # type: ignore[misc]
            10.0,
            what=f"the {name} recorder's arm model {n}",
        )


@pytest.fixture(scope="module")
def fr3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Files]:
    folder = tmp_path_factory.mktemp("fr3")
    early_path, late_path = folder / "early.mcap", folder / "late.mcap"
    net = Net()
    arm: ArmService | None = None
    recorders: dict[str, Recorder] = {}
    try:
        recorders["early"] = Recorder(
            net.node("record-early"), RecorderConfig(output=str(early_path), chunk_interval_s=0.2)
        )
        arm = ArmService(net.node("arm"), ArmConfig(model="fr3", sim_calibration_s=0.05))
        op = net.node("operator")
        state = op.subscribe(keys.STATE)
        assert state.wait_for(lambda s: True, 10.0) is not None
        recorders["late"] = Recorder(
            net.node("record-late"),
            RecorderConfig(output=str(late_path), keys=("robot/**",), chunk_interval_s=0.2),
        )
        _wait_models(recorders, 1)
        op.call("arm", "connect", {}, timeout_s=10.0)
        op.call("arm", "initialize", {"wait": True}, timeout_s=20.0)
        assert state.wait_for(lambda s: s.status == "ready", 20.0) is not None
        q1 = np.asarray(FR3.home) + np.array([0.3, 0.2, -0.2, 0.25, 0.3, -0.2, 0.4])
        op.call("arm", "move_joints", {"q": q1.tolist(), "wait": True}, timeout_s=30.0)
        op.call("arm", "set_tool", {"p": list(NEW_TOOL_P), "R": list(NEW_TOOL_R)}, timeout_s=10.0)
        _wait_models(recorders, 2)
        op.call("arm", "move_joints", {"q": list(FR3.home), "wait": True}, timeout_s=30.0)
        assert state.wait_count(state.received + 20, 10.0)
    finally:
        if arm is not None:
            arm.close()
        stats = {name: rec.stop() for name, rec in recorders.items()}
        net.close()
    yield Files(early_path, late_path, stats)


def _topics(path: Path) -> tuple[dict[str, list[Any]], list[Any]]:
    out: dict[str, list[Any]] = defaultdict(list)
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for _, channel, message in reader.iter_messages():
            out[channel.topic].append(message)
        attachments = list(reader.iter_attachments())
    return out, attachments


@pytest.mark.parametrize("which", ["early", "late"])
def test_the_robot_model_is_the_fr3_s_urdf_with_each_tool(fr3: Files, which: str) -> None:
    path = getattr(fr3, which)
    stats = fr3.stats[which]
    assert stats.dropped == 0 and stats.error == ""
    assert stats.arm_model == "fr3" and stats.robot_models == 2
    topics, attachments = _topics(path)
    # Each description once: the one the arm had at start-up (live, or from its cache) and
    # the one set_tool published.
    assert len(topics["/raw/" + DESC]) == 2
    want = [
        urdf_with_tool(FR3.urdf, FR3.flange_frame, FR3.tool_p, FR3.tool_R),
        urdf_with_tool(FR3.urdf, FR3.flange_frame, NEW_TOOL_P, NEW_TOOL_R),
    ]
    assert [json.loads(m.data)["data"] for m in topics[foxglove3d.DESCRIPTION_TOPIC]] == want
    assert [a.data.decode() for a in attachments if a.name == "fr3.urdf"] == want
    links = {j.child for j in urdf_tree(want[0])} | {j.parent for j in urdf_tree(want[0])}
    for m in topics[foxglove3d.MODEL_TOPIC]:
        model = json.loads(m.data)
        frames = {e["frame_id"] for e in model["entities"]}
        assert {"fr3_link0", "fr3_link7", "fr3_hand", "fr3_leftfinger"} <= frames <= links
        assert sum(len(e["models"]) for e in model["entities"]) == 9  # links 0 … 7, the hand
        assert all(e["frame_locked"] for e in model["entities"])
    # the model follows its description
    (d1, d2), (m1, m2) = topics["/raw/" + DESC], topics[foxglove3d.MODEL_TOPIC]
    assert d1.log_time == m1.log_time and d2.log_time == m2.log_time


@pytest.mark.parametrize("which", ["early", "late"])
def test_the_fr3_frames_compose_to_the_states_tool_poses(fr3: Files, which: str) -> None:
    """Each /tf message built from the description composes, world → … → tool, to its
    robot/state's tool pose within 1e-9; its flange is the state's flange, and the flange
    → tool transform the eMt in use."""
    tools = [
        pin.SE3(np.reshape(FR3.tool_R, (3, 3)), np.asarray(FR3.tool_p)),
        pin.SE3(np.reshape(NEW_TOOL_R, (3, 3)), np.asarray(NEW_TOOL_P)),
    ]
    pairs: dict[int, dict[str, bytes]] = defaultdict(dict)
    described_ns = None
    with getattr(fr3, which).open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(
            topics=["robot/state", "/tf", foxglove3d.MODEL_TOPIC]
        ):
            if channel.topic == foxglove3d.MODEL_TOPIC:
                described_ns = described_ns or message.log_time
            else:
                pairs[message.log_time][channel.topic] = message.data
    checked, used = 0, set()
    for log_ns, both in pairs.items():
        st = json.loads(both["robot/state"])
        assert len(st["q"]) == 7
        tfs = json.loads(both["/tf"])["transforms"]
        if len(tfs) == 2:  # before the description arrived: the state's own poses only
            assert described_ns is None or log_ns < described_ns
            continue
        poses = _compose(tfs)
        assert np.allclose(poses["tool"][0], st["tool_p"], atol=1e-9)
        assert np.allclose(poses["tool"][1], np.reshape(st["tool_R"], (3, 3)), atol=1e-9)
        assert np.allclose(poses["fr3_link8"][0], st["flange_p"], atol=1e-9)
        assert np.allclose(poses["fr3_link8"][1], np.reshape(st["flange_R"], (3, 3)), atol=1e-9)
        fMt = tfs[-1]
        assert (fMt["parent_frame_id"], fMt["child_frame_id"]) == ("fr3_link8", "tool")
        t = fMt["translation"]
        p, R = np.array([t["x"], t["y"], t["z"]]), foxglove3d.rotation(fMt["rotation"])
        k = next(
            i
            for i, eMt in enumerate(tools)
            if np.allclose(p, eMt.translation, atol=1e-9)
            and np.allclose(R, eMt.rotation, atol=1e-9)
        )
        used.add(k)
        checked += 1
    assert checked > 50 and used == {0, 1}


def test_the_report_reads_the_fr3_recording(fr3: Files, tmp_path: Path) -> None:
    msgs = list(Recording(fr3.early).raw())
    report = analyze([fr3.early])
    assert report.messages == len(msgs) and report.truncated == []
    states = [m for m in msgs if m.key == "robot/state"]
    assert report.key("robot/state").count == len(states) and report.key(DESC).count == 2
    assert report.key("robot/state").rejected == 0 and report.key(DESC).rejected == 0
    assert report.key(DESC).stalls == 0
    assert report.recorder is not None and report.recorder["arm_model"] == "fr3"
    assert len(report.traces.tool_p) > 0
    out = io.StringIO()
    with redirect_stdout(out):
        assert telerobot(["report", str(fr3.early), "--plots", str(tmp_path)]) == 0
    text = out.getvalue()
    assert "arm fr3" in text
    row = next(line for line in text.splitlines() if line.startswith("robot/state "))
    assert str(len(states)) in row.split()
    assert (tmp_path / "path.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    out = io.StringIO()
    with redirect_stdout(out):
        assert telerobot(["report", str(fr3.late), "--json"]) == 0
    data = json.loads(out.getvalue())
    assert data["recorder"]["arm_model"] == "fr3" and data["recorder"]["robot_models"] == 2
