"""PUMA 560 kinematics against an independent DH product, IK round trips, singularity handling."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from services.control.arm.kinematics import IkSolution, Unreachable
from services.control.arm.puma560 import DEFAULT_eMt, Puma560, qn, qr, qs, qz

Mat = NDArray[np.float64]

# PROTOCOL.md §1, typed in again so the model is checked against the contract, not itself.
TABLE = [  # d (m), a (m), alpha (deg), lo (deg), hi (deg)
    (0.67183, 0.0, 90.0, -160.0, 160.0),
    (0.0, 0.4318, 0.0, -45.0, 225.0),
    (0.15005, 0.0203, -90.0, -225.0, 45.0),
    (0.4318, 0.0, 90.0, -110.0, 170.0),
    (0.0, 0.0, -90.0, -100.0, 100.0),
    (0.0, 0.0, 0.0, -266.0, 266.0),
]
D1, A2, D3, A3, D4 = 0.67183, 0.4318, 0.15005, 0.0203, 0.4318
LO = np.radians([row[3] for row in TABLE])
HI = np.radians([row[4] for row in TABLE])

ARM = Puma560()


def homog(R: Mat, p: Mat) -> Mat:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def rz(t: float) -> Mat:
    return homog(pin.utils.rotate("z", t), np.zeros(3))


def rx(t: float) -> Mat:
    return homog(pin.utils.rotate("x", t), np.zeros(3))


def trans(x: float, y: float, z: float) -> Mat:
    return homog(np.eye(3), np.array([x, y, z]))


def dh_frames(q: Mat) -> list[Mat]:
    """World poses of DH frames 0..6 by the literal product A_i = Rz·Tz·Tx·Rx."""
    T = np.eye(4)
    out = [T]
    for qi, (d, a, alpha, _, _) in zip(q, TABLE, strict=True):
        T = T @ rz(qi) @ trans(0, 0, d) @ trans(a, 0, 0) @ rx(math.radians(alpha))
        out.append(T)
    return out


def se3_close(M: pin.SE3, T: Mat, tol: float) -> bool:
    return bool(
        np.max(np.abs(M.translation - T[:3, 3])) < tol
        and np.max(np.abs(M.rotation - T[:3, :3])) < tol
    )


def wrap(x: Mat) -> Mat:
    return np.asarray((np.asarray(x) + np.pi) % (2 * np.pi) - np.pi)


def expected_config(q: Mat) -> str:
    """The config letters recomputed from their geometric definitions (PROTOCOL §1)."""
    V = A2 * math.cos(q[1]) + A3 * math.cos(q[1] + q[2]) - D4 * math.sin(q[1] + q[2])
    # Elbow vs the shoulder→wrist-centre line, in the arm plane (x1 = reach, y1 = up).
    Y = A2 * math.sin(q[1]) + A3 * math.sin(q[1] + q[2]) + D4 * math.cos(q[1] + q[2])
    ex, ey = A2 * math.cos(q[1]), A2 * math.sin(q[1])
    line_y_at_elbow = Y / V * ex
    up = ey > line_y_at_elbow
    return ("r" if V > 0 else "l") + ("u" if up else "d") + ("p" if wrap(q[4]) >= 0 else "m")


def in_limits_mod_2pi(q: Mat) -> bool:
    for qi, lo, hi in zip(q, LO, HI, strict=True):
        ks = range(-2, 3)
        if not any(lo - 1e-9 <= qi + 2 * np.pi * k <= hi + 1e-9 for k in ks):
            return False
    return True


def shoulder_singular(q2: float) -> Mat:
    """Joints with the wrist centre on the joint-1 axis line: V = a2 c2 + L cos(q23 + β) = 0."""
    L, beta = math.hypot(A3, D4), math.atan2(D4, A3)
    q3 = math.acos(-A2 * math.cos(q2) / L) - beta - q2
    q = np.array([0.2, q2, q3, 0.3, 0.8, 0.1])
    assert abs(A2 * math.cos(q2) + A3 * math.cos(q2 + q3) - D4 * math.sin(q2 + q3)) < 1e-12
    return q


def random_tool(rng: np.random.Generator) -> pin.SE3:
    return pin.SE3(pin.exp3(rng.normal(size=3)), rng.uniform(-0.15, 0.15, size=3))


# ---------------------------------------------------------------- model and forward kinematics


def test_named_configurations_are_the_contract_values() -> None:
    assert np.array_equal(qz, np.zeros(6))
    assert np.allclose(qr, [0, np.pi / 2, -np.pi / 2, 0, 0, 0])
    assert np.allclose(qs, [0, 0, -np.pi / 2, 0, 0, 0])
    assert np.allclose(qn, [0, np.pi / 4, -np.pi, 0, np.pi / 4, 0])
    with pytest.raises(ValueError):
        qn[0] = 1.0
    assert np.allclose(ARM.q_lo, LO) and np.allclose(ARM.q_hi, HI)
    assert np.allclose(ARM.model.lowerPositionLimit, LO)
    assert np.allclose(DEFAULT_eMt.rotation, np.eye(3))
    assert np.allclose(DEFAULT_eMt.translation, [0, 0, 0.2])


@pytest.mark.parametrize("name", ["qz", "qr", "qs", "qn"])
def test_fk_of_named_configurations_matches_the_dh_product(name: str) -> None:
    q = {"qz": qz, "qr": qr, "qs": qs, "qn": qn}[name]
    frames = dh_frames(q)
    assert se3_close(ARM.fk_flange(q), frames[6], 1e-9)
    eMt = pin.SE3(pin.utils.rotate("y", 0.7), np.array([0.05, -0.02, 0.18]))
    assert se3_close(ARM.fk_tool(q, eMt), frames[6] @ eMt.homogeneous, 1e-9)
    assert se3_close(ARM.fk_tool(q), frames[6] @ trans(0, 0, 0.2), 1e-9)
    # the world origin, each joint's frame origin (joint i turns in DH frame i − 1), the flange
    origins = ARM.link_origins(q)
    assert origins.shape == (8, 3)
    assert np.allclose(origins[1:], [T[:3, 3] for T in frames], atol=1e-9)


def test_fk_of_qz_hand_worked() -> None:
    # At qz the DH rotations cancel (Rx(90)·Rx(−90)·Rx(90)·Rx(−90)); the wrist centre is
    # a2 + a3 forward, d3 to the right and d1 + d4 up.
    oMe = ARM.fk_flange(qz)
    assert np.allclose(oMe.rotation, np.eye(3), atol=1e-12)
    assert np.allclose(oMe.translation, [A2 + A3, -D3, D1 + D4], atol=1e-12)
    assert np.allclose(ARM.fk_tool(qz).translation, [A2 + A3, -D3, D1 + D4 + 0.2], atol=1e-12)


def test_fk_of_random_q_matches_the_dh_product() -> None:
    rng = np.random.default_rng(1)
    for q in rng.uniform(LO, HI, size=(200, 6)):
        assert se3_close(ARM.fk_flange(q), dh_frames(q)[6], 1e-9)


def test_jacobian_matches_finite_differences_at_a_rotated_offset_tool() -> None:
    rng = np.random.default_rng(2)
    eMt = pin.SE3(
        pin.utils.rotate("x", 0.4) @ pin.utils.rotate("z", -1.1), np.array([0.03, 0.1, 0.15])
    )
    h = 1e-6
    for q in rng.uniform(LO, HI, size=(20, 6)):
        J = ARM.jacobian(q, eMt)
        assert J.shape == (6, 6)
        T = ARM.fk_tool(q, eMt)
        for k in range(6):
            dq = np.zeros(6)
            dq[k] = h
            Tp, Tm = ARM.fk_tool(q + dq, eMt), ARM.fk_tool(q - dq, eMt)
            v = (Tp.translation - Tm.translation) / (2 * h)
            w = pin.log3(Tp.rotation @ Tm.rotation.T) / (2 * h)
            assert np.allclose(J[:3, k], v, atol=1e-7)
            assert np.allclose(J[3:, k], w, atol=1e-7)
        del T


def test_manipulability_is_yoshikawa_and_vanishes_at_the_wrist_singularity() -> None:
    J = ARM.jacobian(qn)
    assert ARM.manipulability(qn) == pytest.approx(math.sqrt(np.linalg.det(J @ J.T)), rel=1e-9)
    assert ARM.manipulability(qn) > 0.05
    for q in (qz, qr, qs):
        assert ARM.manipulability(q) < 1e-9


def test_within_limits() -> None:
    assert ARM.within_limits(qn)
    assert not ARM.within_limits(np.array([0, 0, 0, 0, math.radians(101), 0]))
    assert ARM.within_limits(np.array([0, 0, 0, 0, math.radians(101), 0]), tol=math.radians(2))
    assert ARM.within_limits(HI) and ARM.within_limits(LO)


def test_singularity_classification() -> None:
    assert ARM.singularity(qn) is None
    assert ARM.singularity(qz) == "wrist"
    assert ARM.singularity(qr) == "wrist"
    beta = math.atan2(D4, A3)
    straight = np.array([0.2, 0.3, -beta, 0.1, 0.8, 0.0])
    assert ARM.singularity(straight) == "elbow"
    over = shoulder_singular(1.2)
    assert ARM.singularity(over) == "shoulder"
    assert ARM.singularities(qr) == ["wrist", "shoulder", "elbow"]
    assert ARM.config(qn) == "rup" == expected_config(qn)


# ---------------------------------------------------------------- inverse kinematics


def test_ik_round_trip_on_random_reachable_poses() -> None:
    rng = np.random.default_rng(3)
    n = 1200
    eMts = [DEFAULT_eMt] + [random_tool(rng) for _ in range(3)]
    for i, q in enumerate(rng.uniform(LO, HI, size=(n, 6))):
        eMt = eMts[i % len(eMts)]
        oMt = ARM.fk_tool(q, eMt)
        sols = ARM.ik(oMt, eMt)
        assert len(sols) == 8
        assert sorted(s.config for s in sols) == sorted(
            a + e + w for a in "rl" for e in "ud" for w in "pm"
        )
        assert any(np.max(np.abs(wrap(s.q - q))) < 1e-7 for s in sols)
        for s in sols:
            T = ARM.fk_tool(s.q, eMt)
            assert np.max(np.abs(T.translation - oMt.translation)) < 1e-9
            assert np.max(np.abs(T.rotation - oMt.rotation)) < 1e-9
            assert s.config == expected_config(s.q)
            assert s.in_limits == in_limits_mod_2pi(s.q)
            if s.in_limits:
                assert ARM.within_limits(s.q)


def test_ik_at_the_wrist_singularity_gives_one_wrist_and_keeps_q4() -> None:
    # q5 = 0 on the ru branch only: the other arm/elbow branches put the forearm elsewhere,
    # so they keep both wrist flips: 1 + 3 × 2 solutions.
    q = np.array([0.3, 0.5, -2.5, 0.0, 0.0, 0.7])
    oMt = ARM.fk_tool(q)
    for q4_ref in (0.0, 1.2):
        sols = ARM.ik(oMt, q_ref=np.array([0, 0, 0, q4_ref, 0, 0]))
        assert len(sols) == 7
        singular = [s for s in sols if s.config[:2] == ARM.config(q)[:2]]
        assert len(singular) == 1
        assert singular[0].q[3] == pytest.approx(q4_ref)
        assert singular[0].q[4] == pytest.approx(0.0, abs=1e-12)
        for s in sols:
            assert se3_close(ARM.fk_tool(s.q), oMt.homogeneous, 1e-9)
            assert s.config == expected_config(s.q)


def test_ik_at_the_elbow_and_shoulder_boundaries_dedupes() -> None:
    beta = math.atan2(D4, A3)
    straight = np.array([0.3, 0.6, -beta, 0.4, 0.9, 0.1])
    sols = ARM.ik(ARM.fk_tool(straight))
    assert len(sols) == 4
    assert all(se3_close(ARM.fk_tool(s.q), ARM.fk_tool(straight).homogeneous, 1e-9) for s in sols)
    over = shoulder_singular(1.2)
    assert ARM.singularities(over) == ["shoulder"]
    sols = ARM.ik(ARM.fk_tool(over))
    assert len(sols) == 4
    # At V = 0 the letters r|l and u|d are degenerate; the two elbows are still both there.
    elbows = sorted(np.sign(D4 * math.cos(s.q[2]) + A3 * math.sin(s.q[2])) for s in sols)
    assert elbows == [-1, -1, 1, 1]
    assert all(se3_close(ARM.fk_tool(s.q), ARM.fk_tool(over).homogeneous, 1e-7) for s in sols)


def test_ik_out_of_reach_is_empty() -> None:
    far = pin.SE3(np.eye(3), np.array([1.5, 0.0, 0.7]))
    assert ARM.ik(far) == []
    inside_offset = pin.SE3(np.eye(3), np.array([0.05, 0.0, 1.0]))
    assert ARM.ik(inside_offset, pin.SE3.Identity()) == []


# ---------------------------------------------------------------- choosing a solution


def test_choose_nearest_in_limits_and_shifts_q6_by_two_pi() -> None:
    q = np.array([0.2, 0.7, -2.4, 0.5, 0.6, 3.0])
    sols = ARM.ik(ARM.fk_tool(q))
    now = q.copy()
    now[5] = 3.0 - 2 * np.pi + 0.01  # the same wrist, reached from the other side of ±π
    best = ARM.choose(sols, now)
    assert best is not None
    assert best.config == ARM.config(q)
    assert best.q[5] == pytest.approx(3.0 - 2 * np.pi)
    assert ARM.within_limits(best.q)
    assert ARM.choose([IkSolution(q, "rup", False)], q) is None
    assert ARM.choose([], q) is None


def smooth_path(center: Mat, amp: Mat, phase: Mat, n: int) -> Mat:
    t = np.linspace(0.0, 2 * np.pi, n)[:, None]
    return np.asarray(center + amp * np.sin(t + phase))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(seed=st.integers(0, 2**32 - 1))
def test_chooser_never_flips_branch_on_a_smooth_path(seed: int) -> None:
    rng = np.random.default_rng(seed)
    margin = np.radians(20)
    center = rng.uniform(LO + margin, HI - margin)
    path = smooth_path(center, rng.uniform(0, 0.3, 6), rng.uniform(0, 6.3, 6), 150)
    path = np.clip(path, LO, HI)
    if any(ARM.singularity(q) is not None for q in path):
        return
    q_prev = path[0]
    for q in path[1:]:
        best = ARM.choose(ARM.ik(ARM.fk_tool(q), q_ref=q_prev), q_prev)
        assert best is not None
        assert best.config == ARM.config(path[0])
        assert np.max(np.abs(best.q - q)) < 1e-7
        q_prev = best.q


# ---------------------------------------------------------------- solve: analytic and DLS


def test_solve_is_analytic_when_well_conditioned() -> None:
    target = ARM.fk_tool(qn) * pin.SE3(pin.utils.rotate("z", 0.02), np.array([0.01, 0, 0]))
    s = ARM.solve(qn, target)
    assert s.method == "analytic" and not s.near_singular and s.config == "rup"
    assert se3_close(ARM.fk_tool(s.q), target.homogeneous, 1e-9)


def test_dls_step_is_bounded_reduces_error_and_stays_in_limits() -> None:
    rng = np.random.default_rng(4)
    for q in rng.uniform(LO, HI, size=(50, 6)):
        target = ARM.fk_tool(np.clip(q + rng.normal(0, 0.02, 6), LO, HI))
        q1 = ARM.dls_step(q, target, max_step_rad=0.05)
        assert np.max(np.abs(q1 - q)) <= 0.05 + 1e-12
        assert ARM.within_limits(q1)
        e0, e1 = ARM.pose_error(q, target), ARM.pose_error(q1, target)
        assert e1[0] + e1[1] < e0[0] + e0[1]


def straight_path(a: pin.SE3, b: pin.SE3, n: int) -> list[pin.SE3]:
    """Positions on the segment, orientations on the geodesic: a straight tool path."""
    w = pin.log3(a.rotation.T @ b.rotation)
    return [
        pin.SE3(a.rotation @ pin.exp3(s * w), (1 - s) * a.translation + s * b.translation)
        for s in np.linspace(0.0, 1.0, n)
    ]


def test_straight_path_through_the_wrist_singularity_is_smooth() -> None:
    qa = np.array([0.3, 0.6, -2.6, 0.4, 0.2, -0.5])
    qb = qa.copy()
    qb[4] = -0.2
    path = straight_path(ARM.fk_tool(qa), ARM.fk_tool(qb), 300)
    q, q_an = qa.copy(), qa.copy()
    steps, analytic_steps, near, methods = [], [], [], []
    for target in path:
        s = ARM.solve(q, target)
        steps.append(np.max(np.abs(s.q - q)))
        near.append(s.near_singular)
        methods.append(s.method)
        assert ARM.within_limits(s.q)
        assert s.pos_err_m < 5e-3 and s.rot_err_rad < 5e-2
        q = s.q
        best = ARM.choose(ARM.ik(target, q_ref=q_an), q_an)
        assert best is not None
        analytic_steps.append(np.max(np.abs(best.q - q_an)))
        q_an = best.q
    # The analytic solution alone whips q4/q6 round by about π close to q5 = 0.
    assert max(analytic_steps) > 1.0
    assert max(steps) < 0.05
    assert any(near) and "dls" in methods and methods[0] == methods[-1] == "analytic"
    assert ARM.pose_error(q, path[-1])[0] < 1e-9


def test_straight_path_across_the_shoulder_singularity_keeps_q1() -> None:
    # The wrist centre slides along a line tangent to the d3 cylinder, over the shoulder:
    # V changes sign with q1 fixed, which relabels r|l and u|d (PROTOCOL §1 letters).
    eMt = pin.SE3.Identity()
    R = pin.utils.rotate("y", math.pi / 2)
    path = [pin.SE3(R, np.array([x, -D3, D1 + 0.55])) for x in np.linspace(-0.25, 0.25, 251)]
    start = ARM.choose(ARM.ik(path[0], eMt), np.array([0, 1.2, -2.5, 0, 0.5, 0]))
    assert start is not None and start.config == "ldm"
    q = start.q
    near = False
    for target in path:
        s = ARM.solve(q, target, eMt)
        assert np.max(np.abs(s.q - q)) < 0.05
        assert abs(s.q[0]) < 0.01
        near |= s.near_singular
        q = s.q
    assert near and ARM.config(q) == "rum"
    assert ARM.pose_error(q, path[-1], eMt)[0] < 1e-9


def test_pushing_out_of_reach_degrades_then_refuses() -> None:
    q = qn.copy()
    start = ARM.fk_tool(q)
    radial = np.array([start.translation[0], start.translation[1], 0.0])
    out = start.translation + 0.6 * radial / np.linalg.norm(radial)
    path = straight_path(start, pin.SE3(start.rotation, out), 200)
    solved, near = 0, False
    for target in path:
        try:
            s = ARM.solve(q, target)
        except Unreachable:
            break
        assert np.max(np.abs(s.q - q)) <= 0.25 + 1e-9
        near |= s.near_singular
        q = s.q
        solved += 1
    else:
        pytest.fail("a target 0.6 m beyond the reach was accepted")
    assert solved > 50
    # Refused on the way to straight: the elbow had opened from folded (|sin(q3 + β)| ≈ 1).
    assert near and abs(math.sin(q[2] + math.atan2(D4, A3))) < 0.35


def test_solve_refuses_a_branch_change() -> None:
    rng = np.random.default_rng(5)
    refused = 0
    for _ in range(400):
        q_now = rng.uniform(LO, HI)
        q_far = rng.uniform(LO, HI)
        if ARM.singularity(q_now) or ARM.singularity(q_far):
            continue
        target = ARM.fk_tool(q_far)
        in_limits = {s.config for s in ARM.ik(target) if s.in_limits}
        if not in_limits or ARM.config(q_now) in in_limits:
            continue
        try:
            s = ARM.solve(q_now, target)
        except Unreachable:
            refused += 1
            continue
        # The one exception: DLS reached a singularity whose branch letter is the difference.
        assert s.method == "dls" and s.near_singular
        assert np.max(np.abs(s.q - q_now)) <= 0.25 + 1e-9
    assert refused >= 20


@settings(max_examples=150, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    spread=st.sampled_from([0.0, 0.01, 0.1, 1.0, 3.0]),
)
def test_solve_result_is_within_limits_and_bounded(seed: int, spread: float) -> None:
    rng = np.random.default_rng(seed)
    q_now = rng.uniform(LO, HI)
    target = ARM.fk_tool(q_now) * pin.SE3(
        pin.exp3(rng.normal(0, spread, 3)), rng.normal(0, spread / 4, 3)
    )
    try:
        s = ARM.solve(q_now, target)
    except Unreachable:
        return
    assert ARM.within_limits(s.q)
    assert np.max(np.abs(s.q - q_now)) <= 0.25 + 1e-9
    if s.method == "analytic":
        assert se3_close(ARM.fk_tool(s.q), target.homogeneous, 1e-9)
