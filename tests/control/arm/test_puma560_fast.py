"""The plain-float kinematics against Pinocchio and a straightforward numpy reference.

`services.control.arm.kinematics` computes IK, FK, singularities and manipulability in scalar
Python floats for speed. These tests hold it to the slow, obvious versions: FK(IK) within 1e-12 over
30 000 random reachable poses (FK by Pinocchio's model), the same solutions, config strings,
`in_limits` flags and representatives as a numpy transcription of the method (which is how it
was written before), and the same choices at the boundary cases.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from numpy.typing import NDArray

from services.control.arm.kinematics import IkSolution
from services.control.arm.puma560 import (
    A2_M,
    A3_M,
    D1_M,
    D3_M,
    D4_M,
    FOREARM_ANGLE_RAD,
    FOREARM_M,
    PUMA560_DH,
    DEFAULT_eMt,
    Puma560,
    config_of,
    dh_transform,
    qn,
    qr,
    qs,
    qz,
    wrap_pi,
)

Mat = NDArray[np.float64]
ARM = Puma560()
LO, HI = np.array(ARM.q_lo), np.array(ARM.q_hi)


# --- the reference: Paul & Zhang with numpy matrices, as docs/puma560.md states it ---


def ref_representatives(q: Mat, ref: Mat) -> Mat | None:
    k_lo = np.ceil((LO - 1e-12 - q) / (2 * np.pi))
    k_hi = np.floor((HI + 1e-12 - q) / (2 * np.pi))
    if np.any(k_lo > k_hi):
        return None
    k = np.clip(np.round((ref - q) / (2 * np.pi)), k_lo, k_hi)
    return np.asarray(np.clip(q + 2 * np.pi * k, LO, HI))


def rot(axis: str, t: float) -> Mat:
    return np.asarray(pin.utils.rotate(axis, t))


def ref_ik(oMt: pin.SE3, eMt: pin.SE3, q_ref: Mat | None = None) -> list[IkSolution]:
    ref = np.zeros(6) if q_ref is None else np.asarray(q_ref, dtype=float)
    oMe = oMt * eMt.inverse()
    wx, wy, wz = oMe.translation
    r = math.hypot(wx, wy)
    if r < D3_M * (1 - 1e-12):
        return []
    y = wz - D1_M
    K = (r * r - D3_M**2 + y * y - A2_M**2 - FOREARM_M**2) / (2 * A2_M * FOREARM_M)
    if abs(K) > 1 + 1e-12:
        return []
    phi, shoulder = math.atan2(wy, wx), math.asin(min(1.0, D3_M / r))
    elbow = math.acos(min(1.0, max(-1.0, K)))
    q1s = [phi + shoulder] + ([phi + math.pi - shoulder] if D3_M / r < 1 - 1e-12 else [])
    q3s = [-FOREARM_ANGLE_RAD - elbow]
    q3s += [-FOREARM_ANGLE_RAD + elbow] if abs(K) < 1 - 1e-12 else []
    out = []
    for q1 in q1s:
        v = wx * math.cos(q1) + wy * math.sin(q1)
        for q3 in q3s:
            u = A2_M + A3_M * math.cos(q3) - D4_M * math.sin(q3)
            w = A3_M * math.sin(q3) + D4_M * math.cos(q3)
            q2 = math.atan2(y, v) - math.atan2(w, u)
            r03 = np.eye(3)
            for link, qi in zip(PUMA560_DH[:3], (q1, q2, q3), strict=True):
                r03 = r03 @ dh_transform(link, qi)[:3, :3]
            m = r03.T @ oMe.rotation
            s5 = math.hypot(m[0, 2], m[1, 2])
            if s5 < 1e-12:
                wrists = [(float(ref[3]), math.atan2(s5, m[2, 2]))]
            else:
                q4, q5 = math.atan2(-m[1, 2], -m[0, 2]), math.atan2(s5, m[2, 2])
                wrists = [(q4, q5), (q4 + math.pi, -q5)]
            for q4, q5 in wrists:
                n = rot("y", q5) @ rot("z", -q4) @ m
                q = wrap_pi([q1, q2, q3, q4, q5, math.atan2(n[1, 0], n[0, 0])])
                rep = ref_representatives(q, ref)
                out.append(IkSolution(q if rep is None else rep, config_of(q), rep is not None))
    return out


def same_solutions(a: list[IkSolution], b: list[IkSolution], tol: float = 1e-9) -> bool:
    return len(a) == len(b) and all(
        x.config == y.config and x.in_limits == y.in_limits and np.max(np.abs(x.q - y.q)) < tol
        for x, y in zip(a, b, strict=True)
    )


def pin_flange(q: Mat) -> pin.SE3:
    """The flange by Pinocchio's model, independent of the float FK."""
    data = ARM.model.createData()
    pin.framesForwardKinematics(ARM.model, data, np.asarray(q, dtype=float))
    return pin.SE3(data.oMf[ARM.model.getFrameId("flange")])


def random_tool(rng: np.random.Generator) -> pin.SE3:
    return pin.SE3(pin.exp3(rng.normal(size=3)), rng.uniform(-0.15, 0.15, size=3))


# --- accuracy ------------------------------------------------------------------------


def dh_fk_batch(q: Mat) -> Mat:
    """(n, 4, 4) flange poses of (n, 6) joint vectors: the literal DH product, vectorized."""
    T = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
    for j, link in enumerate(PUMA560_DH):
        ct, st = np.cos(q[:, j]), np.sin(q[:, j])
        ca, sa = math.cos(link.alpha_rad), math.sin(link.alpha_rad)
        A = np.zeros((len(q), 4, 4))
        A[:, 0] = np.stack([ct, -st * ca, st * sa, link.a_m * ct], axis=1)
        A[:, 1] = np.stack([st, ct * ca, -ct * sa, link.a_m * st], axis=1)
        A[:, 2] = [0.0, sa, ca, link.d_m]
        A[:, 3, 3] = 1.0
        T = T @ A
    return T


@pytest.mark.timeout(900)  # ~2 s alone on 2 cores; a loaded machine can make it 50x that
def test_fk_of_ik_is_exact_to_1e_12_over_30000_random_reachable_poses() -> None:
    rng = np.random.default_rng(30_000)
    q_true = rng.uniform(LO, HI, size=(30_000, 6))
    oMe = dh_fk_batch(q_true)
    tools = [DEFAULT_eMt, pin.SE3.Identity(), *(random_tool(rng) for _ in range(6))]
    solutions, targets = [], []
    for i in range(len(q_true)):
        eMt = tools[i % len(tools)]
        sols = ARM.ik(pin.SE3(oMe[i]) * eMt, eMt)
        assert len({s.config for s in sols}) == 8
        solutions += [s.q for s in sols]
        targets += [i] * len(sols)
    assert len(solutions) == 8 * 30_000
    err = np.abs(dh_fk_batch(np.array(solutions)) - oMe[targets])
    assert float(np.max(err)) <= 1e-12
    assert np.allclose(dh_fk_batch(q_true[:50]), [pin_flange(q).homogeneous for q in q_true[:50]])


def test_float_fk_matches_pinocchio_and_the_named_poses() -> None:
    rng = np.random.default_rng(11)
    for q in [qz, qr, qs, qn, *rng.uniform(LO - 7, HI + 7, size=(2000, 6))]:
        got, want = ARM.fk_flange(q), pin_flange(q)
        assert np.max(np.abs(got.homogeneous - want.homogeneous)) < 1e-14
        assert isinstance(got, pin.SE3)


def test_manipulability_closed_form_is_abs_det_j() -> None:
    rng = np.random.default_rng(12)
    for q in rng.uniform(LO, HI, size=(500, 6)):
        J = ARM.jacobian(q)
        assert ARM.manipulability(q) == pytest.approx(abs(np.linalg.det(J)), rel=1e-8, abs=1e-12)
    J = ARM.jacobian(qn)
    assert ARM.manipulability(qn) == pytest.approx(math.sqrt(np.linalg.det(J @ J.T)), rel=1e-9)
    assert ARM.manipulability(qz) == 0.0 and ARM.manipulability(qr) == 0.0


# --- the same answers as the reference -----------------------------------------------


def test_ik_matches_the_reference_on_random_poses_and_references() -> None:
    rng = np.random.default_rng(13)
    for i, q in enumerate(rng.uniform(LO, HI, size=(800, 6))):
        eMt = DEFAULT_eMt if i % 2 else random_tool(rng)
        oMt = ARM.fk_tool(q, eMt)
        q_ref = None if i % 3 == 0 else rng.uniform(LO - 3, HI + 3)
        assert same_solutions(ARM.ik(oMt, eMt, q_ref), ref_ik(oMt, eMt, q_ref)), i


def straight_forearm(q1: float, q2: float) -> Mat:
    return np.array([q1, q2, -FOREARM_ANGLE_RAD, 0.4, 0.9, 0.1])


def shoulder_over(q2: float) -> Mat:
    q3 = math.acos(-A2_M * math.cos(q2) / FOREARM_M) - FOREARM_ANGLE_RAD - q2
    return np.array([0.2, q2, q3, 0.3, 0.8, 0.1])


@pytest.mark.parametrize(
    ("q", "count"),
    [
        (np.array([0.3, 0.5, -2.5, 0.0, 0.0, 0.7]), 7),  # q5 = 0 on one branch
        (straight_forearm(0.3, 0.6), 4),  # elbow straight
        (shoulder_over(1.2), 4),  # wrist centre on the d3 cylinder
        (np.array([0.0, 0.0, -FOREARM_ANGLE_RAD, 0.0, 0.0, 0.0]), 3),  # straight, q5 = 0
        (qz, 7),
        (qn, 8),
        (HI, 8),
        (LO, 8),
    ],
    ids=["q5=0", "elbow", "shoulder", "elbow+wrist", "qz", "qn", "hi", "lo"],
)
def test_boundary_cases_give_the_reference_solutions(q: Mat, count: int) -> None:
    oMt = ARM.fk_tool(q)
    for q_ref in (None, np.array([0.0, 0.0, 0.0, 1.2, 0.0, -4.0]), np.array(HI)):
        sols = ARM.ik(oMt, q_ref=q_ref)
        assert len(sols) == count
        assert same_solutions(sols, ref_ik(oMt, DEFAULT_eMt, q_ref))
        now = np.clip(q + 0.01, LO, HI)
        best = ARM.choose(sols, now)
        assert best is not None and best.config == ARM.config(best.q)


def test_out_of_reach_and_inside_the_d3_cylinder_are_empty() -> None:
    for p in ([1.5, 0.0, 0.7], [0.0, 0.0, 2.0]):
        assert ARM.ik(pin.SE3(np.eye(3), np.array(p))) == []
    inside = pin.SE3(np.eye(3), np.array([0.05, 0.0, 1.0]))
    assert ARM.ik(inside, pin.SE3.Identity()) == ref_ik(inside, pin.SE3.Identity()) == []


def test_joint_arguments_are_still_checked() -> None:
    with pytest.raises(ValueError):
        ARM.ik(ARM.fk_tool(qn), q_ref=np.array([0.0, 0.0, math.nan, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError):
        ARM.solve(np.zeros(5), ARM.fk_tool(qn))
    with pytest.raises(ValueError):
        ARM.fk_flange([0.0, 0.0, 0.0, 0.0, 0.0, math.inf])
    with pytest.raises(ValueError):
        ARM.manipulability(np.zeros(7))
    assert ARM.config([[0.0, 0.7, -2.4, 0.0, 0.5, 0.0]]) == config_of(qn + 0.0 * qn) == "rup"


def test_limits_are_read_only_copies_of_the_table() -> None:
    assert np.array_equal(ARM.q_lo, [link.lo_rad for link in PUMA560_DH])
    assert np.array_equal(ARM.q_hi, [link.hi_rad for link in PUMA560_DH])
    with pytest.raises(ValueError):
        ARM.q_lo[0] = 0.0
