"""PUMA 560 kinematics: the contract's DH model in Pinocchio, closed-form IK, DLS for singularities.

Frames (PROTOCOL.md §1): world R_w is the DH base frame (z up, origin on the floor under the
pedestal); the effector R_e ("flange") is DH frame 6, whose origin is the wrist centre; the tool
R_t is placed in R_e by `eMt` (default: no rotation, 0.2 m along the flange z axis). Units: m, rad.
SE3 names say their frames: `oMe` (flange in world), `oMt` (tool in world), `eMt` (tool in flange).

`Puma560` owns one `pin.Data`: use one instance per thread (the service's loop thread).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from services.bus.errors import TelerobotError

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


PUMA560_DH: tuple[DHLink, ...] = (
    DHLink(0.67183, 0.0, _deg(90.0), _deg(-160.0), _deg(160.0)),
    DHLink(0.0, 0.4318, 0.0, _deg(-45.0), _deg(225.0)),
    DHLink(0.15005, 0.0203, _deg(-90.0), _deg(-225.0), _deg(45.0)),
    DHLink(0.4318, 0.0, _deg(90.0), _deg(-110.0), _deg(170.0)),
    DHLink(0.0, 0.0, _deg(-90.0), _deg(-100.0), _deg(100.0)),
    DHLink(0.0, 0.0, 0.0, _deg(-266.0), _deg(266.0)),
)
"""PUMA 560 standard DH parameters and joint limits, joint 1 first.

Source: PROTOCOL.md §1, which takes the lengths of Paul & Zhang (1986) as tabulated in Corke's
Robotics Toolbox `Puma560` (d1 = 0.67183 m is the pedestal height) and the Unimation joint ranges.
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
qn: Vec = _named(0.0, math.pi / 4, -math.pi, 0.0, math.pi / 4, 0.0)
"""Nominal: a dexterous right-arm elbow-up pose, well away from every singularity."""

DEFAULT_eMt: pin.SE3 = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.2]))
"""Default tool placement in the flange frame: R_et = I, p_et = (0, 0, 0.2) m. Do not mutate."""

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

_COINCIDENT = 1e-12
_EXACT_WRIST_SINGULAR = 1e-12
_CONVERGED = 1e-12

SingularityKind = Literal["wrist", "shoulder", "elbow"]


@dataclass(frozen=True, slots=True)
class IkSolution:
    """One closed-form IK solution: joints (rad), config string (PROTOCOL §1), within limits.

    `in_limits` is checked modulo 2π; when True, `q` is the representative inside the limits.
    """

    q: Vec
    config: str
    in_limits: bool


@dataclass(frozen=True, slots=True)
class Solve:
    """What `Puma560.solve` commands: joints (rad, within limits) and how they were found.

    `pos_err_m` / `rot_err_rad` are the remaining tool pose errors of `q` (0 for analytic); a DLS
    result near a singularity may still be catching up with the target.
    """

    q: Vec
    config: str
    near_singular: bool
    method: Literal["analytic", "dls"]
    pos_err_m: float = 0.0
    rot_err_rad: float = 0.0


class Unreachable(TelerobotError):
    """No joint vector within the limits reaches the pose (without a branch change)."""


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


def _reach_v(q: Vec) -> float:
    """V = a2·c2 + a3·c23 − d4·s23: wrist centre ahead of the shoulder, m (PROTOCOL §1)."""
    q23 = q[1] + q[2]
    return A2_M * math.cos(q[1]) + A3_M * math.cos(q23) - D4_M * math.sin(q23)


def config_of(q: ArrayLike) -> str:
    """The 3-letter config string of a joint vector (PROTOCOL §1).

    `r` ⇔ V > 0. `u` ⇔ the elbow is above the shoulder→wrist-centre line: in the arm plane that
    line is y = (Y/V)·x with the elbow at (a2 c2, a2 s2), which works out to
    sign(V)·(d4·c3 + a3·s3) < 0. `p` ⇔ q5 ≥ 0 (q5 wrapped into (−π, π]).
    """
    qv = np.asarray(q, dtype=np.float64)
    v = _reach_v(qv)
    side = 1.0 if v > 0.0 else -1.0
    elbow = D4_M * math.cos(qv[2]) + A3_M * math.sin(qv[2])
    return (
        ("r" if v > 0.0 else "l")
        + ("u" if side * elbow < 0.0 else "d")
        + ("p" if float(wrap_pi(qv[4])) >= 0.0 else "m")
    )


def _rot_z(t: float) -> NDArray[np.float64]:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(t: float) -> NDArray[np.float64]:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _r03(q1: float, q2: float, q3: float) -> NDArray[np.float64]:
    r = np.eye(3)
    for link, qi in zip(PUMA560_DH[:3], (q1, q2, q3), strict=True):
        r = r @ dh_transform(link, qi)[:3, :3]
    return r


def _wrist(m36: NDArray[np.float64], q4_ref: float) -> list[tuple[float, float, float]]:
    """Solve R_36 = Rz(q4)·Ry(−q5)·Rz(q6) (the PUMA wrist, Rx(90)Rz(q5)Rx(−90) = Ry(−q5)).

    Returns both wrist flips (q5 ≥ 0 first), or one solution with q4 = `q4_ref` when exactly
    singular. q6 is taken from the residual rotation so FK stays exact however small sin q5 is.
    """
    s5 = math.hypot(m36[0, 2], m36[1, 2])
    c5 = m36[2, 2]
    if s5 < _EXACT_WRIST_SINGULAR:
        candidates = [(q4_ref, math.atan2(s5, c5))]
    else:
        q4 = math.atan2(-m36[1, 2], -m36[0, 2])
        q5 = math.atan2(s5, c5)
        candidates = [(q4, q5), (q4 + math.pi, -q5)]
    out = []
    for q4, q5 in candidates:
        n = _rot_y(q5) @ _rot_z(-q4) @ m36
        out.append((q4, q5, math.atan2(n[1, 0], n[0, 0])))
    return out


class Puma560:
    """The PUMA 560 of the contract: FK, Jacobian, closed-form IK (Paul & Zhang 1986) and DLS.

    All joint vectors are (6,) float64 in rad, joint 1 first; poses are `pin.SE3` in the world
    frame R_w. Not thread-safe (one `pin.Data`): one instance per thread.
    """

    def __init__(self) -> None:
        self.model: pin.Model = build_model()
        self.data: pin.Data = self.model.createData()
        self.q_lo: Vec = np.array(self.model.lowerPositionLimit, dtype=np.float64)
        self.q_hi: Vec = np.array(self.model.upperPositionLimit, dtype=np.float64)
        self._flange = self.model.getFrameId("flange")
        self._dh = [self.model.getFrameId(f"dh{i}") for i in range(1, 7)]

    @staticmethod
    def _vec(q: ArrayLike) -> Vec:
        v = np.array(q, dtype=np.float64).reshape(-1)
        if v.shape != (6,) or not np.all(np.isfinite(v)):
            raise ValueError(f"expected 6 finite joint angles, got {q!r}")
        return v

    def fk_flange(self, q: ArrayLike) -> pin.SE3:
        """oMe: the flange (DH frame 6, origin at the wrist centre) in the world."""
        pin.framesForwardKinematics(self.model, self.data, self._vec(q))
        return pin.SE3(self.data.oMf[self._flange])

    def fk_tool(self, q: ArrayLike, eMt: pin.SE3 = DEFAULT_eMt) -> pin.SE3:
        """oMt = oMe·eMt: the tool frame in the world (eq. 1: T_w = E_w + M_w^e M_e^t T_t)."""
        return self.fk_flange(q) * eMt

    def link_origins(self, q: ArrayLike) -> Vec:
        """(7, 3) world positions, m: the base origin, then the origins of DH frames 1..6."""
        pin.framesForwardKinematics(self.model, self.data, self._vec(q))
        out = np.zeros((7, 3))
        for i, fid in enumerate(self._dh, start=1):
            out[i] = self.data.oMf[fid].translation
        return out

    def jacobian(self, q: ArrayLike, eMt: pin.SE3 = DEFAULT_eMt) -> Vec:
        """(6, 6) geometric Jacobian of the tool point, world-aligned: rows (v; ω), m/s and rad/s.

        Shifted from the flange: v_t = v_e + ω × r with r = R_we·p_et (flange origin → tool point).
        """
        qv = self._vec(q)
        pin.framesForwardKinematics(self.model, self.data, qv)
        j = np.array(
            pin.computeFrameJacobian(
                self.model, self.data, qv, self._flange, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
            )
        )
        r = self.data.oMf[self._flange].rotation @ eMt.translation
        j[:3] -= pin.skew(r) @ j[3:]
        return j

    def manipulability(self, q: ArrayLike) -> float:
        """Yoshikawa's sqrt(det(J Jᵀ)) = |det J|; the same for every tool point of a 6×6 J."""
        j = self.jacobian(q, pin.SE3.Identity())
        return float(math.sqrt(max(np.linalg.det(j @ j.T), 0.0)))

    def within_limits(self, q: ArrayLike, tol: float = 0.0) -> bool:
        """Every joint in [lo − tol, hi + tol] as given (no 2π shifting), rad."""
        qv = self._vec(q)
        return bool(np.all(qv >= self.q_lo - tol) and np.all(qv <= self.q_hi + tol))

    def config(self, q: ArrayLike) -> str:
        """The config string (PROTOCOL §1) of a joint vector; see `config_of`."""
        return config_of(self._vec(q))

    def singularities(self, q: ArrayLike) -> list[SingularityKind]:
        """Every singularity q is near, in the order wrist, shoulder, elbow (see `singularity`)."""
        qv = self._vec(q)
        out: list[SingularityKind] = []
        if abs(math.sin(qv[4])) < math.sin(WRIST_SINGULAR_RAD):
            out.append("wrist")
        if abs(_reach_v(qv)) < SHOULDER_SINGULAR_M:
            out.append("shoulder")
        if abs(math.sin(qv[2] + FOREARM_ANGLE_RAD)) < math.sin(ELBOW_SINGULAR_RAD):
            out.append("elbow")
        return out

    def singularity(self, q: ArrayLike) -> SingularityKind | None:
        """The first singularity q is near, checked in the order wrist, shoulder, elbow, or None.

        wrist: |sin q5| < sin(WRIST_SINGULAR_RAD) (axes 4 and 6 aligned); shoulder:
        |V| < SHOULDER_SINGULAR_M (wrist centre on the joint 1 axis line); elbow:
        |sin(q3 + β)| < sin(ELBOW_SINGULAR_RAD) (arm straight or folded).
        """
        kinds = self.singularities(q)
        return kinds[0] if kinds else None

    def _representatives(self, q: Vec, ref: Vec) -> Vec | None:
        """Per joint, q + 2πk inside the limits nearest `ref`; None if some joint has none."""
        k_lo = np.ceil((self.q_lo - 1e-12 - q) / TWO_PI)
        k_hi = np.floor((self.q_hi + 1e-12 - q) / TWO_PI)
        if np.any(k_lo > k_hi):
            return None
        k = np.clip(np.round((ref - q) / TWO_PI), k_lo, k_hi)
        return np.asarray(np.clip(q + TWO_PI * k, self.q_lo, self.q_hi), dtype=np.float64)

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
        ref = np.zeros(6) if q_ref is None else self._vec(q_ref)
        oMe = oMt * eMt.inverse()
        wx, wy, wz = (float(x) for x in oMe.translation)
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
        r06 = oMe.rotation
        # Branches that coincide (wrist centre on the d3 cylinder, arm straight or folded) are
        # given once; asin/acos near ±1 put their twins ~1e-6 rad apart, both exact.
        q1s = [phi + shoulder]
        if D3_M / r_xy < 1.0 - _COINCIDENT:
            q1s.append(phi + math.pi - shoulder)
        q3s = [-FOREARM_ANGLE_RAD - elbow]
        if abs(k) < 1.0 - _COINCIDENT:
            q3s.append(-FOREARM_ANGLE_RAD + elbow)
        out: list[IkSolution] = []
        for q1 in q1s:
            # V is the wrist centre's x in DH frame 1: ±sqrt(r² − d3²) by branch.
            v = wx * math.cos(q1) + wy * math.sin(q1)
            for q3 in q3s:
                u = A2_M + A3_M * math.cos(q3) - D4_M * math.sin(q3)
                w = A3_M * math.sin(q3) + D4_M * math.cos(q3)
                q2 = math.atan2(y, v) - math.atan2(w, u)
                m36 = _r03(q1, q2, q3).T @ r06
                for q4, q5, q6 in _wrist(m36, float(ref[3])):
                    q = wrap_pi(np.array([q1, q2, q3, q4, q5, q6]))
                    rep = self._representatives(q, ref)
                    out.append(
                        IkSolution(
                            q=q if rep is None else rep,
                            config=config_of(q),
                            in_limits=rep is not None,
                        )
                    )
        return out

    def choose(self, sols: list[IkSolution], q_now: ArrayLike) -> IkSolution | None:
        """The in-limits solution nearest `q_now` (Euclidean, rad), or None.

        Each joint is first shifted by 2πk to its in-limits representative nearest `q_now` (joint
        6 spans 532°), so the choice never spins a joint a full turn; away from singularities a
        smoothly moving target keeps its branch.
        """
        now = self._vec(q_now)
        best: IkSolution | None = None
        best_d = math.inf
        for s in sols:
            if not s.in_limits:
                continue
            rep = self._representatives(s.q, now)
            if rep is None:
                continue
            d = float(np.sum((rep - now) ** 2))
            if d < best_d:
                best, best_d = IkSolution(rep, s.config, True), d
        return best

    def pose_error(
        self, q: ArrayLike, oMt_target: pin.SE3, eMt: pin.SE3 = DEFAULT_eMt
    ) -> tuple[float, float]:
        """(position error m, orientation error rad) of the tool at q from the target."""
        oMt = self.fk_tool(q, eMt)
        e_p = float(np.linalg.norm(oMt_target.translation - oMt.translation))
        e_r = float(np.linalg.norm(pin.log3(oMt_target.rotation @ oMt.rotation.T)))
        return e_p, e_r

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

    def solve(self, q_now: ArrayLike, oMt_target: pin.SE3, eMt: pin.SE3 = DEFAULT_eMt) -> Solve:
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
        now = np.clip(self._vec(q_now), self.q_lo, self.q_hi)
        sols = self.ik(oMt_target, eMt, q_ref=now)
        best = self.choose(sols, now)
        config_now = config_of(now)
        near_now = self.singularities(now)
        near_best = [] if best is None else self.singularities(best.q)
        if (
            best is not None
            and not near_now
            and not near_best
            and best.config == config_now
            and float(np.max(np.abs(best.q - now))) <= MAX_ANALYTIC_STEP_RAD
        ):
            return Solve(best.q, best.config, False, "analytic")
        q = now
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
        for s in sols:
            changed = {i for i in range(3) if s.config[i] != config_now[i]}
            if s.in_limits and changed <= explained:
                return Solve(q, config_of(q), bool(near), "dls", e_p, e_r)
        raise Unreachable(
            f"target needs a branch change {config_now} -> {best.config}; use move_pose"
        )


def _random_q(rng: np.random.Generator, arm: Puma560, n: int) -> NDArray[np.float64]:
    return rng.uniform(arm.q_lo, arm.q_hi, size=(n, 6))


def bench_ik(n: int) -> dict[str, float]:
    """Analytic IK solves per second and DLS steps per second over `n` random reachable poses."""
    if n < 1:
        raise ValueError("n must be >= 1")
    arm = Puma560()
    rng = np.random.default_rng(560)
    qs_ = _random_q(rng, arm, n)
    poses = [arm.fk_tool(q) for q in qs_]
    t0 = time.perf_counter()
    for pose in poses:
        arm.ik(pose)
    t_ik = time.perf_counter() - t0
    starts = np.clip(qs_ + rng.normal(0.0, 0.05, size=qs_.shape), arm.q_lo, arm.q_hi)
    t0 = time.perf_counter()
    for q, pose in zip(starts, poses, strict=True):
        arm.dls_step(q, pose)
    t_dls = time.perf_counter() - t0
    return {
        "n": float(n),
        "analytic_ik_per_s": n / max(t_ik, 1e-12),
        "dls_steps_per_s": n / max(t_dls, 1e-12),
    }
