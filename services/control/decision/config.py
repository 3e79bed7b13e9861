"""The decision server's configuration: the `[decision]` table, read once into a frozen dataclass.

Read through the bus's one config reader (`services.bus.config.section`), which refuses
unknown keys and checks every value's type against the annotations (a bool, a finite number,
3 numbers); `__post_init__` checks the ranges. A bad value raises
`ConfigError("decision.<key>", …)`.
The supervisory settings (everything but `rate_hz`, `rpc_timeout_s`, `wait_timeout_s` and
`passivity`) can also be changed while the service runs through the `supervisor` method,
which builds a new config with the same checks.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

from services.bus.bounds import check_config
from services.bus.errors import ConfigError
from services.geometry import V3

#: settings fixed at start-up: the `supervisor` method refuses to change them.
#: (`passivity`: the slave port's energies are counted from the service's start.)
STARTUP_ONLY: frozenset[str] = frozenset(
    {
        "rate_hz",
        "rpc_timeout_s",
        "wait_timeout_s",
        "passivity",
        "passivity_yield_m_s_n",
        "passivity_yield_max_rtt_ms",
    }
)

_POSITIVE = (
    "rate_hz",
    "watchdog_ms",
    "stale_ms",
    "state_stale_ms",
    "max_force_n",
    "max_torque_nm",
    "contact_stiffness_n_per_m",
    "max_tool_speed_m_s",
    "max_tool_rot_speed_rad_s",
    "rpc_timeout_s",
    "wait_timeout_s",
    "task_speed_m_s",
    "guarded_speed_m_s",
    "guarded_max_force_n",
    "guarded_max_distance_m",
    "approach_speed_m_s",
    "motion_guard_speed_m_s",
    "arrive_tol_m",
    "event_interval_s",
    "passivity_yield_max_rtt_ms",
)
_NON_NEGATIVE = (
    "admittance_m_per_n_s",
    "admittance_rad_per_nm_s",
    "admittance_deadband_n",
    "admittance_deadband_nm",
    "tool_tip_radius_m",
    "grip_time_s",
    "approach_zone_m",
    "motion_guard_zone_m",
    "passivity_yield_m_s_n",
)


#: the physical bound (services/bus/bounds.py) each numeric setting must respect
_KINDS: dict[str, str] = {
    "rate_hz": "rate_hz",
    "watchdog_ms": "watchdog_ms",
    "stale_ms": "watchdog_ms",
    "state_stale_ms": "watchdog_ms",
    "max_force_n": "force_n",
    "max_torque_nm": "torque_nm",
    "contact_stiffness_n_per_m": "stiffness_n_m",
    "admittance_m_per_n_s": "admittance_m_n_s",
    "passivity_yield_m_s_n": "admittance_m_n_s",
    "passivity_yield_max_rtt_ms": "watchdog_ms",
    "admittance_rad_per_nm_s": "admittance_rad_nm_s",
    "admittance_deadband_n": "force_n",
    "admittance_deadband_nm": "torque_nm",
    "workspace_min": "position_m",
    "workspace_max": "position_m",
    "max_tool_speed_m_s": "speed_m_s",
    "max_tool_rot_speed_rad_s": "rot_speed_rad_s",
    "approach_zone_m": "distance_m",
    "approach_speed_m_s": "speed_m_s",
    "motion_guard_zone_m": "distance_m",
    "motion_guard_speed_m_s": "speed_m_s",
    "rpc_timeout_s": "timeout_s",
    "wait_timeout_s": "timeout_s",
    "task_speed_m_s": "speed_m_s",
    "guarded_speed_m_s": "speed_m_s",
    "guarded_max_force_n": "force_n",
    "guarded_max_distance_m": "distance_m",
    "tool_tip_radius_m": "distance_m",
    "arrive_tol_m": "distance_m",
    "grip_time_s": "duration_s",
    "event_interval_s": "duration_s",
}


@dataclass(frozen=True, slots=True)
class DecisionConfig:
    """Settings of the decision server (units in the names; world frame = DH base frame).

    Loop and watchdogs:
      rate_hz: the supervisory loop rate (≥ 500 Hz by design; every tick publishes one
        command to the arm while teleoperation or a task runs).
      watchdog_ms: no fresh command from the lease holder for this long → hold.
      stale_ms: with compliance on, no force sample for this long → hold.
      state_stale_ms: no robot/state for this long → hold (the arm is gone or frozen).

    Supervision (§2.1.4's "active compliance … as supervisory functions"):
      max_force_n, max_torque_nm: above these the motion into the contact is removed.
        A watched motion (`move_*`, `home`) is stopped at once when the force, or the
        force it rises to within the reaction time (`watch.CONTACT_REACT_S`), would pass
        max_force_n; after such a stop the arm backs off along the contact force until the
        force is under the limit; a motion that lowers a contact force is never stopped
        for it (docs/decision.md "Contact").
      contact_stiffness_n_per_m: the stiffest contact the cell expects (default 20 000,
        the simulated blocks'; a real cell's steel fixture is stiffer, a foam pad softer):
        teleoperation slows into a touched contact so the force can stop within the limit,
        and a back-off travels force / stiffness.
      passivity: time-domain passivity on the slave port (docs/passivity.md): the
        command's motion into a contact is bounded by the energy the operator put in.
      passivity_yield_m_s_n: with passivity on, the tool backs out of a contact at this
        many m/s per newton it presses harder than the master shows the operator (0: off;
        default 5e-5, the rate measured; docs/passivity.md "Yielding to the hand"), for a
        contact that began while the link's round trip, measured from the master's
        echoes, was at most passivity_yield_max_rtt_ms (default 500; 1 … 60 000).
      compliance: admittance on: the target yields to the wrist force,
        dp = admittance_m_per_n_s · f_world · dt, dθ = admittance_rad_per_nm_s · c_tool · dt,
        with deadbands admittance_deadband_n / admittance_deadband_nm.
      workspace_min, workspace_max: the box (m, world) the tool point must stay in. The
        default spans the table (x 0.35…0.85, y −0.45…0.45, top z = 0.40) and its margins;
        its floor is the table top, so the tool point never enters the table.
      workspace_from_arm: while true (the default), the box is the one the arm's
        description gives (robot/arm/description `workspace`, its model file's), when it
        gives one; false: workspace_min/workspace_max as set here. Setting either through
        the `supervisor` call sets it false (the box given wins over the arm's). The tool
        speeds are never above what the description says the arm holds the tool to.
      max_tool_speed_m_s, max_tool_rot_speed_rad_s: the supervised target never moves
        faster: a step covers at most speed × the time since the previous one (at most
        0.1 s of it: `target.MAX_SPAN_S`), whatever the master's rate.
      approach_zone_m, approach_speed_m_s: within approach_zone_m of a face of the
        workspace box, the target moves towards that face at most at approach_speed_m_s
        (guarded approach: the floor is the table top, so a tool that touches it arrives
        slowly and the impact stays small). 0 (the default): off.
      motion_guard_zone_m, motion_guard_speed_m_s: a forwarded motion (`move_*`) whose
        goal lies within motion_guard_zone_m above the workspace floor, where the table's
        objects are, is planned at most at motion_guard_speed_m_s (default 0.10 m, 0.05 m/s:
        the speed from which the arm stops against a 20 kN/m block within 1.5 × max_force_n;
        docs/decision.md "Contact"). 0: off.

    Methods and tasks:
      rpc_timeout_s: timeout of a forwarded call; wait_timeout_s: of one with "wait": true.
      task_speed_m_s: default speed of a task's moves; guarded_speed_m_s,
        guarded_max_force_n, guarded_max_distance_m: defaults of `guarded_move`.
      tool_tip_radius_m: radius of the tool's round tip around the tool point: a guarded
        move reports the contact point this far ahead of the tool point.
      arrive_tol_m: a task move is done when the measured tool point is this close.
      grip_time_s: how long a task waits for the gripper to open or close.
      event_interval_s: an intervention's event is sent at most once per this interval per
        reason (and per master for refusals).
      estop_power_off: `estop` also powers the arm off through arm's `estop` extension
        (recovery then needs `connect` and `initialize`); default: arm `stop` (brake, hold).
    """

    rate_hz: float = 500.0
    watchdog_ms: float = 100.0
    stale_ms: float = 50.0
    state_stale_ms: float = 200.0
    max_force_n: float = 40.0
    max_torque_nm: float = 4.0
    contact_stiffness_n_per_m: float = 20_000.0
    compliance: bool = False
    admittance_m_per_n_s: float = 0.002
    admittance_rad_per_nm_s: float = 0.02
    admittance_deadband_n: float = 2.0
    admittance_deadband_nm: float = 0.2
    workspace_min: V3 = (0.25, -0.5, 0.40)
    workspace_max: V3 = (0.95, 0.5, 1.2)
    workspace_from_arm: bool = True
    max_tool_speed_m_s: float = 0.25
    max_tool_rot_speed_rad_s: float = 1.0
    approach_zone_m: float = 0.0
    approach_speed_m_s: float = 0.02
    motion_guard_zone_m: float = 0.10
    motion_guard_speed_m_s: float = 0.05
    rpc_timeout_s: float = 2.0
    wait_timeout_s: float = 60.0
    task_speed_m_s: float = 0.05
    guarded_speed_m_s: float = 0.02
    guarded_max_force_n: float = 5.0
    guarded_max_distance_m: float = 0.2
    tool_tip_radius_m: float = 0.005
    arrive_tol_m: float = 0.002
    grip_time_s: float = 0.5
    event_interval_s: float = 1.0
    estop_power_off: bool = False
    passivity: bool = False
    passivity_yield_m_s_n: float = 5e-5  # the rate measured (passivity.slave.YIELD_M_S_N)
    passivity_yield_max_rtt_ms: float = 500.0

    def __post_init__(self) -> None:
        for key in _POSITIVE:
            if not getattr(self, key) > 0:
                raise _err(key, f"must be > 0, got {getattr(self, key)}")
        for key in _NON_NEGATIVE:
            if not getattr(self, key) >= 0:
                raise _err(key, f"must be ≥ 0, got {getattr(self, key)}")
        for i, (lo, hi) in enumerate(zip(self.workspace_min, self.workspace_max, strict=True)):
            if not lo < hi:
                raise _err(
                    "workspace_max",
                    f"axis {'xyz'[i]}: max {hi} must be above min {lo}",
                )
        check_config("decision", self, _KINDS)
        if self.guarded_speed_m_s > self.max_tool_speed_m_s:
            raise _err("guarded_speed_m_s", "must not exceed max_tool_speed_m_s")
        if self.task_speed_m_s > self.max_tool_speed_m_s:
            raise _err("task_speed_m_s", "must not exceed max_tool_speed_m_s")
        if self.approach_speed_m_s > self.max_tool_speed_m_s:
            raise _err("approach_speed_m_s", "must not exceed max_tool_speed_m_s")

    @property
    def period_s(self) -> float:
        """The nominal loop period (s): the speed limits are applied per this period."""
        return 1.0 / self.rate_hz

    def with_arm(self, arm: Any) -> DecisionConfig:
        """These settings bound by the arm's description (an ArmDescription): its workspace
        box unless `workspace_from_arm` is false or it gives none, and tool speeds (the
        task, guarded and approach speeds with them) no higher than it holds the tool to."""
        changes: dict[str, Any] = {}
        ws = arm.workspace or {}
        if self.workspace_from_arm and "min" in ws and "max" in ws:
            changes["workspace_min"] = tuple(float(x) for x in ws["min"])
            changes["workspace_max"] = tuple(float(x) for x in ws["max"])
        top = arm.max_tool_speed_m_s
        if top is not None and top < self.max_tool_speed_m_s:
            changes["max_tool_speed_m_s"] = top
            for key in (
                "task_speed_m_s",
                "guarded_speed_m_s",
                "approach_speed_m_s",
                "motion_guard_speed_m_s",
            ):
                changes[key] = min(getattr(self, key), top)
        turn = arm.max_tool_rot_speed_rad_s
        if turn is not None and turn < self.max_tool_rot_speed_rad_s:
            changes["max_tool_rot_speed_rad_s"] = turn
        return replace(self, **changes) if changes else self

    def settings(self) -> dict[str, Any]:
        """Every setting as a msgpack-friendly map (tuples as lists)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out


def _err(key: str, message: str) -> ConfigError:
    return ConfigError(f"decision.{key}", message)
