"""The arm as ROS sees it, for every shipped model, from its description alone.

Oracles: LinkPoses (services/control/arm/links.py) for each URDF joint's transform, the arm's
own kinematics for the flange and tool poses, Pinocchio reading the published URDF back, and
rosbags for the bytes.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from rosbags.typesys import Stores, get_typestore

from services.bus.errors import ConfigError
from services.bus.messages import ArmDescription, RobotState
from services.control.arm.links import LinkPoses
from services.control.arm.model import SHIPPED, ArmModel, load_model
from services.frontends.ros2 import convert
from services.frontends.ros2.convert import ArmView
from services.frontends.rosmsg import msgs

STORE = get_typestore(Stores.ROS2_KILTED)
BRIDGE = Path(convert.__file__).parent


def describe(model: ArmModel, **changes: Any) -> ArmDescription:
    return dataclasses.replace(ArmDescription(seq=1, t_ns=1, **model.description()), **changes)


def state(model: ArmModel, q: np.ndarray, eMt: pin.SE3 | None = None) -> RobotState:
    kin = model.kinematics()
    oMe = kin.fk_flange(q)
    oMt = kin.fk_tool(q, eMt)
    return RobotState(
        seq=1,
        t_ns=1_700_000_000_123_456_789,
        status="ready",
        q=tuple(float(x) for x in q),
        tool_p=tuple(oMt.translation),
        tool_R=tuple(oMt.rotation.reshape(9)),
        flange_p=tuple(oMe.translation),
        flange_R=tuple(oMe.rotation.reshape(9)),
        engage=0,
        cmd_seq=0,
    )


def se3(t: msgs.TransformStamped) -> pin.SE3:
    x, y, z, w = t.rotation
    return pin.SE3(pin.Quaternion(w, x, y, z).toRotationMatrix(), np.array(t.translation))


def compose(tf: msgs.TFMessage, child: str, root: str) -> pin.SE3:
    by_child = {t.child_frame_id: t for t in tf.transforms}
    M, frame = pin.SE3.Identity(), child
    while frame in by_child:
        t = by_child[frame]
        M = se3(t) * M
        frame = t.header.frame_id
    assert frame == root, f"the chain of {child} ends at {frame}"
    return M


def configurations(model: ArmModel, count: int, seed: int = 20) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(model.q_lo, model.q_hi, (count, model.n))


@pytest.mark.parametrize("name", SHIPPED)
def test_joint_states_and_tf_follow_the_description(name: str) -> None:
    model = load_model(name)
    view = ArmView(describe(model))
    oracle = LinkPoses(model)
    assert view.world_frame == model.base_frame and view.flange_frame == model.flange_frame
    for q in configurations(model, 20):
        st = state(model, q)
        js: Any = STORE.deserialize_cdr(
            msgs.encode(view.joint_state(st)), "sensor_msgs/msg/JointState"
        )
        assert list(js.name) == list(model.joint_names)
        assert tuple(js.position) == st.q
        tf = view.tf(st)
        expected = oracle.transforms(st.q)
        # every URDF joint, in the URDF's order, then flange → tool
        assert [(t.header.frame_id, t.child_frame_id) for t in tf.transforms] == [
            *((j.parent, j.child) for j, _ in expected),
            (model.flange_frame, "tool"),
        ]
        for t, (_, M) in zip(tf.transforms, expected, strict=False):
            assert t.header.t_ns == st.t_ns
            assert np.abs(se3(t).homogeneous - M.homogeneous).max() < 1e-12
        tool = compose(tf, "tool", model.base_frame)
        flange = compose(tf, model.flange_frame, model.base_frame)
        assert np.abs(tool.translation - st.tool_p).max() < 1e-9
        assert np.abs(tool.rotation.reshape(9) - st.tool_R).max() < 1e-9
        assert np.abs(flange.translation - st.flange_p).max() < 1e-9
        # the same bytes rosbags reads
        back: Any = STORE.deserialize_cdr(msgs.encode(tf), "tf2_msgs/msg/TFMessage")
        assert [t.child_frame_id for t in back.transforms] == [
            t.child_frame_id for t in tf.transforms
        ]


@pytest.mark.parametrize("name", SHIPPED)
def test_the_urdf_is_the_described_one_with_the_tool(name: str) -> None:
    model = load_model(name)
    eMt = pin.SE3(pin.rpy.rpyToMatrix(0.1, -0.2, 0.3), np.array([0.01, -0.02, 0.15]))
    desc = describe(model, eMt={"p": list(eMt.translation), "R": list(eMt.rotation.reshape(9))})
    view = ArmView(desc)
    text: Any = STORE.deserialize_cdr(msgs.encode(msgs.String(view.urdf)), "std_msgs/msg/String")
    urdf = text.data
    assert urdf == view.urdf
    full = pin.buildModelFromXML(urdf)
    data = full.createData()
    original = pin.buildModelFromXML(model.urdf)
    assert set(full.names) == set(original.names)  # the same joints, fingers included
    frames = {f.name for f in full.frames}
    assert {f.name for f in original.frames} | {"tool", "tool_joint"} == frames
    kin = model.kinematics()
    for q in configurations(model, 20, seed=3):
        qf = pin.neutral(full)
        for jname, x in zip(model.joint_names, q, strict=True):
            qf[full.joints[full.getJointId(jname)].idx_q] = x
        pin.framesForwardKinematics(full, data, qf)
        oMt = data.oMf[full.getFrameId("tool")]
        assert np.abs(oMt.homogeneous - kin.fk_tool(q, eMt).homogeneous).max() < 1e-9


def test_the_tool_on_tf_is_the_one_the_state_reports() -> None:
    """Between set_tool and the new description, /tf already follows the state's tool."""
    model = load_model("ur5e")
    view = ArmView(describe(model))
    eMt = pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.5, 0.0), np.array([0.0, 0.05, 0.3]))
    st = state(model, np.asarray(model.home), eMt)
    last = view.tf(st).transforms[-1]
    assert (last.header.frame_id, last.child_frame_id) == ("tool0", "tool")
    assert np.abs(se3(last).homogeneous - eMt.homogeneous).max() < 1e-12


def test_a_state_of_another_arm_is_not_converted() -> None:
    model = load_model("fr3")
    view = ArmView(describe(model))
    puma = load_model("puma560")
    st = state(puma, np.asarray(puma.home))
    assert not view.fits(st)
    with pytest.raises(ValueError):
        view.joint_state(st)
    with pytest.raises(ValueError):
        view.tf(st)


def test_descriptions_that_cannot_be_drawn_are_refused() -> None:
    ur5e = load_model("ur5e")
    with pytest.raises(ConfigError) as e:
        ArmView(describe(ur5e), tool_frame="tool0")  # a link of the UR5e's URDF
    assert e.value.key == "ros2.tool_frame"
    joints = [dict(j) for j in ur5e.description()["joints"]]
    joints[0]["name"] = "not_in_the_urdf"
    with pytest.raises(ConfigError) as e:
        ArmView(describe(ur5e, joints=tuple(joints)))
    assert e.value.key == "arm.model"
    fr3 = load_model("fr3")
    assert ArmView(describe(fr3), tool_frame="tcp").urdf.count('<link name="tcp"') == 1


def test_the_bridge_names_no_model() -> None:
    """Every arm fact comes from the description: no model, DH table or joint count here."""
    for path in sorted(BRIDGE.glob("*.py")):
        text = path.read_text()
        for word in ("puma", "Puma", "PUMA", "DH", "kinematics", "joint1", "range(1, 7)"):
            assert word not in text, (path.name, word)
