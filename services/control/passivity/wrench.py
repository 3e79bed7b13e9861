"""One port for the whole wrench: force and moment, translation and rotation.

A device that displays moments (the serial master arm) closes a second loop through the
delay, the moment at the tool against the rotation of the hand; passivated alone, the force
loop leaves that one unguarded. The port's power is `f·v + c·ω` (the force and the moment
about the same point, the tool point at the slave and the hand's at the master, both in one
frame), so both sides observe, budget and correct the six-vector at once, in one energy
count: the rotational work is paid from the same reservoir as the translational one, and the
energies on the wire are the port's whole (docs/passivity.md, "Rotations").

The controllers work on vectors of any length; a six-vector mixes metres and radians, so
each side maps the wrench and the motion into coordinates where the controller's geometry
means something (`WrenchCoords`), with `f·dx` unchanged: at the master, mass-normalised
coordinates (x·√m, θ·√I; f/√m, c/√I), so the limiter's unit-mass device model is the
device's own mass and inertia; at the slave, a characteristic length L (θ·L; c/L), so that
its back-out, dead band and drift, in metres and newtons, mean L·rad and N·m/L in rotation.

The angles are `RotationTrack`'s: the sum of each step's rotation `log(R·R_prevᵀ)` (spatial
frame), whose differences are the body's angular displacement step by step. The orientation's
own rotation vector `log(R)` would not do: its rate is not ω away from the identity, and a
moment times it is not work.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from numpy.typing import ArrayLike

from services.control.passivity.controller import MasterPassivity
from services.geometry import M9, V3, add3, exp9, log9, m9, mul9, mv9, tmul9


def spatial_step(R_prev: M9, R: M9) -> V3:
    """The rotation from `R_prev` to `R` as a rotation vector in the spatial frame:
    log(R·R_prevᵀ) = R_prev·log(R_prevᵀ·R) (rad)."""
    return mv9(R_prev, log9(tmul9(R_prev, R)))


def rotate_towards(R: M9, w: V3) -> M9:
    """exp(w)·R: `R` turned by the spatial rotation vector `w` (rad)."""
    return mul9(exp9(w), R)


class RotationTrack:
    """The angular position of a body: the sum of its spatial rotation steps (rad), exact
    step by step (see the module docstring). `update(R)` takes the orientation now (a 3×3
    or 9 row-major floats) and returns the angles; `reset()` starts again from zero at the
    next orientation."""

    __slots__ = ("_R", "theta")

    def __init__(self) -> None:
        self._R: M9 | None = None
        self.theta: V3 = (0.0, 0.0, 0.0)

    @property
    def R(self) -> M9 | None:
        """The orientation last taken (None before the first)."""
        return self._R

    def reset(self) -> None:
        self._R = None
        self.theta = (0.0, 0.0, 0.0)

    def update(self, R: ArrayLike) -> V3:
        r = m9(R)
        if self._R is not None and r != self._R:
            self.theta = add3(self.theta, spatial_step(self._R, r))
        self._R = r
        return self.theta


@dataclass(frozen=True, slots=True)
class WrenchCoords:
    """Six-vector coordinates of one port: motion `(x·a, θ·b)`, wrench `(f/a, c/b)`, so
    that `wrench·motion = f·x + c·θ` (the energy is the same in joules).

    `master(mass_kg, inertia_kg_m2)`: a = √m, b = √I (a device of unit mass in every
    coordinate). `slave(length_m)`: a = 1, b = L (a rotation by 1 rad counts as L metres).
    """

    a: float
    b: float

    @classmethod
    def master(cls, mass_kg: float, inertia_kg_m2: float) -> WrenchCoords:
        return cls(math.sqrt(mass_kg), math.sqrt(inertia_kg_m2))

    @classmethod
    def slave(cls, length_m: float) -> WrenchCoords:
        return cls(1.0, length_m)

    def motion(self, x: Iterable[float], theta: Iterable[float]) -> list[float]:
        a, b = self.a, self.b
        return [a * float(v) for v in x] + [b * float(v) for v in theta]

    def wrench(self, f: Iterable[float], c: Iterable[float]) -> list[float]:
        a, b = self.a, self.b
        return [float(v) / a for v in f] + [float(v) / b for v in c]

    def split_wrench(self, w: Sequence[float]) -> tuple[V3, V3]:
        """(f, c) of a wrench in these coordinates."""
        a, b = self.a, self.b
        return (
            (w[0] * a, w[1] * a, w[2] * a),
            (w[3] * b, w[4] * b, w[5] * b),
        )

    def split_motion(self, m: Sequence[float]) -> tuple[V3, V3]:
        """(x, θ) of a motion in these coordinates."""
        a, b = self.a, self.b
        return (
            (m[0] / a, m[1] / a, m[2] / a),
            (m[3] / b, m[4] / b, m[5] / b),
        )


class MasterWrenchPort:
    """The master port over the whole wrench (`pc`: a `MasterPassivity` built for unit
    mass, e.g. `master_port(m, wrench=True)`). `step(f, c, x, R, dt_s)` takes the force
    (N) and moment (N·m) about to be shown, the hand's position (m) and orientation (a
    rotation) now, all in the master frame, and the time since the previous step; returns
    the force and moment to show until the next step. `pc.asked_n` / `pc.shown_n` are the
    forces' magnitudes (N), as the translational port's."""

    def __init__(self, pc: MasterPassivity, coords: WrenchCoords) -> None:
        self.pc = pc
        self.coords = coords
        self.track = RotationTrack()

    def reset(self, epoch: int) -> None:
        self.pc.reset(epoch)
        self.track.reset()

    def step(
        self,
        f: Iterable[float],
        c: Iterable[float],
        x: Iterable[float],
        R: ArrayLike,
        dt_s: float,
    ) -> tuple[V3, V3]:
        cs = self.coords
        f_in = [float(v) for v in f]
        theta = self.track.update(R)
        out = self.pc.step(cs.wrench(f_in, c), cs.motion(x, theta), dt_s)
        f_out, c_out = cs.split_wrench(out)
        self.pc.asked_n = math.hypot(*f_in)
        self.pc.shown_n = math.hypot(*f_out)
        return f_out, c_out
