"""The plain-float eq. (4) kernel gives the numpy model's numbers (both ways, both modes)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.force.gravity import ToolLoad
from services.control.force.kernel import WristKernel, mat9, vec3, weight_wrench
from services.control.force.model import WristModel
from tests.control.force.helpers import quat_to_R

small = st.floats(-1.0, 1.0, allow_nan=False)
quat = st.tuples(small, small, small, small).filter(lambda q: sum(x * x for x in q) > 1e-2)
vec = st.tuples(small, small, small)


def model_of(qs: tuple, qt: tuple, p_es: tuple, p_et: tuple, mode: str, cal: bool) -> WristModel:
    rng = np.random.default_rng(7)
    calibration = np.eye(6) + 0.2 * rng.standard_normal((6, 6)) if cal else np.eye(6)
    return WristModel(
        calibration=calibration,
        K_l=np.array([1e4, 2e4, 5e3]),
        K_r=np.array([50.0, 80.0, 30.0]),
        R_es=quat_to_R(qs),
        p_es=0.05 * np.asarray(p_es),
        R_et=quat_to_R(qt),
        p_et=0.3 * np.asarray(p_et),
        mode=mode,  # type: ignore[arg-type]
    )


@settings(max_examples=150, deadline=None)
@given(quat, quat, vec, vec, st.sampled_from(["exact", "small_angle"]), st.booleans(), vec, vec)
def test_kernel_matches_the_model_both_ways(
    qs: tuple, qt: tuple, p_es: tuple, p_et: tuple, mode: str, cal: bool, f: tuple, c: tuple
) -> None:
    model = model_of(qs, qt, p_es, p_et, mode, cal)
    k = WristKernel(model)
    F, C = 50.0 * np.asarray(f), 5.0 * np.asarray(c)
    s_ref = model.signals_from_wrench(F, C)
    s = k.signals_from_wrench(vec3(F), vec3(C))
    np.testing.assert_allclose(s, s_ref, rtol=1e-9, atol=1e-12)
    f_ref, c_ref = model.wrench_from_signals(s_ref)
    f_k, c_k = k.wrench_from_signals(tuple(float(x) for x in s_ref))
    np.testing.assert_allclose(f_k, f_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(c_k, c_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(f_k, F, atol=1e-6)  # and forward ∘ inverse is the identity
    np.testing.assert_allclose(c_k, C, atol=1e-6)
    fs, cs = model.sensor_wrench_from_tool(F, C)
    ft, ct = k.wrench_from_sensor_wrench(vec3(fs), vec3(cs))
    np.testing.assert_allclose(ft, F, atol=1e-9)
    np.testing.assert_allclose(ct, C, atol=1e-9)


@pytest.mark.parametrize("angle", [math.pi - 1e-4, math.pi + 0.5, 4.0])
def test_rotations_past_pi_wrap_as_the_model(angle: float) -> None:
    model = WristModel(R_et=quat_to_R((1.0, 0.2, -0.3, 0.1)))
    k = WristKernel(model)
    signals = np.array([1e-4, -2e-4, 3e-4, 0.0, angle, 0.0])
    f_ref, c_ref = model.wrench_from_signals(signals)
    f, c = k.wrench_from_signals(tuple(signals.tolist()))
    np.testing.assert_allclose(f, f_ref, atol=1e-9)
    np.testing.assert_allclose(c, c_ref, atol=1e-9)
    C = np.array([0.0, 0.0, 50.0 * angle])  # |θ| = angle
    np.testing.assert_allclose(
        k.signals_from_wrench((1.0, 2.0, 3.0), vec3(C)),
        model.signals_from_wrench(np.array([1.0, 2.0, 3.0]), C),
        atol=1e-12,
    )


@given(quat, st.floats(0.0, 20.0), vec)
def test_weight_wrench_is_the_tool_load(q: tuple, mass: float, com: tuple) -> None:
    R = quat_to_R(q)
    load = ToolLoad(mass, com)
    f_ref, c_ref = load.wrench(R)
    f, c = weight_wrench(mass, load.gravity_mps2, com, mat9(R))
    np.testing.assert_allclose(f, f_ref, atol=1e-12)
    np.testing.assert_allclose(c, c_ref, atol=1e-12)
