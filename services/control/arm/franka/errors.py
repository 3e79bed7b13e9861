"""libfranka's errors and reflexes, named for the arm's `error` status and its event.

A reflex is the robot stopping itself (a collision threshold crossed, a limit, a
discontinuity in what it was sent): libfranka ends the motion with a `ControlException`
("Motion aborted by reflex!") and the robot's mode is `Reflex` with the cause among the
last motion's error flags (`franka::Errors`, 41 booleans). `fault_message` says which, in
the words of the flags, so the event names the reflex.
"""

from __future__ import annotations

from typing import Any

ERROR_FLAGS: tuple[str, ...] = (
    "joint_position_limits_violation",
    "cartesian_position_limits_violation",
    "self_collision_avoidance_violation",
    "joint_velocity_violation",
    "cartesian_velocity_violation",
    "force_control_safety_violation",
    "joint_reflex",
    "cartesian_reflex",
    "max_goal_pose_deviation_violation",
    "max_path_pose_deviation_violation",
    "cartesian_velocity_profile_safety_violation",
    "joint_position_motion_generator_start_pose_invalid",
    "joint_motion_generator_position_limits_violation",
    "joint_motion_generator_velocity_limits_violation",
    "joint_motion_generator_velocity_discontinuity",
    "joint_motion_generator_acceleration_discontinuity",
    "cartesian_position_motion_generator_start_pose_invalid",
    "cartesian_motion_generator_elbow_limit_violation",
    "cartesian_motion_generator_velocity_limits_violation",
    "cartesian_motion_generator_velocity_discontinuity",
    "cartesian_motion_generator_acceleration_discontinuity",
    "cartesian_motion_generator_elbow_sign_inconsistent",
    "cartesian_motion_generator_start_elbow_invalid",
    "cartesian_motion_generator_joint_position_limits_violation",
    "cartesian_motion_generator_joint_velocity_limits_violation",
    "cartesian_motion_generator_joint_velocity_discontinuity",
    "cartesian_motion_generator_joint_acceleration_discontinuity",
    "cartesian_position_motion_generator_invalid_frame",
    "force_controller_desired_force_tolerance_violation",
    "controller_torque_discontinuity",
    "start_elbow_sign_inconsistent",
    "communication_constraints_violation",
    "power_limit_violation",
    "joint_p2p_insufficient_torque_for_planning",
    "tau_j_range_violation",
    "instability_detected",
    "joint_move_in_wrong_direction",
    "cartesian_spline_motion_generator_violation",
    "joint_via_motion_generator_planning_joint_limit_violation",
    "base_acceleration_initialization_timeout",
    "base_acceleration_invalid_reading",
)
"""The 41 flags of `franka::Errors`, in the order of libfranka's `Error` enum (errors.h)."""


def error_names(errors: Any) -> list[str]:
    """The flags set in a `franka::Errors` (or a sequence of 41 booleans)."""
    if isinstance(errors, list | tuple):
        return [name for name, on in zip(ERROR_FLAGS, errors, strict=False) if on]
    return [name for name in ERROR_FLAGS if bool(getattr(errors, name, False))]


def fault_kind(mode: str, message: str) -> str:
    """`reflex` when the robot stopped itself, else `control` (the command was refused)."""
    if mode == "Reflex" or "reflex" in message.lower():
        return "reflex"
    return "control"


def fault_message(kind: str, message: str, errors: list[str]) -> str:
    """One line for people: what happened, and the flags that say why."""
    flags = ", ".join(errors) if errors else "no error flag set"
    if kind == "reflex":
        return f"reflex: {flags} ({message})"
    if kind == "link":
        return message
    return f"libfranka: {message} [{flags}]"
