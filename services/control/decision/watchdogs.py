"""The supervisor's watchdogs, as pure functions of the settings and the arrival times
(monotonic ns): whether a stream is fresh, why following the lease holder must stop, and
when the next deadline falls."""

from __future__ import annotations

from services.bus.messages import RobotState
from services.control.decision.config import DecisionConfig


def fresh(stale_ms: float, now_ns: int, rx_ns: int) -> bool:
    """A sample received at `rx_ns` is fresh at `now_ns` (no older than `stale_ms`)."""
    return now_ns - rx_ns <= stale_ms * 1e6


def follow_problem(
    cfg: DecisionConfig,
    now_ns: int,
    cmd_rx_ns: int,
    lease: str | None,
    state: RobotState | None,
    state_ok: bool,
    force_ok: bool,
) -> tuple[str, str] | None:
    """Why teleoperation must hold (the hold's reason and message), or None: no command
    from the lease holder for watchdog_ms, a stale robot/state, a robot in error, a stale
    force stream with compliance on."""
    if now_ns - cmd_rx_ns > cfg.watchdog_ms * 1e6:
        return (
            "command_timeout",
            f"no command from master {lease!r} for {cfg.watchdog_ms:g} ms: holding",
        )
    if not state_ok or state is None:
        return "state_stale", "robot/state is stale: holding"
    if state.status == "error":
        return "robot_error", "the robot reports an error: holding"
    if cfg.compliance and not force_ok:
        return (
            "force_stale",
            f"no force sample for {cfg.stale_ms:g} ms with compliance on: holding",
        )
    return None


def follow_deadline_ns(cfg: DecisionConfig, cmd_rx_ns: int, state_rx_ns: int) -> int:
    """When following holds unless a command or a robot/state arrives first."""
    return min(cmd_rx_ns + int(cfg.watchdog_ms * 1e6), state_rx_ns + int(cfg.state_stale_ms * 1e6))
