"""Models for closing the bilateral loop in simulation (pure, n-DoF translational).

- `Operator`: the hand as a spring–damper pulling the device towards an intended path; in
  contact the operator also pushes until the force felt reaches the force meant (a person
  presses "until it feels right", not to a position), by moving the intended point.
- `Device`: the haptic master's own mass and viscous damping, integrated semi-implicitly.
- `Wall`: a stiff, damped half-space `n·x ≤ d` that only pushes (unilateral contact).

Vectors are lists of plain floats of one length (1 or 3).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from services.control.passivity.observer import dot

RELAX_M_S = 0.05
"""How fast the operator lets go of the extra push once no longer pressing (m/s)."""

Path = Callable[[float], Sequence[float]]
"""t_s → the position the operator intends (m)."""


@dataclass(slots=True)
class Operator:
    """The operator's hand: stiffness_n_m (N/m) and damping_ns_m (N·s/m) towards `path`
    shifted by `push_m` along `press` (a unit vector).

    While `pressing(t)` is true, the operator moves that shift at `gain_m_ns` (m/s per N)
    times (`goal_force_n` − the force felt against `press`), within ±`max_push_m`; outside,
    the shift relaxes back to zero at `RELAX_M_S`. gain 0 = a pure position operator.
    """

    path: Path
    stiffness_n_m: float = 300.0
    damping_ns_m: float = 10.0
    press: tuple[float, ...] = (1.0,)
    goal_force_n: float = 0.0
    gain_m_ns: float = 0.0
    max_push_m: float = 0.05
    pressing: Callable[[float], bool] = lambda t: False
    push_m: float = 0.0

    def force(self, t_s: float, x: Sequence[float], v: Sequence[float]) -> list[float]:
        """The force (N) the hand applies to the device at time t_s."""
        base = self.path(t_s)
        target = [b + self.push_m * u for b, u in zip(base, self.press, strict=True)]
        return [
            self.stiffness_n_m * (xt - xi) - self.damping_ns_m * vi
            for xt, xi, vi in zip(target, x, v, strict=True)
        ]

    def feel(self, t_s: float, f_display: Sequence[float], dt_s: float) -> None:
        """Adapts the push to the force displayed on the hand (N) over dt_s."""
        if self.gain_m_ns <= 0.0:
            return
        if self.pressing(t_s):
            felt = -dot(f_display, self.press)
            step = self.gain_m_ns * (self.goal_force_n - felt) * dt_s
        else:
            step = -math.copysign(min(abs(self.push_m), RELAX_M_S * dt_s), self.push_m)
        self.push_m = min(max(self.push_m + step, -self.max_push_m), self.max_push_m)


@dataclass(slots=True)
class Device:
    """A haptic master: mass_kg, damping_ns_m; position x (m) and velocity v (m/s)."""

    mass_kg: float = 0.5
    damping_ns_m: float = 2.0
    x: list[float] = field(default_factory=lambda: [0.0])
    v: list[float] = field(default_factory=lambda: [0.0])

    def step(self, f_n: Sequence[float], dt_s: float) -> None:
        """Integrates m·a = f − b·v over dt_s (semi-implicit Euler: energy-stable)."""
        for i, fi in enumerate(f_n):
            a = (fi - self.damping_ns_m * self.v[i]) / self.mass_kg
            self.v[i] += a * dt_s
            self.x[i] += self.v[i] * dt_s


@dataclass(frozen=True, slots=True)
class Wall:
    """The half-space beyond `n·x = offset_m` (n a unit normal pointing into the wall)."""

    normal: tuple[float, ...] = (1.0,)
    offset_m: float = 0.05
    stiffness_n_m: float = 5000.0
    damping_ns_m: float = 5.0

    def penetration_m(self, x: Sequence[float]) -> float:
        return max(dot(self.normal, x) - self.offset_m, 0.0)

    def force(self, x: Sequence[float], v: Sequence[float]) -> list[float]:
        """The force (N) the wall applies to a point at x moving at v: along −n, never pulling."""
        pen = self.penetration_m(x)
        if pen <= 0.0:
            return [0.0] * len(x)
        push = max(self.stiffness_n_m * pen + self.damping_ns_m * dot(self.normal, v), 0.0)
        return [-push * ni for ni in self.normal]


def press_hold_release(
    start: Sequence[float],
    target: Sequence[float],
    *,
    approach_s: float = 1.0,
    hold_s: float = 3.0,
    release_s: float = 1.0,
) -> Path:
    """The contact task: from start to target (past the wall) in approach_s, hold, return."""
    a = [float(x) for x in start]
    b = [float(x) for x in target]

    def smooth(s: float) -> float:
        s = min(max(s, 0.0), 1.0)
        return 0.5 - 0.5 * math.cos(math.pi * s)

    def path(t_s: float) -> list[float]:
        if t_s < approach_s:
            k = smooth(t_s / approach_s)
        elif t_s < approach_s + hold_s:
            k = 1.0
        else:
            k = 1.0 - smooth((t_s - approach_s - hold_s) / release_s)
        return [ai + k * (bi - ai) for ai, bi in zip(a, b, strict=True)]

    return path
