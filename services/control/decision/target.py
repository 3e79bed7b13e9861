"""The supervised target: the tool pose the decision server commands the arm to, shaped
from the operator's (or a task's) goal through the filters, and the targets that carry it.

Each outgoing engagement (`engage_out`, its own `seq_out`, master id "decision") starts
from the tool pose (p0, R0) then (the setpoint's position, where the arm is told to be,
when robot/state carries it). The target (p_sup, R_sup) moves towards the goal through
(a) contact, (b) active compliance, (c) tool speed, (d) workspace box, and the arm is sent
that pose itself (ArmTarget, robot/arm/target); whatever a filter held back stays an
offset of the target (off_p, off_R): it never turns into a jump.

Pure: the supervisor passes the time and the sensed state in a `Sensed` each tick. It runs on
every operator command, so it computes in plain floats (`V3`, row-major `M9`: a numpy call
on a 3-vector costs more than the arithmetic); the pose attributes read as numpy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.bus.messages import ArmTarget, ForceSample, OperatorCommand, RobotState
from services.control.decision.config import DecisionConfig
from services.control.decision.filters import (
    admittance_step,
    clamp_box,
    clip_norm,
    effective_box,
    slow_near_box,
    without_motion_into,
)
from services.control.decision.notices import Notices
from services.geometry import (
    I9,
    M9,
    V3,
    add3,
    as_mat3,
    dot3,
    exp9,
    finite9,
    len3,
    log9,
    m9,
    mul9,
    mv9,
    ortho9,
    scale3,
    sub3,
    tmul9,
    v3,
)

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

MASTER_ID = "decision"
"""The decision's own master id on robot/arm/target."""
MOVING_STATUSES = ("ready", "moving")
"""The robot statuses in which an engagement (teleoperation or a task) may start."""
STEP_EPS_M = 1e-9
STEP_EPS_RAD = 1e-9
MAX_SPAN_S = 0.1
"""The longest time one step of the target may cover (the rate limit's Δt). A master
as slow as 10 Hz is followed at full speed; after a longer silence (a stream stalled by a
lost TCP segment over a WAN, where the watchdogs are set to seconds) the target does not
leap by the whole silence's worth of speed: it moves on at the limit speed, on the timer."""
HOLD_RESEND_NS = 50_000_000
"""A hold is re-sent this often (20 Hz): one lost packet must not matter, and the arm needs
nothing more while nothing changes."""
_ZERO: V3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class Sensed:
    """What the filters see in one tick: the settings, the monotonic time (ns), the newest
    robot/state, the newest force sample if fresh (else None), and the events' sink."""

    cfg: DecisionConfig
    now_ns: int
    state: RobotState | None
    force: ForceSample | None
    notices: Notices


class SupervisedTarget:
    """The target of the current outgoing engagement and the outgoing counters.

    `seq_start` and `engage_start` seed the counters. `p0` is None until the first
    engagement: before it there is nothing to command. The poses (`p0`, `R0`, `p_sup`,
    `R_sup`, `off_p`, `off_R`) read as fresh numpy arrays; `p_sup` and `R_sup` may be set.
    """

    def __init__(self, seq_start: int, engage_start: int, period_s: float) -> None:
        self.seq_out = seq_start
        self.engage_out = engage_start
        self._p0: V3 | None = None
        self._R0: M9 = I9
        self._p: V3 = _ZERO
        self._R: M9 = I9
        self._off_p: V3 = _ZERO
        self._off_R: M9 = I9
        self.grip: float | None = None
        self.dt_s = period_s
        self.lagging = False
        """The target has not caught up with the operator's (the speed limit holds it)."""
        self.last_adv_ns: int | None = None
        self.last_out_ns: int | None = None
        self.last_out_active = False

    # --- the poses, as numpy for the rest of the decision -----------------------------------
    @property
    def p0(self) -> Vec | None:
        return None if self._p0 is None else np.array(self._p0)

    @property
    def R0(self) -> Mat:
        return as_mat3(self._R0)

    @property
    def p_sup(self) -> Vec:
        return np.array(self._p)

    @p_sup.setter
    def p_sup(self, p: ArrayLike) -> None:
        self._p = v3(p)

    @property
    def R_sup(self) -> Mat:
        return as_mat3(self._R)

    @R_sup.setter
    def R_sup(self, R: ArrayLike) -> None:
        self._R = m9(R)

    @property
    def off_p(self) -> Vec:
        return np.array(self._off_p)

    @property
    def off_R(self) -> Mat:
        return as_mat3(self._off_R)

    @property
    def offset_rot_rad(self) -> float:
        """The angle (rad) of the rotation the filters hold back."""
        return len3(log9(self._off_R))

    def start_tick(self, now_ns: int, cfg: DecisionConfig) -> None:
        """The time the target may move over this tick: since its last step, at most
        MAX_SPAN_S or one watchdog period, whichever is shorter."""
        last = self.last_adv_ns
        self.dt_s = (
            cfg.period_s
            if last is None
            else min(max((now_ns - last) * 1e-9, 0.0), cfg.watchdog_ms * 1e-3, MAX_SPAN_S)
        )

    def wait(self, now_ns: int) -> None:
        """The target stays put this tick: the time is not motion to catch up later."""
        self.last_adv_ns = now_ns

    def begin(self, state: RobotState, now_ns: int, period_s: float) -> None:
        """Start a new engagement towards the arm, rebased on the current tool pose: the
        setpoint's (`tool_p_cmd`), where the arm is told to be and what it measures the
        first target's step from, when the state carries it; the measured one trails it by
        the servo's error."""
        self.engage_out = max(self.engage_out, state.engage) + 1
        start = state.tool_p_cmd if state.tool_p_cmd is not None else state.tool_p
        self._p0 = self._p = v3(start)
        self._R0 = self._R = ortho9(m9(state.tool_R))
        self._off_p = _ZERO
        self._off_R = I9
        self.lagging = False
        # The engagement's first step may move one period's worth, as a tick always could.
        self.last_adv_ns = now_ns - int(period_s * 1e9)
        self.dt_s = period_s

    def hold_due(self, now_ns: int) -> bool:
        """The first hold after motion goes out at once, then every HOLD_RESEND_NS."""
        last = self.last_out_ns
        return last is None or self.last_out_active or now_ns - last >= HOLD_RESEND_NS

    def next_hold_ns(self, now_ns: int) -> int:
        """When the hold is due next (monotonic ns, at least now + 1)."""
        last = self.last_out_ns
        if last is None or self.last_out_active:
            return now_ns + 1
        return max(last + HOLD_RESEND_NS, now_ns + 1)

    def follow(self, cmd: OperatorCommand, sensed: Sensed) -> bool:
        """Move the target one step towards the operator's pose for `cmd` (PROTOCOL §2,
        from the engagement pose), keeping what the filters remove as the offset. False
        (nothing moved) if that pose is not finite."""
        assert self._p0 is not None
        # The operator's pose, eq. 2–3 (geometry.tool_target_pose): p0 + dp (world) or
        # p0 + R0·dp (tool); R0·dR.
        dp = v3(cmd.dp)
        if cmd.frame not in ("world", "tool"):
            raise ValueError(f"frame must be 'world' or 'tool', got {cmd.frame!r}")
        p_des = add3(self._p0, dp if cmd.frame == "world" else mv9(self._R0, dp))
        R_des = mul9(self._R0, m9(cmd.dR))
        g_p = add3(p_des, self._off_p)
        g_R = mul9(R_des, self._off_R)
        if not (finite9(g_p) and finite9(g_R)):
            return False
        g_p, g_R = self._advance(g_p, g_R, sensed)
        self._off_p = sub3(g_p, p_des)
        self._off_R = ortho9(tmul9(R_des, g_R))
        self.lagging = (
            len3(sub3(g_p, self._p)) > STEP_EPS_M or len3(log9(tmul9(self._R, g_R))) > STEP_EPS_RAD
        )
        self.grip = cmd.grip
        return True

    def advance(self, g_p: ArrayLike, g_R: ArrayLike, sensed: Sensed) -> tuple[Vec, Mat]:
        """Move the supervised target one tick towards the goal (g_p, g_R) through the
        filters; return the goal with what the filters removed folded in (the new offset).

        (a) contact: above max_force_n (max_torque_nm) the goal's component into the
            contact is removed (and a target deeper than the measured tool is pulled back);
        (b) compliance: the goal yields along the force (admittance);
        (c) speed: the step is at most max_tool_speed · dt, dt the time since the last
            step (rotation likewise): a rate limit over time, whatever the input rate;
            within approach_zone_m of a face of the box, at most approach_speed · dt
            towards it;
        (d) workspace: goal and target are clamped to the box (grown to contain the current
            target, so a target outside may only come back).
        """
        p, R = self._advance(v3(g_p), m9(g_R), sensed)
        return np.array(p), as_mat3(R)

    def _advance(self, g_p: V3, g_R: M9, sensed: Sensed) -> tuple[V3, M9]:
        """`advance` in plain floats."""
        cfg, now, notices = sensed.cfg, sensed.now_ns, sensed.notices
        dt = self.dt_s
        self.last_adv_ns = now
        p_sup, R_sup = self._p, self._R
        lo, hi = effective_box(cfg.workspace_min, cfg.workspace_max, p_sup)
        g1 = clamp_box(g_p, lo, hi)
        clamped = len3(sub3(g1, g_p)) > STEP_EPS_M
        inc = sub3(g1, p_sup)
        w = log9(tmul9(R_sup, g_R))
        state, force = sensed.state, sensed.force
        if force is not None and state is not None:
            f_t, c_t = v3(force.f), v3(force.c)
            f_w = mv9(m9(state.tool_R), f_t)
            f_n = len3(f_w)
            if f_n > cfg.max_force_n:
                inc, removed = without_motion_into(inc, f_w)
                n = scale3(1.0 / f_n, f_w)
                behind = dot3(sub3(v3(state.tool_p), p_sup), n)
                ahead = dot3(inc, n)
                # The arm lags its target: pull the target back to the tool, so the arm
                # stops where the force crossed the threshold instead of pressing on, and
                # out of the contact by what the force is above the limit over the
                # contact's stiffness, so the press comes down to the limit (measured from
                # the tool each tick, never accumulated while the arm catches up).
                behind += (f_n - cfg.max_force_n) / cfg.contact_stiffness_n_per_m
                if behind > ahead:
                    inc = add3(inc, scale3(behind - ahead, n))
                    removed += behind - ahead
                notices.edge(
                    now,
                    "contact",
                    removed > STEP_EPS_M,
                    "contact",
                    f"contact force {f_n:.1f} N > {cfg.max_force_n:g} N: motion into it stopped",
                    {
                        "reason": "force",
                        "f": list(f_w),
                        "force_n": f_n,
                        "tool_p": list(state.tool_p),
                    },
                )
            c_n = len3(c_t)
            if c_n > cfg.max_torque_nm:
                w, removed_r = without_motion_into(w, c_t)
                notices.edge(
                    now,
                    "torque",
                    removed_r > STEP_EPS_M,
                    "contact",
                    f"contact moment {c_n:.2f} N·m > {cfg.max_torque_nm:g} N·m: rotation into "
                    "it stopped",
                    {"reason": "torque", "c": list(c_t), "torque_nm": c_n},
                )
            if cfg.compliance:
                inc = add3(
                    inc,
                    admittance_step(f_w, cfg.admittance_m_per_n_s, cfg.admittance_deadband_n, dt),
                )
                w = add3(
                    w,
                    admittance_step(
                        c_t, cfg.admittance_rad_per_nm_s, cfg.admittance_deadband_nm, dt
                    ),
                )
        goal_p = add3(p_sup, inc)
        goal_R = mul9(R_sup, exp9(w))
        step, fast = clip_norm(inc, cfg.max_tool_speed_m_s * dt)
        wstep, spin = clip_norm(w, cfg.max_tool_rot_speed_rad_s * dt)
        near = False
        if cfg.approach_zone_m > 0.0:
            step, near = slow_near_box(
                p_sup, step, lo, hi, cfg.approach_zone_m, cfg.approach_speed_m_s * dt
            )
        free = add3(p_sup, step)
        p_new = clamp_box(free, lo, hi)
        pulled = sub3(p_new, free)
        if len3(pulled) > STEP_EPS_M:
            clamped = True
            goal_p = add3(goal_p, pulled)
        notices.edge(
            now,
            "workspace",
            clamped,
            "limit",
            "workspace limit: target clamped to the box",
            {
                "reason": "workspace",
                "goal": list(g_p),
                "min": list(cfg.workspace_min),
                "max": list(cfg.workspace_max),
            },
        )
        notices.edge(
            now,
            "speed",
            fast or spin,
            "limit",
            "tool speed limit: target slowed down",
            {
                "reason": "speed",
                "max_tool_speed_m_s": cfg.max_tool_speed_m_s,
                "max_tool_rot_speed_rad_s": cfg.max_tool_rot_speed_rad_s,
            },
        )
        if near:  # (no event data built per tick while nothing happens)
            notices.edge(
                now,
                "approach",
                True,
                "limit",
                "approach zone: target slowed near the workspace boundary",
                {
                    "reason": "approach",
                    "approach_zone_m": cfg.approach_zone_m,
                    "approach_speed_m_s": cfg.approach_speed_m_s,
                },
            )
        self._p = p_new
        self._R = ortho9(mul9(R_sup, exp9(wstep)))
        return goal_p, ortho9(goal_R)

    def command(self, now_ns: int, wall_ns: int, active: bool, origin_t_ns: int) -> ArmTarget:
        """The next target for robot/arm/target (`t_ns` = wall_ns): the supervised pose
        (p_sup, R_sup) itself; `hold` when it is not `active` (the supervisor holds).
        `origin_t_ns`: the operator command it carries out (wall_ns for holds and tasks)."""
        assert self._p0 is not None
        self.seq_out += 1
        self.last_out_ns = now_ns
        self.last_out_active = active
        return ArmTarget(
            seq=self.seq_out,
            t_ns=wall_ns,
            origin_t_ns=origin_t_ns,
            master=MASTER_ID,
            engage=self.engage_out,
            p=self._p,
            R=self._R,
            grip=self.grip,
            hold=None if active else True,
        )
