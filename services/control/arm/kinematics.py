"""The kinematics seam: FK, Jacobian and IK of any arm model, numerical unless it has a plug-in.

`Kinematics` works on the Pinocchio model of an `ArmModel` (its chain from the world frame to
the flange): forward kinematics, the tool point's Jacobian, and a numerical IK — damped
least squares (Levenberg–Marquardt steps) that keeps every joint inside its position limits
(a joint at a limit is taken out of the step, the others make up for it) and, for a
redundant arm, a posture task in the Jacobian's null space that keeps the elbow near the
model's posture configuration instead of letting it drift. The joint speed limits are the
servo's to keep (`safety.safe_step`): IK gives the goal, the arm moves there within them.

Why our own DLS and not pin-pink's QP: measured here on the FR3 (2026-12-01), one pink
`solve_ik` step (FrameTask + PostureTask, quadprog/daqp/proxqp) takes 0.31–0.55 ms and a
solve from a warm seed several steps; this DLS reaches 1e-10 m from a warm seed in 2–3
steps of ~30 µs (the bench's `ik_fr3_per_s`), which is what a 1 kHz target stream needs.

A model with closed-form IK provides it as a plug-in (`[ik] analytic` in its TOML, a
subclass of `Kinematics`: the PUMA 560's `services.control.arm.puma560.Puma560`); `ik` then
returns every branch with its `config`, a numerical arm one solution without.

Frames: world R_w (the model's base frame), flange R_e, tool R_t placed in R_e by `eMt`.
SE3 names say their frames: `oMe`, `oMt`, `eMt`. Units: m, rad. One instance owns one
`pin.Data`: use one per thread.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, cast

import numpy as np
import pinocchio as pin
from eigenpy import LLT
from numpy.typing import ArrayLike, NDArray

from services.bus.errors import ConfigError, TelerobotError
from services.geometry import M9, V3, PoseFloats, mul9, mv9

if TYPE_CHECKING:
    from services.control.arm.model import ArmModel

Vec = NDArray[np.float64]

LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
DAMPING2 = 1e-6
"""λ² of the damped least squares (m², rad²): small enough to converge to 1e-10 in a few
steps away from singularities, enough to keep the step bounded at one."""
LM_GAIN = 0.5
"""Levenberg–Marquardt damping (Sugihara 2011): λ² grows with the squared error, so far
from the target the step is a short gradient step that cannot overshoot into a limit or a
singularity, and near it a Gauss–Newton step that converges in a few steps."""
MAX_STEP_RAD = 0.3
"""No joint moves more than this in one IK step."""
POSTURE_GAIN = 0.1
"""Per step, the share of the posture error a redundant arm's null-space task removes."""
POSTURE_UNTIL_M = 1e-5
POSTURE_UNTIL_RAD = 1e-4
NULL_EPS = 1e-10
"""The null space is projected with J Jᵀ + NULL_EPS·I, not the task's damped matrix: the
damped projector leaks λ²/σ² of the posture step into the task, which held the FR3's
solutions 2e-5 m off their target near singularities."""
SOLVE_ITERATIONS = 12
"""Steps one `solve` (a streamed target, warm seed) may take."""
IK_ITERATIONS = 200
"""Steps one `ik` attempt (a method call) may take, per seed."""
IK_SEEDS = 32
"""Seeds `ik` tries before it gives up (32: none of 2 572 random reachable poses away from
singularities and limits failed, against 8 with 12): the caller's, the posture, home, then fixed
pseudo-random ones (the same every time)."""
CONVERGED_M = 1e-10
CONVERGED_RAD = 1e-10
IK_TOL_M = 1e-9
IK_TOL_RAD = 1e-8
"""An `ik` solution is this exact (FK of it, against the target)."""
SOLVE_TOL_M = 1e-6
SOLVE_TOL_RAD = 1e-5
"""A streamed target is reached when the solution is this close."""
SOLVE_AIM_M = 1e-8
SOLVE_AIM_RAD = 1e-7
"""A streamed target's steps stop this close (0.01 µm: far below any servo's resolution;
the next target is solved afresh from this solution, so nothing accumulates)."""
CATCH_UP_M = 0.02
CATCH_UP_RAD = 0.1
"""Near a singularity a streamed target may be left this far, still catching up, if the
step made the error smaller: motion there slows instead of stopping."""
CLOSE_M = 1e-4
"""Within this of the target, an IK step's error is first checked by FK alone."""
MAX_TOOL_FRAMES = 16
"""Tool frames kept in a kinematics instance's model (a new tool after `set_tool`)."""
SINGULAR_SIGMA = 0.01
"""The smallest singular value of the flange Jacobian (m/rad or rad/rad) below which a
configuration is near a singularity."""


class Unreachable(TelerobotError):
    """No joint vector within the limits reaches the pose (without a branch change)."""


@dataclass(frozen=True, slots=True)
class IkSolution:
    """One IK solution: joints (rad), the branch (config string) for an analytic arm (None
    for a numerical one), and whether it is within the joint limits."""

    q: Vec
    config: str | None
    in_limits: bool


@dataclass(frozen=True, slots=True)
class Solve:
    """What `solve` commands: joints (rad, within limits) and how they were found.

    `pos_err_m` / `rot_err_rad` are the remaining tool pose errors of `q`; a solution near a
    singularity may still be catching up with the target."""

    q: Vec
    config: str | None
    near_singular: bool
    method: Literal["analytic", "dls"]
    pos_err_m: float = 0.0
    rot_err_rad: float = 0.0


def se3_floats(M: pin.SE3) -> PoseFloats:
    """(p, R row-major) of an SE3, as plain floats."""
    (a, b, c, x), (d, e, f, y), (g, h, i, z), _ = M.homogeneous.tolist()
    return [x, y, z], [a, b, c, d, e, f, g, h, i]


def compose_floats(
    aMb: tuple[Sequence[float], Sequence[float]], bMc: tuple[Sequence[float], Sequence[float]]
) -> PoseFloats:
    """aMc = aMb·bMc on (p, R) floats: p = p_ab + R_ab·p_bc, R = R_ab·R_bc."""
    (p_ab, R_ab), (p_bc, R_bc) = aMb, bMc
    r_ab = cast(M9, R_ab)  # 9 floats, row-major: geometry's products read them as they are
    x, y, z = mv9(r_ab, cast(V3, p_bc))
    return [p_ab[0] + x, p_ab[1] + y, p_ab[2] + z], list(mul9(r_ab, cast(M9, R_bc)))


def tool_se3(model: ArmModel) -> pin.SE3:
    """The model's default tool placement eMt."""
    return pin.SE3(np.array(model.tool_R, dtype=np.float64).reshape(3, 3), np.array(model.tool_p))


def make_kinematics(model: ArmModel) -> Kinematics:
    """The model's kinematics: its analytic plug-in (`module:Class`) or the numerical one."""
    if model.analytic_ik is None:
        return Kinematics(model)
    module, _, name = model.analytic_ik.partition(":")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError) as e:
        raise ConfigError(
            "arm.model", f"{model.path}: [ik] analytic {model.analytic_ik!r}: {e}"
        ) from None
    if not (isinstance(cls, type) and issubclass(cls, Kinematics)):
        raise ConfigError(
            "arm.model", f"{model.path}: [ik] analytic {model.analytic_ik!r} is not a Kinematics"
        )
    return cast(Kinematics, cls(model))


class Kinematics:
    """FK, Jacobian and numerical IK of one arm model (see the module docstring).

    Joint vectors are (n,) float64 in rad, joint 1 first; poses are `pin.SE3` in the world
    frame. Not thread-safe (one `pin.Data`): one instance per thread.
    """

    analytic = False

    def __init__(self, arm: ArmModel) -> None:
        self.arm = arm
        self.model: pin.Model = arm.pin_model()
        self.data: pin.Data = self.model.createData()
        self.n: int = self.model.nq
        self.q_lo: Vec = _frozen(arm.q_lo)
        """Joint lower limits, rad (read-only)."""
        self.q_hi: Vec = _frozen(arm.q_hi)
        """Joint upper limits, rad (read-only)."""
        self._lo: tuple[float, ...] = arm.q_lo
        self._hi: tuple[float, ...] = arm.q_hi
        self._flange = self.model.getFrameId(arm.flange_frame)
        first = self.model.frames[self.model.getFrameId(arm.joint_names[0])]
        self._base_link = first.parentFrame
        """The link the first joint turns in (where a mounted arm stands)."""
        self._posture = np.array(arm.named[arm.posture], dtype=np.float64)
        self._home = np.array(arm.home, dtype=np.float64)
        self._eye = np.eye(6) * DAMPING2
        self._null_eps = np.eye(6) * NULL_EPS
        self._tools: dict[tuple[float, ...], int] = {}
        self._rng = np.random.default_rng(1)  # the fixed seeds of `ik`
        self.eMt0: pin.SE3 = tool_se3(arm)
        """The model's default tool placement (where a method is given none)."""

    # --- checks ---------------------------------------------------------------------------

    def _vec(self, q: ArrayLike) -> Vec:
        v = np.array(q, dtype=np.float64).reshape(-1)
        if v.shape != (self.n,) or not np.all(np.isfinite(v)):
            raise ValueError(f"expected {self.n} finite joint angles, got {q!r}")
        return v

    def _floats(self, q: ArrayLike) -> list[float]:
        """`q` as a list of n Python floats (ValueError unless n finite angles)."""
        v = np.asarray(q, dtype=np.float64).reshape(-1).tolist()
        if len(v) != self.n or not all(map(math.isfinite, v)):
            raise ValueError(f"expected {self.n} finite joint angles, got {q!r}")
        return v

    def within_limits(self, q: ArrayLike, tol: float = 0.0) -> bool:
        """Every joint in [lo − tol, hi + tol] as given, rad."""
        qv = self._vec(q)
        return bool(np.all(qv >= self.q_lo - tol) and np.all(qv <= self.q_hi + tol))

    def clamp(self, q: Sequence[float]) -> list[float]:
        """q with every joint clamped into its limits."""
        return [
            lo if x < lo else hi if x > hi else x
            for x, lo, hi in zip(q, self._lo, self._hi, strict=True)
        ]

    # --- forward kinematics ---------------------------------------------------------------

    def fk_flange(self, q: ArrayLike) -> pin.SE3:
        """oMe: the flange in the world."""
        pin.forwardKinematics(self.model, self.data, self._vec(q))
        return pin.SE3(pin.updateFramePlacement(self.model, self.data, self._flange))

    def fk_tool(self, q: ArrayLike, eMt: pin.SE3 | None = None) -> pin.SE3:
        """oMt = oMe·eMt: the tool frame in the world (eq. 1: T_w = E_w + M_w^e M_e^t T_t)."""
        return self.fk_flange(q) * (self.eMt0 if eMt is None else eMt)

    def flange_pose_floats(self, q: Sequence[float]) -> PoseFloats:
        """oMe at joints q (n floats, rad) as (p, R) floats, for the control loop (no checks:
        q must be n finite floats)."""
        pin.forwardKinematics(self.model, self.data, np.array(q, dtype=np.float64))
        return se3_floats(pin.updateFramePlacement(self.model, self.data, self._flange))

    def tool_pose_floats(
        self, q: Sequence[float], eMt: tuple[Sequence[float], Sequence[float]]
    ) -> PoseFloats:
        """oMt at joints q as (p, R) floats: the flange pose composed with eMt."""
        return compose_floats(self.flange_pose_floats(q), eMt)

    def link_origins(self, q: ArrayLike) -> Vec:
        """(n + 2, 3) world positions, m: the origin of the link the first joint turns in
        (the arm's base), each joint's frame origin, the flange: the arm's skeleton, for
        drawing."""
        pin.forwardKinematics(self.model, self.data, self._vec(q))
        fl = pin.updateFramePlacement(self.model, self.data, self._flange)
        base = pin.updateFramePlacement(self.model, self.data, self._base_link)
        out = np.zeros((self.n + 2, 3))
        out[0] = base.translation
        for i in range(1, self.model.njoints):
            out[i] = self.data.oMi[i].translation
        out[-1] = fl.translation
        return out

    # --- differential kinematics --------------------------------------------------------------

    def _flange_jacobian(self, qv: Vec) -> tuple[Vec, pin.SE3]:
        """The flange's world-aligned Jacobian (6, n) and its pose, at qv."""
        J = pin.computeFrameJacobian(self.model, self.data, qv, self._flange, LWA)
        return np.array(J), pin.updateFramePlacement(self.model, self.data, self._flange)

    def jacobian(self, q: ArrayLike, eMt: pin.SE3 | None = None) -> Vec:
        """(6, n) geometric Jacobian of the tool point, world-aligned: rows (v; ω), m/s and
        rad/s. Shifted from the flange: v_t = v_e + ω × r with r = R_we·p_et."""
        J, oMe = self._flange_jacobian(self._vec(q))
        r = oMe.rotation @ (self.eMt0 if eMt is None else eMt).translation
        J[:3] -= pin.skew(r) @ J[3:]
        return J

    def manipulability(self, q: ArrayLike) -> float:
        """Yoshikawa's sqrt(det(J Jᵀ)) of the flange Jacobian."""
        J, _ = self._flange_jacobian(self._vec(q))
        return float(math.sqrt(max(float(np.linalg.det(J @ J.T)), 0.0)))

    def singularities(self, q: ArrayLike) -> list[str]:
        """["singular"] when the flange Jacobian's smallest singular value is below
        SINGULAR_SIGMA, else []."""
        J, _ = self._flange_jacobian(self._vec(q))
        sigma = np.linalg.svd(J, compute_uv=False)
        return ["singular"] if float(sigma[-1]) < SINGULAR_SIGMA else []

    def singularity(self, q: ArrayLike) -> str | None:
        kinds = self.singularities(q)
        return kinds[0] if kinds else None

    def config(self, q: ArrayLike) -> str | None:
        """The branch of a configuration: None for a numerical arm (no branches named)."""
        return None

    # --- inverse kinematics -------------------------------------------------------------------

    def pose_error(
        self, q: ArrayLike, oMt_target: pin.SE3, eMt: pin.SE3 | None = None
    ) -> tuple[float, float]:
        """(position error m, orientation error rad) of the tool at q from the target."""
        oMt = self.fk_tool(q, eMt)
        e_p = float(np.linalg.norm(oMt_target.translation - oMt.translation))
        e_r = float(np.linalg.norm(pin.log3(oMt_target.rotation @ oMt.rotation.T)))
        return e_p, e_r

    def _dls(
        self,
        q0: Vec,
        oMt_target: pin.SE3,
        eMt: pin.SE3,
        iterations: int,
        tol_m: float = CONVERGED_M,
        tol_rad: float = CONVERGED_RAD,
    ) -> tuple[Vec, float, float]:
        """Damped-least-squares steps from q0 towards the target, within the joint limits
        (a joint the step would push past a limit is held there, the others re-solved),
        with the posture task in the null space of a redundant arm. Returns the joints and
        their remaining (position, orientation) error."""
        tid = self._tool_frame(eMt)  # first: a new frame means a new `data`
        model, data = self.model, self.data
        q = q0.copy()
        p_t, R_t = oMt_target.translation, oMt_target.rotation
        lo, hi = self.q_lo, self.q_hi
        posture = self.n > 6
        err = np.empty(6)
        e_p = e_r = math.inf
        jacobian_ready = False
        for it in range(iterations + 1):
            # The error first, from FK alone: the last evaluation needs no Jacobian. Once
            # close (where the next step usually converges), one cheap FK decides; farther,
            # the Jacobian's pass computes FK too.
            if e_p < CLOSE_M:
                pin.forwardKinematics(model, data, q)
                jacobian_ready = False
            else:
                pin.computeJointJacobians(model, data, q)
                jacobian_ready = True
            oMt = pin.updateFramePlacement(model, data, tid)
            err[:3] = p_t - oMt.translation
            err[3:] = pin.log3(R_t @ oMt.rotation.T)
            e_p = math.sqrt(err[0] ** 2 + err[1] ** 2 + err[2] ** 2)
            e_r = math.sqrt(err[3] ** 2 + err[4] ** 2 + err[5] ** 2)
            if (e_p <= tol_m and e_r <= tol_rad) or it == iterations:
                break
            if not jacobian_ready:
                pin.computeJointJacobians(model, data, q)
            J = pin.getFrameJacobian(model, data, tid, LWA)
            damp = self._eye * (1.0 + LM_GAIN * (e_p * e_p + e_r * e_r) / DAMPING2)
            # the posture steps until the last digits, which pure Gauss–Newton settles
            posture = posture and (e_p > POSTURE_UNTIL_M or e_r > POSTURE_UNTIL_RAD)
            free: NDArray[np.bool_] | None = None
            for _pass in range(2):
                Jf = J if free is None else J * free
                JJ = Jf @ Jf.T
                # Cholesky: both matrices are symmetric positive definite (λ², ε > 0), and
                # Eigen's (through eigenpy, Pinocchio's own binding) takes 3 µs where
                # numpy.linalg.solve takes 9–15 µs of call overhead on a 6×6.
                dq = Jf.T @ LLT(JJ + damp).solve(err)
                if posture:
                    z = POSTURE_GAIN * (self._posture - q)
                    if free is not None:
                        z *= free
                    dq += z - Jf.T @ LLT(JJ + self._null_eps).solve(Jf @ z)
                big = float(np.abs(dq).max())
                if big > MAX_STEP_RAD:
                    dq *= MAX_STEP_RAD / big
                nxt = q + dq
                out = (nxt < lo) | (nxt > hi)
                if not out.any():
                    break
                keep = ~out if free is None else free & ~out
                if _pass == 1 or not keep.any():
                    break
                free = keep  # hold those at their limits, let the others make up
            q = np.clip(nxt, lo, hi) if out.any() else nxt
        return q, e_p, e_r

    def _tool_frame(self, eMt: pin.SE3) -> int:
        """The id of a frame of the Pinocchio model at the tool point for `eMt` (added the
        first time a tool is seen, so FK and the Jacobian give the tool's directly)."""
        key = tuple(eMt.homogeneous.reshape(-1).tolist())
        fid = self._tools.get(key)
        if fid is None:
            flange = self.model.frames[self._flange]
            placement = flange.placement * eMt
            fid = self.model.addFrame(
                pin.Frame(f"tool_{len(self._tools)}", flange.parentJoint, placement,
                          pin.FrameType.OP_FRAME)
            )  # fmt: skip
            self.data = self.model.createData()
            if len(self._tools) >= MAX_TOOL_FRAMES:
                self._tools.clear()
            self._tools[key] = fid
        return fid

    def ik(
        self, oMt: pin.SE3, eMt: pin.SE3 | None = None, q_ref: ArrayLike | None = None
    ) -> list[IkSolution]:
        """The numerical solution for the tool pose `oMt` nearest `q_ref` (default: the
        posture configuration), within the joint limits: [one IkSolution], or [] when none
        of IK_SEEDS seeds converges (out of reach, or out of the limits)."""
        eMt = self.eMt0 if eMt is None else eMt
        seeds = [self._posture if q_ref is None else self._vec(q_ref), self._posture, self._home]
        for k in range(IK_SEEDS):
            if k >= len(seeds):
                seeds.append(self._rng.uniform(self.q_lo, self.q_hi))
            q, e_p, e_r = self._dls(
                np.clip(seeds[k], self.q_lo, self.q_hi), oMt, eMt, IK_ITERATIONS
            )
            if e_p <= IK_TOL_M and e_r <= IK_TOL_RAD:
                return [IkSolution(q, None, True)]
        return []

    def choose(self, sols: list[IkSolution], q_now: ArrayLike) -> IkSolution | None:
        """The in-limits solution nearest `q_now` (Euclidean, rad), or None."""
        now = self._vec(q_now)
        best, best_d = None, math.inf
        for s in sols:
            if not s.in_limits:
                continue
            d = float(np.sum((s.q - now) ** 2))
            if d < best_d:
                best, best_d = s, d
        return best

    def solve(
        self,
        q_now: ArrayLike,
        oMt_target: pin.SE3,
        eMt: pin.SE3 | None = None,
        seed: ArrayLike | None = None,
    ) -> Solve:
        """Joints to command now so the tool reaches `oMt_target` (the streamed-target path):
        DLS from `seed` (default `q_now`), at most SOLVE_ITERATIONS steps. The result is
        within the joint limits; it reaches the target within SOLVE_TOL_M / SOLVE_TOL_RAD,
        or — near a singularity, still catching up — is within CATCH_UP_M / CATCH_UP_RAD and
        closer than where it started. Raises `Unreachable` otherwise."""
        eMt = self.eMt0 if eMt is None else eMt
        start = np.clip(self._vec(q_now if seed is None else seed), self.q_lo, self.q_hi)
        q, e_p, e_r = self._dls(
            start, oMt_target, eMt, SOLVE_ITERATIONS, SOLVE_AIM_M, SOLVE_AIM_RAD
        )
        if e_p <= SOLVE_TOL_M and e_r <= SOLVE_TOL_RAD:
            return Solve(q, None, False, "dls", e_p, e_r)
        e0_p, e0_r = self.pose_error(start, oMt_target, eMt)
        if e_p <= CATCH_UP_M and e_r <= CATCH_UP_RAD and (e_p < e0_p or e_r < e0_r):
            return Solve(q, None, bool(self.singularities(q)), "dls", e_p, e_r)
        raise Unreachable(
            f"no joint solution within the limits (DLS left {e_p:.4f} m, {e_r:.4f} rad)"
        )


def _frozen(values: Sequence[float]) -> Vec:
    v = np.array(values, dtype=np.float64)
    v.setflags(write=False)
    return v
