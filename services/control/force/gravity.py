"""Gravity compensation of the tool's own weight.

The wrist sensor carries the tool, so its reading includes the tool's weight, which turns
with the tool. Given the tool's orientation in the world (R world←tool = M_w^t, RobotState's
`tool_R`), the weight seen in the tool frame is known and is subtracted, so a tool at rest
reads ≈ 0 whatever its orientation. The world frame is the DH base frame, z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Vec = NDArray[np.float64]

STANDARD_GRAVITY_MPS2 = 9.80665


@dataclass(frozen=True, slots=True)
class ToolLoad:
    """The tool's mass (kg) and centre of mass (m, tool frame, from the tool point)."""

    mass_kg: float = 0.0
    com_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gravity_mps2: float = STANDARD_GRAVITY_MPS2

    def __post_init__(self) -> None:
        if not (np.isfinite(self.mass_kg) and self.mass_kg >= 0.0):
            raise ValueError(f"mass_kg: must be ≥ 0 and finite, got {self.mass_kg}")
        if len(self.com_m) != 3 or not np.all(np.isfinite(self.com_m)):
            raise ValueError(f"com_m: 3 finite numbers, got {self.com_m}")
        if not (np.isfinite(self.gravity_mps2) and self.gravity_mps2 >= 0.0):
            raise ValueError(f"gravity_mps2: must be ≥ 0 and finite, got {self.gravity_mps2}")

    def wrench(self, tool_R: ArrayLike) -> tuple[Vec, Vec]:
        """The weight's force (N) and moment about the tool point (N·m), in the tool frame.

        F_g = m · (M_w^t)ᵀ (0, 0, −g),   C_g = c × F_g   (c: centre of mass in R_t)
        """
        R = np.asarray(tool_R, dtype=float).reshape(3, 3)
        f = R.T @ np.array([0.0, 0.0, -self.mass_kg * self.gravity_mps2])
        return f, np.cross(np.asarray(self.com_m, dtype=float), f)


def compensate(f: Vec, c: Vec, load: ToolLoad, tool_R: ArrayLike) -> tuple[Vec, Vec]:
    """The measured (f, c) minus the tool's weight: what the environment applies to the tool."""
    fg, cg = load.wrench(tool_R)
    return f - fg, c - cg
