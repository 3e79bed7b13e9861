"""The arm service's control core: the fixed-rate tick, streamed targets, motions, status.

`ProxyControl` holds the arm's state and turns the streamed supervised targets (PROTOCOL.md
§3, `robot/arm/target`) and the motion generators into one joint setpoint per control cycle
for an `Arm`, through the safety filter (`safety.safe_step`); it reports status changes and
other events through `emit(kind, message, data)`. `ArmProxy` (proxy.py) adds the methods of
§4 on top. Everything about the arm — joints, limits, frames, kinematics — comes from its
`ArmModel`.

Frames: world R_w (the model's base frame), flange R_e (the model's flange frame), tool R_t
(placed in R_e by `eMt`, set with `set_tool`). Units: m, rad, s.

The per-tick and per-target state is plain floats (joint vectors: lists of n; the tool pose:
`services.geometry.PoseFloats`): at 1 kHz of targets a numpy call on a few joints costs more
than the arithmetic. Arrays appear only at the boundaries (the arm, planning, the methods' replies).

Who calls what: `tick(dt_s)` is called by the service's fixed-rate loop and is the only
place that talks to the arm's setpoint stream; `on_target` and the proxy's methods may be
called from any thread (the bus's callbacks). One lock serialises them; motion planning (many
IK solves) runs outside it on a kinematics instance of its own.

Safety, whatever the source of the motion: `safe_step` applies every tick. Motions are
planned, and streamed targets chased, within the limits (with margin), so the filter is a
last line that seldom has to act. An arm error, a following error or a failed read puts the
proxy in `error`: the motion is abandoned, the arm holds, and nothing moves until `connect`
and `initialize`.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, Literal, Self

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from services.bus.events import EventLimiter
from services.bus.messages import ArmTarget
from services.control.arm.arguments import RelFrame, is_number, too_long
from services.control.arm.config import ArmConfig
from services.control.arm.driver import Arm, ArmError, Gripping
from services.control.arm.kinematics import Kinematics, Unreachable, se3_floats, tool_se3
from services.control.arm.model import ArmModel, load_model
from services.control.arm.motions import (
    GOAL_TOL_RAD,
    Brake,
    Generator,
    Motion,
    Planned,
    Servo,
    servo_target,
)
from services.control.arm.safety import MotionLimits, safe_step
from services.geometry import PoseFloats, angle9, rotation_problem

Vec = NDArray[np.float64]
Status = Literal["disconnected", "connected", "initializing", "ready", "moving", "error"]
EmitFn = Callable[[str, str, dict[str, Any]], None]

MAX_MOTION_HISTORY = 128
SAME_TARGET_M = 1e-6
SAME_TARGET_R = 1e-6
"""A streamed target within these of the one aimed at (each coordinate in m, each rotation
entry) is that one re-sent: nothing to solve, and the motion may settle. A supervisor whose
target is rebuilt every tick from what the arm measures (compliance on at rest) sends poses
that differ in their last bits; compared exactly, each restarted the settle time and an arm
at rest read `moving` forever (the compose run's new engagement waited for `ready`)."""


class ProxyControl:
    """The state and control loop of `ArmProxy` over an `Arm` (see the module docstring).

    Events go out through `emit`, outside the lock, in the order they happened.
    """

    def __init__(
        self, arm: Arm, config: ArmConfig, emit: EmitFn, model: ArmModel | None = None
    ) -> None:
        self.model = model if model is not None else load_model(config.model)
        config = config.bind(self.model)
        self.arm = arm
        self.config = config
        self.n = self.model.n
        self._emit = emit
        self._lock = threading.RLock()
        self._status_changed = threading.Condition(self._lock)
        self._plan_lock = threading.Lock()
        self._emit_lock = threading.RLock()
        self._events: list[tuple[str, str, dict[str, Any]]] = []
        self._kin: Kinematics = self.model.kinematics()  # the loop's: tick, targets, state
        self._plan_kin: Kinematics = self.model.kinematics()  # the methods': planning, fk, ik
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
        self._eMt: pin.SE3 = tool_se3(self.model)
        self._eMt_floats = se3_floats(self._eMt)
        self._reach_m = self.model.reach_m
        """How far from the world origin the tool point can be, for the tool in use."""
        self._tool_version = 0
        self._frame: RelFrame = "world"
        self._t_s = 0.0
        self._q_cmd: list[float] = list(config.home_q)
        self._qd_cmd: list[float] = [0.0] * self.n
        self._q_meas: list[float] | None = None
        self._pose_memo: tuple[list[float], PoseFloats] | None = None
        self._pose_cmd: PoseFloats = self._tool_pose(self._q_cmd)
        self._gen: Generator | None = None
        self._motion: Motion | None = None
        self._motions: OrderedDict[int, Motion] = OrderedDict()
        self._next_id = 1
        self._last_seq = -1
        self._engage: int | None = None
        self._target_ref: PoseFloats | None = None
        """The last target applied in this engagement (None: the next one is measured
        from the commanded pose): the step bound's reference."""
        self._grip: float | None = None
        self._gripper: Gripping | None = arm if isinstance(arm, Gripping) else None
        """The driver's gripper, when it has one: an accepted target's grip goes to it."""
        self._last_cmd_t_ns = 0
        self._cmd_rx_ns: int | None = None
        self._cmd_origin_t_ns: int | None = None
        self._setpoint_ns: int | None = None
        self._awaiting_setpoint = False
        self._fk_cache: tuple[list[float], int, dict[str, Any]] | None = None
        self._limiter = EventLimiter(config.event_interval_s)  # on proxy time
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
            return self._gen is not None or any(self._qd_cmd)

    def __enter__(self) -> Self:
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
            q_meas: list[float] = self.arm.read_joints().tolist()
        except ArmError as e:
            self._fail("internal", f"arm: {e}")
            return
        self._q_meas = q_meas
        follow = max(abs(a - b) for a, b in zip(q_meas, self._q_cmd, strict=True))
        if follow > self.config.max_following_error_rad:
            self._fail("internal", f"following error {follow:.3f} rad: the arm does not follow")
            return
        if self._gen is None and not any(self._qd_cmd):
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
        self.arm.command(np.array(self._q_cmd))
        if self._awaiting_setpoint:
            self._awaiting_setpoint = False
            self._setpoint_ns = time.time_ns()
        self._update_motion(dt_s)

    def _desired(self, dt_s: float) -> list[float]:
        gen = self._gen
        if gen is None:
            return self._q_cmd
        if isinstance(gen, Planned):
            q_des: list[float] = gen.next(dt_s).tolist()
            return q_des
        if isinstance(gen, Brake):
            t_stop = max(
                abs(v) / a for v, (_, _, _, a) in zip(self._qd_cmd, self.limits.joints, strict=True)
            )
            k = max(0.0, 1.0 - dt_s / t_stop) if t_stop > 0.0 else 0.0
            return [q + v * k * dt_s for q, v in zip(self._q_cmd, self._qd_cmd, strict=True)]
        return servo_target(
            gen.goal, self._q_cmd, self._qd_cmd, self._pose_cmd, dt_s, self.limits, self._tool_pose
        )

    def _update_motion(self, dt_s: float) -> None:
        gen = self._gen
        if gen is None:
            return
        if isinstance(gen, Brake):
            if not any(self._qd_cmd):
                self._end_motion("stopped")
            return
        if isinstance(gen, Planned):
            if gen.finished:
                goal: list[float] = gen.goal.tolist()
                if _max_diff(goal, self._q_cmd) <= GOAL_TOL_RAD:
                    self._q_cmd = goal
                    self._end_motion("completed")
                else:
                    # The filter held the plan back somewhere: finish by chasing the goal.
                    self._gen = Servo(goal, self._t_s, 0.0)
            return
        e = _max_diff(gen.goal, self._q_cmd)
        if e <= GOAL_TOL_RAD and max(map(abs, self._qd_cmd)) < 1e-6:
            self._q_cmd = list(gen.goal)
            if self._t_s - gen.last_goal_t_s >= gen.settle_s:
                self._qd_cmd = [0.0] * self.n
                self._end_motion("completed")

    def _halt_here(self) -> None:
        """End the motion holding the measured joints at once (a contact stop: braking
        would carry the tool on into what it touches). The setpoint steps back to where the
        arm is, never ahead of it; within the joint limits, as the arm is."""
        q = list(self._q_meas or self._q_cmd)
        if len(q) != self.n or not all(math.isfinite(x) for x in q):
            q = list(self._q_cmd)
        joints = self.limits.joints
        self._q_cmd = [min(max(x, j[0]), j[1]) for x, j in zip(q, joints, strict=True)]
        self._qd_cmd = [0.0] * self.n
        self._pose_cmd = self._tool_pose(self._q_cmd)
        self.arm.command(np.array(self._q_cmd))
        self._end_motion("stopped")

    def _end_motion(self, reason: str) -> None:
        motion = self._motion
        self._gen = None
        self._motion = None
        if motion is None or motion.kind != "teleop" or reason != "completed":
            # Something other than the operator's commands moved the arm (or cut a command
            # short): the next command re-bases there instead of jumping back.
            self._target_ref = None
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
                "q": list(self._q_cmd),
                "tool_p": list(p),
            },
        )

    def _finish_initialization(self) -> None:
        try:
            q = self.arm.read_joints()
        except ArmError as e:
            self._fail("internal", f"arm: {e}")
            return
        self._q_meas = q.tolist()
        self._q_cmd = q.tolist()
        self._qd_cmd = [0.0] * self.n
        self._pose_cmd = self._tool_pose(self._q_cmd)
        self._target_ref = None
        self._set_status("ready")
        # The first setpoint is where the arm is: from here on it holds what it was sent.
        self.arm.command(np.array(self._q_cmd))
        self._event("data", "arm calibrated", {"q": [float(x) for x in q]})

    # --- streamed targets -----------------------------------------------------------------

    def on_target(self, tgt: ArmTarget, rx_ns: int | None = None) -> None:
        """A streamed ArmTarget (`robot/arm/target`: the supervised tool pose; PROTOCOL §3).

        Ignored unless `ready` or `moving` (and while `stop` brakes), and when stale (a `seq`
        not above the last applied one, or an `engage` below it). Checked once: a grip
        outside [0, 1], a tool point beyond the arm's reach, or a pose further from the
        previous target (the commanded pose, at a new engagement) than the step bound
        (`max_target_step_m`, `max_target_step_rad`) is rejected (a rate-limited `rejected`
        event) and moves nothing. Otherwise it is solved once (`Kinematics.solve`) into a
        joint goal the arm chases within every limit, pre-empting a running motion; a pose
        without a solution within the limits leaves the last goal in place (the arm holds
        there) and raises a rate-limited `unreachable` event. Nothing is clamped into a
        different pose.

        `rx_ns` (when the service received it) and the target's `origin_t_ns` (the
        operator's send time) are reported in the state with the time of the first setpoint
        it produced, so the operator's path can be timed on one clock.
        """
        with self._lock:
            self._on_target_locked(tgt, rx_ns)
        self._flush()

    def _target_problem(self, tgt: ArmTarget) -> str | None:
        """Why `tgt` may not move the arm (None: it may). The codec has checked that `p`
        and `R` are finite and `R` a rotation; in-process callers pass through here too."""
        p, R = tgt.p, tgt.R
        if len(p) != 3 or not all(map(is_number, p)) or not all(map(math.isfinite, p)):
            return "p: not 3 finite numbers"
        if len(R) != 9 or not all(map(is_number, R)):
            return "R: not 9 numbers"
        if (r := rotation_problem(np.asarray(R, dtype=np.float64).reshape(3, 3))) is not None:
            return f"R: {r}"
        grip = tgt.grip
        if grip is not None and not (is_number(grip) and 0.0 <= grip <= 1.0):
            return "grip: must be within [0, 1]"
        reach = self._reach_m
        if too_long(np.asarray(p), reach):
            return f"p: {math.hypot(*p):.3g} m from the base, beyond the arm's reach ({reach} m)"
        ref_p, ref_R = self._target_ref if self._target_ref is not None else self._pose_cmd
        step_m = math.dist(p, ref_p)
        if not step_m <= self.config.max_target_step_m:
            return (
                f"p: {step_m:.3g} m from the previous target (step bound "
                f"{self.config.max_target_step_m} m)"
            )
        step_rad = angle9(ref_R, R)
        if not step_rad <= self.config.max_target_step_rad:
            return (
                f"R: {step_rad:.3g} rad from the previous target (step bound "
                f"{self.config.max_target_step_rad} rad)"
            )
        return None

    def _on_target_locked(self, tgt: ArmTarget, rx_ns: int | None) -> None:
        self.counters["commands"] += 1
        if self._status not in ("ready", "moving") or isinstance(self._gen, Brake):
            self.counters["commands_ignored"] += 1
            return
        if tgt.seq <= self._last_seq or (self._engage is not None and tgt.engage < self._engage):
            self.counters["commands_ignored"] += 1
            return  # stale: an older seq or engagement
        if tgt.engage != self._engage:
            self._target_ref = None  # a new engagement starts from where the arm is told to be
        why = self._target_problem(tgt)
        if why is not None:
            self.counters["rejected"] += 1
            self._event_limited(
                "rejected",
                "rejected",
                f"target {tgt.seq} rejected: {why}",
                {"seq": tgt.seq, "reason": why},
            )
            return
        self._last_seq, self._engage = tgt.seq, tgt.engage
        self._last_cmd_t_ns = int(tgt.t_ns)
        self._cmd_rx_ns = rx_ns
        self._cmd_origin_t_ns = tgt.origin_t_ns
        self._setpoint_ns = None
        self._awaiting_setpoint = True
        if tgt.grip is not None:
            self._grip = float(tgt.grip)
            if self._gripper is not None:
                self._gripper.grip(self._grip)
        ref = self._target_ref
        if ref is not None and _same_pose(ref, tgt.p, tgt.R):
            return  # the pose already aimed at (a hold re-sent): nothing to solve or restart
        target = pin.SE3(np.array(tgt.R, dtype=np.float64).reshape(3, 3), np.array(tgt.p))
        gen = self._gen
        # The previous target's solution is the nearest seed (a numerical IK converges from
        # it in a step or two); at a new engagement, where the arm is told to be.
        seed = gen.goal if isinstance(gen, Servo) and self._motion is not None else None
        try:
            sol = self._kin.solve(self._q_cmd, target, self._eMt, seed)
        except Unreachable as e:
            self.counters["unreachable"] += 1
            self._event_limited(
                "unreachable",
                "unreachable",
                f"target {tgt.seq} unreachable: {e}",
                {"code": "unreachable", "seq": tgt.seq},
            )
            return
        self._target_ref = (tuple(tgt.p), tuple(tgt.R))
        if sol.near_singular:
            self._event_limited(
                "singular",
                "limit",
                "near a singularity: motion slowed",
                {"singularity": self._kin.singularity(sol.q)},
            )
        goal: list[float] = sol.q.tolist()
        gen = self._gen
        if isinstance(gen, Servo) and self._motion is not None and self._motion.kind == "teleop":
            gen.goal = goal
            gen.last_goal_t_s = self._t_s
            return
        if self._motion is not None:
            self._motion.finish("preempted", self._q_cmd)
        self._start(
            Motion(self._new_id(), "teleop"), Servo(goal, self._t_s, self.config.teleop_settle_s)
        )

    # --- lifecycle --------------------------------------------------------------------------

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

    def _tool_pose(self, q: list[float]) -> PoseFloats:
        """The tool pose at joints q. The last one is kept: a tick that holds or settles
        asks again for the pose of the setpoint it already has (twice)."""
        memo = self._pose_memo
        if memo is not None and memo[0] == q:
            return memo[1]
        pose = self._kin.tool_pose_floats(q, self._eMt_floats)
        self._pose_memo = (list(q), pose)
        return pose

    def _set_tool(self, eMt: pin.SE3) -> None:
        """Place the tool in the flange frame; the caller holds the lock and is not moving."""
        self._eMt = eMt
        self._eMt_floats = se3_floats(eMt)
        self._reach_m = (
            self.model.reach_m
            - math.hypot(*self.model.tool_p)
            + float(np.linalg.norm(eMt.translation))
        )
        self._pose_memo = None
        self._tool_version += 1
        self._pose_cmd = self._tool_pose(self._q_cmd)
        self._target_ref = None

    def _start(self, motion: Motion, gen: Generator) -> None:
        self._motions[motion.id] = motion
        while len(self._motions) > MAX_MOTION_HISTORY:
            self._motions.popitem(last=False)
        self._motion = motion
        self._gen = gen
        if motion.kind != "teleop":
            self._target_ref = None
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
        self._qd_cmd = [0.0] * self.n
        self._target_ref = None

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
        if not self._events:
            # Nothing queued (most ticks and commands): whoever queues an event flushes it
            # after releasing the lock, so an event appended meanwhile is not lost.
            return
        with self._emit_lock:
            while True:
                with self._lock:
                    if not self._events:
                        return
                    kind, message, data = self._events.pop(0)
                self._emit(kind, message, data)


def _max_diff(a: Sequence[float], b: Sequence[float]) -> float:
    """max |a − b| over the joints."""
    return max(abs(x - y) for x, y in zip(a, b, strict=True))


def _same_pose(
    ref: tuple[Sequence[float], Sequence[float]], p: Sequence[float], R: Sequence[float]
) -> bool:
    """Whether target (p, R) is `ref` re-sent, within SAME_TARGET_M and SAME_TARGET_R."""
    return all(abs(a - b) <= SAME_TARGET_M for a, b in zip(ref[0], p, strict=True)) and all(
        abs(a - b) <= SAME_TARGET_R for a, b in zip(ref[1], R, strict=True)
    )
