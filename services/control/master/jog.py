"""Rate control for desk devices: deflection → hand velocity → integrated hand pose.

A SpaceMouse or a keyboard gives a deflection per axis, not a pose. We turn the six
normalised deflections (tx, ty, tz, rx, ry, rz ∈ [−1, 1]) into a hand twist and integrate it
into a virtual hand pose that the teleoperation core treats like a master arm's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.geometry import exp_so3, orthonormalize

MAX_STEP_S = 0.05
"""Longest time step integrated at once: after a stall (a slow read, a paused process) the
hand must not leap by the stall × speed; the lost time is simply not integrated."""


def apply_deadband(deflection: ArrayLike, deadband: float) -> NDArray[np.float64]:
    """Deadband with rescaling, per axis: |v| ≤ d → 0, else sign(v)·(|v| − d)/(1 − d).

    Continuous at the band edge (no step when leaving the band) and still reaches ±1 at full
    deflection. Input is clipped to [−1, 1] first.
    """
    v = np.clip(np.asarray(deflection, dtype=float), -1.0, 1.0)
    if not 0.0 <= deadband < 1.0:
        raise ValueError("deadband must satisfy 0 ≤ d < 1")
    mag = np.maximum(np.abs(v) - deadband, 0.0) / (1.0 - deadband)
    return np.asarray(np.sign(v) * mag, dtype=float)


@dataclass(frozen=True, slots=True)
class RateScale:
    """Hand speeds at full deflection: translation (m/s) and rotation (rad/s), both already
    multiplied by the sensitivity."""

    speed_m_s: float
    rate_rad_s: float

    def twist(self, deflection: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(v (3,) m/s, ω (3,) rad/s) for six deflections (tx, ty, tz, rx, ry, rz)."""
        d = np.asarray(deflection, dtype=float)
        if d.shape != (6,):
            raise ValueError("deflection must have 6 axes")
        return d[:3] * self.speed_m_s, d[3:] * self.rate_rad_s


class HandIntegrator:
    """Integrates a hand twist into a pose (p, R) in the master frame.

    Translation v is in the master frame (p += v·dt). Rotation ω is in the hand frame
    (R ← R·exp([ω]×·dt), exact on SO(3)), so twisting the cap about its own z turns the hand
    about its own z whatever the accumulated orientation, which eq. 5 then maps to a turn of
    the tool about its own z.
    """

    def __init__(self) -> None:
        self._p = np.zeros(3)
        self._R = np.eye(3)

    @property
    def pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Copies of (p (3,) m, R (3, 3))."""
        return self._p.copy(), self._R.copy()

    def reset(self) -> None:
        """Back to p = 0, R = I."""
        self._p = np.zeros(3)
        self._R = np.eye(3)

    def step(self, v_m_s: ArrayLike, w_rad_s: ArrayLike, dt_s: float) -> None:
        """Advance by dt_s (clamped to [0, MAX_STEP_S]) at constant twist (v, ω)."""
        dt = min(max(float(dt_s), 0.0), MAX_STEP_S)
        if dt == 0.0:
            return
        self._p = self._p + np.asarray(v_m_s, dtype=float) * dt
        self._R = orthonormalize(self._R @ exp_so3(np.asarray(w_rad_s, dtype=float) * dt))
