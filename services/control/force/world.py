"""The simulated wrist's world: the workcell scene at its live poses, as plain-float geometry.

The workcell service (services/world/workcell/) moves objects: the gripper carries them, they
fall, stack and topple, and it publishes where they are on `workcell/state`. The scene
description (`services.world.workcell.scene`: the floor, the fixtures, each object's shape and
stiffness) is the one the workcell simulates; `ContactWorld.build(scene, poses)` places each
object at its pose from that message (position and orientation: a toppled block lies on its
side) and precomputes, once per message, what the per-sample contact query needs: each
solid's frame as 9 floats, its half sizes, and a world-aligned bounding box grown by the
probe radius for a cheap rejection. `force(x, y, z)` then sums the penalty forces on the
probe sphere exactly as `Scene.contacts` does for an axis-aligned scene
(tests/control/force/test_world.py checks it against the scene), in plain floats.

`CarriedLoad` is what the gripper holds: its mass from the scene description (a block's
volume × `block_density_kg_m3`; a bottle's `bottle_mass_kg` plus the liquid still in it),
its centre of mass and a few points of its surface (`surface_points`), in the tool frame,
where it touches the rest of the world.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from services.control.force.kernel import F3, M3, ZERO3, mul, transpose
from services.world.workcell.scene import Box, Cylinder, Scene

IDENTITY9: M3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
LIQUID_KG_PER_ML = 1e-3


@dataclass(frozen=True, slots=True)
class Pose:
    """Where an object is: `p` (m, world: a box's centre, a cylinder's base centre, as
    `workcell/state`), `R` (world←object, 9 row-major floats)."""

    p: F3
    R: M3 = IDENTITY9


class _Solid:
    """One box or cylinder in world space, precomputed for the per-sample query."""

    __slots__ = ("R", "Rt", "axis_aligned", "bhi", "blo", "cyl", "h", "hi", "k", "lo", "name", "o")

    def __init__(self, solid: Box | Cylinder, pose: Pose | None, radius: float) -> None:
        self.name = solid.name
        self.k = solid.stiffness_n_per_m
        self.cyl = isinstance(solid, Cylinder)
        if isinstance(solid, Box):
            o = pose.p if pose is not None else solid.center
            self.h: F3 = (0.5 * solid.size[0], 0.5 * solid.size[1], 0.5 * solid.size[2])
        else:
            o = pose.p if pose is not None else solid.base
            self.h = (solid.radius, solid.radius, solid.height)  # radius, -, height
        self.o: F3 = (float(o[0]), float(o[1]), float(o[2]))
        self.R: M3 = pose.R if pose is not None else IDENTITY9
        self.Rt: M3 = transpose(self.R)
        self.axis_aligned = self.R == IDENTITY9
        # A box's faces: in the world for an axis-aligned box (as the scene computes them,
        # so ties between faces break the same way), else in its own frame.
        hx, hy, hz = self.h
        if self.axis_aligned and not self.cyl:
            ox, oy, oz = self.o
            self.blo: F3 = (ox - hx, oy - hy, oz - hz)
            self.bhi: F3 = (ox + hx, oy + hy, oz + hz)
        else:
            self.blo, self.bhi = (-hx, -hy, -hz), (hx, hy, hz)
        # World-aligned bounds of the solid grown by the probe radius (broad phase).
        if self.cyl:
            r, hgt = self.h[0], self.h[2]
            local = [(x, y, z) for x in (-r, r) for y in (-r, r) for z in (0.0, hgt)]
        else:
            hx, hy, hz = self.h
            local = [(x, y, z) for x in (-hx, hx) for y in (-hy, hy) for z in (-hz, hz)]
        pts = [mul(self.R, *v) for v in local]
        self.lo: F3 = tuple(self.o[i] + min(q[i] for q in pts) - radius for i in range(3))  # type: ignore[assignment]
        self.hi: F3 = tuple(self.o[i] + max(q[i] for q in pts) + radius for i in range(3))  # type: ignore[assignment]

    def force(self, x: float, y: float, z: float, radius: float) -> F3 | None:
        """The penalty force (N, world) on a probe sphere at (x, y, z), None if apart."""
        lo, hi = self.lo, self.hi
        if not (lo[0] < x < hi[0] and lo[1] < y < hi[1] and lo[2] < z < hi[2]):
            return None
        if self.axis_aligned and not self.cyl:
            return _box(self, x, y, z, radius)
        dx, dy, dz = x - self.o[0], y - self.o[1], z - self.o[2]
        if not self.axis_aligned:
            dx, dy, dz = mul(self.Rt, dx, dy, dz)
        n = _cylinder(self, dx, dy, dz, radius) if self.cyl else _box(self, dx, dy, dz, radius)
        if n is None:
            return None
        if not self.axis_aligned:
            n = mul(self.R, *n)
        return n


def _box(s: _Solid, x: float, y: float, z: float, radius: float) -> F3 | None:
    """`scene._box_contact` between the faces `blo`, `bhi`: k·depth·normal."""
    (lx, ly, lz), (hx, hy, hz) = s.blo, s.bhi
    cx = lx if x < lx else hx if x > hx else x
    cy = ly if y < ly else hy if y > hy else y
    cz = lz if z < lz else hz if z > hz else z
    ex, ey, ez = x - cx, y - cy, z - cz
    d2 = ex * ex + ey * ey + ez * ez
    if d2 > 0.0:
        dist = math.sqrt(d2)
        if dist >= radius:
            return None
        g = s.k * (radius - dist) / dist
        return (g * ex, g * ey, g * ez)
    # Centre inside: out through the nearest face (first of −x, −y, −z, +x, +y, +z on ties).
    faces = (x - lx, y - ly, z - lz, hx - x, hy - y, hz - z)
    k = min(range(6), key=faces.__getitem__)
    g = s.k * (faces[k] + radius) * (-1.0 if k < 3 else 1.0)
    return (g, 0.0, 0.0) if k % 3 == 0 else (0.0, g, 0.0) if k % 3 == 1 else (0.0, 0.0, g)


def _cylinder(s: _Solid, x: float, y: float, z: float, radius: float) -> F3 | None:
    """`scene._cylinder_contact` in the cylinder's frame (origin at its base centre)."""
    r_c, _, height = s.h
    r_xy = math.hypot(x, y)
    out_r = r_xy - r_c
    out_z = max(-z, z - height)
    up = 1.0 if z > height else -1.0
    if out_r > 0.0 and out_z > 0.0:
        dist = math.hypot(out_r, out_z)
        if dist >= radius:
            return None
        g = s.k * (radius - dist) / dist
        return (g * out_r * x / r_xy, g * out_r * y / r_xy, g * out_z * up)
    if out_r > 0.0 or out_z > 0.0:
        dist = out_r if out_r > 0.0 else out_z
        if dist >= radius:
            return None
        g = s.k * (radius - dist)
        if out_r > 0.0:
            return (g * x / r_xy, g * y / r_xy, 0.0)
        return (0.0, 0.0, g * up)
    if -out_r < -out_z:
        g = s.k * (-out_r + radius)
        return (g * x / r_xy, g * y / r_xy, 0.0) if r_xy > 1e-12 else (g, 0.0, 0.0)
    g = s.k * (-out_z + radius) * (1.0 if z > 0.5 * height else -1.0)
    return (0.0, 0.0, g)


class ContactWorld:
    """The scene's solids at given poses, for a probe sphere of `radius` (m).

    Immutable once built: the sampling thread swaps the reference when a new
    `workcell/state` arrives. `exclude` names a solid that is not touched (the one in the
    gripper: the palm holds it, it does not push the probe).
    """

    __slots__ = ("_floor_k", "_floor_z", "_solids", "radius")

    def __init__(self, scene: Scene, radius: float, solids: list[_Solid]) -> None:
        self.radius = radius
        self._floor_z = scene.floor_z
        self._floor_k = scene.floor_stiffness_n_per_m
        self._solids = tuple(solids)

    @classmethod
    def build(
        cls,
        scene: Scene,
        radius: float,
        poses: Mapping[str, Pose] | None = None,
        exclude: str = "",
    ) -> ContactWorld:
        """`scene` with each solid named in `poses` at that pose (others where the scene
        puts them), without `exclude`."""
        poses = poses or {}
        solids = [_Solid(s, poses.get(s.name), radius) for s in scene.solids() if s.name != exclude]
        return cls(scene, radius, solids)

    def near(self, x: float, y: float, z: float, reach: float) -> tuple[_Solid, ...] | None:
        """The solids whose bounds come within `reach` (m) of (x, y, z) per axis, or None
        when neither they nor the floor do: the broad phase for a carried object."""
        found = tuple(
            s
            for s in self._solids
            if s.lo[0] - reach < x < s.hi[0] + reach
            and s.lo[1] - reach < y < s.hi[1] + reach
            and s.lo[2] - reach < z < s.hi[2] + reach
        )
        if not found and z - reach > self._floor_z:
            return None
        return found

    def point_force(self, solids: tuple[_Solid, ...], x: float, y: float, z: float) -> F3:
        """The contact force (N, world) on the point (x, y, z) from `solids` (from `near`)
        and the floor."""
        fx = fy = fz = 0.0
        depth = self._floor_z - z
        if depth > 0.0:
            fz = self._floor_k * depth
        for s in solids:
            f = s.force(x, y, z, 0.0)
            if f is not None:
                fx += f[0]
                fy += f[1]
                fz += f[2]
        return (fx, fy, fz)

    def force(self, x: float, y: float, z: float, radius: float | None = None) -> F3:
        """The summed contact force (N, world) on the probe sphere centred at (x, y, z)
        (of `radius`, m, at most the world's; None: the world's)."""
        r = self.radius if radius is None else radius
        fx = fy = fz = 0.0
        depth = self._floor_z - (z - r)
        if depth > 0.0:
            fz = self._floor_k * depth
        for s in self._solids:
            f = s.force(x, y, z, r)
            if f is not None:
                fx += f[0]
                fy += f[1]
                fz += f[2]
        return (fx, fy, fz)


def carried_mass_kg(
    solid: Box | Cylinder,
    liquid_ml: float | None,
    block_density_kg_m3: float,
    bottle_mass_kg: float,
) -> float:
    """The mass (kg) of a carried object: a box of uniform density; a bottle and its liquid."""
    if isinstance(solid, Box):
        sx, sy, sz = solid.size
        return block_density_kg_m3 * sx * sy * sz
    # No more liquid than the bottle holds, whatever a message says.
    full_ml = math.pi * solid.radius**2 * solid.height * 1e6
    return bottle_mass_kg + LIQUID_KG_PER_ML * min(full_ml, max(0.0, liquid_ml or 0.0))


@dataclass(frozen=True, slots=True)
class CarriedLoad:
    """The object in the gripper: `mass_kg`, centre of mass `com_t` (m, tool frame, from the
    tool point). It moves rigidly with the tool, so `com_t` holds while it is held."""

    name: str
    mass_kg: float
    com_t: F3 = ZERO3
    points_t: tuple[F3, ...] = ()
    """Contact points on its surface (m, tool frame): its corners and the centre of its base."""
    centre_t: F3 = ZERO3
    """The centre of `points_t` (m, tool frame) …"""
    reach_m: float = 0.0
    """… and how far from it the farthest point is (m): the broad phase's sphere."""


BASE_POINTS = 5
"""`surface_points` on an object's base: 4 corners (rim points) and its centre."""


def surface_points(kind: str, p: F3, R: M3, size: F3) -> tuple[F3, ...]:
    """Where a carried object touches things first (m, world): a box's 8 corners and the
    centre of its base; a cylinder's base centre and 4 points on each rim. `p`, `R`, `size`
    as `workcell/state` gives them (a box's centre, a cylinder's base centre)."""
    hx, hy, h = 0.5 * size[0], 0.5 * size[1], size[2]
    if kind == "box":
        hz = 0.5 * h
        local = [(x, y, z) for x in (-hx, hx) for y in (-hy, hy) for z in (-hz, hz)]
        local.append((0.0, 0.0, -hz))
    else:
        rim = [(hx, 0.0), (-hx, 0.0), (0.0, hy), (0.0, -hy)]
        local = [(x, y, z) for z in (0.0, h) for x, y in rim]
        local.append((0.0, 0.0, 0.0))
    out = []
    for v in local:
        w = mul(R, *v)
        out.append((p[0] + w[0], p[1] + w[1], p[2] + w[2]))
    return tuple(out)
