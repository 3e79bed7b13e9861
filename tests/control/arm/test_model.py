"""Arm models as data: every shipped model loads, says what its URDF says, and a bad model
fails at start-up naming its file and the element."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from services.bus import codec
from services.bus.errors import ConfigError
from services.bus.messages import ArmDescription
from services.control.arm.kinematics import Kinematics
from services.control.arm.model import MODELS_DIR, SHIPPED, load_model, model_path
from services.control.arm.puma560 import PUMA560_DH, build_model

EXPECTED_N = {"puma560": 6, "fr3": 7, "ur5e": 6}


def urdf_limits(name: str) -> dict[str, tuple[float, float, float]]:
    """(lower, upper, velocity) of every revolute joint, read straight from the file."""
    path = MODELS_DIR / name / f"{name}.urdf"
    out = {}
    for j in ET.parse(path).getroot().iter("joint"):
        lim = j.find("limit")
        if j.get("type") == "revolute" and lim is not None:
            out[str(j.get("name"))] = tuple(
                float(lim.get(k, "nan")) for k in ("lower", "upper", "velocity")
            )
    return out  # type: ignore[return-value]


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_model_loads_with_its_urdf_s_joints_and_limits(name: str) -> None:
    m = load_model(name)
    assert m.name == name and m.n == EXPECTED_N[name]
    limits = urdf_limits(name)
    for j in m.joints:
        lo, hi, v = limits[j.name]
        assert (j.lo, j.hi, j.max_speed) == (lo, hi, v)
        assert j.max_accel > 0
    assert all(0 < s <= j.max_speed for s, j in zip(m.plan_speed_rad_s, m.joints, strict=True))
    assert m.base_frame == "world" and m.pin_model().existFrame(m.flange_frame)
    for q in m.named.values():
        assert len(q) == m.n and all(j.lo <= x <= j.hi for x, j in zip(q, m.joints, strict=True))
    # each ships with its licence and says where it came from
    folder = model_path(name).parent
    readme = (folder / "README.md").read_text()
    assert "Licence:" in readme and ("Source:" in readme or "generated once" in readme)
    assert (folder / "LICENSE").is_file() or name == "puma560"


@pytest.mark.parametrize("name", SHIPPED)
def test_the_description_is_a_valid_message_with_the_model_s_joints(name: str) -> None:
    m = load_model(name)
    desc = ArmDescription(seq=1, t_ns=1, **m.description())
    back = codec.decode(ArmDescription, codec.encode(desc))
    assert back.n == m.n and [j["name"] for j in back.joints] == list(m.joint_names)
    assert back.analytic_ik == (name == "puma560")
    assert back.urdf == m.urdf and back.named is not None and "home" in back.named


def test_the_puma_s_urdf_is_its_dh_table() -> None:
    """The checked-in URDF was generated once from the DH table: Pinocchio's FK of it and of
    the DH model agree everywhere, and the closed form agrees with both."""
    m = load_model("puma560")
    urdf = Kinematics(m)
    dh = build_model()
    data = dh.createData()
    closed = m.kinematics()
    rng = np.random.default_rng(5)
    fid = dh.getFrameId("flange")
    for _ in range(200):
        q = rng.uniform(m.q_lo, m.q_hi)
        import pinocchio as pin

        pin.framesForwardKinematics(dh, data, q)
        a = urdf.fk_flange(q).homogeneous
        assert np.allclose(a, data.oMf[fid].homogeneous, atol=1e-12)
        assert np.allclose(a, closed.fk_flange(q).homogeneous, atol=1e-12)
    assert m.q_lo == tuple(link.lo_rad for link in PUMA560_DH)


def test_fr3_mount_and_tool_put_the_tcp_where_the_hand_is() -> None:
    m = load_model("fr3")
    k = m.kinematics()
    # the gripper's fingers are not arm joints: they are held, the chain is the 7 joints
    assert set(m.locked) == {"fr3_finger_joint1", "fr3_finger_joint2"}
    assert m.grip_joints == ("fr3_finger_joint1", "fr3_finger_joint2")
    oMt = k.fk_tool(m.home)
    assert np.allclose(oMt.translation, [0.55, 0.0, 0.65], atol=1e-6)
    assert oMt.rotation[2, 2] == pytest.approx(-1.0, abs=1e-6)  # pointing down


def _model(tmp_path: Path, toml: str, urdf: str | None = None) -> Path:
    base = (MODELS_DIR / "puma560" / "arm.toml").read_text()
    (tmp_path / "puma560.urdf").write_text(
        urdf if urdf is not None else (MODELS_DIR / "puma560" / "puma560.urdf").read_text()
    )
    path = tmp_path / "arm.toml"
    path.write_text(toml if toml else base)
    return path


def _broken(tmp_path: Path, old: str, new: str, in_urdf: bool = False) -> ConfigError:
    toml = (MODELS_DIR / "puma560" / "arm.toml").read_text()
    urdf = (MODELS_DIR / "puma560" / "puma560.urdf").read_text()
    if in_urdf:
        assert old in urdf
        urdf = urdf.replace(old, new, 1)
    else:
        assert old in toml
        toml = toml.replace(old, new, 1)
    path = _model(tmp_path, toml, urdf)
    with pytest.raises(ConfigError) as info:
        load_model(path)
    assert info.value.key == "arm.model"
    return info.value


def test_a_user_s_own_model_is_a_path(tmp_path: Path) -> None:
    path = _model(tmp_path, "")
    m = load_model(path)
    assert m.n == 6 and m.path == path.resolve()
    assert load_model(tmp_path).path == path.resolve()  # the folder works too


@pytest.mark.parametrize(
    ("old", "new", "in_urdf", "says"),
    [
        ('<robot name="puma560">', '<robot name="puma560"', True, "not well-formed"),
        ("joints = 6", "joints = 7", False, "6 moving joints"),
        ('flange_frame = "flange"', 'flange_frame = "wrist"', False, "'wrist'"),
        ("max_target_step_m = 0.05", "max_target_step_mm = 50", False, "max_target_step_mm"),
        ("[limits]", "[limts]", False, "limts"),
        ("speed_rad_s = [2.0, 2.0, 2.0, 4.0, 4.0, 4.0]", "speed_rad_s = [2.0, 2.0]", False,
         "must be 6 numbers"),
        ("speed_rad_s = [2.0, 2.0, 2.0, 4.0, 4.0, 4.0]",
         "speed_rad_s = [9.0, 2.0, 2.0, 4.0, 4.0, 4.0]", False, "above what it can do"),
        ('home = [0.276321', 'home = [9.276321', False, "home"),
        ('urdf = "puma560.urdf"', 'urdf = "nothing.urdf"', False, "nothing.urdf"),
    ],
)  # fmt: skip
def test_a_bad_model_fails_naming_the_file_and_the_element(
    tmp_path: Path, old: str, new: str, in_urdf: bool, says: str
) -> None:
    err = _broken(tmp_path, old, new, in_urdf)
    assert says in str(err)
    assert str(tmp_path) in str(err)


def test_a_joint_without_limits_is_named(tmp_path: Path) -> None:
    urdf = (MODELS_DIR / "puma560" / "puma560.urdf").read_text()
    root = ET.fromstring(urdf.split("\n", 1)[1].split("-->", 1)[1])
    for j in root.iter("joint"):
        if j.get("name") == "joint3":
            j.remove(j.find("limit"))  # type: ignore[arg-type]
    path = _model(
        tmp_path,
        (MODELS_DIR / "puma560" / "arm.toml").read_text(),
        ET.tostring(root, encoding="unicode"),
    )
    with pytest.raises(ConfigError) as info:
        load_model(path)
    assert "<joint name='joint3'> has no <limit>" in str(info.value)


def test_an_unknown_model_name_lists_the_shipped_ones() -> None:
    with pytest.raises(ConfigError) as info:
        load_model("kuka")
    assert info.value.key == "arm.model" and all(name in str(info.value) for name in SHIPPED)


def test_reach_bounds_every_tool_point(tmp_path: Path) -> None:
    for name in SHIPPED:
        m = load_model(name)
        k = m.kinematics()
        rng = np.random.default_rng(3)
        far = max(
            float(np.linalg.norm(k.fk_tool(rng.uniform(m.q_lo, m.q_hi)).translation))
            for _ in range(300)
        )
        assert far <= m.reach_m and m.reach_m < 3 * far, (name, far, m.reach_m)
        assert math.isfinite(m.reach_m)


@pytest.mark.parametrize(
    ("changes", "field_name"),
    [
        ({"n": 5}, "joints"),
        ({"workspace": {"min": [0, 0, 0], "max": [1, 1]}}, "workspace.max"),
        ({"workspace": {"min": [0, 0, "x"], "max": [1, 1, 1]}}, "workspace.min"),
        ({"workspace": {"min": [0, 0, 0], "max": [1, 1, 1e9]}}, "workspace.max"),
        ({"workspace": {"min": [0, 0, 0], "max": [1, -1, 1]}}, "workspace"),
        ({"eMt": {"p": [0, 0, 0.1], "R": [2, 0, 0, 0, 1, 0, 0, 0, 1]}}, "eMt.R"),
        ({"named": {"home": [0.0] * 5}}, "named.home"),
    ],
)
def test_a_description_that_contradicts_itself_is_refused_naming_the_field(
    changes: dict[str, object], field_name: str
) -> None:
    from services.bus.errors import ProtocolError

    fields = {**load_model("puma560").description(), **changes}
    with pytest.raises(ProtocolError) as info:
        ArmDescription(seq=1, t_ns=1, **fields)
    assert info.value.field == field_name
