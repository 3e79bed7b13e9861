"""The workcell's physics for the three tasks: gripper, carrying, falling, stacking, liquid.

Pure and deterministic: `WorkcellSim.step(tool_p, tool_R, grip, dt_s)` advances the movable
objects of a `Scene` by `dt_s` given the tool pose (world, m; R world←tool) and the gripper
command from `robot/state`. Not thread-safe: the service calls it under one lock.

The model (docs/tasks.md, "The simulated workcell", equations W1–W4):

- Gripper (W1): a parallel gripper whose tool point is the centre of its palm; its fingers
  close below it. Closing it (grip rising above `close_threshold`) with the palm just above
  an object's top, near its axis and with the tool z axis along the object's downward axis,
  attaches the object kinematically: it then moves rigidly with the tool. Opening it
  releases the object. Closing on nothing grasps nothing, a gripper already closed cannot
  pick anything up, and neither can one whose object has something resting on it.
- Falling and support (W2): a released object falls (gravity, no air) onto the highest
  surface under its footprint: the table, another object or the floor. It comes to rest
  there if its centre is over that surface, otherwise it slides off the edge and falls on.
  It rests upright, its yaw kept, unless it landed tilted beyond its tipping angle; then it
  lies on its side (`toppled`). A block landing on a block within `snap_xy_m` and
  `snap_yaw_deg` of it is stacked exactly on it. An object whose support goes away falls.
- Liquid (W3, W4): an open-topped cylinder tilted by θ holds at most V_max(θ); liquid above
  that spills with a rate proportional to the excess.
- Collisions: a carried object that sinks into another solid (bounding boxes) by more
  than `collision_tol_m` is counted and reported; the model does not push back (the force
  sensor's model of contact is the tool's, services/control/force/sim_sensor.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.bus.errors import ConfigError
from services.geometry import rot_z, rotation_about
from services.world.workcell.scene import Box, Cylinder, Scene

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]
Solid = Box | Cylinder
Phase = Literal["resting", "held", "falling", "toppled"]
SimEventKind = Literal["grasp", "missed", "release", "settled", "toppled", "collision", "spill"]

FLOOR = "floor"
_EPS_M = 1e-9
_TOUCH_M = 1e-5
"""Footprints overlapping by less than this only touch: a block slides past a neighbour
into a gap of its own width."""
_CLEAR_M = 1e-7
"""How far past an edge a sliding object ends (≪ _TOUCH_M)."""
_LEVEL_M = 1e-3
"""Surfaces within this of the same height carry a landing object together."""
_LYING_RAD = math.pi / 2
_QUAD_POINTS = 256


@dataclass(frozen=True, slots=True)
class PhysicsParams:
    """The workcell model's parameters (units in the names).

    close_threshold: the gripper is closed while grip > this (0 open … 1 closed).
    grasp_xy_m: the palm centre must be within this of the object's axis (W1).
    grasp_gap_m: … and between the object's top and this far above it (W1).
    max_grasp_angle_deg: … with the tool z axis within this of the object's downward axis.
    snap_xy_m, snap_yaw_deg: a block landing on a block this close is stacked exactly (W2).
    gravity_mps2: free fall acceleration.
    spill_rate_1_s: k of W4, the spill rate per unit of excess volume.
    collision_tol_m: a carried object sinking deeper than this into a solid is a collision.
    """

    close_threshold: float = 0.5
    grasp_xy_m: float = 0.012
    grasp_gap_m: float = 0.02
    max_grasp_angle_deg: float = 20.0
    snap_xy_m: float = 0.01
    snap_yaw_deg: float = 10.0
    gravity_mps2: float = 9.81
    spill_rate_1_s: float = 20.0
    collision_tol_m: float = 0.001

    def __post_init__(self) -> None:
        if not 0.0 < self.close_threshold < 1.0:
            raise ConfigError("workcell.physics.close_threshold", "must be within (0, 1)")
        for key in ("grasp_xy_m", "grasp_gap_m", "gravity_mps2", "spill_rate_1_s"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v > 0.0):
                raise ConfigError(f"workcell.physics.{key}", f"must be > 0, got {v}")
        for key in ("snap_xy_m", "snap_yaw_deg", "collision_tol_m"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v >= 0.0):
                raise ConfigError(f"workcell.physics.{key}", f"must be ≥ 0, got {v}")
        if not 0.0 < self.max_grasp_angle_deg <= 90.0:
            raise ConfigError("workcell.physics.max_grasp_angle_deg", "must be within (0, 90]")


@dataclass(frozen=True, slots=True)
class SimEvent:
    """Something that happened in the workcell: `kind`, the object, a message, data."""

    kind: SimEventKind
    body: str
    message: str
    data: dict[str, Any] = field(default_factory=dict)


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


# --- geometry (pure) -----------------------------------------------------------------------
def half_extents(solid: Solid) -> Vec:
    """Half sizes (m) of the object's box in its own frame: a cylinder's bounding box."""
    if isinstance(solid, Box):
        return 0.5 * np.asarray(solid.size, dtype=float)
    return np.array([solid.radius, solid.radius, 0.5 * solid.height])


def centre_of(solid: Solid, p: ArrayLike, R: ArrayLike) -> Vec:
    """The object's geometric centre (m, world) from its origin `p` and orientation `R`."""
    p = np.asarray(p, dtype=float)
    if isinstance(solid, Box):
        return p
    return p + np.asarray(R, dtype=float) @ np.array([0.0, 0.0, 0.5 * solid.height])


def top_centre(solid: Solid, p: ArrayLike, R: ArrayLike) -> Vec:
    """The centre of the object's top face (m, world)."""
    up = np.asarray(R, dtype=float) @ np.array([0.0, 0.0, half_extents(solid)[2]])
    return centre_of(solid, p, R) + up


def aabb(solid: Solid, p: ArrayLike, R: ArrayLike) -> tuple[Vec, Vec]:
    """World axis-aligned bounds (lo, hi) of the object's (bounding) box: c ∓ |R|·h."""
    c = centre_of(solid, p, R)
    reach = np.abs(np.asarray(R, dtype=float)) @ half_extents(solid)
    return c - reach, c + reach


def tilt_of(R: ArrayLike) -> float:
    """The angle (rad) between the object's axis R·z and the world's z axis."""
    return float(math.acos(min(1.0, max(-1.0, float(np.asarray(R, dtype=float)[2, 2])))))


def yaw_of(R: ArrayLike) -> float:
    """The heading (rad) of the object's x axis projected on the horizontal plane."""
    m = np.asarray(R, dtype=float)
    x = m[:, 0] if abs(m[2, 0]) < 0.999 else m[:, 1]
    return float(math.atan2(x[1], x[0]))


def tipping_angle(solid: Solid) -> float:
    """The tilt (rad) beyond which an object standing on its base falls over: its centre
    of mass passes the edge of the base, atan(half base width / half height)."""
    he = half_extents(solid)
    return float(math.atan2(min(he[0], he[1]), he[2]))


def in_grasp_region(
    solid: Solid,
    p: ArrayLike,
    R: ArrayLike,
    tool_p: ArrayLike,
    tool_R: ArrayLike,
    params: PhysicsParams,
) -> bool:
    """W1: the palm (tool point) is within `grasp_xy_m` of the object's axis, between its
    top and `grasp_gap_m` above it, and the tool z axis is within `max_grasp_angle_deg`
    of the object's downward axis."""
    Ro = np.asarray(R, dtype=float)
    rel = Ro.T @ (np.asarray(tool_p, dtype=float) - top_centre(solid, p, Ro))
    if math.hypot(rel[0], rel[1]) > params.grasp_xy_m:
        return False
    if not -_EPS_M <= rel[2] <= params.grasp_gap_m:
        return False
    tool_z = np.asarray(tool_R, dtype=float)[:, 2]
    cos_angle = float(tool_z @ -Ro[:, 2])
    return cos_angle >= math.cos(math.radians(params.max_grasp_angle_deg))


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


def penetration_m(a_lo: Vec, a_hi: Vec, b_lo: Vec, b_hi: Vec) -> float:
    """How deep two boxes overlap (m): the smallest overlap along an axis, 0 if apart."""
    overlap = np.minimum(a_hi, b_hi) - np.maximum(a_lo, b_lo)
    return float(max(0.0, float(np.min(overlap))))


def _overlap_xy(a_lo: Vec, a_hi: Vec, b_lo: Vec, b_hi: Vec) -> bool:
    """Footprints that overlap by more than touching (_TOUCH_M): one can carry the other."""
    return bool(
        min(a_hi[0], b_hi[0]) - max(a_lo[0], b_lo[0]) > _TOUCH_M
        and min(a_hi[1], b_hi[1]) - max(a_lo[1], b_lo[1]) > _TOUCH_M
    )


def _wrap(a: float, period: float) -> float:
    """`a` wrapped into (−period/2, period/2]."""
    return a - period * math.floor(a / period + 0.5)


# --- the simulation ------------------------------------------------------------------------
class _Body:
    """A movable object's mutable state (internal to WorkcellSim)."""

    __slots__ = (
        "R",
        "colliding",
        "liquid_m3",
        "max_tilt_rad",
        "on",
        "p",
        "phase",
        "solid",
        "spilled_m3",
        "spilling",
        "tMo",
        "v_z",
    )

    def __init__(self, solid: Solid) -> None:
        self.solid = solid
        if isinstance(solid, Box):
            self.p = np.asarray(solid.center, dtype=float)
        else:
            self.p = np.asarray(solid.base, dtype=float)
        self.R = np.eye(3)
        self.phase: Phase = "resting"
        self.on = ""
        self.v_z = 0.0
        self.tMo: tuple[Vec, Mat] | None = None
        self.liquid_m3 = 0.0
        if isinstance(solid, Cylinder) and solid.liquid_height_m > 0.0:
            self.liquid_m3 = math.pi * solid.radius**2 * min(solid.liquid_height_m, solid.height)
        self.spilled_m3 = 0.0
        self.max_tilt_rad = 0.0
        self.spilling = False
        self.colliding = False

    @property
    def name(self) -> str:
        return self.solid.name

    def bounds(self) -> tuple[Vec, Vec]:
        return aabb(self.solid, self.p, self.R)

    def centre(self) -> Vec:
        return centre_of(self.solid, self.p, self.R)

    @property
    def supports(self) -> bool:
        """Whether something may rest on it now."""
        return self.phase in ("resting", "toppled")


@dataclass(frozen=True, slots=True)
class _Support:
    name: str
    lo: Vec
    hi: Vec
    body: _Body | None


class WorkcellSim:
    """The movable objects of `scene` under the gripper (see the module docstring).

    `step()` returns what happened as `SimEvent`s. `bodies()` is the state now; `counters`
    counts grasps, misses, releases, collisions and topples; `max_penetration_m` is the
    deepest a carried object sank into a solid.
    """

    def __init__(self, scene: Scene, params: PhysicsParams | None = None) -> None:
        self.scene = scene
        self.params = params or PhysicsParams()
        self._fixed = tuple(s for s in scene.solids() if not s.movable)
        self.reset()

    def reset(self, gripper_closed: bool = False) -> None:
        """Every object back where the scene puts it, at rest; the gripper empty, closed or
        open as said (a closed one must open before it can grasp)."""
        self._bodies = [_Body(s) for s in self.scene.movables()]
        self._closed = gripper_closed
        self.held: str | None = None
        self.t_s = 0.0
        self.counters: dict[str, int] = dict.fromkeys(
            ("grasps", "missed", "releases", "collisions", "toppled"), 0
        )
        self.max_penetration_m = 0.0
        self._settle_all()

    # --- queries ---------------------------------------------------------------------------
    def body(self, name: str) -> BodyState:
        for b in self._bodies:
            if b.name == name:
                return self._snapshot(b)
        raise KeyError(name)

    def bodies(self) -> list[BodyState]:
        return [self._snapshot(b) for b in self._bodies]

    @property
    def gripper_closed(self) -> bool:
        return self._closed

    def current_scene(self) -> Scene:
        """The scene with every object at its current place (axis-aligned, upright: see
        `Scene.moved`), for a contact model or renderer that wants the dynamic scene."""
        return self.scene.moved({b.name: tuple(b.p) for b in self._bodies})

    def _snapshot(self, b: _Body) -> BodyState:
        s = b.solid
        size = (
            np.asarray(s.size, dtype=float)
            if isinstance(s, Box)
            else np.array([2 * s.radius, 2 * s.radius, s.height])
        )
        return BodyState(
            name=b.name,
            kind="box" if isinstance(s, Box) else "cylinder",
            p=b.p.copy(),
            R=b.R.copy(),
            phase=b.phase,
            on=b.on,
            size=size,
            liquid_m3=b.liquid_m3,
            spilled_m3=b.spilled_m3,
            tilt_rad=tilt_of(b.R),
            max_tilt_rad=b.max_tilt_rad,
        )

    # --- the step ----------------------------------------------------------------------------
    def step(
        self, tool_p: ArrayLike, tool_R: ArrayLike, grip: float | None, dt_s: float
    ) -> list[SimEvent]:
        """Advance by `dt_s` (s) with the tool at (tool_p, tool_R) (world) and the gripper
        commanded to `grip` (0 open … 1 closed; None: unchanged)."""
        if not dt_s >= 0.0:
            raise ValueError("dt_s must be ≥ 0")
        p_t = np.asarray(tool_p, dtype=float).reshape(3)
        R_t = np.asarray(tool_R, dtype=float).reshape(3, 3)
        events: list[SimEvent] = []
        self.t_s += dt_s
        if grip is not None:
            closed = grip > self.params.close_threshold
            if closed and not self._closed:
                events += self._close(p_t, R_t)
            elif not closed and self._closed:
                events += self._open()
            self._closed = closed
        held = self._held_body()
        if held is not None:
            assert held.tMo is not None
            o_p, o_R = held.tMo
            held.p = p_t + R_t @ o_p
            held.R = R_t @ o_R
            events += self._collisions(held)
        for b in self._bodies:
            if b.supports:
                support = self._find(b.on)  # None: a fixture or the floor, which stay
                if support is not None and not support.supports:
                    b.phase, b.on, b.v_z = "falling", "", 0.0
        for b in sorted(self._bodies, key=lambda x: float(x.bounds()[0][2])):
            if b.phase == "falling":
                events += self._fall(b, dt_s)
        for b in self._bodies:
            events += self._liquid(b, dt_s)
        return events

    def _held_body(self) -> _Body | None:
        return None if self.held is None else self._find(self.held)

    def _find(self, name: str) -> _Body | None:
        for b in self._bodies:
            if b.name == name:
                return b
        return None

    def _close(self, p_t: Vec, R_t: Vec) -> list[SimEvent]:
        if self.held is not None:
            return []
        best: tuple[float, _Body] | None = None
        covered = {b.on for b in self._bodies if b.supports}
        for b in self._bodies:
            if b.name in covered:
                continue  # something rests on its top: the palm cannot get there
            if b.supports and in_grasp_region(b.solid, b.p, b.R, p_t, R_t, self.params):
                d = float(np.linalg.norm(p_t - top_centre(b.solid, b.p, b.R)))
                if best is None or d < best[0]:
                    best = (d, b)
        if best is None:
            self.counters["missed"] += 1
            return [
                SimEvent(
                    "missed",
                    "",
                    "the gripper closed on nothing",
                    {"tool_p": [float(x) for x in p_t]},
                )
            ]
        b = best[1]
        b.tMo = (R_t.T @ (b.p - p_t), R_t.T @ b.R)
        b.phase, b.on, b.v_z = "held", "", 0.0
        self.held = b.name
        self.counters["grasps"] += 1
        return [SimEvent("grasp", b.name, f"{b.name} grasped", {"p": _floats(b.p)})]

    def _open(self) -> list[SimEvent]:
        b = self._held_body()
        if b is None:
            return []
        self.held = None
        b.tMo = None
        b.phase, b.on, b.v_z = "falling", "", 0.0
        b.colliding = False
        self.counters["releases"] += 1
        return [SimEvent("release", b.name, f"{b.name} released", {"p": _floats(b.p)})]

    def _collisions(self, b: _Body) -> list[SimEvent]:
        lo, hi = b.bounds()
        deepest, into = max(0.0, self.scene.floor_z - float(lo[2])), FLOOR
        for s in self._supports(exclude=b):
            d = penetration_m(lo, hi, s.lo, s.hi)
            if d > deepest:
                deepest, into = d, s.name
        self.max_penetration_m = max(self.max_penetration_m, deepest)
        colliding = deepest > self.params.collision_tol_m
        events: list[SimEvent] = []
        if colliding and not b.colliding:
            self.counters["collisions"] += 1
            events.append(
                SimEvent(
                    "collision",
                    b.name,
                    f"{b.name} pushed {deepest * 1e3:.1f} mm into {into}",
                    {"into": into, "depth_m": deepest},
                )
            )
        b.colliding = colliding
        return events

    def _supports(self, exclude: _Body | None = None) -> list[_Support]:
        out = []
        for s in self._fixed:
            lo, hi = aabb(s, _origin(s), np.eye(3))
            out.append(_Support(s.name, lo, hi, None))
        for b in self._bodies:
            if b is not exclude and b.supports:
                lo, hi = b.bounds()
                out.append(_Support(b.name, lo, hi, b))
        return out

    def _support_under(self, b: _Body) -> _Support | None:
        """The highest surface under the body's footprint whose top is below the body's
        mid-height: at or below its bottom, or above it when the body was released pushed
        into it (it then comes to rest on top, not inside)."""
        lo, hi = b.bounds()
        mid = 0.5 * float(lo[2] + hi[2])
        best: _Support | None = None
        for s in self._supports(exclude=b):
            below = s.hi[2] <= max(lo[2] + 1e-6, mid) and _overlap_xy(lo, hi, s.lo, s.hi)
            if below and (best is None or s.hi[2] > best.hi[2]):
                best = s
        return best

    def _fall(self, b: _Body, dt_s: float) -> list[SimEvent]:
        support = self._support_under(b)
        top = self.scene.floor_z if support is None else float(support.hi[2])
        lo, _hi = b.bounds()
        gap = float(lo[2]) - top
        b.v_z += self.params.gravity_mps2 * dt_s
        drop = b.v_z * dt_s
        if drop < gap - _EPS_M:
            b.p = b.p - np.array([0.0, 0.0, drop])
            return []
        return self._land(b, support, top)

    def _land(self, b: _Body, support: _Support | None, top: float) -> list[SimEvent]:
        c = b.centre()
        if support is not None:
            # Every surface at the landing height under the footprint carries it together
            # (a block bridging a gap); it stays if its centre is over what they span.
            lo, hi = b.bounds()
            level = [
                s
                for s in self._supports(exclude=b)
                if abs(float(s.hi[2]) - top) <= _LEVEL_M and _overlap_xy(lo, hi, s.lo, s.hi)
            ]
            span_lo = np.min([s.lo for s in level] + [support.lo], axis=0)
            span_hi = np.max([s.hi for s in level] + [support.hi], axis=0)
            over = bool(
                span_lo[0] - _EPS_M <= c[0] <= span_hi[0] + _EPS_M
                and span_lo[1] - _EPS_M <= c[1] <= span_hi[1] + _EPS_M
            )
            if not over and self._slide_off(b, span_lo, span_hi, top):
                return []
        b.v_z = 0.0
        tilt = tilt_of(b.R)
        if tilt > tipping_angle(b.solid):
            z = b.R[:, 2]
            axis = np.cross(np.array([0.0, 0.0, 1.0]), z)
            if np.linalg.norm(axis) < 1e-9:
                axis = np.array([1.0, 0.0, 0.0])
            b.R = rotation_about(axis, _LYING_RAD - tilt) @ b.R
            phase: Phase = "toppled"
        else:
            b.R = rot_z(yaw_of(b.R))
            phase = "resting"
        if phase == "resting" and support is not None and support.body is not None:
            self._snap(b, support.body)
        lo, _ = b.bounds()
        b.p = b.p + np.array([0.0, 0.0, top - float(lo[2])])
        b.phase = phase
        b.on = FLOOR if support is None else support.name
        if phase == "toppled":
            self.counters["toppled"] += 1
            return [
                SimEvent(
                    "toppled",
                    b.name,
                    f"{b.name} fell over on {b.on}",
                    {"on": b.on, "p": _floats(b.p)},
                )
            ]
        return [
            SimEvent(
                "settled", b.name, f"{b.name} rests on {b.on}", {"on": b.on, "p": _floats(b.p)}
            )
        ]

    def _slide_off(self, b: _Body, s_lo: Vec, s_hi: Vec, top: float) -> bool:
        """The centre is past the edge of the supports (they span s_lo…s_hi): the body
        slides off that edge, to the nearest side clear of them, and keeps falling. If
        every way off runs into a surface at that height or higher, it is wedged and rests
        where it is (False: it did not move)."""
        lo, hi = b.bounds()
        c = b.centre()
        moves = []
        for k in (0, 1):
            mid = 0.5 * (s_lo[k] + s_hi[k])
            d = s_hi[k] - lo[k] + _CLEAR_M if c[k] >= mid else s_lo[k] - hi[k] - _CLEAR_M
            move = np.zeros(3)
            move[k] = d
            moves.append(move)
        moves.sort(key=lambda m: float(np.abs(m).sum()))
        for move in moves:
            n_lo, n_hi = lo + move, hi + move
            blocked = any(
                float(s.hi[2]) > top - _LEVEL_M and _overlap_xy(n_lo, n_hi, s.lo, s.hi)
                for s in self._supports(exclude=b)
            )
            if not blocked:
                b.p = b.p + move
                return True
        return False

    def _snap(self, b: _Body, base: _Body) -> None:
        if not (isinstance(b.solid, Box) and isinstance(base.solid, Box)):
            return
        if base.phase != "resting":
            return
        cb, cs = b.centre(), base.centre()
        if math.hypot(cb[0] - cs[0], cb[1] - cs[1]) > self.params.snap_xy_m:
            return
        square = abs(b.solid.size[0] - b.solid.size[1]) < 1e-9
        period = math.pi / 2 if square else math.pi
        d = _wrap(yaw_of(b.R) - yaw_of(base.R), period)
        if abs(d) > math.radians(self.params.snap_yaw_deg):
            return
        b.R = rot_z(yaw_of(b.R) - d)
        b.p = np.array([cs[0], cs[1], b.p[2]])

    def _liquid(self, b: _Body, dt_s: float) -> list[SimEvent]:
        tilt = tilt_of(b.R)
        b.max_tilt_rad = max(b.max_tilt_rad, tilt)
        s = b.solid
        if not isinstance(s, Cylinder) or b.liquid_m3 <= 0.0:
            b.spilling = False
            return []
        v_max = holdable_volume_m3(s.radius, s.height, tilt)
        before = b.liquid_m3
        b.liquid_m3 = spill_step(before, v_max, self.params.spill_rate_1_s, dt_s)
        b.spilled_m3 += before - b.liquid_m3
        spilling = before > v_max
        events = []
        if spilling and not b.spilling:
            events.append(
                SimEvent(
                    "spill",
                    b.name,
                    f"{b.name} spills: tilted {math.degrees(tilt):.1f}°",
                    {"tilt_deg": math.degrees(tilt), "spilled_m3": b.spilled_m3},
                )
            )
        b.spilling = spilling
        return events

    def _settle_all(self) -> None:
        """At start: every object rests on whatever is under it (the scene's placement)."""
        for b in sorted(self._bodies, key=lambda x: float(x.bounds()[0][2])):
            support = self._support_under(b)
            lo, _ = b.bounds()
            top = self.scene.floor_z if support is None else float(support.hi[2])
            if abs(float(lo[2]) - top) <= 1e-6:
                b.on = FLOOR if support is None else support.name
            else:
                b.phase = "falling"


def _origin(s: Solid) -> Vec:
    return np.asarray(s.center if isinstance(s, Box) else s.base, dtype=float)


def _floats(v: Vec) -> list[float]:
    return [float(x) for x in v]


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
