"""Force feedback: the wrist wrench measured at the slave's tool, shown on the operator's hand.

Inputs: a ForceSample (f, c at the tool point, tool frame) and the tool orientation
`tool_R` (world ← tool) from RobotState. The operator moves in the master frame, which A
maps onto the slave axes the command is expressed in: world axes in `world` mode, tool axes
in `tool` mode (PROTOCOL §2). The displayed wrench is mapped back the same way (A is a
rotation, so its inverse is Aᵀ), scaled, and saturated with its direction kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.master.config import Frame, MasterConfig
from services.master.so3 import is_rotation

Vec3 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class DisplayWrench:
    """What to show the operator: force f (3,) N and moment c (3,) N·m in the master frame,
    and whether each was cut down to its limit."""

    f: Vec3
    c: Vec3
    force_saturated: bool
    torque_saturated: bool


def saturate(v: ArrayLike, max_norm: float) -> tuple[Vec3, bool]:
    """v scaled down to norm max_norm when longer, direction kept; (v', was_saturated)."""
    x = np.asarray(v, dtype=float).reshape(3)
    norm = float(np.linalg.norm(x))
    if norm > max_norm:
        return x * (max_norm / norm), True
    return x, False


def operator_wrench(
    f_tool: ArrayLike,
    c_tool: ArrayLike,
    tool_R: ArrayLike,
    *,
    alignment: ArrayLike,
    frame: Frame,
    force_scale: float,
    max_force_n: float,
    max_torque_nm: float,
) -> DisplayWrench:
    """The wrench to display on the operator's hand.

    world mode: f_m = s · Aᵀ · tool_R · f_tool (tool → world → master frame);
    tool mode:  f_m = s · Aᵀ · f_tool (the operator's axes are mapped onto the tool's);
    the same for c; then |f_m| ≤ max_force_n and |c_m| ≤ max_torque_nm, direction kept.
    Raises ValueError on non-finite input or a tool_R that is not a rotation.
    """
    f = np.asarray(f_tool, dtype=float).reshape(3)
    c = np.asarray(c_tool, dtype=float).reshape(3)
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(c))):
        raise ValueError("force and moment must be finite")
    A = np.asarray(alignment, dtype=float).reshape(3, 3)
    if frame == "world":
        R = np.asarray(tool_R, dtype=float).reshape(3, 3)
        if not is_rotation(R):
            raise ValueError("tool_R must be a rotation")
        to_master = A.T @ R
    elif frame == "tool":
        to_master = A.T
    else:
        raise ValueError("frame must be 'world' or 'tool'")
    f_m, f_sat = saturate(force_scale * (to_master @ f), max_force_n)
    c_m, c_sat = saturate(force_scale * (to_master @ c), max_torque_nm)
    return DisplayWrench(f_m, c_m, f_sat, c_sat)


class ForceFeedback:
    """`operator_wrench` with the settings of a MasterConfig."""

    def __init__(self, config: MasterConfig) -> None:
        self._A = config.alignment_matrix
        self._force_scale = config.force_scale
        self._max_force_n = config.max_force_n
        self._max_torque_nm = config.max_torque_nm

    def compute(
        self, f_tool: ArrayLike, c_tool: ArrayLike, tool_R: ArrayLike, frame: Frame
    ) -> DisplayWrench:
        """The display wrench for a ForceSample (f, c) and RobotState.tool_R (9 or 3×3);
        `frame` is the teleoperation frame in use (Teleop.frame)."""
        return operator_wrench(
            f_tool,
            c_tool,
            tool_R,
            alignment=self._A,
            frame=frame,
            force_scale=self._force_scale,
            max_force_n=self._max_force_n,
            max_torque_nm=self._max_torque_nm,
        )

    @staticmethod
    def zero() -> DisplayWrench:
        """Nothing to display (no or stale force data)."""
        return DisplayWrench(np.zeros(3), np.zeros(3), False, False)
