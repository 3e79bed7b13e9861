"""The 3D views a recording holds, for any arm its description describes: /tf (the URDF's
frames at the recorded joints), /robot_model and /robot_description, /workcell."""

from __future__ import annotations

import base64
import json
import logging
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from mcap.reader import make_reader

from services.bus import codec, keys
from services.bus.messages import vec
from services.control.arm.links import LinkPoses, urdf_tree, urdf_with_tool
from services.control.arm.model import ArmModel, load_model
from services.control.arm.puma560 import DEFAULT_eMt, Puma560, qn
from services.geometry import rot_x, rot_z
from services.tools.record import foxglove3d
from services.tools.record.recorder import McapSink, Received, RecorderConfig
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState
from services.world.workcell.scene import default_scene

from .helpers import T0_NS, FakeClock, arm_state, conforms, description, state, write_file

PUMA = load_model("puma560")
FR3 = load_model("fr3")
KIN = Puma560()
SCENE = default_scene()
RNG = np.random.default_rng(7)
QS = [np.asarray(qn)] + [
    KIN.q_lo + RNG.uniform(0.05, 0.95, 6) * (KIN.q_hi - KIN.q_lo) for _ in range(9)
]
DESC = keys.ARM_DESCRIPTION.key


def robot_state(seq: int, q: np.ndarray) -> bytes:
    """A PUMA state, its poses in closed form (the DH table, not the URDF)."""
    return arm_state(seq, q, KIN.fk_flange(q), DEFAULT_eMt)


def random_q(model: ArmModel, n: int, seed: int = 3) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(model.q_lo), np.asarray(model.q_hi)
    return [lo + rng.uniform(0.05, 0.95, model.n) * (hi - lo) for _ in range(n)]


def tool_se3(p: Any, R: Any) -> pin.SE3:
    return pin.SE3(np.reshape(np.asarray(R, dtype=float), (3, 3)), np.asarray(p, dtype=float))


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
        R = foxglove3d.rotation(tf["rotation"])
        poses[tf["child_frame_id"]] = (p0 + R0 @ p, R0 @ R)
    return poses


def _joints(urdf: str) -> set[tuple[str, str]]:
    return {(j.parent, j.child) for j in urdf_tree(urdf)}


def _doc(message: Any) -> Any:
    return json.loads(message.data)


def test_puma_frames_reproduce_its_dh_forward_kinematics_and_the_tool_pose(
    tmp_path: Path,
) -> None:
    """The PUMA's description drives the scene: its URDF's frames at the recorded q are the
    contract's DH frames (closed-form FK, not the URDF's), and world → tool is the state's."""
    path = tmp_path / "arm.mcap"
    items = [(DESC, description(PUMA))]
    items += [("robot/state", robot_state(i + 1, q)) for i, q in enumerate(QS)]
    sink, written = write_file(path, items)
    topics, attachments = _read(path)
    tf_msgs = topics[foxglove3d.TF_TOPIC]
    assert len(tf_msgs) == len(QS) == len(topics["robot/state"])
    for (schema, channel, message), q, (_, _, state_msg) in zip(
        tf_msgs, QS, topics["robot/state"], strict=True
    ):
        assert schema.name == foxglove3d.FRAME_TRANSFORMS and schema.encoding == "jsonschema"
        assert channel.message_encoding == "json"
        doc = _doc(message)
        assert conforms(json.loads(schema.data), doc) == []
        assert message.publish_time == state_msg.publish_time
        assert [tf["child_frame_id"] for tf in doc["transforms"]] == [
            "link1", "link2", "link3", "link4", "link5", "link6", "flange", "tool"
        ]  # fmt: skip
        stamp = doc["transforms"][0]["timestamp"]
        assert stamp["sec"] * 1_000_000_000 + stamp["nsec"] == state_msg.publish_time
        poses = _compose(doc["transforms"])
        # world → link i is DH frame i−1 turned by q_i: its origin is joint i's.
        origins = KIN.link_origins(q)
        for i in range(1, 7):
            assert np.allclose(poses[f"link{i}"][0], origins[i], atol=1e-9)
        oMe = KIN.fk_flange(q)
        assert np.allclose(poses["flange"][0], oMe.translation, atol=1e-9)
        assert np.allclose(poses["flange"][1], oMe.rotation, atol=1e-9)
        st = _doc(state_msg)
        assert np.allclose(poses["tool"][0], st["tool_p"], atol=1e-9)
        assert np.allclose(poses["tool"][1], np.reshape(st["tool_R"], (3, 3)), atol=1e-9)
    # The model: drawn once, each entity locked to a frame /tf moves; written right after
    # the description, at its receive time.
    ((schema, channel, message),) = topics[foxglove3d.MODEL_TOPIC]
    assert channel.metadata == {"key": DESC, "role": "derived", "type": foxglove3d.SCENE_UPDATE}
    assert message.log_time == message.publish_time == written[0].log_time_ns
    model = _doc(message)
    assert conforms(json.loads(schema.data), model) == []
    frames = {e["frame_id"] for e in model["entities"]}
    assert frames == {"world", "link1", "link2", "link3", "link4", "link5", "link6", "flange"}
    assert all(e["frame_locked"] for e in model["entities"])
    # the tool shaft, flange → tool point
    (flange,) = [e for e in model["entities"] if e["frame_id"] == "flange"]
    (shaft,) = flange["cylinders"]
    assert shaft["size"]["z"] == pytest.approx(np.linalg.norm(DEFAULT_eMt.translation))
    # The URDF, on /robot_description and attached: the description's, with the tool link,
    # naming the same frame tree as /tf.
    want = urdf_with_tool(PUMA.urdf, "flange", PUMA.tool_p, PUMA.tool_R)
    ((schema, _, message),) = topics[foxglove3d.DESCRIPTION_TOPIC]
    assert schema.name == "std_msgs/String" and _doc(message) == {"data": want}
    assert conforms(json.loads(schema.data), _doc(message)) == []
    (urdf,) = [a for a in attachments if a.name == "puma560.urdf"]
    assert urdf.data.decode() == want and urdf.media_type == "application/xml"
    tf_pairs = {(tf["parent_frame_id"], tf["child_frame_id"]) for tf in doc["transforms"]}
    assert _joints(want) == tf_pairs
    assert sink.stats.arm_model == "puma560" and sink.stats.robot_models == 1
    assert sink.derive_errors == 0


def test_fr3_frames_compose_to_its_tool_pose_and_its_model_is_its_urdf(tmp_path: Path) -> None:
    """A 7-joint arm with a mount, fixed links and fingers: every frame of its URDF at the
    recorded q, world → tool the states' tool poses within 1e-9, and its visuals (meshes
    embedded) where Pinocchio places them."""
    kin = FR3.kinematics()
    eMt = tool_se3(FR3.tool_p, FR3.tool_R)
    qs = [np.asarray(FR3.home), *random_q(FR3, 7)]
    items = [(DESC, description(FR3))]
    items += [("robot/state", arm_state(i + 1, q, kin.fk_flange(q), eMt)) for i, q in enumerate(qs)]
    sink, _ = write_file(tmp_path / "fr3.mcap", items)
    topics, attachments = _read(tmp_path / "fr3.mcap")
    assert sink.derive_errors == 0 and sink.stats.arm_model == "fr3"
    want = urdf_with_tool(FR3.urdf, FR3.flange_frame, FR3.tool_p, FR3.tool_R)
    ((_, _, message),) = topics[foxglove3d.DESCRIPTION_TOPIC]
    assert _doc(message)["data"] == want
    (urdf,) = [a for a in attachments if a.name == "fr3.urdf"]
    assert urdf.data.decode() == want
    links = {e.get("name") for e in ET.fromstring(want).iter("link")}
    assert {"fr3_link0", "fr3_link8", "fr3_leftfinger", "tool"} <= links

    lp = LinkPoses(FR3)
    tf_msgs = topics[foxglove3d.TF_TOPIC]
    assert len(tf_msgs) == len(qs)
    for (schema, _, message), q, (_, _, st_msg) in zip(
        tf_msgs, qs, topics["robot/state"], strict=True
    ):
        doc = _doc(message)
        assert conforms(json.loads(schema.data), doc) == []
        assert _joints(want) == {
            (tf["parent_frame_id"], tf["child_frame_id"]) for tf in doc["transforms"]
        }
        poses = _compose(doc["transforms"])
        assert set(poses) == links
        st = _doc(st_msg)
        assert np.allclose(poses["tool"][0], st["tool_p"], atol=1e-9)
        assert np.allclose(poses["tool"][1], np.reshape(st["tool_R"], (3, 3)), atol=1e-9)
        oMe = kin.fk_flange(q)
        assert np.allclose(poses["fr3_link8"][0], oMe.translation, atol=1e-9)
        assert np.allclose(poses["fr3_link8"][1], oMe.rotation, atol=1e-9)
        for link, oMl in lp.poses(q.tolist()).items():
            assert np.allclose(poses[link][0], oMl.translation, atol=1e-9), link
            assert np.allclose(poses[link][1], oMl.rotation, atol=1e-9), link

    # The visuals: each where Pinocchio's geometry placement puts it, at the last q.
    ((schema, _, message),) = topics[foxglove3d.MODEL_TOPIC]
    model = _doc(message)
    assert conforms(json.loads(schema.data), model) == []
    pm = FR3.pin_model()
    geom = FR3.geometry()
    data, gdata = pm.createData(), geom.createData()
    pin.forwardKinematics(pm, data, np.asarray(q))
    pin.updateGeometryPlacements(pm, data, geom, gdata)
    placed = [gdata.oMg[i] for i in range(len(geom.geometryObjects))]
    drawn = []
    for e in model["entities"]:
        p0, R0 = poses[e["frame_id"]]
        for kind in ("cubes", "models"):
            for prim in e[kind]:
                pos = prim["pose"]["position"]
                R = foxglove3d.rotation(prim["pose"]["orientation"])
                drawn.append((p0 + R0 @ np.array([pos["x"], pos["y"], pos["z"]]), R0 @ R))
                if kind == "models":
                    assert prim["media_type"] == "model/stl" and prim["override_color"]
    assert len(drawn) == len(placed) == 9 + 8  # 8 links and the hand; 4 boxes per finger
    for oMg in placed:
        assert any(
            np.allclose(p, oMg.translation, atol=1e-9) and np.allclose(R, oMg.rotation, atol=1e-9)
            for p, R in drawn
        )
    meshes = [m for e in model["entities"] for m in e["models"]]
    files = {
        Path(g.meshPath).read_bytes() for g in geom.geometryObjects if Path(g.meshPath).is_file()
    }
    assert {base64.b64decode(m["data"]) for m in meshes} <= files and len(meshes) == 9


def test_without_a_description_there_is_no_robot_model_and_the_stats_say_so(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An old system (or a recording of keys without the description): /tf is what the
    states themselves say, world → flange → tool; no model, no URDF."""
    path = tmp_path / "old.mcap"
    with caplog.at_level(logging.INFO, logger="telerobot.record"):
        sink, _ = write_file(
            path, [("robot/state", robot_state(i + 1, q)) for i, q in enumerate(QS)]
        )
    topics, attachments = _read(path)
    assert foxglove3d.MODEL_TOPIC not in topics and foxglove3d.DESCRIPTION_TOPIC not in topics
    assert attachments == []
    for (_, _, message), (_, _, st_msg) in zip(
        topics[foxglove3d.TF_TOPIC], topics["robot/state"], strict=True
    ):
        doc = _doc(message)
        assert [(t["parent_frame_id"], t["child_frame_id"]) for t in doc["transforms"]] == [
            ("world", "flange"),
            ("flange", "tool"),
        ]
        poses, st = _compose(doc["transforms"]), _doc(st_msg)
        assert np.allclose(poses["flange"][0], st["flange_p"], atol=1e-12)
        assert np.allclose(poses["tool"][0], st["tool_p"], atol=1e-12)
        assert np.allclose(poses["tool"][1], np.reshape(st["tool_R"], (3, 3)), atol=1e-12)
    assert sink.stats.arm_model == "" and sink.stats.robot_models == 0
    summary = sink.stats.snapshot().as_dict()
    assert summary["arm_model"] is None and summary["robot_models"] == 0
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert any("no arm description" in r.getMessage() for r in warned)
    assert any("/robot_model" in r.getMessage() for r in warned)


def test_a_description_after_the_first_states_takes_over_from_there(tmp_path: Path) -> None:
    """The recorder started before the arm: the first states have only their own poses;
    from the description on, the arm's frames."""
    items = [("robot/state", robot_state(1, QS[0])), (DESC, description(PUMA))]
    items += [("robot/state", robot_state(2, QS[1]))]
    sink, _ = write_file(tmp_path / "late.mcap", items)
    topics, _ = _read(tmp_path / "late.mcap")
    first, second = (_doc(m) for _, _, m in topics[foxglove3d.TF_TOPIC])
    assert len(first["transforms"]) == 2 and len(second["transforms"]) == 8
    assert len(topics[foxglove3d.MODEL_TOPIC]) == 1 and sink.stats.robot_models == 1


def test_a_new_tool_rewrites_the_model_and_each_part_has_its_own(tmp_path: Path) -> None:
    """set_tool re-publishes the description: the model and URDF follow the new eMt (the same
    description again changes nothing); a new part of a split recording starts with the
    current model."""
    clock = FakeClock()
    sink = McapSink(
        RecorderConfig(output=str(tmp_path / "t.mcap"), max_duration_s=1.0, split=True),
        monotonic_s=clock,
    )
    new_p, new_R = (0.0, 0.05, 0.25), vec(rot_z(0.5))
    new_eMt = tool_se3(new_p, new_R)
    seq = 0

    def put(t_s: float, key: str, payload: bytes) -> None:
        nonlocal seq
        seq += 1
        clock.now_s = t_s
        assert sink.write(Received(T0_NS + seq * 1_000_000, key, payload))

    put(0.0, DESC, description(PUMA, 1))
    put(0.1, "robot/state", robot_state(1, QS[0]))
    put(0.2, DESC, description(PUMA, 2))  # the same arm and tool: nothing new to draw
    put(0.3, DESC, description(PUMA, 3, new_p, new_R))
    put(0.4, "robot/state", arm_state(2, QS[1], KIN.fk_flange(QS[1]), new_eMt))
    put(1.5, "robot/state", arm_state(3, QS[2], KIN.fk_flange(QS[2]), new_eMt))  # part 2
    sink.close()
    first, second = sink.stats.files
    topics, attachments = _read(first)
    assert len(topics["/raw/" + DESC]) == 3
    models = [_doc(m) for _, _, m in topics[foxglove3d.MODEL_TOPIC]]
    urdfs = [_doc(m)["data"] for _, _, m in topics[foxglove3d.DESCRIPTION_TOPIC]]
    assert len(models) == len(urdfs) == len(attachments) == 2
    assert urdfs[1] == urdf_with_tool(PUMA.urdf, "flange", new_p, new_R)
    assert [a.data.decode() for a in attachments] == urdfs
    assert models[1]["deletions"] == [{"timestamp": models[1]["entities"][0]["timestamp"],
                                       "type": 1, "id": ""}]  # fmt: skip
    (shaft,) = next(e for e in models[1]["entities"] if e["frame_id"] == "flange")["cylinders"]
    assert shaft["size"]["z"] == pytest.approx(np.linalg.norm(new_p))
    tool_tf = _doc(topics[foxglove3d.TF_TOPIC][-1][2])["transforms"][-1]
    assert tool_tf["child_frame_id"] == "tool"
    t = tool_tf["translation"]
    assert np.allclose([t["x"], t["y"], t["z"]], new_p, atol=1e-9)
    assert np.allclose(foxglove3d.rotation(tool_tf["rotation"]), new_eMt.rotation, atol=1e-9)
    # the second part: no description of its own, the model all the same, before its /tf
    topics, attachments = _read(second)
    assert "/raw/" + DESC not in topics
    (model_msg,) = [m for _, _, m in topics[foxglove3d.MODEL_TOPIC]]
    ((_, _, tf_msg),) = topics[foxglove3d.TF_TOPIC]
    assert model_msg.log_time == tf_msg.log_time
    assert [_doc(m)["data"] for _, _, m in topics[foxglove3d.DESCRIPTION_TOPIC]] == [urdfs[1]]
    assert [a.name for a in attachments] == ["puma560.urdf"]
    assert sink.stats.robot_models == 3


def test_an_arm_of_the_user_s_own_is_drawn_from_its_description_alone(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Not a shipped model: a PUMA whose URDF root is `pedestal` (world → pedestal is then
    the identity) is drawn from its URDF's primitives; a UR5e under another name, whose
    meshes this checkout does not have, with its tool shaft only (and a warning)."""
    urdf = PUMA.urdf.replace('"world"', '"pedestal"')
    mine = codec.pack(
        {
            **codec.unpack(description(PUMA)),
            "model": "my_puma",
            "urdf": urdf,
            "base_frame": "pedestal",
        }
    )
    ur = codec.pack({**codec.unpack(description(load_model("ur5e"))), "model": "my_ur"})
    items = [(DESC, mine), ("robot/state", robot_state(1, QS[3])), (DESC, ur)]
    with caplog.at_level(logging.WARNING, logger="telerobot.record"):
        sink, _ = write_file(tmp_path / "own.mcap", items)
    topics, attachments = _read(tmp_path / "own.mcap")
    assert sink.derive_errors == 0
    tfs = _doc(topics[foxglove3d.TF_TOPIC][0][2])["transforms"]
    assert (tfs[0]["parent_frame_id"], tfs[0]["child_frame_id"]) == ("world", "pedestal")
    assert foxglove3d.rotation(tfs[0]["rotation"]).tolist() == np.eye(3).tolist()
    poses, st = _compose(tfs), _doc(topics["robot/state"][0][2])
    assert np.allclose(poses["tool"][0], st["tool_p"], atol=1e-9)
    assert np.allclose(poses["flange"][0], KIN.fk_flange(QS[3]).translation, atol=1e-9)
    puma_model, ur_model = (_doc(m) for _, _, m in topics[foxglove3d.MODEL_TOPIC])
    assert {e["frame_id"] for e in puma_model["entities"]} >= {"pedestal", "link2", "flange"}
    assert [e["frame_id"] for e in ur_model["entities"]] == ["tool0"]  # the shaft alone
    assert [a.name for a in attachments] == ["my_puma.urdf", "my_ur.urdf"]
    assert any("my_ur.urdf drawn without its visuals" in r.getMessage() for r in caplog.records)


def test_a_description_outside_the_key_filter_still_draws_the_arm(tmp_path: Path) -> None:
    sink = McapSink(RecorderConfig(output=str(tmp_path / "f.mcap"), keys=("robot/state",)))
    assert sink.write(Received(T0_NS, DESC, description(FR3), record=False))
    kin, eMt = FR3.kinematics(), tool_se3(FR3.tool_p, FR3.tool_R)
    q = np.asarray(FR3.home)
    assert sink.write(Received(T0_NS + 1, "robot/state", arm_state(1, q, kin.fk_flange(q), eMt)))
    sink.close()
    topics, _ = _read(tmp_path / "f.mcap")
    assert DESC not in topics and "/raw/" + DESC not in topics and DESC not in sink.stats.keys
    assert len(topics[foxglove3d.MODEL_TOPIC]) == 1 and len(topics[foxglove3d.TF_TOPIC]) == 1
    assert sink.stats.written == 1 and sink.stats.arm_model == "fr3"


def test_states_that_do_not_fit_the_arm_and_bad_descriptions_are_counted(
    tmp_path: Path,
) -> None:
    """A state of another arm (7 joints for the 6 described) has no /tf; a description that
    does not check out is kept raw and changes nothing."""
    kin, eMt = FR3.kinematics(), tool_se3(FR3.tool_p, FR3.tool_R)
    q7 = np.asarray(FR3.home)
    items = [
        (DESC, description(PUMA)),
        ("robot/state", arm_state(1, q7, kin.fk_flange(q7), eMt)),
        (DESC, codec.pack({"seq": 9, "t_ns": T0_NS, "model": "fr3"})),
        ("robot/state", robot_state(2, QS[0])),
    ]
    sink, _ = write_file(tmp_path / "bad.mcap", items)
    topics, _ = _read(tmp_path / "bad.mcap")
    assert len(topics["/raw/" + DESC]) == 2 and len(topics[DESC]) == 1
    assert len(topics[foxglove3d.TF_TOPIC]) == 1 and len(topics[foxglove3d.MODEL_TOPIC]) == 1
    assert sink.derive_errors == 2 and sink.stats.arm_model == "puma560"
    assert sink.stats.keys[DESC].no_view == 1


def test_the_view_of_an_old_six_joint_state_still_has_its_schema(tmp_path: Path) -> None:
    """RobotState.q is 1 … 32 floats on the wire: the helper's 6 zeros and the FR3's 7
    both conform to the channel's schema."""
    kin, eMt = FR3.kinematics(), tool_se3(FR3.tool_p, FR3.tool_R)
    q7 = np.asarray(FR3.home)
    items = [("robot/state", state(1)), ("robot/state", arm_state(2, q7, kin.fk_flange(q7), eMt))]
    write_file(tmp_path / "q.mcap", items)
    topics, _ = _read(tmp_path / "q.mcap")
    for schema, _, message in topics["robot/state"]:
        q_schema = json.loads(schema.data)["properties"]["q"]
        assert (q_schema["minItems"], q_schema["maxItems"]) == (1, 32)
        assert conforms(json.loads(schema.data), _doc(message)) == []
    assert [len(_doc(m)["q"]) for _, _, m in topics["robot/state"]] == [6, 7]


def test_workcell_objects_match_workcell_state(tmp_path: Path) -> None:
    path = tmp_path / "cell.mcap"
    write_file(path, [(WORKCELL_STATE.key, workcell_state(k)) for k in range(1, 6)])
    topics, _ = _read(path)
    updates = topics[foxglove3d.WORKCELL_TOPIC]
    assert len(updates) == 5
    areas: list[float] = []
    for k, (schema, _, message) in enumerate(updates, start=1):
        assert schema.name == foxglove3d.SCENE_UPDATE
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
            assert np.allclose(foxglove3d.rotation(prim["pose"]["orientation"]), R, atol=1e-9)
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
    assert len(topics[foxglove3d.WORKCELL_TOPIC]) == 1
    assert sink.derive_errors == 1


def test_quaternions_round_trip_every_rotation_branch() -> None:
    for R in [np.eye(3), _rx(179.9), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
              np.diag([-1.0, -1.0, 1.0])] + [KIN.fk_tool(q).rotation for q in QS]:  # fmt: skip
        q = foxglove3d.quaternion(R)
        assert q["w"] >= 0.0
        assert np.isclose(sum(v * v for v in q.values()), 1.0)
        assert np.allclose(foxglove3d.rotation(q), R, atol=1e-12)


def test_no_3d_writes_only_the_bus_channels(tmp_path: Path) -> None:
    from services.tools.record.__main__ import parser

    assert parser().parse_args(["-o", "s.mcap", "--no-3d"]).no_3d
    path = tmp_path / "plain.mcap"
    items = [
        (DESC, description(PUMA)),
        ("robot/state", robot_state(1, QS[0])),
        (WORKCELL_STATE.key, workcell_state(1)),
    ]
    sink, _ = write_file(path, items, view3d=False)
    topics, attachments = _read(path)
    assert set(topics) == {
        DESC, "/raw/" + DESC, "robot/state", "/raw/robot/state",
        WORKCELL_STATE.key, "/raw/" + WORKCELL_STATE.key,
    }  # fmt: skip
    assert attachments == []
    assert sink.stats.arm_model == "puma560" and sink.stats.robot_models == 0
