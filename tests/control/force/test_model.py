"""Eq. (4) against hand-worked cases, its inverse, and the SO(3) helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from services.control.force.model import (
    WristModel,
    as_calibration,
    as_rotation,
    as_vec3,
    plate_motion,
    tool_deflection,
    tool_wrench,
)
from services.geometry import exp_so3, log_so3
from tests.control.force.helpers import quat_to_R, rot

H = 0.2  # tool length (m): PROTOCOL.md's default eMt
K_L = 1000.0  # N/m
K_R = 20.0  # N·m/rad


def model(**kw: object) -> WristModel:
    kw.setdefault("K_l", K_L)
    kw.setdefault("K_r", K_R)
    return WristModel(**kw)  # type: ignore[arg-type]


# --- hand-worked cases ------------------------------------------------------------------


def test_pure_translation_is_stiffness_times_plate_shift() -> None:
    # ΔS = 1 mm along x, ΔM = I: the tool point moves with the plate, ΔT_t = ΔS.
    f, c = model().wrench_from_signals([1e-3, 0, 0, 0, 0, 0])
    assert_allclose(f, [K_L * 1e-3, 0, 0], atol=1e-12)
    assert_allclose(c, [0, 0, 0], atol=1e-12)


def test_pure_rotation_moves_the_tool_point_on_an_arc() -> None:
    # ΔM = Ry(a) about the sensor origin, tool point at (0, 0, h):
    # ΔT_e = (Ry − I) p = (h sin a, 0, h (cos a − 1)); ΔT_t = Ryᵀ ΔT_e = p − Ryᵀ p
    #      = (h sin a, 0, h (1 − cos a)).  C_t = K_r (0, a, 0).
    a = 0.01
    f, c = model().wrench_from_signals([0, 0, 0, 0, a, 0])
    assert_allclose(f, K_L * np.array([H * math.sin(a), 0, H * (1 - math.cos(a))]), atol=1e-12)
    assert_allclose(c, [0, K_R * a, 0], atol=1e-12)


def test_pure_rotation_small_angle_mode() -> None:
    # ΔM = I + [θ]×, θ = (0, a, 0): ΔT_e = θ × p = (a h, 0, 0);
    # (I + [θ]×)⁻¹ (a h, 0, 0) = (a h, 0, a² h) / (1 + a²).
    a = 0.01
    f, c = model(mode="small_angle").wrench_from_signals([0, 0, 0, 0, a, 0])
    assert_allclose(f, K_L * np.array([a * H, 0, a * a * H]) / (1 + a * a), atol=1e-12)
    assert_allclose(c, [0, K_R * a, 0], atol=1e-12)


def test_translation_and_rotation_together() -> None:
    # ΔS = (0, 0, −d), ΔM = Rx(a): ΔT_t = Rxᵀ(ΔS + (Rx − I) p)
    #   = (0, −(d + h) sin a, h − (d + h) cos a).
    d, a = 2e-3, 0.02
    f, c = model().wrench_from_signals([0, 0, -d, a, 0, 0])
    expected = np.array([0, -(d + H) * math.sin(a), H - (d + H) * math.cos(a)])
    assert_allclose(f, K_L * expected, atol=1e-12)
    assert_allclose(c, [K_R * a, 0, 0], atol=1e-12)


def test_rotated_sensor_frame() -> None:
    # The sensor is mounted turned 90° about z in the flange, 5 cm out; the tool is the
    # default eMt. Then R_st = Rz(−90°), p_st = (0, 0, 0.15). A plate shift along the
    # sensor's x is along the tool's y; a tilt about the sensor's x is about the tool's y.
    R_es = rot("z", math.pi / 2)
    m = model(R_es=R_es, p_es=np.array([0, 0, 0.05]))
    assert_allclose(m.p_st, [0, 0, 0.15], atol=1e-15)
    f, c = m.wrench_from_signals([1e-3, 0, 0, 0, 0, 0])
    assert_allclose(f, [0, K_L * 1e-3, 0], atol=1e-12)
    assert_allclose(c, [0, 0, 0], atol=1e-12)
    a, h = 0.01, 0.15
    f, c = m.wrench_from_signals([0, 0, 0, a, 0, 0])
    # In the tool frame the tilt is Ry(a) (sensor x = tool y … with sign: Rz(90°) x = y).
    assert_allclose(c, [0, K_R * a, 0], atol=1e-12)
    assert_allclose(f, K_L * np.array([h * math.sin(a), 0, h * (1 - math.cos(a))]), atol=1e-12)


def test_calibration_maps_device_units() -> None:
    # Signals in ADC counts: 1 count = 0.1 µm or 1 µrad.
    cal = np.diag([1e-7, 1e-7, 1e-7, 1e-6, 1e-6, 1e-6])
    f, _c = model(calibration=cal).wrench_from_signals([10_000, 0, 0, 0, 0, 0])
    assert_allclose(f, [K_L * 1e-3, 0, 0], atol=1e-12)
    dS, dM = plate_motion([0, 0, 0, 0, 0, 5000], cal)
    assert_allclose(dS, 0, atol=1e-15)
    assert_allclose(dM, rot("z", 5e-3), atol=1e-15)


def test_matches_the_papers_literal_formulas() -> None:
    # With the paper's R_s ≡ R_e at rest: M_e^t = ΔM M_s^t and ΔT_t = M_t^s ΔM⁻¹ ΔT_e.
    R_st = rot("x", 0.3) @ rot("z", -0.7)
    T_t = np.array([0.01, -0.02, 0.18])  # tool point in tool coordinates
    p_st = R_st @ T_t  # M_s^t T_t
    dS = np.array([1e-4, -2e-4, 3e-4])
    dM = exp_so3([0.002, -0.001, 0.003])
    dT_e = dS + (dM - np.eye(3)) @ R_st @ T_t
    M_e_t = dM @ R_st
    dT_t_paper = np.linalg.inv(M_e_t) @ dT_e
    dM_t_paper = R_st.T @ dM @ R_st
    dT_t, dM_t = tool_deflection(dS, dM, R_st, p_st)
    assert_allclose(dT_t, dT_t_paper, atol=1e-15)
    assert_allclose(dM_t, dM_t_paper, atol=1e-15)
    f, c = tool_wrench(dT_t, dM_t, np.full(3, K_L), np.array([10.0, 20.0, 30.0]))
    assert_allclose(f, K_L * dT_t_paper)
    assert_allclose(c, np.array([10.0, 20.0, 30.0]) * log_so3(dM_t_paper))


def test_sensor_wrench_moves_to_the_tool_point() -> None:
    # A force F at the tool tip reads at the sensor as F and C_s = p_st × F; at the tool
    # point the moment is zero again.
    m = model()
    f_t, c_t = m.wrench_from_sensor_wrench([1.0, 0, 0], [0, H, 0])
    assert_allclose(f_t, [1.0, 0, 0], atol=1e-15)
    assert_allclose(c_t, [0, 0, 0], atol=1e-15)


def test_tool_placement_follows_set_tool() -> None:
    m = model().with_tool([0, 0, 0.3], rot("y", math.pi / 2))
    assert_allclose(m.p_st, [0, 0, 0.3])
    # A plate shift along the flange x is along the tool's −z once the tool is turned
    # 90° about y (tool z = flange x).
    f, _ = m.wrench_from_signals([1e-3, 0, 0, 0, 0, 0])
    assert_allclose(f, [0, 0, K_L * 1e-3], atol=1e-12)


def test_compliance_is_per_axis() -> None:
    m = model().with_compliance(K_l=[100.0, 200.0, 300.0], K_r=5.0)
    f, c = m.wrench_from_signals([1e-3, 1e-3, 1e-3, 0, 0, 0])
    assert_allclose(f, [0.1, 0.2, 0.3], atol=1e-12)
    f, c = m.wrench_from_signals([0, 0, 0, 0, 0, 0.01])  # about the tool axis: no lever
    assert_allclose(f, [0, 0, 0], atol=1e-12)
    assert_allclose(c, [0, 0, 0.05], atol=1e-12)
    assert_allclose(m.with_compliance(K_r=[1.0, 2.0, 3.0]).K_l, [100.0, 200.0, 300.0])


# --- inverse and round trips --------------------------------------------------------------

finite = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.tuples(
    st.floats(0.1, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)
)
forces = st.tuples(*[st.floats(-200.0, 200.0)] * 3)
moments = st.tuples(*[st.floats(-10.0, 10.0)] * 3)


@settings(max_examples=200, deadline=None)
@given(
    F=forces,
    C=moments,
    q_es=quats,
    q_et=quats,
    p_et=st.tuples(finite, finite, finite),
    mode=st.sampled_from(["exact", "small_angle"]),
    scale=st.floats(1e-8, 1.0),
)
def test_forward_of_inverse_is_identity(
    F: tuple[float, float, float],
    C: tuple[float, float, float],
    q_es: tuple[float, float, float, float],
    q_et: tuple[float, float, float, float],
    p_et: tuple[float, float, float],
    mode: str,
    scale: float,
) -> None:
    rng = np.random.default_rng(0)
    cal = np.diag(np.full(6, scale)) + 0.1 * scale * rng.standard_normal((6, 6))
    m = WristModel(
        calibration=cal,
        K_l=np.array([5e3, 1e4, 2e4]),
        K_r=np.array([30.0, 50.0, 80.0]),
        R_es=quat_to_R(q_es),
        p_es=np.array([0.0, 0.0, 0.05]),
        R_et=quat_to_R(q_et),
        p_et=np.asarray(p_et),
        mode=mode,  # type: ignore[arg-type]
    )
    s = m.signals_from_wrench(F, C)
    f, c = m.wrench_from_signals(s)
    assert_allclose(f, F, atol=1e-6)
    assert_allclose(c, C, atol=1e-7)
    fs, cs = m.sensor_wrench_from_tool(F, C)
    f2, c2 = m.wrench_from_sensor_wrench(fs, cs)
    assert_allclose(f2, F, atol=1e-9)
    assert_allclose(c2, C, atol=1e-9)


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="K_l"):
        as_vec3(-1.0, "K_l")
    with pytest.raises(ValueError, match="K_r"):
        as_vec3([1.0, float("nan"), 1.0], "K_r")
    with pytest.raises(ValueError, match="3 numbers"):
        as_vec3([1.0, 2.0], "K_l")
    with pytest.raises(ValueError, match="36"):
        as_calibration([1.0] * 35)
    with pytest.raises(ValueError, match="singular"):
        as_calibration([0.0] * 36)
    with pytest.raises(ValueError, match="identity"):
        as_calibration("eye")
    with pytest.raises(ValueError, match="rotation"):
        as_rotation(np.diag([1.0, 1.0, -1.0]), "R")
    with pytest.raises(ValueError, match="rotation"):
        WristModel(R_et=2 * np.eye(3))
