"""The supervised target: the tool pose the decision server commands the puma to, shaped
from the operator's (or a task's) goal through the filters, and the commands that carry it.

Each outgoing engagement (`engage_out`, its own `seq_out`, master id "decision") starts
from the tool pose (p0, R0) then measured. The target (p_sup, R_sup) moves towards the goal
through (a) contact, (b) active compliance, (c) tool speed, (d) workspace box; the puma is
sent `dp = p_sup − p0`, `dR = R0ᵀ·R_sup` in the world frame, so whatever a filter held back
stays an offset of the target (off_p, off_R): it never turns into a jump.

Pure: the supervisor passes the time and the sensed state in a `Sensed` each tick.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.bus.messages import ForceSample, OperatorCommand, RobotState, mat3, vec
from services.control.decision.config import DecisionConfig
from services.control.decision.filters import (
    admittance_step,
    clamp_box,
    clip_norm,
    effective_box,
    engagement_command,
    without_motion_into,
)
from services.control.decision.notices import Notices, floats
from services.geometry import exp_so3, log_so3, norm3, orthonormalize, tool_target_pose

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

MASTER_ID = "decision"
"""The decision's own master id on robot/puma/cmd."""
MOVING_STATUSES = ("ready", "moving")
"""The robot statuses in which an engagement (teleoperation or a task) may start."""
STEP_EPS_M = 1e-9
STEP_EPS_RAD = 1e-9
HOLD_RESEND_NS = 50_000_000
"""A hold is re-sent this often (20 Hz): one lost packet must not matter, and the puma needs
nothing more while nothing changes."""


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
    engagement: before it there is nothing to command.
    """

    def __init__(self, seq_start: int, engage_start: int, period_s: float) -> None:
        self.seq_out = seq_start
        self.engage_out = engage_start
        self.p0: Vec | None = None
        self.R0: Mat = np.eye(3)
        self.p_sup: Vec = np.zeros(3)
        self.R_sup: Mat = np.eye(3)
        self.off_p: Vec = np.zeros(3)
        self.off_R: Mat = np.eye(3)
        self.grip: float | None = None
        self.dt_s = period_s
        self.lagging = False
        """The target has not caught up with the operator's (the speed limit holds it)."""
        self.last_adv_ns: int | None = None
        self.last_out_ns: int | None = None
        self.last_out_active = False

    def start_tick(self, now_ns: int, cfg: DecisionConfig) -> None:
        """The time the target may move over this tick: since its last step, at most one
        watchdog period (a longer gap is a hold anyway)."""
        last = self.last_adv_ns
        self.dt_s = (
            cfg.period_s
            if last is None
            else min(max((now_ns - last) * 1e-9, 0.0), cfg.watchdog_ms * 1e-3)
        )

    def begin(self, state: RobotState, now_ns: int, period_s: float) -> None:
        """Start a new engagement towards the puma, rebased on the current tool pose."""
        self.engage_out = max(self.engage_out, state.engage) + 1
        self.p0 = np.array(state.tool_p, dtype=float)
        self.R0 = orthonormalize(mat3(state.tool_R))
        self.p_sup = self.p0.copy()
        self.R_sup = self.R0.copy()
        self.off_p = np.zeros(3)
        self.off_R = np.eye(3)
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
        assert self.p0 is not None
        p_des, R_des = tool_target_pose(self.p0, self.R0, cmd.dp, mat3(cmd.dR), cmd.frame)
        g_p = p_des + self.off_p
        g_R = R_des @ self.off_R
        if not (np.isfinite(g_p).all() and np.isfinite(g_R).all()):
            return False
        g_p, g_R = self.advance(g_p, g_R, sensed)
        self.off_p = g_p - p_des
        self.off_R = orthonormalize(R_des.T @ g_R)
        self.lagging = (
            norm3(g_p - self.p_sup) > STEP_EPS_M
            or norm3(log_so3(self.R_sup.T @ g_R)) > STEP_EPS_RAD
        )
        self.grip = cmd.grip
        return True

    def advance(self, g_p: Vec, g_R: Mat, sensed: Sensed) -> tuple[Vec, Mat]:
        """Move the supervised target one tick towards the goal (g_p, g_R) through the
        filters; return the goal with what the filters removed folded in (the new offset).

        (a) contact: above max_force_n (max_torque_nm) the goal's component into the
            contact is removed (and a target deeper than the measured tool is pulled back);
        (b) compliance: the goal yields along the force (admittance);
        (c) speed: the step is at most max_tool_speed · dt, dt the time since the last
            step (rotation likewise): a rate limit over time, whatever the input rate;
        (d) workspace: goal and target are clamped to the box (grown to contain the current
            target, so a target outside may only come back).
        """
        cfg, now, notices = sensed.cfg, sensed.now_ns, sensed.notices
        dt = self.dt_s
        self.last_adv_ns = now
        lo, hi = effective_box(cfg.workspace_min, cfg.workspace_max, self.p_sup)
        g1 = clamp_box(g_p, lo, hi)
        clamped = norm3(g1 - g_p) > STEP_EPS_M
        inc = g1 - self.p_sup
        w = log_so3(self.R_sup.T @ g_R)
        state, force = sensed.state, sensed.force
        if force is not None and state is not None:
            f_t = np.asarray(force.f, dtype=float)
            c_t = np.asarray(force.c, dtype=float)
            f_w = mat3(state.tool_R) @ f_t
            f_n = norm3(f_w)
            if f_n > cfg.max_force_n:
                inc, removed = without_motion_into(inc, f_w)
                n = f_w / f_n
                behind = float((np.asarray(state.tool_p) - self.p_sup) @ n)
                ahead = float(inc @ n)
                if behind > ahead:
                    # The arm lags its target: pull the target back to the tool, so the arm
                    # stops where the force crossed the threshold instead of pressing on.
                    inc = inc + (behind - ahead) * n
                    removed += behind - ahead
                notices.edge(
                    now,
                    "contact",
                    removed > STEP_EPS_M,
                    "contact",
                    f"contact force {f_n:.1f} N > {cfg.max_force_n:g} N: motion into it stopped",
                    {
                        "reason": "force",
                        "f": floats(f_w),
                        "force_n": f_n,
                        "tool_p": list(state.tool_p),
                    },
                )
            c_n = norm3(c_t)
            if c_n > cfg.max_torque_nm:
                w, removed_r = without_motion_into(w, c_t)
                notices.edge(
                    now,
                    "torque",
                    removed_r > STEP_EPS_M,
                    "contact",
                    f"contact moment {c_n:.2f} N·m > {cfg.max_torque_nm:g} N·m: rotation into "
                    "it stopped",
                    {"reason": "torque", "c": floats(c_t), "torque_nm": c_n},
                )
            if cfg.compliance:
                inc = inc + admittance_step(
                    f_w, cfg.admittance_m_per_n_s, cfg.admittance_deadband_n, dt
                )
                w = w + admittance_step(
                    c_t, cfg.admittance_rad_per_nm_s, cfg.admittance_deadband_nm, dt
                )
        goal_p = self.p_sup + inc
        goal_R = self.R_sup @ exp_so3(w)
        step, fast = clip_norm(inc, cfg.max_tool_speed_m_s * dt)
        wstep, spin = clip_norm(w, cfg.max_tool_rot_speed_rad_s * dt)
        free = self.p_sup + step
        p_new = clamp_box(free, lo, hi)
        if norm3(p_new - free) > STEP_EPS_M:
            clamped = True
            goal_p = goal_p + (p_new - free)
        notices.edge(
            now,
            "workspace",
            clamped,
            "limit",
            "workspace limit: target clamped to the box",
            {
                "reason": "workspace",
                "goal": floats(g_p),
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
        self.p_sup = p_new
        self.R_sup = orthonormalize(self.R_sup @ exp_so3(wstep))
        return goal_p, orthonormalize(goal_R)

    def command(
        self, now_ns: int, wall_ns: int, active: bool, origin_t_ns: int | None = None
    ) -> OperatorCommand:
        """The next command for robot/puma/cmd carrying the target (`t_ns` = wall_ns)."""
        assert self.p0 is not None
        dp, dR = engagement_command(self.p0, self.R0, self.p_sup, self.R_sup)
        self.seq_out += 1
        self.last_out_ns = now_ns
        self.last_out_active = active
        return OperatorCommand(
            seq=self.seq_out,
            t_ns=wall_ns,
            master=MASTER_ID,
            engage=self.engage_out,
            active=active,
            frame="world",
            dp=vec(dp),
            dR=vec(dR),
            grip=self.grip,
            origin_t_ns=origin_t_ns,
        )
