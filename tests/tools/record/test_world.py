"""The 3D views a recording holds: /tf (FK of the recorded joints), /robot_model, /workcell."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from services.bus import codec
from services.bus.messages import RobotState, vec
from services.control.arm.kinematics import DEFAULT_eMt, Puma560, qn
from services.geometry import rot_x
from services.tools.record import world
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState
from services.world.workcell.scene import default_scene

from .helpers import T0_NS, conforms, write_file

KIN = Puma560()
SCENE = default_scene()
RNG = np.random.default_rng(7)
QS = [np.asarray(qn)] + [
    KIN.q_lo + RNG.uniform(0.05, 0.95, 6) * (KIN.q_hi - KIN.q_lo) for _ in range(9)
]


def robot_state(seq: int, q: np.ndarray) -> bytes:
    oMe = KIN.fk_flange(q)
    oMt = KIN.fk_tool(q, DEFAULT_eMt)
    return codec.encode(
        RobotState(
            seq=seq,
            t_ns=T0_NS + seq,
            status="ready",
            q=vec(q),
            tool_p=vec(oMt.translation),
            tool_R=vec(oMt.rotation),
            flange_p=vec(oMe.translation),
            flange_R=vec(oMe.rotation),
            engage=0,
            cmd_seq=0,
            grip=0.0,
        )
    )


def _rx(deg: float) -> np.ndarray:
    return rot_x(np.radians(deg))


def workcell_objects(k: int) -> dict[str, dict[str, Any]]:
    """Block 2 carried along y, the bottle tilting, blocks 0 and 1 stacked."""
    top = 0.40
    objs: dict[str, dict[str, Any]] = {}
    poses = {
        "block0": ((0.5, -0.2, top + 0.025), np.eye(3)),
        "block1": ((0.5, -0.2, top + 0.075), np.eye(3)),
        "block2": ((0.55, -0.1 + 0.01 * k, 0.6), np.eye(3)),
    }
    for name, (p, R) in poses.items():
        objs[name] = {
            "kind": "box", "p": list(p), "R": list(vec(R)), "size": [0.05, 0.05, 0.05],
            "phase": "held" if name == "block2" else "resting", "on": "table",
            "tilt_deg": 0.0, "max_tilt_deg": 0.0,
        }  # fmt: skip
    objs["bottle"] = {
        "kind": "cylinder", "p": [0.55, 0.25, top], "R": list(vec(_rx(5.0 * k))),
        "size": [0.07, 0.07, 0.2], "phase": "resting", "on": "table",
        "tilt_deg": 5.0 * k, "max_tilt_deg": 5.0 * k,
        "liquid_ml": 600.0 - 10 * k, "spilled_ml": 10.0 * k,
    }  # fmt: skip
    return objs


def workcell_state(seq: int) -> bytes:
    return codec.encode(
        WorkcellState(
            seq=seq,
            t_ns=T0_NS + 1000 + seq,
            tool_p=(0.55, -0.1, 0.62),
            grip=1.0,
            held="block2",
            objects=workcell_objects(seq),
        )
    )


def _read(path: Path) -> tuple[dict[str, list[tuple[Any, Any, Any]]], list[Any]]:
    out: dict[str, list[tuple[Any, Any, Any]]] = defaultdict(list)
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, message in reader.iter_messages():
            out[channel.topic].append((schema, channel, message))
        attachments = list(reader.iter_attachments())
    return out, attachments


def _compose(tfs: list[dict[str, Any]]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """world → every frame, by walking the tree parent first."""
    poses = {"world": (np.zeros(3), np.eye(3))}
    for tf in tfs:  # written parent first
        p0, R0 = poses[tf["parent_frame_id"]]
        t = tf["translation"]
        p = np.array([t["x"], t["y"], t["z"]])
        R = world.rotation(tf["rotation"])
        poses[tf["child_frame_id"]] = (p0 + R0 @ p, R0 @ R)
    return poses


def test_transforms_reproduce_fk_of_the_recorded_joints_and_the_tool_pose(
    tmp_path: Path,
) -> None:
    path = tmp_path / "arm.mcap"
    items = [("robot/state", robot_state(i + 1, q)) for i, q in enumerate(QS)]
    write_file(path, items)
    topics, attachments = _read(path)
    tf_msgs = topics[world.TF_TOPIC]
    assert len(tf_msgs) == len(QS) == len(topics["robot/state"])
    for (schema, channel, message), q, (_, _, state_msg) in zip(
        tf_msgs, QS, topics["robot/state"], strict=True
    ):
        assert schema.name == world.FRAME_TRANSFORMS and schema.encoding == "jsonschema"
        assert channel.message_encoding == "json"
        doc = json.loads(message.data)
        assert conforms(json.loads(schema.data), doc) == []
        assert message.publish_time == state_msg.publish_time
        assert [tf["child_frame_id"] for tf in doc["transforms"]] == [
            "link1", "link2", "link3", "link4", "link5", "link6", "flange", "tool"
        ]  # fmt: skip
        stamp = doc["transforms"][0]["timestamp"]
        assert stamp["sec"] * 1_000_000_000 + stamp["nsec"] == state_msg.publish_time
        poses = _compose(doc["transforms"])
        # world → link i is DH frame i−1 turned by q_i: its origin is DH frame i−1's.
        origins = KIN.link_origins(q)
        for i in range(1, 7):
            assert np.allclose(poses[f"link{i}"][0], origins[i - 1], atol=1e-9)
        oMe = KIN.fk_flange(q)
        assert np.allclose(poses["flange"][0], oMe.translation, atol=1e-9)
        assert np.allclose(poses["flange"][1], oMe.rotation, atol=1e-9)
        st = json.loads(state_msg.data)
        assert np.allclose(poses["tool"][0], st["tool_p"], atol=1e-6)
        assert np.allclose(poses["tool"][1], np.reshape(st["tool_R"], (3, 3)), atol=1e-6)
    # The model: drawn once, each entity locked to a frame /tf moves.
    ((schema, _, message),) = topics[world.MODEL_TOPIC]
    model = json.loads(message.data)
    assert conforms(json.loads(schema.data), model) == []
    frames = {e["frame_id"] for e in model["entities"]}
    assert frames == {"world", "link1", "link2", "link3", "link4", "link5", "link6", "flange"}
    assert all(e["frame_locked"] for e in model["entities"])
    # The URDF attached names the same frame tree.
    (urdf,) = [a for a in attachments if a.name == world.URDF_NAME]
    robot = ET.fromstring(urdf.data)
    joints = {
        (j.find("parent").attrib["link"], j.find("child").attrib["link"])  # type: ignore[union-attr]
        for j in robot.iter("joint")
    }
    tf_pairs = {(tf["parent_frame_id"], tf["child_frame_id"]) for tf in doc["transforms"]}
    assert joints == tf_pairs


def test_workcell_objects_match_workcell_state(tmp_path: Path) -> None:
    path = tmp_path / "cell.mcap"
    write_file(path, [(WORKCELL_STATE.key, workcell_state(k)) for k in range(1, 6)])
    topics, _ = _read(path)
    updates = topics[world.WORKCELL_TOPIC]
    assert len(updates) == 5
    areas: list[float] = []
    for k, (schema, _, message) in enumerate(updates, start=1):
        assert schema.name == world.SCENE_UPDATE
        doc = json.loads(message.data)
        assert conforms(json.loads(schema.data), doc) == []
        entities = {e["id"]: e for e in doc["entities"]}
        assert "workcell/table" in entities
        for name, obj in workcell_objects(k).items():
            e = entities[f"workcell/{name}"]
            assert e["frame_id"] == "world" and not e["frame_locked"]
            prim = (e["cubes"] or e["cylinders"])[0]
            pos = prim["pose"]["position"]
            R = np.reshape(obj["R"], (3, 3))
            centre = np.asarray(obj["p"])
            if obj["kind"] == "cylinder":
                centre = centre + R @ np.array([0.0, 0.0, 0.5 * obj["size"][2]])
                assert len(e["cylinders"]) == 2  # the bottle and its liquid
            assert np.allclose([pos["x"], pos["y"], pos["z"]], centre, atol=1e-9)
            assert np.allclose(world.rotation(prim["pose"]["orientation"]), R, atol=1e-9)
            size = prim["size"]
            assert [size["x"], size["y"], size["z"]] == obj["size"]
            b, g, r = SCENE.solid(name).color
            assert [prim["color"][c] for c in "rgb"] == [r / 255, g / 255, b / 255]
        meta = {m["key"]: m["value"] for m in entities["workcell/block2"]["metadata"]}
        assert meta["held"] == "true" and meta["phase"] == "held"
        # 10 ml more spilled at each state, from a rim tilted more and more towards −y:
        # puddles on the table beside the bottle on that side, their area growing.
        puddles = entities["workcell/spills"]["cylinders"]
        assert puddles
        for pd in puddles:
            pos = pd["pose"]["position"]
            assert pos["z"] == pytest.approx(0.40 + 0.001)
            assert abs(pos["x"] - 0.55) < 1e-9 and 0.1 < pos["y"] < 0.25 - 0.035
        areas.append(sum(pd["size"]["x"] ** 2 for pd in puddles))
    assert areas == sorted(areas) and areas[0] < areas[-1]


def test_a_bad_workcell_state_is_kept_raw_with_no_3d_view(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    objs = workcell_objects(1)
    objs["block0"] = {"kind": "box"}  # no pose
    bad = codec.encode(
        WorkcellState(seq=1, t_ns=T0_NS, tool_p=(0, 0, 0), grip=0.0, held="", objects=objs)
    )
    sink, _ = write_file(path, [(WORKCELL_STATE.key, bad), (WORKCELL_STATE.key, workcell_state(2))])
    topics, _ = _read(path)
    assert len(topics["/raw/" + WORKCELL_STATE.key]) == 2
    assert len(topics[world.WORKCELL_TOPIC]) == 1
    assert sink.derive_errors == 1


def test_quaternions_round_trip_every_rotation_branch() -> None:
    for R in [np.eye(3), _rx(179.9), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
              np.diag([-1.0, -1.0, 1.0])] + [KIN.fk_tool(q).rotation for q in QS]:  # fmt: skip
        q = world.quaternion(R)
        assert q["w"] >= 0.0
        assert np.isclose(sum(v * v for v in q.values()), 1.0)
        assert np.allclose(world.rotation(q), R, atol=1e-12)


def test_no_3d_writes_only_the_bus_channels(tmp_path: Path) -> None:
    from services.tools.record.__main__ import parser

    assert parser().parse_args(["-o", "s.mcap", "--no-3d"]).no_3d
    path = tmp_path / "plain.mcap"
    items = [("robot/state", robot_state(1, QS[0])), (WORKCELL_STATE.key, workcell_state(1))]
    write_file(path, items, world=False)
    topics, attachments = _read(path)
    assert set(topics) == {
        "robot/state", "/raw/robot/state", WORKCELL_STATE.key, "/raw/" + WORKCELL_STATE.key
    }  # fmt: skip
    assert attachments == []
