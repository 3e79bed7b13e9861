"""The PUMA 560 model's plug-in: closed-form FK and IK (Paul & Zhang 1986), DLS at singularities.

The `puma560` model (models/puma560: its URDF, generated once from the DH table below, and
its arm.toml naming `services.control.arm.puma560:Puma560` as `[ik] analytic`) gets the
kinematics of every other model from Pinocchio and, from here, the closed forms: FK in plain
floats for the control loop, all 8 IK branches with their config strings, manipulability
and the three singularities by name. tests/control/arm/test_kinematics.py checks the closed
forms against Pinocchio's FK of the URDF.

Frames (PROTOCOL.md §1): world R_w is the DH base frame (z up, origin on the floor under the
pedestal); the effector R_e ("flange") is DH frame 6, whose origin is the wrist centre; the tool
R_t is placed in R_e by `eMt` (default: no rotation, 0.2 m along the flange z axis). Units: m, rad.
SE3 names say their frames: `oMe` (flange in world), `oMt` (tool in world), `eMt` (tool in flange).

`Puma560` owns one `pin.Data`: use one instance per thread (the service's loop thread).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from services.control.arm.kinematics import (
    IkSolution,
    Kinematics,
    Solve,
    Unreachable,
    compose_floats,
    tool_se3,
)
from services.control.arm.model import ArmModel, load_model
from services.geometry import PoseFloats

Vec = NDArray[np.float64]

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True, slots=True)
class DHLink:
    """One row of the standard DH table: A_i = Rz(q_i)·Tz(d_m)·Tx(a_m)·Rx(alpha_rad)."""

    d_m: float
    a_m: float
    alpha_rad: float
    lo_rad: float
    hi_rad: float


def _deg(x: float) -> float:
    return math.radians(x)


JOINT_LIMITS_DEG: tuple[tuple[float, float], ...] = (
    (-160.0, 160.0),
    (-45.0, 225.0),
    (-225.0, 45.0),
    (-110.0, 170.0),
    (-100.0, 100.0),
    (-266.0, 266.0),
)
"""The Unimation joint ranges (PROTOCOL.md §1), as the URDF's <limit> has them too."""
Q_LO_RAD: tuple[float, ...] = tuple(math.radians(lo) for lo, _ in JOINT_LIMITS_DEG)
Q_HI_RAD: tuple[float, ...] = tuple(math.radians(hi) for _, hi in JOINT_LIMITS_DEG)
QN_RAD: tuple[float, ...] = (0.0, math.pi / 4, -math.pi, 0.0, math.pi / 4, 0.0)


PUMA560_DH: tuple[DHLink, ...] = (
    DHLink(0.67183, 0.0, _deg(90.0), Q_LO_RAD[0], Q_HI_RAD[0]),
    DHLink(0.0, 0.4318, 0.0, Q_LO_RAD[1], Q_HI_RAD[1]),
    DHLink(0.15005, 0.0203, _deg(-90.0), Q_LO_RAD[2], Q_HI_RAD[2]),
    DHLink(0.4318, 0.0, _deg(90.0), Q_LO_RAD[3], Q_HI_RAD[3]),
    DHLink(0.0, 0.0, _deg(-90.0), Q_LO_RAD[4], Q_HI_RAD[4]),
    DHLink(0.0, 0.0, 0.0, Q_LO_RAD[5], Q_HI_RAD[5]),
)
"""PUMA 560 standard DH parameters and joint limits, joint 1 first.

Source: PROTOCOL.md §1, which takes the lengths of Paul & Zhang (1986) as tabulated in Corke's
Robotics Toolbox `Puma560` (d1 = 0.67183 m is the pedestal height) and the Unimation joint ranges
(`JOINT_LIMITS_DEG`).
"""

D1_M = PUMA560_DH[0].d_m
A2_M = PUMA560_DH[1].a_m
D3_M = PUMA560_DH[2].d_m
A3_M = PUMA560_DH[2].a_m
D4_M = PUMA560_DH[3].d_m
FOREARM_M = math.hypot(A3_M, D4_M)
"""Elbow (DH frame 2 origin) to wrist centre, m."""
FOREARM_ANGLE_RAD = math.atan2(D4_M, A3_M)
"""β: the arm is straight (elbow singular) at q3 = −β, folded onto itself at q3 = π − β."""


def _named(*q: float) -> Vec:
    v = np.array(q, dtype=np.float64)
    v.setflags(write=False)
    return v


qz: Vec = _named(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
"""Zero angles: upper arm horizontal, forearm up (wrist-singular)."""
qr: Vec = _named(0.0, math.pi / 2, -math.pi / 2, 0.0, 0.0, 0.0)
"""Ready: arm straight up (wrist-, shoulder- and elbow-singular)."""
qs: Vec = _named(0.0, 0.0, -math.pi / 2, 0.0, 0.0, 0.0)
"""Stretch: arm straight out horizontally (wrist- and elbow-singular)."""
qn: Vec = _named(*QN_RAD)
"""Nominal: a dexterous right-arm elbow-up pose, well away from every singularity."""

DEFAULT_eMt: pin.SE3 = tool_se3(load_model("puma560"))
"""The model's default tool placement: R_et = I, p_et = (0, 0, 0.2) m. Do not mutate."""

WRIST_SINGULAR_RAD = 0.15
"""|sin q5| below sin(this) is near the wrist singularity (axes 4 and 6 aligned)."""
SHOULDER_SINGULAR_M = 0.05
"""|V| below this is near the shoulder singularity (wrist centre on the joint 1 axis line)."""
ELBOW_SINGULAR_RAD = 0.10
"""|sin(q3 + β)| below sin(this) is near the elbow singularity (arm straight)."""
POS_TOL_M = 1e-3
"""Largest tool position error `solve` accepts from a DLS solution, m."""
ROT_TOL_RAD = 1e-2
"""Largest tool orientation error `solve` accepts from a DLS solution, rad."""
DLS_ITERATIONS = 5
"""DLS steps per `solve` call; with `max_step_rad` = 0.05 a call moves a joint ≤ 0.25 rad."""
MAX_ANALYTIC_STEP_RAD = 0.25
"""An analytic solution farther than this from the current joints (any joint) is a jump."""

_SIN_WRIST = math.sin(WRIST_SINGULAR_RAD)
_SIN_ELBOW = math.sin(ELBOW_SINGULAR_RAD)
_COINCIDENT = 1e-12
_EXACT_WRIST_SINGULAR = 1e-12
_CONVERGED = 1e-12

SingularityKind = Literal["wrist", "shoulder", "elbow"]


_NEW = object.__new__
_SET_Q, _SET_CONFIG, _SET_IN_LIMITS = (
    IkSolution.__dict__[name].__set__ for name in ("q", "config", "in_limits")
)
assert not hasattr(IkSolution, "__post_init__"), "ik() builds IkSolution without __init__"


def dh_transform(link: DHLink, q_rad: float) -> NDArray[np.float64]:
    """The 4×4 homogeneous A_i = Rz(q)·Tz(d)·Tx(a)·Rx(α) of one DH link (standard DH)."""
    ct, st = math.cos(q_rad), math.sin(q_rad)
    ca, sa = math.cos(link.alpha_rad), math.sin(link.alpha_rad)
    return np.array(
        [
            [ct, -st * ca, st * sa, link.a_m * ct],
            [st, ct * ca, -ct * sa, link.a_m * st],
            [0.0, sa, ca, link.d_m],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def _fixed_part(link: DHLink) -> pin.SE3:
    """Tz(d)·Tx(a)·Rx(α): the constant part of a DH link, after its joint rotation."""
    return pin.SE3(pin.utils.rotate("x", link.alpha_rad), np.array([link.a_m, 0.0, link.d_m]))


def build_model() -> pin.Model:
    """The Pinocchio model of PUMA560_DH: revolute-z joints j1..j6, frames dh1..dh6 and flange.

    Joint i turns about z_{i-1}; its placement in joint i−1 is the fixed part of link i−1, so the
    frame `dh<i>` (= joint i frame · fixed part of link i) is DH frame i; `flange` is DH frame 6.
    """
    model = pin.Model()
    model.name = "puma560"
    parent = 0
    placement = pin.SE3.Identity()
    for i, link in enumerate(PUMA560_DH, start=1):
        parent = model.addJoint(parent, pin.JointModelRZ(), placement, f"j{i}")
        model.addFrame(pin.Frame(f"dh{i}", parent, _fixed_part(link), pin.FrameType.OP_FRAME))
        placement = _fixed_part(link)
    model.addFrame(pin.Frame("flange", parent, _fixed_part(PUMA560_DH[-1]), pin.FrameType.OP_FRAME))
    model.lowerPositionLimit = np.array([link.lo_rad for link in PUMA560_DH])
    model.upperPositionLimit = np.array([link.hi_rad for link in PUMA560_DH])
    return model


def wrap_pi(x: ArrayLike) -> Vec:
    """Angles wrapped into (−π, π]."""
    a = np.asarray(x, dtype=np.float64)
    return np.asarray(-(np.remainder(-a + math.pi, TWO_PI) - math.pi), dtype=np.float64)


def config_of(q: ArrayLike) -> str:
    """The 3-letter config string of a joint vector (PROTOCOL §1).

    `r` ⇔ V > 0. `u` ⇔ the elbow is above the shoulder→wrist-centre line: in the arm plane that
    line is y = (Y/V)·x with the elbow at (a2 c2, a2 s2), which works out to
    sign(V)·(d4·c3 + a3·s3) < 0. `p` ⇔ q5 ≥ 0 (q5 wrapped into (−π, π]).
    """
    return _config(np.asarray(q, dtype=np.float64).reshape(-1).tolist())


# --- plain-float kernels ---------------------------------------------------------------
# `solve` runs once per operator command and `ik` up to 8 branches per call: with numpy a
# call on a 6-vector costs ~1 µs, so the per-branch work below is scalar Python floats
# (about 25× faster here than the numpy version; docs/puma560.md "Throughput"). They
# use the same IEEE operations as `wrap_pi` and numpy's clip/ceil/floor/round, so limits
# and config letters come out the same bit for bit.

_LO: tuple[float, ...] = tuple(link.lo_rad for link in PUMA560_DH)
_HI: tuple[float, ...] = tuple(link.hi_rad for link in PUMA560_DH)
_SURE: tuple[tuple[float, float], ...] = tuple(
    (max(lo, hi + 1e-12 - TWO_PI + 1e-9), min(hi, lo - 1e-12 + TWO_PI - 1e-9))
    for lo, hi in zip(_LO, _HI, strict=True)
)
"""Per joint, the range where q is its own (and only) in-limits representative: all of
[lo, hi] for joints 1–5, which span less than a turn; |q| ≲ 1.64 rad for joint 6 (532°)."""
_PI = math.pi


def _wrap(a: float) -> float:
    """`wrap_pi` of one float, by the same operations (Python's % is numpy's remainder)."""
    return -((-a + _PI) % TWO_PI - _PI)


def _rep(x: float, r: float, j: int) -> float:
    """Joint j's angle x shifted by 2πk into its limits (±1e-12, then clipped) nearest `r`,
    or NaN if it has no such representative: numpy's ceil/floor/round/clip, one joint."""
    lo, hi = _LO[j], _HI[j]
    k_lo = math.ceil((lo - 1e-12 - x) / TWO_PI)
    k_hi = math.floor((hi + 1e-12 - x) / TWO_PI)
    if k_lo > k_hi:
        return math.nan
    k = round((r - x) / TWO_PI)
    x = x + TWO_PI * (k_lo if k < k_lo else k_hi if k > k_hi else k)
    return lo if x < lo else hi if x > hi else x


def _reps(q: Sequence[float], ref: Sequence[float]) -> list[float] | None:
    """Every joint's in-limits representative nearest `ref` (`_rep`), or None."""
    out: list[float] = []
    for j, x in enumerate(q):
        lo, hi = _SURE[j]
        r = ref[j]
        y = x if lo <= x <= hi else _rep(x, r, j)
        if y != y:
            return None
        out.append(y)
    return out


def _arm_letters(q2: float, q3: float) -> str:
    """The r|l and u|d letters of `config_of` from (wrapped) q2, q3."""
    q23 = q2 + q3
    v = A2_M * math.cos(q2) + A3_M * math.cos(q23) - D4_M * math.sin(q23)
    elbow = D4_M * math.cos(q3) + A3_M * math.sin(q3)
    side = 1.0 if v > 0.0 else -1.0
    return ("r" if v > 0.0 else "l") + ("u" if side * elbow < 0.0 else "d")


def _config(q: Sequence[float]) -> str:
    return _arm_letters(q[1], q[2]) + ("p" if _wrap(q[4]) >= 0.0 else "m")


def _singularities(q: Sequence[float]) -> list[SingularityKind]:
    out: list[SingularityKind] = []
    if abs(math.sin(q[4])) < _SIN_WRIST:
        out.append("wrist")
    q23 = q[1] + q[2]
    if abs(A2_M * math.cos(q[1]) + A3_M * math.cos(q23) - D4_M * math.sin(q23)) < (
        SHOULDER_SINGULAR_M
    ):
        out.append("shoulder")
    if abs(math.sin(q[2] + FOREARM_ANGLE_RAD)) < _SIN_ELBOW:
        out.append("elbow")
    return out


def _flange_floats(q: Sequence[float]) -> tuple[list[float], list[float]]:
    """(R06 row-major, wrist centre) of the flange in the world, closed form.

    R03 = Rz(q1)Rx(90°)·Rz(q2 + q3)Rx(−90°) and R36 = Rz(q4)·Ry(−q5)·Rz(q6) (the α of the
    table); the wrist centre is (V, Y, d3) in DH frame 1 (see `Puma560.ik`).
    """
    q1, q2, q3, q4, q5, q6 = q
    c1, s1 = math.cos(q1), math.sin(q1)
    c23, s23 = math.cos(q2 + q3), math.sin(q2 + q3)
    c4, s4 = math.cos(q4), math.sin(q4)
    c5, s5 = math.cos(q5), math.sin(q5)
    c6, s6 = math.cos(q6), math.sin(q6)
    v = A2_M * math.cos(q2) + A3_M * c23 - D4_M * s23
    y = A2_M * math.sin(q2) + A3_M * s23 + D4_M * c23
    # R36 = Rz(q4)·Ry(−q5)·Rz(q6)
    m00 = c4 * c5 * c6 - s4 * s6
    m01 = -c4 * c5 * s6 - s4 * c6
    m02 = -c4 * s5
    m10 = s4 * c5 * c6 + c4 * s6
    m11 = -s4 * c5 * s6 + c4 * c6
    m12 = -s4 * s5
    m20 = s5 * c6
    m21 = -s5 * s6
    m22 = c5
    # R03 = [[c1 c23, −s1, −c1 s23], [s1 c23, c1, −s1 s23], [s23, 0, c23]]
    a0, a1, a2 = c1 * c23, -s1, -c1 * s23
    b0, b1, b2 = s1 * c23, c1, -s1 * s23
    rot = [
        a0 * m00 + a1 * m10 + a2 * m20,
        a0 * m01 + a1 * m11 + a2 * m21,
        a0 * m02 + a1 * m12 + a2 * m22,
        b0 * m00 + b1 * m10 + b2 * m20,
        b0 * m01 + b1 * m11 + b2 * m21,
        b0 * m02 + b1 * m12 + b2 * m22,
        s23 * m00 + c23 * m20,
        s23 * m01 + c23 * m21,
        s23 * m02 + c23 * m22,
    ]
    return rot, [c1 * v + s1 * D3_M, s1 * v - c1 * D3_M, D1_M + y]


def flange_pose_floats(q: Sequence[float]) -> PoseFloats:
    """oMe at joints q (6 floats, rad) as (p, R): `Puma560.fk_flange` in plain floats for
    the control loop (no checks: q must be 6 finite floats)."""
    rot, p = _flange_floats(q)
    return p, rot


def tool_pose_floats(
    q: Sequence[float], eMt: tuple[Sequence[float], Sequence[float]]
) -> PoseFloats:
    """oMt = oMe·eMt at joints q (6 floats, rad) as (p, R), eMt as (p, R) (`se3_floats`):
    `Puma560.fk_tool` in plain floats for the control loop (no checks: q must be finite)."""
    return compose_floats(flange_pose_floats(q), eMt)


def manipulability_floats(q: Sequence[float]) -> float:
    """`Puma560.manipulability` of 6 floats (no checks)."""
    _, q2, q3, _, q5, _ = q
    q23 = q2 + q3
    v = A2_M * math.cos(q2) + A3_M * math.cos(q23) - D4_M * math.sin(q23)
    elbow = D4_M * math.cos(q3) + A3_M * math.sin(q3)
    return abs(A2_M * elbow * v * math.sin(q5))


def _ik_floats(
    r: Sequence[float], wx: float, wy: float, wz: float, ref: Sequence[float]
) -> list[tuple[list[float], str, bool]]:
    """Every closed-form solution (q, config, in_limits) for the flange rotation `r` (R06,
    row-major) and wrist centre (wx, wy, wz); see `Puma560.ik` for the method."""
    r_xy = math.hypot(wx, wy)
    if r_xy < D3_M * (1.0 - _COINCIDENT):
        return []
    phi = math.atan2(wy, wx)
    shoulder = math.asin(min(1.0, D3_M / r_xy))
    y = wz - D1_M
    d_sq = r_xy * r_xy - D3_M * D3_M + y * y
    k = (d_sq - A2_M * A2_M - FOREARM_M * FOREARM_M) / (2.0 * A2_M * FOREARM_M)
    if abs(k) > 1.0 + 1e-12:
        return []
    elbow = math.acos(min(1.0, max(-1.0, k)))
    # Branches that coincide (wrist centre on the d3 cylinder, arm straight or folded) are
    # given once; asin/acos near ±1 put their twins ~1e-6 rad apart, both exact.
    q1s = [phi + shoulder]
    if D3_M / r_xy < 1.0 - _COINCIDENT:
        q1s.append(phi + _PI - shoulder)
    q3s = [-FOREARM_ANGLE_RAD - elbow]
    if abs(k) < 1.0 - _COINCIDENT:
        q3s.append(-FOREARM_ANGLE_RAD + elbow)
    # (V, Y) = Rot(q2)·(u, w): the forearm's angle atan2(w, u) depends on q3 only.
    forearm = [
        (
            q3,
            math.atan2(
                A3_M * math.sin(q3) + D4_M * math.cos(q3),
                A2_M + A3_M * math.cos(q3) - D4_M * math.sin(q3),
            ),
        )
        for q3 in q3s
    ]
    r00, _, r02, r10, _, r12, r20, _, r22 = r
    r1, r2, r3, r4, r5, r6 = ref
    # `_reps` unrolled (a loop over 6 joints was 40% of this function): a joint inside its
    # `_SURE` range is its own representative, else `_rep` decides (NaN: none in limits).
    (a1, b1), (a2, b2), (a3, b3), (a4, b4), (a5, b5), (a6, b6) = _SURE
    out: list[tuple[list[float], str, bool]] = []
    for q1 in q1s:
        c1, s1 = math.cos(q1), math.sin(q1)
        # V is the wrist centre's x in DH frame 1: ±sqrt(r² − d3²) by branch.
        reach = math.atan2(y, wx * c1 + wy * s1)
        # R_36 = R_03ᵀ·R_06; only its first and third columns are needed (m_i0, m_i2).
        u0, u2 = c1 * r00 + s1 * r10, c1 * r02 + s1 * r12
        m10, m12 = c1 * r10 - s1 * r00, c1 * r12 - s1 * r02
        w1 = -((-q1 + _PI) % TWO_PI - _PI)  # _wrap, inline: ~40 calls a solve
        x1 = w1 if a1 <= w1 <= b1 else _rep(w1, r1, 0)
        for q3, forearm_angle in forearm:
            q2 = reach - forearm_angle
            c23, s23 = math.cos(q2 + q3), math.sin(q2 + q3)
            m00, m02 = c23 * u0 + s23 * r20, c23 * u2 + s23 * r22
            m20, m22 = c23 * r20 - s23 * u0, c23 * r22 - s23 * u2
            w2 = -((-q2 + _PI) % TWO_PI - _PI)
            w3 = -((-q3 + _PI) % TWO_PI - _PI)
            x2 = w2 if a2 <= w2 <= b2 else _rep(w2, r2, 1)
            x3 = w3 if a3 <= w3 <= b3 else _rep(w3, r3, 2)
            arm_in = x1 == x1 and x2 == x2 and x3 == x3
            letters = _arm_letters(w2, w3)
            # The wrist R_36 = Rz(q4)·Ry(−q5)·Rz(q6) (Rx(90)Rz(q5)Rx(−90) = Ry(−q5)): both flips
            # (q5 ≥ 0 first), or one with q4 = q_ref[3] when exactly singular. q6 is taken from
            # the residual Ry(q5)·Rz(−q4)·R_36 so FK stays exact however small sin q5 is.
            # The flip (q4 + π, −q5) negates both atan2 arguments of q6: q6 + π.
            s5 = math.hypot(m02, m12)
            if s5 < _EXACT_WRIST_SINGULAR:
                q4, q5 = r4, math.atan2(s5, m22)
                wrists = [(-((-q4 + _PI) % TWO_PI - _PI), q5, 1.0)]
            else:
                q4, q5 = math.atan2(-m12, -m02), math.atan2(s5, m22)
                # atan2 gives [−π, π] (q5: [0, π]); (−π, π] needs only ±π folded, not `_wrap`.
                wrists = [
                    (q4 if q4 > -_PI else _PI, q5, 1.0),
                    (q4 - _PI if q4 > 0.0 else q4 + _PI, -q5 if q5 < _PI else _PI, -1.0),
                ]
            c4, s4 = math.cos(q4), math.sin(q4)
            a = c4 * m00 + s4 * m10
            n10, n00 = c4 * m10 - s4 * m00, math.cos(q5) * a + math.sin(q5) * m20
            for w4, w5, sign in wrists:
                w6 = math.atan2(sign * n10, sign * n00)
                if w6 <= -_PI:
                    w6 = _PI
                config = letters + ("p" if w5 >= 0.0 else "m")
                if arm_in:
                    x4 = w4 if a4 <= w4 <= b4 else _rep(w4, r4, 3)
                    x5 = w5 if a5 <= w5 <= b5 else _rep(w5, r5, 4)
                    x6 = w6 if a6 <= w6 <= b6 else _rep(w6, r6, 5)
                    if x4 == x4 and x5 == x5 and x6 == x6:
                        out.append(([x1, x2, x3, x4, x5, x6], config, True))
                        continue
                out.append(([w1, w2, w3, w4, w5, w6], config, False))
    return out


def _choose(
    sols: Sequence[tuple[Sequence[float], str, bool]], now: Sequence[float]
) -> tuple[list[float], str] | None:
    """`Puma560.choose` on floats: the in-limits solution nearest `now`, re-represented."""
    best: tuple[list[float], str] | None = None
    best_d = math.inf
    for q, config, in_limits in sols:
        if not in_limits:
            continue
        rep = _reps(q, now)
        if rep is None:
            continue
        d = 0.0
        for x, n in zip(rep, now):  # noqa: B905 (both 6 long; strict= costs 0.2 µs a call)
            d += (x - n) * (x - n)
        if d < best_d:
            best, best_d = (rep, config), d
    return best


def _pose_floats(oMt: pin.SE3, eMt: pin.SE3) -> tuple[list[float], float, float, float]:
    """(R06 row-major, wx, wy, wz) of the flange target oMe = oMt·eMt⁻¹."""
    (a, b, c, wx), (d, e, f, wy), (g, h, i, wz), _ = oMt.act(eMt.inverse()).homogeneous.tolist()
    return [a, b, c, d, e, f, g, h, i], wx, wy, wz


class Puma560(Kinematics):
    """The PUMA 560 of the contract: closed-form FK and IK (Paul & Zhang 1986), DLS at
    singularities, over the generic `Kinematics` of its model (the Jacobian, limits).

    All joint vectors are (6,) float64 in rad, joint 1 first; poses are `pin.SE3` in the world
    frame R_w. Not thread-safe (one `pin.Data`): one instance per thread.
    """

    analytic = True

    def __init__(self, arm: ArmModel | None = None) -> None:
        super().__init__(arm if arm is not None else load_model("puma560"))
        if self.n != 6 or self.arm.q_lo != Q_LO_RAD or self.arm.q_hi != Q_HI_RAD:
            raise ValueError("the PUMA 560 plug-in needs the puma560 model's 6 joints and limits")

    def fk_flange(self, q: ArrayLike) -> pin.SE3:
        """oMe: the flange (DH frame 6, origin at the wrist centre) in the world."""
        rot, p = _flange_floats(self._floats(q))
        return pin.SE3(np.array(rot).reshape(3, 3), np.array(p))

    def fk_tool(self, q: ArrayLike, eMt: pin.SE3 | None = None) -> pin.SE3:
        """oMt = oMe·eMt: the tool frame in the world (eq. 1: T_w = E_w + M_w^e M_e^t T_t)."""
        return self.fk_flange(q) * (DEFAULT_eMt if eMt is None else eMt)

    def flange_pose_floats(self, q: Sequence[float]) -> PoseFloats:
        """oMe at joints q (6 floats) in closed form (no checks: q must be finite)."""
        return flange_pose_floats(q)

    def manipulability(self, q: ArrayLike) -> float:
        """Yoshikawa's sqrt(det(J Jᵀ)) = |det J|; the same for every tool point of a 6×6 J.

        Closed form: |det J| = |a2 · (d4·c3 + a3·s3) · V · s5| (the arm's 3×3 position block
        at the wrist centre times the wrist's), exact where the determinant of J Jᵀ loses
        digits near a singularity.
        """
        return manipulability_floats(self._floats(q))

    def config(self, q: ArrayLike) -> str:
        """The config string (PROTOCOL §1) of a joint vector; see `config_of`."""
        return _config(self._floats(q))

    def singularities(self, q: ArrayLike) -> list[SingularityKind]:  # type: ignore[override]
        """Every singularity q is near, in the order wrist, shoulder, elbow (see `singularity`)."""
        return _singularities(self._floats(q))

    def singularity(self, q: ArrayLike) -> SingularityKind | None:
        """The first singularity q is near, checked in the order wrist, shoulder, elbow, or None.

        wrist: |sin q5| < sin(WRIST_SINGULAR_RAD) (axes 4 and 6 aligned); shoulder:
        |V| < SHOULDER_SINGULAR_M (wrist centre on the joint 1 axis line); elbow:
        |sin(q3 + β)| < sin(ELBOW_SINGULAR_RAD) (arm straight or folded).
        """
        kinds = self.singularities(q)
        return kinds[0] if kinds else None

    def ik(
        self, oMt: pin.SE3, eMt: pin.SE3 = DEFAULT_eMt, q_ref: ArrayLike | None = None
    ) -> list[IkSolution]:
        """Every closed-form solution for the tool pose `oMt` (Paul & Zhang 1986).

        Up to 8: arm r/l (q1) × elbow u/d (q3) × wrist p/m (q5), in or out of the joint limits;
        fewer where branches meet (shoulder, elbow straight, q5 = 0 exactly), none out of reach.
        At q5 = 0 exactly, q4 is taken from `q_ref` (default 0) and q6 follows. Each joint is
        given as its in-limits representative (mod 2π) nearest `q_ref` when one exists, else
        wrapped into (−π, π].
        """
        ref = [0.0] * 6 if q_ref is None else self._floats(q_ref)
        out = []
        for q, config, in_limits in _ik_floats(*_pose_floats(oMt, eMt), ref):
            # IkSolution(q, config, in_limits) with its slots set directly: the frozen
            # dataclass __init__ costs a third of a solve's 8 objects (0.35 µs each).
            s = _NEW(IkSolution)
            _SET_Q(s, np.array(q))
            _SET_CONFIG(s, config)
            _SET_IN_LIMITS(s, in_limits)
            out.append(s)
        return out

    def choose(self, sols: list[IkSolution], q_now: ArrayLike) -> IkSolution | None:
        """The in-limits solution nearest `q_now` (Euclidean, rad), or None.

        Each joint is first shifted by 2πk to its in-limits representative nearest `q_now` (joint
        6 spans 532°), so the choice never spins a joint a full turn; away from singularities a
        smoothly moving target keeps its branch.
        """
        best = _choose(
            [(s.q.tolist(), s.config or "", s.in_limits) for s in sols], self._floats(q_now)
        )
        return None if best is None else IkSolution(np.array(best[0]), best[1], True)

    def dls_step(
        self,
        q: ArrayLike,
        oMt_target: pin.SE3,
        eMt: pin.SE3 = DEFAULT_eMt,
        damping: float = 0.05,
        max_step_rad: float = 0.05,
    ) -> Vec:
        """One damped-least-squares step towards `oMt_target`; returns the NEW joint vector.

        dq = Jᵀ (J Jᵀ + λ² I)⁻¹ e with e = (p* − p; log(R* Rᵀ)) world-aligned and J the tool
        Jacobian, scaled so no joint moves more than `max_step_rad`, then clipped to the limits.
        Stays finite and bounded at singularities, where the damping trades accuracy for speed.
        """
        qv = self._vec(q)
        j = self.jacobian(qv, eMt)
        oMt = self.data.oMf[self._flange] * eMt
        err = np.concatenate(
            [
                oMt_target.translation - oMt.translation,
                pin.log3(oMt_target.rotation @ oMt.rotation.T),
            ]
        )
        dq = j.T @ np.linalg.solve(j @ j.T + damping * damping * np.eye(6), err)
        biggest = float(np.max(np.abs(dq)))
        if biggest > max_step_rad:
            dq *= max_step_rad / biggest
        return np.asarray(np.clip(qv + dq, self.q_lo, self.q_hi), dtype=np.float64)

    def solve(
        self,
        q_now: ArrayLike,
        oMt_target: pin.SE3,
        eMt: pin.SE3 = DEFAULT_eMt,
        seed: ArrayLike | None = None,
    ) -> Solve:
        """Joints to command now so the tool reaches `oMt_target` (the teleoperation path).

        Analytic (IK + `choose`) when q_now and the chosen solution are away from singularities,
        on the same branch, and within MAX_ANALYTIC_STEP_RAD. Otherwise DLS_ITERATIONS DLS steps
        from q_now: the result is returned if it reaches the target within POS_TOL_M/ROT_TOL_RAD,
        or — still catching up, with bounded joint steps — if the target has an in-limits solution
        on q_now's branch or on one that differs only in letters a nearby singularity lets the
        arm cross continuously; so motion near singularities degrades smoothly instead
        of stopping. Raises `Unreachable` otherwise (out of reach, out of the limits, or only
        through a branch change). The result is always within the joint limits.
        """
        now = [
            lo if x < lo else hi if x > hi else x
            for x, lo, hi in zip(self._floats(q_now), _LO, _HI, strict=True)
        ]
        sols = _ik_floats(*_pose_floats(oMt_target, eMt), now)
        best = _choose(sols, now)
        config_now = _config(now)
        near_now = _singularities(now)
        near_best = [] if best is None else _singularities(best[0])
        if (
            best is not None
            and not near_now
            and not near_best
            and best[1] == config_now
            and max(abs(x - n) for x, n in zip(best[0], now, strict=True)) <= MAX_ANALYTIC_STEP_RAD
        ):
            return Solve(np.array(best[0]), best[1], False, "analytic")
        q = np.array(now)
        for _ in range(DLS_ITERATIONS):
            e_p, e_r = self.pose_error(q, oMt_target, eMt)
            if e_p < _CONVERGED and e_r < _CONVERGED:
                break
            q = self.dls_step(q, oMt_target, eMt)
        e_p, e_r = self.pose_error(q, oMt_target, eMt)
        near = set(near_now) | set(near_best) | set(self.singularities(q))
        if e_p <= POS_TOL_M and e_r <= ROT_TOL_RAD:
            return Solve(q, config_of(q), bool(near), "dls", e_p, e_r)
        if best is None:
            raise Unreachable(
                f"no joint solution within the limits (DLS left {e_p:.4f} m, {e_r:.4f} rad)"
            )
        # Still catching up: fine while the target has an in-limits solution on our branch, or on
        # one that differs only in letters a nearby singularity lets the arm cross continuously.
        # Through the shoulder singularity V changes sign with q2, q3 continuous, which flips
        # r|l and (by its definition) u|d.
        crossable = {"shoulder": (0, 1), "elbow": (1,), "wrist": (2,)}
        explained = {i for k in near for i in crossable[k]}
        for _, config, in_limits in sols:
            changed = {i for i in range(3) if config[i] != config_now[i]}
            if in_limits and changed <= explained:
                return Solve(q, config_of(q), bool(near), "dls", e_p, e_r)
        raise Unreachable(f"target needs a branch change {config_now} -> {best[1]}; use move_pose")
