"""The PUMA proxy: the paper's IProxyRobot component, free of the bus.

`PumaProxy` turns method calls (PROTOCOL.md §4) and the streamed operator commands (§2, §3)
into one joint setpoint per control cycle for an `Arm`, and reports status changes and
other events through `emit(kind, message, data)`.

Frames: world R_w (the DH base frame), wrist R_e (the flange, DH frame 6, origin at the wrist
centre), tool R_t (placed in R_e by `eMt`, set with `set_tool`). Units: m, rad, s.

Who calls what: `tick(dt_s)` is called by the service's fixed-rate loop and is the only
place that talks to the arm's setpoint stream; `rpc_*`, `on_command`, `state` and
`wait_motion` may be called from any thread (the bus's callbacks). One lock serialises
them; motion planning (many IK solves) runs outside it on a kinematics instance of its own.

Motions. A method that moves the robot (`move_joints`, `move_pose`, `move_relative`,
`home`) is accepted only when the robot is `ready` (at rest): `busy` while another motion
or the teleoperation stream is moving it. It returns `{"accepted": True, "motion": id}` at
once; `wait_motion(id, timeout_s)` blocks until that motion ends. A streamed command
pre-empts a running motion; `stop` brakes any motion to rest.

Safety, whatever the source of the motion (`safe_step`, applied every tick): a setpoint
never leaves the joint limits, no joint exceeds its speed limit, no joint its acceleration
limit (unless that is the only way to honour the other limits), and the tool point moves at
most `max_tool_speed_m_s` and the tool frame turns at most `max_tool_rot_speed_rad_s`
between two ticks. Motions are planned, and streamed commands chased, within these limits
(with margin), so the filter is a last line that seldom has to act. An arm error, a
following error or a failed read puts the proxy in `error`: the motion is abandoned, the
arm holds, and nothing moves until `connect` and `initialize`.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from services.bus.bounds import check_each, check_norm, short
from services.bus.errors import RpcError
from services.puma.arm import Arm, ArmError
from services.puma.config import PumaConfig
from services.puma.kinematics import DEFAULT_eMt, Puma560, Unreachable
from services.puma.mapping import TeleopInput, TeleopMapping

Vec = NDArray[np.float64]
Status = Literal["disconnected", "connected", "initializing", "ready", "moving", "error"]
RelFrame = Literal["world", "wrist", "tool"]
REL_FRAMES: tuple[str, ...] = get_args(RelFrame)
EmitFn = Callable[[str, str, dict[str, Any]], None]

ROTATION_TOL = 1e-6
"""‖RᵀR − I‖_F above this, or det R < 0, is not a rotation (PROTOCOL.md conventions)."""
PLAN_STEP_M = 0.01
PLAN_STEP_RAD = 0.05
"""Cartesian paths are solved every 1 cm / 0.05 rad of tool motion and interpolated between."""
PLAN_MAX_JOINT_STEP_RAD = 0.2
"""Two consecutive path samples further apart than this in any joint: the straight line
crosses a singularity or a branch change, so the move is made in joint space instead."""
PLAN_SPEED_MARGIN = 0.9
PLAN_ACCEL_SHARE = 0.45
"""Plans use 90 % of each speed limit; a Cartesian path gives 45 % of each joint's
acceleration to the path's acceleration and 45 % to its curvature (q'·s̈ + q''·ṡ²)."""
MAX_MOTION_HISTORY = 128
GOAL_TOL_RAD = 1e-9
"""A motion has reached its goal within this (rounding of q + v·dt)."""


# --- arguments ------------------------------------------------------------------------------


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def opt_vector(args: Mapping[str, Any], key: str, n: int) -> Vec | None:
    """`args[key]` as n finite floats, None if absent, or RpcError("bad_request") naming it."""
    if args.get(key) is None:
        return None
    value = args[key]
    if not isinstance(value, list | tuple) or len(value) != n:
        raise RpcError("bad_request", f"{key}: expected {n} numbers, got {short(value, 80)}")
    if not all(_is_number(x) for x in value):
        raise RpcError("bad_request", f"{key}: every element must be a number")
    arr = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise RpcError("bad_request", f"{key}: not finite")
    return arr


def arg_vector(args: Mapping[str, Any], key: str, n: int) -> Vec:
    """`args[key]` as n finite floats, or RpcError("bad_request") naming the field."""
    v = opt_vector(args, key, n)
    if v is None:
        raise RpcError("bad_request", f"{key}: missing ({n} numbers)")
    return v


def rotation_problem(R: NDArray[np.float64]) -> str | None:
    """Why a 3×3 matrix is not a rotation, or None (PROTOCOL conventions)."""
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        return "not a finite 3x3 matrix"
    if float(np.linalg.norm(R.T @ R - np.eye(3))) > ROTATION_TOL:
        return "not orthonormal"
    if float(np.linalg.det(R)) < 0.0:
        return "a reflection (det < 0)"
    return None


def opt_rotation(args: Mapping[str, Any], key: str) -> Vec | None:
    """`args[key]` as a rotation from 9 floats row-major, None if absent, or
    RpcError("bad_request") naming the field."""
    flat = opt_vector(args, key, 9)
    if flat is None:
        return None
    R = flat.reshape(3, 3)
    why = rotation_problem(R)
    if why is not None:
        raise RpcError("bad_request", f"{key}: {why}")
    return R


def arg_rotation(args: Mapping[str, Any], key: str) -> Vec:
    R = opt_rotation(args, key)
    if R is None:
        raise RpcError("bad_request", f"{key}: missing (9 numbers, row-major)")
    return R


def opt_frame(args: Mapping[str, Any], key: str = "frame") -> RelFrame | None:
    """`args[key]` as world | wrist | tool, None if absent, or RpcError("bad_request")."""
    value = args.get(key)
    if value is None:
        return None
    if value == "world" or value == "wrist" or value == "tool":
        return value
    raise RpcError(
        "bad_request", f"{key}: must be one of {', '.join(REL_FRAMES)}, got {short(value, 40)}"
    )


def arg_config(args: Mapping[str, Any], key: str = "config") -> str | None:
    c = args.get(key)
    if c is None:
        return None
    if not (isinstance(c, str) and len(c) == 3 and c[0] in "rl" and c[1] in "ud" and c[2] in "pm"):
        raise RpcError("bad_request", f"{key}: must be 3 letters r|l, u|d, p|m, got {short(c, 40)}")
    return c


def arg_fraction(args: Mapping[str, Any], key: str) -> float:
    x = args.get(key)
    if x is None:
        return 1.0
    if not _is_number(x) or not math.isfinite(x) or not 0.0 < x <= 1.0:
        raise RpcError("bad_request", f"{key}: must be a number in (0, 1], got {short(x, 40)}")
    return float(x)


# --- trajectories (pure) ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Trapezoid:
    """A trapezoidal (or triangular) time law s(t) from 0 to 1 at rest at both ends.

    `v_peak` (1/s) and `a` (1/s²) are the path speed and acceleration; `duration_s` the total.
    """

    v_peak: float
    a: float
    t_acc_s: float
    duration_s: float

    @staticmethod
    def plan(v_max: float, a_max: float) -> Trapezoid:
        """The fastest law with ṡ ≤ v_max and |s̈| ≤ a_max (both > 0)."""
        if v_max * v_max >= a_max:
            t_acc = math.sqrt(1.0 / a_max)
            return Trapezoid(a_max * t_acc, a_max, t_acc, 2.0 * t_acc)
        t_acc = v_max / a_max
        return Trapezoid(v_max, a_max, t_acc, 1.0 / v_max + t_acc)

    def s_at(self, t_s: float) -> float:
        if t_s <= 0.0:
            return 0.0
        if t_s >= self.duration_s:
            return 1.0
        if t_s < self.t_acc_s:
            return 0.5 * self.a * t_s * t_s
        if t_s <= self.duration_s - self.t_acc_s:
            return 0.5 * self.a * self.t_acc_s**2 + self.v_peak * (t_s - self.t_acc_s)
        r = self.duration_s - t_s
        return 1.0 - 0.5 * self.a * r * r


class SampledPath:
    """A joint path q(s), s ∈ [0, 1], through samples at uniform s, C¹ (cubic Hermite with
    Catmull-Rom tangents) so the joint velocity is continuous along the path."""

    def __init__(self, samples: NDArray[np.float64]) -> None:
        self.q = np.asarray(samples, dtype=np.float64)
        n = len(self.q) - 1
        if n < 1:
            raise ValueError("a path needs at least 2 samples")
        self.n = n
        m = np.empty_like(self.q)
        m[1:-1] = (self.q[2:] - self.q[:-2]) / 2.0
        m[0] = self.q[1] - self.q[0]
        m[-1] = self.q[-1] - self.q[-2]
        self.m = m  # tangents dq/di, per sample index

    def at(self, s: float) -> Vec:
        x = min(max(s, 0.0), 1.0) * self.n
        i = min(int(x), self.n - 1)
        u = x - i
        h00 = 2 * u**3 - 3 * u**2 + 1
        h10 = u**3 - 2 * u**2 + u
        h01 = -2 * u**3 + 3 * u**2
        h11 = u**3 - u**2
        return np.asarray(
            h00 * self.q[i] + h10 * self.m[i] + h01 * self.q[i + 1] + h11 * self.m[i + 1],
            dtype=np.float64,
        )

    def derivative_bounds(self) -> tuple[Vec, Vec]:
        """Per joint max |dq/ds| and max |d²q/ds²| over the samples (finite differences)."""
        d1 = np.abs(np.diff(self.q, axis=0)) * self.n
        d1max = d1.max(axis=0)
        if self.n >= 2:
            d2max = (np.abs(np.diff(self.q, n=2, axis=0)) * self.n * self.n).max(axis=0)
        else:
            d2max = np.zeros(6)
        return np.asarray(d1max, dtype=np.float64), np.asarray(d2max, dtype=np.float64)


def discrete_brake_speed(e_rad: Vec, amax: Vec, dt_s: float) -> Vec:
    """The largest speed (rad/s, ≥ 0) from which each joint stops within |e| when slowing by
    amax·dt per step of dt: v = a·dt·(√(¼ + 2|e|/(a·dt²)) − ½), capped at |e|/dt."""
    ae = np.abs(e_rad)
    v = amax * dt_s * (np.sqrt(0.25 + 2.0 * ae / (amax * dt_s * dt_s)) - 0.5)
    return np.asarray(np.minimum(v, ae / dt_s), dtype=np.float64)


def rotation_angle(Ra: NDArray[np.float64], Rb: NDArray[np.float64]) -> float:
    """The angle (rad) of RaᵀRb, accurate for small angles: ‖Ra − Rb‖_F = 2√2·sin(θ/2)."""
    d = float(np.linalg.norm(Ra - Rb))
    return 2.0 * math.asin(min(1.0, d / (2.0 * math.sqrt(2.0))))


@dataclass(frozen=True, slots=True)
class MotionLimits:
    """What `safe_step` enforces: joint limits (rad), speeds (rad/s), accelerations (rad/s²),
    tool point speed (m/s) and tool frame angular speed (rad/s)."""

    q_lo: Vec
    q_hi: Vec
    vmax: Vec
    amax: Vec
    tool_speed_m_s: float
    tool_rot_speed_rad_s: float


@dataclass(frozen=True, slots=True)
class SafeStep:
    """One filtered setpoint: joints (rad), velocity (rad/s), the tool pose there, and which
    limits acted (`joint_limit`, `joint_speed`, `joint_accel`, `tool_speed`)."""

    q: Vec
    qd: Vec
    tool_p: Vec
    tool_R: Vec
    limited: frozenset[str]


ToolPoseFn = Callable[[Vec], tuple[Vec, Vec]]


def _cut(a: Vec, b: Vec, tol: float) -> bool:
    """Whether a limit changed b into a by more than rounding (q + v·dt is not exact)."""
    return bool(np.any(np.abs(a - b) > tol * (1.0 + np.abs(b))))


def safe_step(
    q: Vec,
    qd: Vec,
    q_des: Vec,
    dt_s: float,
    lim: MotionLimits,
    tool_pose: ToolPoseFn,
    pose_now: tuple[Vec, Vec],
) -> SafeStep:
    """The next setpoint towards `q_des` that honours `lim`, from setpoint `q` moving at `qd`.

    In order: clamp the target into the joint limits; clip the joint velocity to ±vmax and
    its change to ±amax·dt; clamp again; then, if the tool point or tool frame would move
    faster than allowed between the two setpoints (measured exactly with `tool_pose`, the
    tool pose of a joint vector), shrink the step towards `q` until it does not — shrinking
    keeps the joints inside the limits and below their speeds. The joint limits and the tool
    speeds always hold; the acceleration limit gives way only to them.
    """
    limited: set[str] = set()
    target = np.clip(q_des, lim.q_lo, lim.q_hi)
    if _cut(target, q_des, 1e-12):
        limited.add("joint_limit")
    v = (target - q) / dt_s
    v_c = np.clip(v, -lim.vmax, lim.vmax)
    if _cut(v_c, v, 1e-9):
        limited.add("joint_speed")
    dv = lim.amax * dt_s
    v_a = np.clip(v_c, qd - dv, qd + dv)
    if _cut(v_a, v_c, 1e-9):
        limited.add("joint_accel")
    v_a = np.clip(v_a, -lim.vmax, lim.vmax)
    q_next = np.clip(q + v_a * dt_s, lim.q_lo, lim.q_hi)
    p0, R0 = pose_now
    max_dp = lim.tool_speed_m_s * dt_s
    max_dth = lim.tool_rot_speed_rad_s * dt_s
    p1, R1 = tool_pose(q_next)
    for _ in range(8):
        over = max(float(np.linalg.norm(p1 - p0)) / max_dp, rotation_angle(R0, R1) / max_dth)
        if over <= 1.0:
            break
        limited.add("tool_speed")
        q_next = q + (q_next - q) * (0.98 / over)
        p1, R1 = tool_pose(q_next)
    else:
        # The step cannot be made slow enough (it never happens for steps this small, as the
        # tool pose is smooth in q): holding is always within every limit.
        q_next, p1, R1 = q.copy(), p0, R0
    return SafeStep(q_next, (q_next - q) / dt_s, p1, R1, frozenset(limited))


# --- motions ----------------------------------------------------------------------------------


class Motion:
    """A handle on one motion: `id`, `kind`, and its result once it has ended.

    The result is a dict: `motion` (id), `done` (bool), `completed` (reached its target),
    `reason` (`completed`, `stopped`, `preempted`, `error`, `estop`, `closed`, or `running`
    while not done), `q` (setpoint joints at the end, rad).
    """

    def __init__(self, motion_id: int, kind: str) -> None:
        self.id = motion_id
        self.kind = kind
        self._done = threading.Event()
        self._result: dict[str, Any] = {
            "motion": motion_id,
            "done": False,
            "completed": False,
            "reason": "running",
        }

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def result(self) -> dict[str, Any]:
        return dict(self._result)

    def wait(self, timeout_s: float | None) -> dict[str, Any]:
        """Block until the motion ends or `timeout_s` passes; the result either way."""
        self._done.wait(timeout_s)
        return self.result()

    def finish(self, reason: str, q: Vec) -> None:
        if self._done.is_set():
            return
        self._result = {
            "motion": self.id,
            "done": True,
            "completed": reason == "completed",
            "reason": reason,
            "q": [float(x) for x in q],
        }
        self._done.set()


class _Planned:
    """A planned motion: q(t) = path(s(t)), at rest at both ends."""

    def __init__(
        self, path: Callable[[float], Vec], law: Trapezoid, goal: Vec, hold_first: bool
    ) -> None:
        self.path = path
        self.law = law
        self.goal = goal
        self.t_s = 0.0
        self.hold_first = hold_first

    def next(self, dt_s: float) -> Vec:
        if self.hold_first:
            self.hold_first = False
            return self.path(0.0)
        self.t_s += dt_s
        if self.t_s >= self.law.duration_s:
            return self.goal
        return self.path(self.law.s_at(self.t_s))

    @property
    def finished(self) -> bool:
        return self.t_s >= self.law.duration_s


class _Servo:
    """Chases a goal (rad) as fast as the joint limits allow, slowing so the tool stays
    below its speed limits; used for streamed commands and to finish a planned motion."""

    def __init__(self, goal: Vec, t_s: float, settle_s: float) -> None:
        self.goal = goal
        self.last_goal_t_s = t_s
        self.settle_s = settle_s


class _Brake:
    """Decelerates every joint in proportion, so the path stays straight, to rest."""


Generator = _Planned | _Servo | _Brake
Plan = tuple[Callable[[float], Vec], Trapezoid, Vec, str]
"""A planned motion: q(s) for s ∈ [0, 1], its time law, the goal joints, `joint`|`cartesian`."""
PlanFn = Callable[[Puma560, Vec, pin.SE3], Plan]


class _Limiter:
    """At most one event per key every `interval_s` of proxy time; counts the rest."""

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self.suppressed: dict[str, int] = {}

    def allow(self, key: str, now_s: float) -> int | None:
        """None to suppress; else how many were suppressed since the last one."""
        last = self._last.get(key)
        if last is not None and now_s - last < self.interval_s:
            self.suppressed[key] = self.suppressed.get(key, 0) + 1
            return None
        self._last[key] = now_s
        return self.suppressed.pop(key, 0)


# --- the proxy --------------------------------------------------------------------------------


class PumaProxy:
    """The IProxyRobot of PROTOCOL.md §4 over an `Arm`; events go out through `emit`.

    `emit(kind, message, data)` is called outside the proxy's lock, in order, from whichever
    thread caused the event; kinds: `status`, `moved`, `error` (data `code`), `data`,
    `rejected`, `limit`, `estop`.
    """

    def __init__(self, arm: Arm, config: PumaConfig, emit: EmitFn) -> None:
        self.arm = arm
        self.config = config
        self._emit = emit
        self._lock = threading.RLock()
        self._status_changed = threading.Condition(self._lock)
        self._plan_lock = threading.Lock()
        self._emit_lock = threading.RLock()
        self._events: list[tuple[str, str, dict[str, Any]]] = []
        self._kin = Puma560()  # the loop's: tick, on_command, state
        self._plan_kin = Puma560()  # the methods': planning, fk, ik
        self.limits = MotionLimits(
            q_lo=self._kin.q_lo.copy(),
            q_hi=self._kin.q_hi.copy(),
            vmax=np.array(config.max_joint_speed_rad_s, dtype=np.float64),
            amax=np.array(config.max_joint_accel_rad_s2, dtype=np.float64),
            tool_speed_m_s=config.max_tool_speed_m_s,
            tool_rot_speed_rad_s=config.max_tool_rot_speed_rad_s,
        )
        self._status: Status = "disconnected"
        self._estopped = False
        self._last_error: str | None = None
        self._eMt: pin.SE3 = pin.SE3(DEFAULT_eMt)
        self._tool_version = 0
        self._frame: RelFrame = "world"
        self._t_s = 0.0
        self._q_cmd = np.zeros(6)
        self._qd_cmd = np.zeros(6)
        self._q_meas: Vec | None = None
        self._pose_cmd: tuple[Vec, Vec] = self._tool_pose(self._q_cmd)
        self._gen: Generator | None = None
        self._motion: Motion | None = None
        self._motions: OrderedDict[int, Motion] = OrderedDict()
        self._next_id = 1
        self._mapping = TeleopMapping()
        self._grip: float | None = None
        self._last_cmd_t_ns = 0
        self._cmd_rx_ns: int | None = None
        self._cmd_origin_t_ns: int | None = None
        self._setpoint_ns: int | None = None
        self._awaiting_setpoint = False
        self._fk_cache: tuple[bytes, int, dict[str, Any]] | None = None
        self._limiter = _Limiter(config.event_interval_s)
        self.counters: dict[str, int] = {
            "ticks": 0,
            "commands": 0,
            "commands_ignored": 0,
            "rejected": 0,
            "unreachable": 0,
            "limited": 0,
        }

    @property
    def status(self) -> Status:
        """The robot status of PROTOCOL §5 (cheap: no kinematics)."""
        with self._lock:
            return self._status

    @property
    def needs_tick(self) -> bool:
        """Whether the control loop must tick at its rate: a motion, a brake or a teleop
        servo runs, the setpoint still has velocity, or calibration is under way. Otherwise
        nothing changes between commands and a slow watch tick is enough."""
        with self._lock:
            if self._status == "initializing":
                return True
            if self._status not in ("ready", "moving"):
                return False
            return self._gen is not None or bool(self._qd_cmd.any())

    def __enter__(self) -> PumaProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the loop -------------------------------------------------------------------------

    def tick(self, dt_s: float) -> None:
        """One control cycle of `dt_s` seconds: advance the motion, filter, command the arm."""
        if not dt_s > 0.0:
            raise ValueError("dt_s must be > 0")
        with self._lock:
            self._t_s += dt_s
            self.counters["ticks"] += 1
            self._tick_locked(dt_s)
        self._flush()

    def _tick_locked(self, dt_s: float) -> None:
        st = self._status
        if st in ("disconnected", "error"):
            return
        arm_status = self.arm.status
        if arm_status == "error" or arm_status == "disconnected":
            self._fail("internal", f"arm: {self.arm.last_error or arm_status}")
            return
        if st == "initializing":
            if arm_status == "ready":
                self._finish_initialization()
            return
        if st not in ("ready", "moving"):
            return
        try:
            q_meas = self.arm.read_joints()
        except ArmError as e:
            self._fail("internal", f"arm: {e}")
            return
        self._q_meas = q_meas
        follow = float(np.max(np.abs(q_meas - self._q_cmd)))
        if follow > self.config.max_following_error_rad:
            self._fail("internal", f"following error {follow:.3f} rad: the arm does not follow")
            return
        if self._gen is None and not self._qd_cmd.any():
            return  # at rest with nothing to do: the arm already holds this setpoint
        q_des = self._desired(dt_s)
        step = safe_step(
            self._q_cmd, self._qd_cmd, q_des, dt_s, self.limits, self._tool_pose, self._pose_cmd
        )
        if step.limited:
            self.counters["limited"] += 1
            self._event_limited(
                "limit", "limit", "a limit held the motion back", {"limits": sorted(step.limited)}
            )
        self._q_cmd, self._qd_cmd = step.q, step.qd
        self._pose_cmd = (step.tool_p, step.tool_R)
        self.arm.command(self._q_cmd)
        if self._awaiting_setpoint:
            self._awaiting_setpoint = False
            self._setpoint_ns = time.time_ns()
        self._update_motion(dt_s)

    def _desired(self, dt_s: float) -> Vec:
        gen = self._gen
        if gen is None:
            return self._q_cmd
        if isinstance(gen, _Planned):
            return gen.next(dt_s)
        if isinstance(gen, _Brake):
            t_stop = float(np.max(np.abs(self._qd_cmd) / self.limits.amax))
            k = max(0.0, 1.0 - dt_s / t_stop) if t_stop > 0.0 else 0.0
            return self._q_cmd + self._qd_cmd * k * dt_s
        return self._servo_target(gen.goal, dt_s)

    def _servo_target(self, goal: Vec, dt_s: float) -> Vec:
        """The next setpoint chasing `goal`: per joint as fast as its speed allows while it can
        still stop at the goal, within the acceleration box around the present velocity, and
        with the tool kept under 90 % of its speeds (so `safe_step` has nothing to cut)."""
        q, qd = self._q_cmd, self._qd_cmd
        e = goal - q
        v_des = np.sign(e) * np.minimum(
            self.limits.vmax, discrete_brake_speed(e, self.limits.amax, dt_s)
        )
        p0, R0 = self._pose_cmd
        max_dp = PLAN_SPEED_MARGIN * self.limits.tool_speed_m_s * dt_s
        max_dth = PLAN_SPEED_MARGIN * self.limits.tool_rot_speed_rad_s * dt_s

        def over(v: Vec) -> float:
            p1, R1 = self._tool_pose(q + v * dt_s)
            return max(float(np.linalg.norm(p1 - p0)) / max_dp, rotation_angle(R0, R1) / max_dth)

        k = over(v_des)
        if k > 1.0:
            v_des = v_des / k
        dv = self.limits.amax * dt_s
        v = np.clip(v_des, qd - dv, qd + dv)
        if over(v) > 1.0:
            # The acceleration box bent the step into a faster tool motion: ask for less until
            # it fits (λ = 0 is the hardest braking the box allows).
            lo, hi = 0.0, 1.0
            for _ in range(12):
                mid = 0.5 * (lo + hi)
                if over(np.clip(mid * v_des, qd - dv, qd + dv)) <= 1.0:
                    lo = mid
                else:
                    hi = mid
            v = np.clip(lo * v_des, qd - dv, qd + dv)
        return np.asarray(q + v * dt_s, dtype=np.float64)

    def _update_motion(self, dt_s: float) -> None:
        gen = self._gen
        if gen is None:
            return
        at_rest = not np.any(self._qd_cmd)
        if isinstance(gen, _Brake):
            if at_rest:
                self._end_motion("stopped")
            return
        if isinstance(gen, _Planned):
            if gen.finished:
                if float(np.max(np.abs(gen.goal - self._q_cmd))) <= GOAL_TOL_RAD:
                    self._q_cmd = gen.goal.copy()
                    self._end_motion("completed")
                else:
                    # The filter held the plan back somewhere: finish by chasing the goal.
                    self._gen = _Servo(gen.goal, self._t_s, 0.0)
            return
        e = float(np.max(np.abs(gen.goal - self._q_cmd)))
        if e <= GOAL_TOL_RAD and float(np.max(np.abs(self._qd_cmd))) < 1e-6:
            self._q_cmd = gen.goal.copy()
            if self._t_s - gen.last_goal_t_s >= gen.settle_s:
                self._qd_cmd = np.zeros(6)
                self._end_motion("completed")

    def _end_motion(self, reason: str) -> None:
        motion = self._motion
        self._gen = None
        self._motion = None
        if motion is None or motion.kind != "teleop" or reason != "completed":
            # Something other than the operator's commands moved the arm (or cut a command
            # short): the next command re-bases there instead of jumping back.
            self._mapping.rebase()
        if motion is not None:
            motion.finish(reason, self._q_cmd)
        self._set_status("ready")
        p, _ = self._pose_cmd
        self._event(
            "moved",
            f"motion {motion.id if motion else '-'} {reason}",
            {
                "motion": motion.id if motion else None,
                "reason": reason,
                "q": [float(x) for x in self._q_cmd],
                "tool_p": [float(x) for x in p],
            },
        )

    def _finish_initialization(self) -> None:
        try:
            q = self.arm.read_joints()
        except ArmError as e:
            self._fail("internal", f"arm: {e}")
            return
        self._q_meas = q.copy()
        self._q_cmd = q.copy()
        self._qd_cmd = np.zeros(6)
        self._pose_cmd = self._tool_pose(self._q_cmd)
        self._mapping.rebase()
        self._set_status("ready")
        # The first setpoint is where the arm is: from here on it holds what it was sent.
        self.arm.command(self._q_cmd)
        self._event("data", "arm calibrated", {"q": [float(x) for x in q]})

    # --- streamed commands ----------------------------------------------------------------

    def on_command(
        self,
        cmd: TeleopInput,
        t_ns: int,
        grip: float | None,
        rx_ns: int | None = None,
        origin_t_ns: int | None = None,
    ) -> None:
        """A streamed OperatorCommand (`robot/puma/cmd`, after supervision; PROTOCOL §2–3).

        Ignored unless `ready` or `moving` (and while `stop` brakes). A command with a
        non-finite or too large `dp` (> `max_dp_m`), a `dR` that is not a rotation or a grip
        outside [0, 1] is rejected (a rate-limited `rejected` event) and moves nothing. An
        active command maps to a tool target (TeleopMapping, eqs. 1–3) and joints
        (`Puma560.solve`) that the arm then chases within every limit, pre-empting a running
        motion. An unreachable target leaves the last reachable goal in place (the arm holds
        there) and raises a rate-limited `error` event with code `unreachable`.

        `rx_ns` (when the service received it) and `origin_t_ns` (the operator's send time
        it carries) are reported in the state with the time of the first setpoint it
        produced, so the operator's path can be timed on one clock.
        """
        with self._lock:
            self._on_command_locked(cmd, t_ns, grip, rx_ns, origin_t_ns)
        self._flush()

    def _on_command_locked(
        self,
        cmd: TeleopInput,
        t_ns: int,
        grip: float | None,
        rx_ns: int | None,
        origin_t_ns: int | None,
    ) -> None:
        self.counters["commands"] += 1
        if self._status not in ("ready", "moving") or isinstance(self._gen, _Brake):
            self.counters["commands_ignored"] += 1
            return
        dp = np.asarray(cmd.dp, dtype=np.float64)
        dR = np.asarray(cmd.dR, dtype=np.float64)
        why: str | None = None
        if dp.shape != (3,) or not np.all(np.isfinite(dp)):
            why = "dp: not 3 finite numbers"
        elif _too_long(dp, self.config.max_dp_m):
            why = f"dp: |dp| above {self.config.max_dp_m} m"
        elif (r := rotation_problem(dR)) is not None:
            why = f"dR: {r}"
        elif grip is not None and not (_is_number(grip) and 0.0 <= grip <= 1.0):
            why = "grip: must be within [0, 1]"
        if why is not None:
            self.counters["rejected"] += 1
            self._event_limited(
                "rejected",
                "rejected",
                f"command {cmd.seq} rejected: {why}",
                {"seq": cmd.seq, "reason": why},
            )
            return
        before = self._mapping.last_seq
        target = self._mapping.apply(cmd, pin.SE3(self._pose_cmd[1], self._pose_cmd[0]))
        if self._mapping.last_seq == before:
            self.counters["commands_ignored"] += 1
            return  # stale: an older seq or engagement
        self._last_cmd_t_ns = int(t_ns)
        self._cmd_rx_ns = rx_ns
        self._cmd_origin_t_ns = origin_t_ns
        self._setpoint_ns = None
        self._awaiting_setpoint = cmd.active
        if grip is not None:
            self._grip = float(grip)
        if target is None:
            return  # master-shift: hold; the goal in place is where the arm stays
        try:
            sol = self._kin.solve(self._q_cmd, target, self._eMt)
        except Unreachable as e:
            self.counters["unreachable"] += 1
            self._event_limited(
                "unreachable",
                "error",
                f"command {cmd.seq} unreachable: {e}",
                {"code": "unreachable", "seq": cmd.seq},
            )
            return
        if sol.near_singular:
            self._event_limited(
                "singular",
                "limit",
                "near a singularity: motion slowed",
                {"singularity": self._kin.singularity(sol.q)},
            )
        goal = np.clip(sol.q, self.limits.q_lo, self.limits.q_hi)
        gen = self._gen
        if isinstance(gen, _Servo) and self._motion is not None and self._motion.kind == "teleop":
            gen.goal = goal
            gen.last_goal_t_s = self._t_s
            return
        if self._motion is not None:
            self._motion.finish("preempted", self._q_cmd)
        self._start(
            Motion(self._new_id(), "teleop"), _Servo(goal, self._t_s, self.config.teleop_settle_s)
        )

    # --- methods (PROTOCOL §4, IProxyRobot) -----------------------------------------------

    def rpc_status(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """The robot state plus the proxy's settings and last error."""
        with self._lock:
            out = self._state_locked()
            out.update(
                {
                    "frame": self._frame,
                    "tool": self._tool_dict(),
                    "motion": self._motion.id if self._motion else None,
                    "estop": self._estopped,
                    "error": self._last_error,
                    "arm_status": self.arm.status,
                    "arm_error": self.arm.last_error,
                    "cmd_t_ns": self._last_cmd_t_ns,
                    "counters": dict(self.counters),
                }
            )
            return out

    def rpc_connect(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Connect to the arm (or reconnect after an error or e-stop). → `{status}`."""
        try:
            with self._lock:
                if self._status in ("connected", "initializing", "ready", "moving"):
                    return {"status": self._status}
                try:
                    self.arm.connect()
                except ArmError as e:
                    self._fail("internal", f"connect failed: {e}")
                    raise RpcError("internal", f"connect failed: {e}") from None
                self._estopped = False
                self._last_error = None
                self._set_status("connected")
                return {"status": self._status}
        finally:
            self._flush()

    def rpc_initialize(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Calibrate the arm; `ready` follows when it is done. → `{status}`."""
        try:
            with self._lock:
                self._check_not_estopped()
                if self._status == "moving":
                    raise RpcError("busy", "the robot is moving; stop it first")
                if self._status == "initializing":
                    return {"status": self._status}
                if self._status not in ("connected", "ready"):
                    raise RpcError("not_ready", f"robot is {self._status}: connect first")
                try:
                    self.arm.initialize()
                except ArmError as e:
                    self._fail("internal", f"initialize failed: {e}")
                    raise RpcError("internal", f"initialize failed: {e}") from None
                self._set_status("initializing")
                return {"status": self._status}
        finally:
            self._flush()

    def rpc_set_tool(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Place the tool frame in the flange frame: `{p (m), R}` = eMt. Not while moving."""
        p = arg_vector(args, "p", 3)
        check_norm("p", p.tolist(), "tool_offset_m")  # a tool over 1 m is not a PUMA tool
        R = arg_rotation(args, "R")
        with self._lock:
            if self._status == "moving":
                raise RpcError("busy", "cannot change the tool while moving")
            self._eMt = pin.SE3(R, p)
            self._tool_version += 1
            self._pose_cmd = self._tool_pose(self._q_cmd)
            self._mapping.rebase()
            return self._tool_dict()

    def rpc_set_frame(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """The default frame of `move_relative`: world, wrist or tool."""
        frame = opt_frame(args)
        if frame is None:
            raise RpcError("bad_request", "frame: missing (world, wrist or tool)")
        with self._lock:
            self._frame = frame
            return {"frame": frame}

    def rpc_move_joints(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Joint-interpolated move to `q` (rad) at `speed` (fraction of the limits, default 1)."""
        q = arg_vector(args, "q", 6)
        speed = arg_fraction(args, "speed")
        self._check_limits(q)
        return self._move(
            "move_joints", lambda kin, q0, eMt: self._plan_joint(kin, q0, q, eMt, speed)
        )

    def rpc_home(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Joint-interpolated move to `home_q` of the configuration."""
        q = np.array(self.config.home_q, dtype=np.float64)
        return self._move("home", lambda kin, q0, eMt: self._plan_joint(kin, q0, q, eMt, 1.0))

    def rpc_move_pose(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Move the tool frame to `{p, R}` (world). A straight line when the target is on the
        current branch and the line is clear of singularities, else joint-interpolated to the
        IK solution of branch `config` (default: the one nearest the current joints)."""
        p = arg_vector(args, "p", 3)
        check_each("p", p.tolist(), "position_m")
        R = arg_rotation(args, "R")
        config = arg_config(args)
        target = pin.SE3(R, p)
        return self._move(
            "move_pose", lambda kin, q0, eMt: self._plan_pose(kin, q0, target, eMt, config)
        )

    def rpc_move_relative(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Move the tool by `dp` (m) and turn it by `dR` about the tool point, both expressed
        in `frame` (world, wrist or tool; default: `set_frame`'s):
        p⁺ = p + R_f·dp, R⁺ = R_f·dR·R_fᵀ·R, with R_f = I, R_we or R_wt. In the tool frame this
        is PROTOCOL §2's tool mode (p + R0·dp, R0·dR)."""
        dp = arg_vector(args, "dp", 3)
        check_norm("dp", dp.tolist(), "displacement_m")
        if _too_long(dp, self.config.max_dp_m):
            raise RpcError("bad_request", f"dp: |dp| above {self.config.max_dp_m} m")
        dR_arg = opt_rotation(args, "dR")
        dR = np.eye(3) if dR_arg is None else dR_arg
        frame_arg = opt_frame(args)
        with self._lock:
            frame: RelFrame = frame_arg or self._frame

        def plan(kin: Puma560, q0: Vec, eMt: pin.SE3) -> Plan:
            oMe = kin.fk_flange(q0)
            oMt = oMe * eMt
            R_f = {"world": np.eye(3), "wrist": oMe.rotation, "tool": oMt.rotation}[frame]
            target = pin.SE3(R_f @ dR @ R_f.T @ oMt.rotation, oMt.translation + R_f @ dp)
            return self._plan_pose(kin, q0, target, eMt, None)

        return self._move("move_relative", plan)

    def rpc_stop(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Brake any motion to rest (within the acceleration limits). → `{status, motion}`."""
        with self._lock:
            motion = self._motion
            if self._status == "moving" and not isinstance(self._gen, _Brake):
                self._gen = _Brake()
            status = self._status
        self._flush()
        return {"status": status, "motion": motion.id if motion else None}

    def rpc_estop(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Emergency stop (an extension of IProxyRobot for the decision server's `estop`):
        the arm halts at once; `error` until `connect` and `initialize`."""
        with self._lock:
            self.arm.estop()
            self._estopped = True
            self._abandon("estop")
            self._event("estop", "emergency stop", {})
            self._set_status("error", "emergency stop")
            status = self._status
        self._flush()
        return {"status": status}

    def rpc_fk(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Tool and flange poses (world) of joints `q` with the current tool."""
        q = arg_vector(args, "q", 6)
        with self._lock:
            eMt = pin.SE3(self._eMt)
        with self._plan_lock:
            oMe = self._plan_kin.fk_flange(q)
        oMt = oMe * eMt
        return {
            "tool_p": _floats(oMt.translation),
            "tool_R": _floats(oMt.rotation.reshape(-1)),
            "flange_p": _floats(oMe.translation),
            "flange_R": _floats(oMe.rotation.reshape(-1)),
        }

    def rpc_ik(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Every IK solution of the tool target `{p, R}` (world), in the limits or not."""
        p = arg_vector(args, "p", 3)
        R = arg_rotation(args, "R")
        with self._lock:
            eMt = pin.SE3(self._eMt)
            q_ref = self._q_cmd.copy()
        with self._plan_lock:
            sols = self._plan_kin.ik(pin.SE3(R, p), eMt, q_ref=q_ref)
        return {
            "solutions": [
                {"q": _floats(s.q), "config": s.config, "in_limits": bool(s.in_limits)}
                for s in sols
            ]
        }

    def rpc_limits(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """The joint limits (rad) and the motion limits the proxy enforces."""
        lim = self.limits
        return {
            "q_lo": _floats(lim.q_lo),
            "q_hi": _floats(lim.q_hi),
            "max_joint_speed_rad_s": _floats(lim.vmax),
            "max_joint_accel_rad_s2": _floats(lim.amax),
            "max_tool_speed_m_s": lim.tool_speed_m_s,
            "max_tool_rot_speed_rad_s": lim.tool_rot_speed_rad_s,
        }

    def motion(self, motion_id: int) -> Motion:
        """The handle of a recent motion; RpcError("bad_request") if unknown."""
        with self._lock:
            m = self._motions.get(motion_id)
        if m is None:
            raise RpcError("bad_request", f"motion: no recent motion {motion_id!r}")
        return m

    def wait_initialized(self, timeout_s: float) -> dict[str, Any]:
        """Block until calibration ends: `{status: ready}`, or RpcError when it failed
        (`internal`) or took longer than `timeout_s` (`busy`: still initializing)."""
        with self._status_changed:
            done = self._status_changed.wait_for(lambda: self._status != "initializing", timeout_s)
            status, error = self._status, self._last_error
        if not done:
            raise RpcError("busy", f"still initializing after {timeout_s:g} s")
        if status != "ready":
            raise RpcError("internal", f"initialization ended {status}: {short(error)}")
        return {"status": status}

    def wait_motion(self, motion_id: int, timeout_s: float) -> dict[str, Any]:
        """Block until motion `motion_id` ends (or `timeout_s` passes): its result dict."""
        return self.motion(motion_id).wait(timeout_s)

    def state(self) -> dict[str, Any]:
        """RobotState of PROTOCOL §3 without seq/t_ns, as plain lists and floats.

        `q` is the measured joints (the last setpoint before the first reading); `engage` and
        `cmd_seq` are those of the last applied command (−1 before any).
        """
        with self._lock:
            return self._state_locked()

    def close(self) -> None:
        """Hold the arm and release it (every exit path of the service calls this)."""
        with self._lock:
            self._abandon("closed")
            try:
                self.arm.stop()
            finally:
                self.arm.close()
                self._set_status("disconnected")
        self._flush()

    # --- internals --------------------------------------------------------------------------

    def _state_locked(self) -> dict[str, Any]:
        out = dict(self._poses_locked())
        out["status"] = self._status
        out["engage"] = self._mapping.engage if self._mapping.engage is not None else -1
        out["cmd_seq"] = self._mapping.last_seq
        if self._grip is not None:
            out["grip"] = self._grip
        if self._cmd_rx_ns is not None:
            out["cmd_rx_ns"] = self._cmd_rx_ns
        if self._cmd_origin_t_ns is not None:
            out["cmd_origin_t_ns"] = self._cmd_origin_t_ns
        if self._setpoint_ns is not None:
            out["setpoint_ns"] = self._setpoint_ns
        return out

    def _poses_locked(self) -> dict[str, Any]:
        """Joints, tool and flange poses and manipulability of the measured joints; computed
        again only when the joints or the tool changed (an arm at rest costs nothing)."""
        q = self._q_meas if self._q_meas is not None else self._q_cmd
        key = q.tobytes()
        cache = self._fk_cache
        if cache is not None and cache[0] == key and cache[1] == self._tool_version:
            return cache[2]
        oMe = self._kin.fk_flange(q)
        oMt = oMe * self._eMt
        poses: dict[str, Any] = {
            "q": _floats(q),
            "tool_p": _floats(oMt.translation),
            "tool_R": _floats(oMt.rotation.reshape(-1)),
            "flange_p": _floats(oMe.translation),
            "flange_R": _floats(oMe.rotation.reshape(-1)),
            "manipulability": self._kin.manipulability(q),
        }
        self._fk_cache = (key, self._tool_version, poses)
        return poses

    def _tool_pose(self, q: Vec) -> tuple[Vec, Vec]:
        oMt = self._kin.fk_tool(q, self._eMt)
        return np.array(oMt.translation), np.array(oMt.rotation)

    def _tool_dict(self) -> dict[str, Any]:
        return {
            "tool_p": _floats(self._eMt.translation),
            "tool_R": _floats(self._eMt.rotation.reshape(-1)),
        }

    def _check_limits(self, q: Vec) -> None:
        for j in range(6):
            lo, hi = self.limits.q_lo[j], self.limits.q_hi[j]
            if not lo <= q[j] <= hi:
                raise RpcError("limit", f"q[{j}] = {q[j]:.6g} rad is outside [{lo:.4f}, {hi:.4f}]")

    def _check_not_estopped(self) -> None:
        if self._estopped:
            raise RpcError("estop", "the robot is e-stopped: connect and initialize to recover")

    def _check_can_move(self) -> None:
        self._check_not_estopped()
        if self._status == "moving":
            raise RpcError("busy", "the robot is moving: stop it or wait for the motion")
        if self._status != "ready":
            raise RpcError("not_ready", f"robot is {self._status}")

    def _move(self, kind: str, plan: PlanFn) -> dict[str, Any]:
        with self._lock:
            self._check_can_move()
            q0 = self._q_cmd.copy()
            eMt = pin.SE3(self._eMt)
            tool_version = self._tool_version
        with self._plan_lock:
            path, law, goal, how = plan(self._plan_kin, q0, eMt)
        with self._lock:
            self._check_can_move()
            if not np.array_equal(q0, self._q_cmd) or self._tool_version != tool_version:
                raise RpcError("busy", "the robot moved while the motion was planned")
            # Right after a motion the setpoint may still carry its last step's velocity
            # (≤ amax·dt): start with one tick of hold so the acceleration stays in bounds.
            motion = Motion(self._new_id(), kind)
            self._start(motion, _Planned(path, law, goal, hold_first=bool(np.any(self._qd_cmd))))
        self._flush()
        return {
            "accepted": True,
            "motion": motion.id,
            "duration_s": law.duration_s,
            "path": how,
            "q": _floats(goal),
        }

    def _plan_joint(self, kin: Puma560, q0: Vec, q1: Vec, eMt: pin.SE3, speed: float) -> Plan:
        """A straight line in joint space with one trapezoidal law for all joints: each
        joint within its speed and acceleration, the tool within its speeds (sampled)."""
        dq = q1 - q0
        if not np.any(dq):
            return (lambda s: q1), Trapezoid(0.0, 1.0, 0.0, 0.0), q1.copy(), "joint"
        adq = np.abs(dq)
        moving = adq > 0.0
        v_max = speed * PLAN_SPEED_MARGIN * float(np.min(self.limits.vmax[moving] / adq[moving]))
        a_max = PLAN_SPEED_MARGIN * float(np.min(self.limits.amax[moving] / adq[moving]))
        lin, ang = 0.0, 0.0
        for s in np.linspace(0.0, 1.0, 41):
            J = kin.jacobian(q0 + s * dq, eMt)
            lin = max(lin, float(np.linalg.norm(J[:3] @ dq)))
            ang = max(ang, float(np.linalg.norm(J[3:] @ dq)))
        v_max = min(v_max, self._tool_speed_bound(lin, ang, speed))
        law = Trapezoid.plan(v_max, a_max)
        return (lambda s: q0 + s * dq), law, q1.copy(), "joint"

    def _tool_speed_bound(self, lin: float, ang: float, speed: float) -> float:
        """The largest ṡ for which |dp/ds|·ṡ and |dθ/ds|·ṡ stay under the tool limits."""
        bound = math.inf
        k = speed * PLAN_SPEED_MARGIN
        if lin > 0.0:
            bound = min(bound, k * self.limits.tool_speed_m_s / lin)
        if ang > 0.0:
            bound = min(bound, k * self.limits.tool_rot_speed_rad_s / ang)
        return bound

    def _plan_pose(
        self, kin: Puma560, q0: Vec, target: pin.SE3, eMt: pin.SE3, config: str | None
    ) -> Plan:
        sols = kin.ik(target, eMt, q_ref=q0)
        if not sols:
            raise RpcError("unreachable", "the target pose is out of reach")
        if config is not None:
            branch = [s for s in sols if s.config == config]
            if not branch:
                raise RpcError("unreachable", f"no solution on branch {config}")
            best = kin.choose(branch, q0)
            if best is None:
                raise RpcError("limit", f"the {config} solution is outside the joint limits")
        else:
            best = kin.choose(sols, q0)
            if best is None:
                raise RpcError("limit", "every solution is outside the joint limits")
        if config is None or config == kin.config(q0):
            line = self._plan_line(kin, q0, target, eMt)
            if line is not None:
                return line
        return self._plan_joint(kin, q0, best.q, eMt, 1.0)

    def _plan_line(self, kin: Puma560, q0: Vec, target: pin.SE3, eMt: pin.SE3) -> Plan | None:
        """A straight tool line (position lerp, rotation slerp), or None if it leaves the
        workspace or the joint limits or needs a joint jump on the way."""
        start = kin.fk_tool(q0, eMt)
        dp = target.translation - start.translation
        w = pin.log3(start.rotation.T @ target.rotation)
        length, angle = float(np.linalg.norm(dp)), float(np.linalg.norm(w))
        n = max(2, math.ceil(max(length / PLAN_STEP_M, angle / PLAN_STEP_RAD)))
        qs = [q0]
        for i in range(1, n + 1):
            s = i / n
            pose = pin.SE3(start.rotation @ pin.exp3(s * w), start.translation + s * dp)
            sol = kin.choose(kin.ik(pose, eMt, q_ref=qs[-1]), qs[-1])
            if sol is None or float(np.max(np.abs(sol.q - qs[-1]))) > PLAN_MAX_JOINT_STEP_RAD:
                return None
            qs.append(sol.q)
        path = SampledPath(np.array(qs))
        if length == 0.0 and angle == 0.0:
            return (lambda s: q0), Trapezoid(0.0, 1.0, 0.0, 0.0), q0.copy(), "cartesian"
        d1, d2 = path.derivative_bounds()
        v_max = self._tool_speed_bound(length, angle, 1.0)
        a_max = math.inf
        for j in range(6):
            if d1[j] > 0.0:
                v_max = min(v_max, PLAN_SPEED_MARGIN * self.limits.vmax[j] / d1[j])
                a_max = min(a_max, PLAN_ACCEL_SHARE * self.limits.amax[j] / d1[j])
            if d2[j] > 0.0:
                v_max = min(v_max, math.sqrt(PLAN_ACCEL_SHARE * self.limits.amax[j] / d2[j]))
        law = Trapezoid.plan(v_max, a_max)
        return path.at, law, path.q[-1].copy(), "cartesian"

    def _start(self, motion: Motion, gen: Generator) -> None:
        self._motions[motion.id] = motion
        while len(self._motions) > MAX_MOTION_HISTORY:
            self._motions.popitem(last=False)
        self._motion = motion
        self._gen = gen
        if motion.kind != "teleop":
            self._mapping.rebase()
        self._set_status("moving")

    def _new_id(self) -> int:
        i = self._next_id
        self._next_id += 1
        return i

    def _abandon(self, reason: str) -> None:
        """End the motion where the setpoint is (the arm holds there)."""
        if self._motion is not None:
            self._motion.finish(reason, self._q_cmd)
        self._motion = None
        self._gen = None
        self._qd_cmd = np.zeros(6)
        self._mapping.rebase()

    def _fail(self, code: str, why: str) -> None:
        self._abandon("error")
        try:
            self.arm.stop()
        except ArmError as e:
            why = f"{why}; hold failed: {e}"
        self._event("error", why, {"code": code})
        self._set_status("error", why)

    def _set_status(self, new: Status, why: str | None = None) -> None:
        if new == "error" and why is not None:
            self._last_error = why
        if new == self._status:
            return
        old, self._status = self._status, new
        self._status_changed.notify_all()
        data: dict[str, Any] = {"status": new, "previous": old}
        if why is not None:
            data["reason"] = why
        self._event("status", f"status: {new}", data)

    def _event(self, kind: str, message: str, data: dict[str, Any]) -> None:
        self._events.append((kind, message, data))

    def _event_limited(self, key: str, kind: str, message: str, data: dict[str, Any]) -> None:
        suppressed = self._limiter.allow(key, self._t_s)
        if suppressed is None:
            return
        if suppressed:
            data = {**data, "suppressed": suppressed}
        self._event(kind, message, data)

    def _flush(self) -> None:
        with self._emit_lock:
            while True:
                with self._lock:
                    if not self._events:
                        return
                    kind, message, data = self._events.pop(0)
                self._emit(kind, message, data)


def _too_long(v: Vec, max_norm: float) -> bool:
    """‖v‖ > max_norm, without overflowing on absurd values."""
    return bool(np.max(np.abs(v)) > max_norm) or float(np.linalg.norm(v)) > max_norm


def _floats(v: Any) -> list[float]:
    return [float(x) for x in np.asarray(v).reshape(-1)]
