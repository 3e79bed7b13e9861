"""The rotational port: moment against rotation, beside the force's port.

A device that displays moments (the serial master arm) closes a second loop through the
delay, the moment at the tool against the turn of the hand; a port of the force alone
leaves that one unguarded. Each side then runs a second port of its own, on the moment and
the rotation about the same point as the force's (the tool point at the slave, where
robot/force gives both; the hand's at the master), with its own energies on the wire
(`rot_e_in`, `rot_e_out`): the channel is passive when each port is, and the two do not
compete for one reservoir. (One port for the whole wrench, tried first in the simulation,
lost both contacts at 50–700 ms where either alone held: the limiter's one gain on force
and moment cut the force the hand was pressing against whenever the turn drew energy, and
the reverse; docs/passivity.md, "Rotations".)

The angles are `RotationTrack`'s: the sum of each step's spatial rotation `log(R·R_prevᵀ)`,
whose differences are the body's angular displacement step by step. The orientation's own
rotation vector `log(R)` would not do: its rate is not ω away from the identity, and a
moment times it is not work.

The slave's controller (`SlavePort`) has its geometry in metres and newtons (a back-out of
at most 2 mm, a drift of 3 cm/s, a clearance of 5 mm); its rotational port sees angles as
`θ·L` and moments as `c/L` (`ROTATION_LENGTH_M`), which keeps `c·θ` and gives those
constants a meaning in rotation. The master's (`MasterPassivity`) needs no such map: its
device model is the handle's rotational inertia in place of its mass.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from numpy.typing import ArrayLike

from services.geometry import M9, V3, add3, exp9, log9, m9, mul9, mv9, tmul9

ROTATION_LENGTH_M = 0.1
"""At the slave's rotational port a rotation of 1 rad counts as this many metres, a moment
of 1 N·m as 1/this newtons: the back-out of at most 2 mm is 0.02 rad (1.1°), the 1 N dead
band 0.1 N·m, the drift's 3 cm/s 0.3 rad/s. Energies are unchanged (joules either way)."""


def spatial_step(R_prev: M9, R: M9) -> V3:
    """The rotation from `R_prev` to `R` as a rotation vector in the spatial frame:
    log(R·R_prevᵀ) = R_prev·log(R_prevᵀ·R) (rad)."""
    return mv9(R_prev, log9(tmul9(R_prev, R)))


def rotate_towards(R: M9, w: V3) -> M9:
    """exp(w)·R: `R` turned by the spatial rotation vector `w` (rad)."""
    return mul9(exp9(w), R)


def angles_towards(theta: Sequence[float], R_now: M9, R_target: M9) -> V3:
    """The angles (`RotationTrack`'s) the body would have at `R_target`, from its angles
    `theta` at `R_now`: theta plus the spatial rotation from R_now to R_target, the short
    way (rad). What a target orientation is in a port's coordinates."""
    turn = spatial_step(R_now, R_target)
    return (theta[0] + turn[0], theta[1] + turn[1], theta[2] + turn[2])


def port_angles(theta: Iterable[float], length_m: float = ROTATION_LENGTH_M) -> list[float]:
    """Angles (rad) as the slave's rotational port sees them: θ·L (m)."""
    return [length_m * float(t) for t in theta]


def port_moment(c: Iterable[float], length_m: float = ROTATION_LENGTH_M) -> list[float]:
    """A moment (N·m) as the slave's rotational port sees it: c/L (N)."""
    return [float(x) / length_m for x in c]


def angles_of(port: Sequence[float], length_m: float = ROTATION_LENGTH_M) -> V3:
    """The angles (rad) of a position of the slave's rotational port."""
    return (port[0] / length_m, port[1] / length_m, port[2] / length_m)


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
