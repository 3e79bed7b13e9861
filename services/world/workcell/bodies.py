"""The workcell's movable objects as every view sees them, and the liquid in the bottle.

`BodyState` is one object now (the physics' answer, what `workcell/state` carries);
`tilt_of` / `yaw_of` read an orientation; W3 (`holdable_volume_m3`, `spill_tilt_rad`) and W4
(`spill_step`) are the bottle's liquid on top of the bottle's pose (docs/tasks.md);
`stack_heights` is task 2's measure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.world.workcell.scene import Box, Scene

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]
Phase = Literal["resting", "held", "falling", "toppled"]
_LYING_RAD = math.pi / 2
_QUAD_POINTS = 256


@dataclass(frozen=True, slots=True)
class BodyState:
    """One movable object now. `p`: a box's centre or a cylinder's base centre (m, world);
    `R`: world←object; `on`: what it rests on ("" while held or falling). Liquid in m³;
    angles in rad."""

    name: str
    kind: Literal["box", "cylinder"]
    p: Vec
    R: Mat
    phase: Phase
    on: str
    size: Vec
    liquid_m3: float
    spilled_m3: float
    tilt_rad: float
    max_tilt_rad: float


def tilt_of(R: ArrayLike) -> float:
    """The angle (rad) between the object's axis R·z and the world's z axis."""
    return float(math.acos(min(1.0, max(-1.0, float(np.asarray(R, dtype=float)[2, 2])))))


def yaw_of(R: ArrayLike) -> float:
    """The heading (rad) of the object's x axis projected on the horizontal plane."""
    m = np.asarray(R, dtype=float)
    x = m[:, 0] if abs(m[2, 0]) < 0.999 else m[:, 1]
    return float(math.atan2(x[1], x[0]))


def holdable_volume_m3(radius_m: float, height_m: float, tilt_rad: float) -> float:
    """W3: the most liquid (m³) an open cylinder of `radius_m`, `height_m` holds when its
    axis is tilted by `tilt_rad` from the vertical.

    The liquid's surface is level and passes through the lowest point of the rim. In the
    bottle's frame (x downhill) it is z(x) = h − (r − x)·tan θ; while it stays above the
    base (2r·tan θ ≤ h) the volume is π r² (h − r tan θ); beyond, the wedge
    ∫ 2√(r² − x²)·max(0, z(x)) dx is integrated numerically. Upright: the full cylinder;
    lying or upside down: nothing.
    """
    r, h = radius_m, height_m
    theta = abs(tilt_rad)
    if theta <= 0.0:
        return math.pi * r * r * h
    if theta >= _LYING_RAD - 1e-9:
        return 0.0
    t = math.tan(theta)
    if 2.0 * r * t <= h:
        return math.pi * r * r * (h - r * t)
    # x = −r cos φ, dx = r sin φ dφ, chord 2 r sin φ (midpoint rule on φ ∈ [0, π]).
    phi = (np.arange(_QUAD_POINTS) + 0.5) * (math.pi / _QUAD_POINTS)
    depth = np.maximum(0.0, h - r * (1.0 + np.cos(phi)) * t)
    return float(np.sum(2.0 * r * r * np.sin(phi) ** 2 * depth) * (math.pi / _QUAD_POINTS))


def spill_tilt_rad(radius_m: float, height_m: float, liquid_height_m: float) -> float:
    """The tilt (rad) at which liquid filled to `liquid_height_m` (upright) starts to spill:
    W3 solved for V_max(θ) = π r² h_l, i.e. tan θ = (h − h_l) / r (for h_l ≥ h/2)."""
    r, h, hl = radius_m, height_m, liquid_height_m
    if hl >= h:
        return 0.0
    if 2.0 * hl >= h:
        return float(math.atan2(h - hl, r))
    lo, hi = 0.0, _LYING_RAD
    target = math.pi * r * r * hl
    for _ in range(60):  # bisection: V_max decreases with the tilt
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if holdable_volume_m3(r, h, mid) > target else (lo, mid)
    return 0.5 * (lo + hi)


def spill_step(volume_m3: float, holdable_m3: float, rate_1_s: float, dt_s: float) -> float:
    """W4: dV/dt = −k·(V − V_max) while V > V_max, solved exactly over `dt_s`:
    V ← V_max + (V − V_max)·exp(−k·dt). Below V_max nothing changes."""
    if volume_m3 <= holdable_m3:
        return volume_m3
    return holdable_m3 + (volume_m3 - holdable_m3) * math.exp(-rate_1_s * dt_s)


def stack_heights(bodies: list[BodyState]) -> dict[str, int]:
    """For each resting box, how many boxes its column holds from the table up to it
    (itself included): 1 on the table, 2 on a block on the table, … (task 2's measure)."""
    by_name = {b.name: b for b in bodies}
    heights: dict[str, int] = {}

    def height(name: str, seen: frozenset[str]) -> int:
        b = by_name.get(name)
        if b is None or b.kind != "box" or b.phase != "resting" or name in seen:
            return 0
        if name not in heights:
            below = by_name.get(b.on)
            heights[name] = 1 + (height(b.on, seen | {name}) if below is not None else 0)
        return heights[name]

    for name in by_name:
        height(name, frozenset())
    return {k: v for k, v in heights.items() if v > 0}


def placed_bodies(scene: Scene) -> list[BodyState]:
    """Every movable object of `scene` where the scene places it, upright and resting (no
    physics: a view's or a test's starting state). Liquid as the scene fills it."""
    out = []
    for s in scene.movables():
        if isinstance(s, Box):
            p, size, liquid = np.asarray(s.center, dtype=float), np.asarray(s.size, float), 0.0
        else:
            p = np.asarray(s.base, dtype=float)
            size = np.array([2 * s.radius, 2 * s.radius, s.height])
            liquid = math.pi * s.radius**2 * min(s.liquid_height_m, s.height)
        out.append(
            BodyState(
                name=s.name,
                kind="box" if isinstance(s, Box) else "cylinder",
                p=p,
                R=np.eye(3),
                phase="resting",
                on="",
                size=size,
                liquid_m3=liquid,
                spilled_m3=0.0,
                tilt_rad=0.0,
                max_tilt_rad=0.0,
            )
        )
    return out
