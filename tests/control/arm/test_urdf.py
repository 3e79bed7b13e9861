"""The generated URDF, read by an independent parser (Pinocchio's URDF reader), is the DH model."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.arm.kinematics import Puma560, qn, qr, qz
from services.control.arm.urdf import UrdfFrames, puma_urdf, rpy_of


def _rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    return pin.rpy.rpyToMatrix(r, p, y)


def _fk_error(xml: str, eMt: pin.SE3, qs: list[np.ndarray]) -> float:
    model = pin.buildModelFromXML(xml)
    data = model.createData()
    arm = Puma560()
    flange, tool = model.getFrameId("flange"), model.getFrameId("tool")
    err = 0.0
    for q in qs:
        pin.framesForwardKinematics(model, data, q)
        err = max(
            err,
            float(np.abs(data.oMf[flange].homogeneous - arm.fk_flange(q).homogeneous).max()),
            float(np.abs(data.oMf[tool].homogeneous - arm.fk_tool(q, eMt).homogeneous).max()),
        )
    return err


def test_fk_of_the_urdf_is_the_dh_model_within_1e_9() -> None:
    rng = np.random.default_rng(20)
    arm = Puma560()
    qs = [qz, qr, qn, *(rng.uniform(arm.q_lo, arm.q_hi) for _ in range(200))]
    assert _fk_error(puma_urdf(), pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.2])), qs) < 1e-9


@settings(max_examples=30, deadline=None)
@given(
    st.tuples(*[st.floats(-math.pi, math.pi)] * 3),
    st.tuples(*[st.floats(-0.3, 0.3)] * 3),
)
def test_any_tool_placement(rpy: tuple[float, float, float], p: tuple[float, ...]) -> None:
    R = _rpy_matrix(*rpy)
    xml = puma_urdf(tool_p=p, tool_R=tuple(R.reshape(9)))
    q = np.array([0.3, 0.8, -2.0, 0.4, -0.9, 1.2])
    assert _fk_error(xml, pin.SE3(R, np.array(p)), [q]) < 1e-9


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_rpy_at_gimbal_lock(pitch: float) -> None:
    R = _rpy_matrix(0.4, pitch, -0.7)
    r, p, y = rpy_of(tuple(R.reshape(9)))
    assert np.allclose(_rpy_matrix(r, p, y), R, atol=1e-12)


def test_structure_limits_and_names() -> None:
    frames = UrdfFrames(world="base", flange="wrist", tool="tcp")
    root = ET.fromstring(puma_urdf(frames=frames))
    links = [e.get("name") for e in root.findall("link")]
    assert links == ["base", "link1", "link2", "link3", "link4", "link5", "link6", "wrist", "tcp"]
    joints = {e.get("name"): e for e in root.findall("joint")}
    assert [j.get("type") for j in joints.values()].count("revolute") == 6
    lim = joints["joint2"].find("limit")
    assert lim is not None
    assert float(lim.get("lower", "nan")) == pytest.approx(math.radians(-45))
    assert float(lim.get("upper", "nan")) == pytest.approx(math.radians(225))
    with pytest.raises(ValueError):
        puma_urdf(tool_p=(0.0, float("nan"), 0.0))
