"""/telerobot/tool_target as a master: validation, then engagement and commands (PROTOCOL §2).

Pure: time is passed in, nothing touches the bus. `check_target` refuses every pose that must
not move the arm (wrong frame, not finite, non-unit quaternion, absurd position, too far from
the tool). `TargetMaster` turns the newest accepted target into OperatorCommand fields:

- the first fresh target starts an engagement (`engage` + 1) rebased on the tool pose then,
  (p0, R0), and every command of it carries `dp = p − p0`, `dR = R0ᵀ·R` in the world frame,
  so the slave's target is the ROS target itself (R_target = R0·dR, p_target = p0 + dp) and
  the decision's speed limit takes the tool there without a jump;
- while the newest target is younger than `timeout_s` the loop sends the newest command at
  the master rate (the decision's watchdog needs a stream, a planner may publish slowly);
- when targets stop, it sends `active = false` (dp/dR unchanged) a few times and goes idle:
  the decision holds and releases the lease. The next target starts a new engagement from
  wherever the arm then is.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

from services.frontends.ros2.convert import relative_pose, rotation_of
from services.frontends.rosmsg.msgs import PoseStamped

HOLD_REPEATS = 3
"""Inactive commands sent when targets stop: one lost packet must not matter."""


class TargetRefused(ValueError):
    """A target that must not move the arm; the message says why."""


@dataclass(frozen=True, slots=True)
class TargetLimits:
    """What a target must satisfy: its frame, |‖q‖ − 1| ≤ `quat_tol`, within `max_radius_m` of
    the world origin and within `max_distance_m` of the tool."""

    frame_id: str = "world"
    quat_tol: float = 1e-3
    max_radius_m: float = 2.0
    max_distance_m: float = 0.5


@dataclass(frozen=True, slots=True)
class Target:
    """An accepted target: tool position (m, world) and row-major rotation (world ← tool)."""

    p: tuple[float, float, float]
    R: tuple[float, ...]


def check_target(pose: PoseStamped, limits: TargetLimits, tool_p: Sequence[float] | None) -> Target:
    """The target of `pose`, or TargetRefused. `tool_p`: the tool now (None: unknown)."""
    if pose.header.frame_id != limits.frame_id:
        raise TargetRefused(
            f"frame_id {pose.header.frame_id[:64]!r} is not {limits.frame_id!r} "
            "(targets are tool poses in the world frame)"
        )
    x, y, z = pose.position
    qx, qy, qz, qw = pose.orientation
    if not all(math.isfinite(v) for v in (x, y, z, qx, qy, qz, qw)):
        raise TargetRefused("position or orientation not finite")
    radius = math.sqrt(x * x + y * y + z * z)
    if radius > limits.max_radius_m:
        raise TargetRefused(
            f"position {radius:.3g} m from the world origin (limit {limits.max_radius_m} m)"
        )
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if not abs(n - 1.0) <= limits.quat_tol:
        raise TargetRefused(f"orientation is not a unit quaternion (norm {n:.6g})")
    if tool_p is None:
        raise TargetRefused("no robot/state yet: the tool pose to start from is unknown")
    d = math.dist((x, y, z), tool_p)
    if d > limits.max_distance_m:
        raise TargetRefused(
            f"target {d:.3g} m from the tool (limit {limits.max_distance_m} m): move closer first"
        )
    return Target((x, y, z), rotation_of((qx / n, qy / n, qz / n, qw / n)))


@dataclass(frozen=True, slots=True)
class Command:
    """The fields of one OperatorCommand (frame "world")."""

    seq: int
    engage: int
    active: bool
    dp: tuple[float, float, float]
    dR: tuple[float, ...]


_IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
_ZERO = (0.0, 0.0, 0.0)


class TargetMaster:
    """The engagement state machine of the ROS target master (see the module doc).

    Not thread-safe: the service calls it under its own lock. Times are monotonic seconds.
    `seq` and `engage` start from the wall clock (µs, ms) like every master's, so a restarted
    bridge is never ignored as stale.
    """

    def __init__(
        self, timeout_s: float, seq_start: int | None = None, engage_start: int | None = None
    ) -> None:
        now_ns = time.time_ns()
        self.timeout_s = timeout_s
        self.seq = now_ns // 1000 if seq_start is None else seq_start
        self.engage = now_ns // 1_000_000 if engage_start is None else engage_start
        self.engaged = False
        self._target: Target | None = None
        self._target_s = -math.inf
        self._p0: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._R0: tuple[float, ...] = _IDENTITY
        self._dp: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._dR: tuple[float, ...] = _IDENTITY
        self._holds_left = 0

    def on_target(self, target: Target, now_s: float) -> None:
        self._target, self._target_s = target, now_s

    def fresh(self, now_s: float) -> bool:
        return self._target is not None and now_s - self._target_s <= self.timeout_s

    @property
    def busy(self) -> bool:
        """Something to send: engaged, or holds still to repeat."""
        return self.engaged or self._holds_left > 0

    def tick(
        self,
        now_s: float,
        tool: tuple[Sequence[float], Sequence[float]] | None,
    ) -> Command | None:
        """The command to send now, or None (idle). `tool`: the newest fresh tool pose
        (p, R) from robot/state, None if there is none (then no engagement starts and a
        running one is held)."""
        target = self._target
        if target is not None and tool is not None and self.fresh(now_s):
            if not self.engaged:
                self.engage += 1
                self.engaged = True
                self._p0, self._R0 = tuple(tool[0]), tuple(tool[1])
            _, self._dR = relative_pose(_ZERO, self._R0, _ZERO, target.R)
            t, p0 = target.p, self._p0
            self._dp = (t[0] - p0[0], t[1] - p0[1], t[2] - p0[2])
            return self._command(True)
        if self.engaged:
            self.engaged = False
            self._holds_left = HOLD_REPEATS
        if self._holds_left > 0:
            self._holds_left -= 1
            return self._command(False)
        return None

    def hold(self) -> Command:
        """An inactive command now (shutdown): the slave holds whatever happens next."""
        self.engaged = False
        self._holds_left = 0
        return self._command(False)

    def _command(self, active: bool) -> Command:
        self.seq += 1
        return Command(self.seq, self.engage, active, self._dp, self._dR)
