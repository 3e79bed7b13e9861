"""Time laws and joint paths of the proxy's planned motions (pure).

A motion is a path q(s), s ∈ [0, 1], followed with a time law s(t) at rest at both ends.
Units: rad, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Vec = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Trapezoid:
    """A trapezoidal (or triangular) time law s(t) from 0 to 1 at rest at both ends.

    `v_peak` (1/s) and `a` (1/s²) are the path speed and acceleration; `duration_s` the total.
    """

    v_peak: float
    a: float
    t_acc_s: float
    duration_s: float

    @staticmethod
    def plan(v_max: float, a_max: float) -> Trapezoid:
        """The fastest law with ṡ ≤ v_max and |s̈| ≤ a_max (both > 0)."""
        if v_max * v_max >= a_max:
            t_acc = math.sqrt(1.0 / a_max)
            return Trapezoid(a_max * t_acc, a_max, t_acc, 2.0 * t_acc)
        t_acc = v_max / a_max
        return Trapezoid(v_max, a_max, t_acc, 1.0 / v_max + t_acc)

    def s_at(self, t_s: float) -> float:
        if t_s <= 0.0:
            return 0.0
        if t_s >= self.duration_s:
            return 1.0
        if t_s < self.t_acc_s:
            return 0.5 * self.a * t_s * t_s
        if t_s <= self.duration_s - self.t_acc_s:
            return 0.5 * self.a * self.t_acc_s**2 + self.v_peak * (t_s - self.t_acc_s)
        r = self.duration_s - t_s
        return 1.0 - 0.5 * self.a * r * r


class SampledPath:
    """A joint path q(s), s ∈ [0, 1], through samples at uniform s, C¹ (cubic Hermite with
    Catmull-Rom tangents) so the joint velocity is continuous along the path."""

    def __init__(self, samples: NDArray[np.float64]) -> None:
        self.q = np.asarray(samples, dtype=np.float64)
        n = len(self.q) - 1
        if n < 1:
            raise ValueError("a path needs at least 2 samples")
        self.n = n
        m = np.empty_like(self.q)
        m[1:-1] = (self.q[2:] - self.q[:-2]) / 2.0
        m[0] = self.q[1] - self.q[0]
        m[-1] = self.q[-1] - self.q[-2]
        self.m = m  # tangents dq/di, per sample index

    def at(self, s: float) -> Vec:
        x = min(max(s, 0.0), 1.0) * self.n
        i = min(int(x), self.n - 1)
        u = x - i
        h00 = 2 * u**3 - 3 * u**2 + 1
        h10 = u**3 - 2 * u**2 + u
        h01 = -2 * u**3 + 3 * u**2
        h11 = u**3 - u**2
        return np.asarray(
            h00 * self.q[i] + h10 * self.m[i] + h01 * self.q[i + 1] + h11 * self.m[i + 1],
            dtype=np.float64,
        )

    def derivative_bounds(self) -> tuple[Vec, Vec]:
        """Per joint max |dq/ds| and max |d²q/ds²| over the samples (finite differences)."""
        d1 = np.abs(np.diff(self.q, axis=0)) * self.n
        d1max = d1.max(axis=0)
        if self.n >= 2:
            d2max = (np.abs(np.diff(self.q, n=2, axis=0)) * self.n * self.n).max(axis=0)
        else:
            d2max = np.zeros(self.q.shape[1])
        return np.asarray(d1max, dtype=np.float64), np.asarray(d2max, dtype=np.float64)


def discrete_brake_speed(e_rad: float, amax: float, dt_s: float) -> float:
    """The largest speed (rad/s, ≥ 0) from which a joint stops within |e| when slowing by
    amax·dt per step of dt: v = a·dt·(√(¼ + 2|e|/(a·dt²)) − ½), capped at |e|/dt. Plain
    floats: it runs for every joint every tick."""
    ae = abs(e_rad)
    v = amax * dt_s * (math.sqrt(0.25 + 2.0 * ae / (amax * dt_s * dt_s)) - 0.5)
    return min(v, ae / dt_s)
