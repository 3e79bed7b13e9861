"""The cell's physics on MuJoCo: the arm's joint servos, the gripper, the objects, the wrist.

`CellPhysics(arm, scene)` owns one `mujoco.MjData` of the cell `build_cell` compiles
(services/world/workcell/mujoco_model.py). The caller sets the arm's joint setpoint and the
grip (`command(q, grip)`), steps (`step(n)`: n MuJoCo steps of `timestep_s`) and reads back:
the joints (`q`, `qd`), the wrist's wrench (`wrench_t`: on the tool, in the tool frame, about
the tool point, as the force service's sensors report it), the tool pose, and the objects
(`bodies()`: `BodyState`s for `workcell/state`). Contacts are MuJoCo's: the tool pushing a
block slides it, a stack stands or falls by itself, the fingers hold by friction, and the
wrist feels what the solver computes. On top of the bottle's pose, its liquid (W3, W4).

What it derives for the views and the tasks, each step from the contacts and velocities:
`held` (the object both fingers of a closed gripper squeeze), each
object's `phase` (held, resting, falling, toppled: lying past its tipping angle) and `on`
(the body or fixture under it), and `SimEvent`s (grasp, missed, release, settled, toppled,
spill). Not thread safe: the owner locks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import mujoco
import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.world.workcell.bodies import (
    BodyState,
    Phase,
    holdable_volume_m3,
    spill_step,
    tilt_of,
)
from services.world.workcell.mujoco_model import (
    FINGERS,
    CellModel,
    PhysicsParams,
    build_cell,
    object_mass_kg,
)
from services.world.workcell.scene import Box, Cylinder, Scene

Vec = NDArray[np.float64]
SimEventKind = Literal["grasp", "missed", "release", "settled", "toppled", "spill", "collision"]
COLLISION_N = 5.0
"""A carried object pressed against something else harder than its own weight and this
(N) collides (set down on its support, it presses with its weight at most)."""
FLOOR = "floor"
CLOSE_THRESHOLD = 0.5
"""The gripper is closed while grip > this (0 open … 1 closed)."""
REST_SPEED_M_S = 0.01
"""An object slower than this (and touching a support) rests."""
SPILL_RATE_1_S = 20.0
"""k of W4."""
SETTLE_STEPS = 20
PHASES_DT_S = 0.01
"""How often (s of the physics' time) the contacts are read for grasps, releases, resting
and collisions: every call of `step` cost 0.1 ms of Python, as much as MuJoCo's steps."""
SETPOINT_GAP_S = 0.05
"""Setpoints further apart than this (s) give no velocity reference."""


@dataclass(frozen=True, slots=True)
class SimEvent:
    """Something that happened in the cell: `kind`, the object, a message, data."""

    kind: SimEventKind
    body: str
    message: str
    data: dict[str, Any] = field(default_factory=dict)


class _Obj:
    __slots__ = (
        "body",
        "geom",
        "liquid_m3",
        "mass0",
        "max_tilt",
        "name",
        "on",
        "phase",
        "qadr",
        "size",
        "solid",
        "spilled_m3",
        "spilling",
        "vadr",
    )

    def __init__(self, solid: Box | Cylinder, cell: CellModel) -> None:
        m = cell.model
        self.solid = solid
        self.name = solid.name
        self.body = cell.objects[solid.name]
        self.geom = int(m.body_geomadr[self.body])
        self.qadr = cell.object_qpos[solid.name]
        self.vadr = int(m.jnt_dofadr[m.body_jntadr[self.body]])
        self.mass0 = float(m.body_mass[self.body])
        if isinstance(solid, Box):
            self.size = np.asarray(solid.size, dtype=float)
        else:
            self.size = np.array([2 * solid.radius, 2 * solid.radius, solid.height])
        self.reset()

    def reset(self) -> None:
        s = self.solid
        self.liquid_m3 = 0.0
        if isinstance(s, Cylinder) and s.liquid_height_m > 0.0:
            self.liquid_m3 = math.pi * s.radius**2 * min(s.liquid_height_m, s.height)
        self.spilled_m3 = 0.0
        self.spilling = False
        self.max_tilt = 0.0
        self.phase: Phase = "resting"
        self.on = ""


def tipping_angle(size: Vec) -> float:
    """The tilt (rad) past which an object standing on its base falls over."""
    return float(math.atan2(0.5 * min(size[0], size[1]), 0.5 * size[2]))


def _cross3(a: Sequence[float], b: Sequence[float]) -> Vec:
    """a × b of two 3-vectors given as floats (numpy's `cross` costs ~20 µs a call)."""
    ax, ay, az = a
    bx, by, bz = b
    return np.array((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx))


class CellPhysics:
    """The MuJoCo cell of `arm` (an ArmModel) in `scene` (see the module docstring).

    `q0` (rad): where the arm's joints start (default: the model's home).
    """

    def __init__(
        self,
        arm: Any,
        scene: Scene,
        params: PhysicsParams | None = None,
        q0: ArrayLike | None = None,
    ) -> None:
        self.arm = arm
        self.scene = scene
        self.params = params or PhysicsParams()
        self.cell = build_cell(arm, scene, self.params)
        self.model = self.cell.model
        self.data = mujoco.MjData(self.model)
        self._objs = [_Obj(s, self.cell) for s in scene.movables()]
        self._by_body = {o.body: o for o in self._objs}
        self._fixture_geoms = {g: n for n, g in self.cell.fixtures.items()}
        self._floor = self.model.geom("floor").id
        self._finger_geoms = {
            int(self.model.body_geomadr[self.model.body(f).id]): f for f in FINGERS
        }
        self._palm = self.model.geom("tr_palm").id
        self._geom_body: list[int] = self.model.geom_bodyid.tolist()
        fingers = [self.model.jnt_dofadr[self.model.joint(f).id] for f in FINGERS]
        self._arm_dofs = np.concatenate([self.cell.dof_adr, fingers])
        """The arm's and the gripper's degrees of freedom (what brakes stop)."""
        Rt = np.asarray(self.cell.tool_R, dtype=float).reshape(3, 3)
        self._R_et = Rt
        self._p_et = np.asarray(self.cell.tool_p, dtype=float)
        parents = self.model.body_parentid
        tool = self.cell.gripper_body

        def under_tool(b: int) -> bool:
            while b > 0:
                if b == tool:
                    return True
                b = int(parents[b])
            return False

        self._tool_bodies = [b for b in range(self.model.nbody) if under_tool(b)]
        """The gripper's subtree (palm, fingers): the bodies whose own inertia the wrist's
        reading leaves out (`wrench_t`)."""
        self._gravity = np.asarray(self.model.opt.gravity, dtype=float).copy()
        self._tool_acc = np.zeros((len(self._tool_bodies), 6))
        self._tool_masses: list[float] = self.model.body_mass[self._tool_bodies].tolist()
        self._gravity_floats: list[float] = self._gravity.tolist()
        self._p_et_floats: list[float] = self._p_et.tolist()
        self.counters: dict[str, int] = dict.fromkeys(
            ("grasps", "missed", "releases", "toppled", "collisions"), 0
        )
        self.reset(q0)

    # --- state ------------------------------------------------------------------------
    def reset(self, q: ArrayLike | None = None, grip: float = 0.0) -> None:
        """Every object back where the scene puts it, at rest; the arm at `q` (default:
        where it is now, or home at first), its servos there; the gripper at `grip`."""
        d = self.data
        q_arm = (
            np.asarray(q, dtype=float)
            if q is not None
            else (d.qpos[self.cell.qpos_adr].copy() if self.data.time > 0 else self.arm.home)
        )
        mujoco.mj_resetData(self.model, d)
        self._braked: Vec | None = None
        self._sp_t = -1.0
        self._sp_dt = 0.0
        self._ramp: tuple[Vec, Vec, float, float] | None = None
        d.qpos[self.cell.qpos_adr] = q_arm
        d.ctrl[self.cell.arm_actuators] = q_arm
        closed = grip > CLOSE_THRESHOLD
        stroke = self.cell.finger_stroke_m if closed else 0.0
        d.qpos[self.cell.finger_qpos] = stroke
        d.ctrl[self.cell.finger_actuators] = stroke
        for o in self._objs:
            o.reset()
            self.model.body_mass[o.body] = o.mass0
        self._closed = closed
        self._close_pending = False
        self._colliding = False
        self.held: str | None = None
        self._phases_t = -math.inf
        # The scene places objects exactly on their supports: a few steps let the contacts
        # take their load (a fraction of a millimetre) before anyone looks.
        # The arm stays exactly where it powers on meanwhile (braked).
        self.brake()
        self.step(SETTLE_STEPS)
        self._braked = None
        self._update_phases([])
        for o in self._objs:
            o.max_tilt = 0.0

    @property
    def t_s(self) -> float:
        """Simulated time (s)."""
        return float(self.data.time)

    @property
    def n(self) -> int:
        return self.arm.n

    @property
    def q(self) -> Vec:
        """The arm's joints (rad)."""
        return self.data.qpos[self.cell.qpos_adr].copy()

    @property
    def qd(self) -> Vec:
        """The arm's joint velocities (rad/s)."""
        return self.data.qvel[self.cell.dof_adr].copy()

    @property
    def tau(self) -> Vec:
        """The torques the arm's joint servos apply (N·m), gravity compensation aside."""
        return self.data.qfrc_actuator[self.cell.dof_adr].copy()

    @property
    def gripper_closed(self) -> bool:
        return self._closed

    def setpoint(self) -> Vec:
        """The servos' setpoint: where the last `command` goes (at the end of its
        interpolation)."""
        if self._ramp is not None:
            return self._ramp[1].copy()
        return self.data.ctrl[self.cell.arm_actuators].copy()

    def command(
        self, q: ArrayLike | None, grip: float | None = None, dt_s: float | None = None
    ) -> None:
        """The arm's joint setpoint (rad; None: unchanged) and the grip (0 open … 1 closed;
        None: unchanged). `dt_s`: the time since the previous setpoint by the sender's clock
        (default: by the simulator's). As a joint controller does, the servos interpolate
        from the previous setpoint to this one over that time (at most SETPOINT_GAP_S;
        further apart, the setpoint is taken at once), with the interpolation's velocity
        as the damping's reference."""
        if q is not None:
            self._braked = None
            d, c = self.data, self.cell
            q_new = np.asarray(q, dtype=float)
            dt = d.time - self._sp_t if dt_s is None else dt_s
            start = d.ctrl[c.arm_actuators].copy()
            if 0.0 < dt <= SETPOINT_GAP_S:
                d.ctrl[c.arm_dampers] = (q_new - start) / dt
                self._sp_dt = dt
                self._ramp = (start, q_new, float(d.time), dt)
            else:
                d.ctrl[c.arm_dampers] = 0.0
                d.ctrl[c.arm_actuators] = q_new
                self._ramp = None
            self._sp_t = d.time
        if grip is not None:
            closed = grip > CLOSE_THRESHOLD
            if closed != self._closed:
                self._close_pending = closed
            self._closed = closed
            stroke = self.cell.finger_stroke_m if closed else 0.0
            self.data.ctrl[self.cell.finger_actuators] = stroke

    def brake(self) -> None:
        """The arm's joints stop dead where they are and stay (brakes), their servos there,
        until the next joint setpoint releases them."""
        self._braked = self.data.qpos[self.cell.qpos_adr].copy()
        self._ramp = None
        self.data.ctrl[self.cell.arm_dampers] = 0.0
        self.data.qvel[self._arm_dofs] = 0.0
        self.data.ctrl[self.cell.arm_actuators] = self._braked

    @property
    def braked(self) -> bool:
        return self._braked is not None

    def tool_pose(self) -> tuple[Vec, Vec]:
        """The tool point (m, world) and R world←tool."""
        d = self.data
        b = self.cell.gripper_body
        R_we = d.xmat[b].reshape(3, 3)
        return d.xpos[b] + R_we @ self._p_et, R_we @ self._R_et

    def wrench_t(self) -> tuple[Vec, Vec]:
        """The wrench on the tool (N, N·m about the tool point, tool frame): what the
        flange's F/T sensor measures, its sign turned from MuJoCo's (the flange's force on
        the tool) to the environment's on the tool, moved to the tool point, with the
        gripper's own inertia taken out (its weight stays).

        The sensor reads m(a − g) of the gripper beside every contact: a joint move at half
        speed read 15–26 N in free space, which the decision's predictive contact watch
        cannot tell from a contact building up (it stopped the move). A real wrist reads the
        same unless its tool's inertia is compensated; the force service compensates the
        tool's weight only, so the simulated wrist gives what a compensated one would, as
        the free-space sim does (`[force] inertia` off): contacts, what is carried (with its
        inertia, through the fingers), and the gripper's weight. Its linear inertia m·a at
        each body's centre of mass, not its rotational (a few mN·m at these rates)."""
        d, c, m = self.data, self.cell, self.model
        f_e = -d.sensordata[c.force_adr : c.force_adr + 3]
        m_e = -d.sensordata[c.torque_adr : c.torque_adr + 3]
        b0 = c.gripper_body
        R_we = d.xmat[b0].reshape(3, 3)
        o = d.xpos[b0]
        acc = self._tool_acc  # one row per tool body
        bodies = self._tool_bodies
        for i, b in enumerate(bodies):
            # [rot; lin] at the body's centre of mass, world frame; MuJoCo's linear part is
            # a − g (the world accelerates up at g in its recursion)
            mujoco.mj_objectAcceleration(m, d, mujoco.mjtObj.mjOBJ_BODY, b, acc[i], 0)
        # The sums in floats, not numpy per body: this runs with every sim/arm/state
        # (500 Hz), and numpy's small-array calls cost 0.14-0.29 ms a state.
        fx = fy = fz = mx = my = mz = 0.0
        ox, oy, oz = o.tolist()
        gx, gy, gz = self._gravity_floats
        for mass, (_, _, _, ax, ay, az), (px, py, pz) in zip(
            self._tool_masses, acc.tolist(), d.xipos[bodies].tolist(), strict=True
        ):
            ux, uy, uz = mass * (ax + gx), mass * (ay + gy), mass * (az + gz)
            rx, ry, rz = px - ox, py - oy, pz - oz
            fx, fy, fz = fx + ux, fy + uy, fz + uz
            mx, my, mz = mx + ry * uz - rz * uy, my + rz * ux - rx * uz, mz + rx * uy - ry * ux
        f_e = f_e + R_we.T @ np.array((fx, fy, fz))
        m_e = m_e + R_we.T @ np.array((mx, my, mz))
        m_tool = m_e - _cross3(self._p_et_floats, f_e.tolist())
        return self._R_et.T @ f_e, self._R_et.T @ m_tool

    # --- stepping ---------------------------------------------------------------------
    def step(self, n: int = 1) -> list[SimEvent]:
        """`n` MuJoCo steps; what happened, as events."""
        braked, d, c = self._braked, self.data, self.cell
        ramp = self._ramp
        for _ in range(n):
            if ramp is not None:
                start, goal, t0, dt = ramp
                u = (d.time + self.model.opt.timestep - t0) / dt
                if u >= 1.0:
                    d.ctrl[c.arm_actuators] = goal
                    d.ctrl[c.arm_dampers] = 0.0  # there: the reference is at rest
                    ramp = self._ramp = None
                else:
                    d.ctrl[c.arm_actuators] = start + u * (goal - start)
            mujoco.mj_step(self.model, d)
            if braked is not None:
                d.qpos[self.cell.qpos_adr] = braked
                d.qvel[self._arm_dofs] = 0.0
        dt = n * self.model.opt.timestep
        events: list[SimEvent] = []
        if d.time - self._phases_t >= PHASES_DT_S - 1e-9:
            self._update_phases(events)
        for o in self._objs:
            events += self._liquid(o, dt)
        return events

    # --- what the contacts say --------------------------------------------------------
    def _touching(self) -> tuple[dict[int, set[str]], dict[int, list[tuple[str, float]]]]:
        """Per object body: the fingers touching it; the supports under it (name, height of
        the contact point)."""
        d = self.data
        fingers: dict[int, set[str]] = {}
        under: dict[int, list[tuple[str, float]]] = {}
        if d.ncon == 0:
            return fingers, under
        geoms = d.contact.geom.tolist()  # (ncon, 2), one call for every contact
        zs = d.contact.pos[:, 2].tolist()
        bodyof = self._geom_body
        for (g1, g2), z in zip(geoms, zs, strict=True):
            for a, b in ((g1, g2), (g2, g1)):
                body = bodyof[a]
                if body not in self._by_body:
                    continue
                if b in self._finger_geoms:
                    fingers.setdefault(body, set()).add(self._finger_geoms[b])
                    continue
                other = self._support_name(b)
                if other is None:
                    continue
                # A support is under the object's centre of mass.
                if z < d.xipos[body][2] - 1e-3:
                    under.setdefault(body, []).append((other, z))
        return fingers, under

    def _support_name(self, geom: int) -> str | None:
        if geom == self._floor:
            return FLOOR
        if geom in self._fixture_geoms:
            return self._fixture_geoms[geom]
        o = self._by_body.get(self._geom_body[geom])
        return o.name if o is not None else None

    def _update_phases(self, events: list[SimEvent]) -> None:
        d = self.data
        self._phases_t = d.time
        fingers, under = self._touching()
        held: str | None = None
        if self._closed:
            gripped = [o for o in self._objs if len(fingers.get(o.body, ())) == 2]
            if gripped:
                held = gripped[0].name
        if held is not None and held != self.held:
            self.counters["grasps"] += 1
            o = self._find(held)
            events.append(SimEvent("grasp", held, f"{held} grasped", {"p": _floats(self._p(o))}))
            self._close_pending = False
        if self.held is not None and held is None and not self._closed:
            self.counters["releases"] += 1
            o = self._find(self.held)
            events.append(
                SimEvent("release", self.held, f"{self.held} released", {"p": _floats(self._p(o))})
            )
        if self._close_pending and self._closed and held is None:
            fq = d.qpos[self.cell.finger_qpos]
            if float(np.min(fq)) > 0.98 * self.cell.finger_stroke_m:
                self.counters["missed"] += 1
                self._close_pending = False
                p, _ = self.tool_pose()
                events.append(
                    SimEvent("missed", "", "the gripper closed on nothing", {"tool_p": _floats(p)})
                )
        if self.held is not None and held is None and self._closed:
            held = self.held if len(fingers.get(self._find(self.held).body, ())) >= 1 else None
        self.held = held
        self._collisions(events)
        for o in self._objs:
            v = d.qvel[o.vadr : o.vadr + 3]
            R = d.xmat[o.body].reshape(3, 3)
            before = o.phase
            if o.name == held:
                o.phase, o.on = "held", ""
                continue
            sup = under.get(o.body)
            if sup and float(np.linalg.norm(v)) < REST_SPEED_M_S:
                on = max(sup, key=lambda x: x[1])[0]
                lying = tilt_of(R) > tipping_angle(o.size)
                o.phase, o.on = ("toppled" if lying else "resting"), on
            elif not sup:
                o.phase, o.on = "falling", ""
            if o.phase != before and before in ("held", "falling"):
                if o.phase == "toppled":
                    self.counters["toppled"] += 1
                    events.append(
                        SimEvent("toppled", o.name, f"{o.name} fell over on {o.on}", {"on": o.on})
                    )
                elif o.phase == "resting":
                    events.append(
                        SimEvent(
                            "settled",
                            o.name,
                            f"{o.name} rests on {o.on}",
                            {"on": o.on, "p": _floats(self._p(o))},
                        )
                    )

    def _collisions(self, events: list[SimEvent]) -> None:
        """A carried object pushed into something (not the fingers) harder than its weight
        and COLLISION_N: counted once per push."""
        held = None if self.held is None else self._find(self.held)
        hit: tuple[str, float] | None = None
        if held is not None:
            m, d = self.model, self.data
            limit = COLLISION_N + float(m.body_mass[held.body]) * -float(m.opt.gravity[2])
            f6 = np.zeros(6)
            for i in range(d.ncon):
                con = d.contact[i]
                g1, g2 = int(con.geom1), int(con.geom2)
                if held.geom not in (g1, g2):
                    continue
                other = g2 if g1 == held.geom else g1
                if other in self._finger_geoms or other == self._palm:
                    continue
                mujoco.mj_contactForce(m, d, i, f6)
                if f6[0] > limit and (hit is None or f6[0] > hit[1]):
                    hit = (self._support_name(other) or m.geom(other).name, float(f6[0]))
        if hit is not None and not self._colliding:
            self.counters["collisions"] += 1
            assert held is not None
            events.append(
                SimEvent(
                    "collision",
                    held.name,
                    f"{held.name} pushed into {hit[0]} ({hit[1]:.0f} N)",
                    {"into": hit[0], "force_n": hit[1]},
                )
            )
        self._colliding = hit is not None

    def _find(self, name: str) -> _Obj:
        for o in self._objs:
            if o.name == name:
                return o
        raise KeyError(name)

    def _p(self, o: _Obj) -> Vec:
        return self.data.xpos[o.body].copy()

    def _liquid(self, o: _Obj, dt: float) -> list[SimEvent]:
        R = self.data.xmat[o.body].reshape(3, 3)
        tilt = tilt_of(R)
        o.max_tilt = max(o.max_tilt, tilt)
        s = o.solid
        if not isinstance(s, Cylinder) or o.liquid_m3 <= 0.0:
            o.spilling = False
            return []
        v_max = holdable_volume_m3(s.radius, s.height, tilt)
        before = o.liquid_m3
        o.liquid_m3 = spill_step(before, v_max, SPILL_RATE_1_S, dt)
        o.spilled_m3 += before - o.liquid_m3
        if o.liquid_m3 < before:
            # The liquid that left no longer weighs: the bottle's mass follows it.
            self.model.body_mass[o.body] = object_mass_kg(s, self.params) - 1e3 * o.spilled_m3
        spilling = before > v_max
        events = []
        if spilling and not o.spilling:
            events.append(
                SimEvent(
                    "spill",
                    o.name,
                    f"{o.name} spills: tilted {math.degrees(tilt):.1f}°",
                    {"tilt_deg": math.degrees(tilt), "spilled_m3": o.spilled_m3},
                )
            )
        o.spilling = spilling
        return events

    # --- the views' answer ------------------------------------------------------------
    def bodies(self) -> list[BodyState]:
        """Every movable object now (`p`: a box's centre, a cylinder's base centre)."""
        d = self.data
        out = []
        for o in self._objs:
            R = d.xmat[o.body].reshape(3, 3).copy()
            out.append(
                BodyState(
                    name=o.name,
                    kind="box" if isinstance(o.solid, Box) else "cylinder",
                    p=d.xpos[o.body].copy(),
                    R=R,
                    phase=o.phase,
                    on=o.on,
                    size=o.size.copy(),
                    liquid_m3=o.liquid_m3,
                    spilled_m3=o.spilled_m3,
                    tilt_rad=tilt_of(R),
                    max_tilt_rad=o.max_tilt,
                )
            )
        return out

    @property
    def arm_dofs(self) -> NDArray[np.intp]:
        """The arm's and the gripper's degrees of freedom."""
        return self._arm_dofs

    def all_resting(self) -> bool:
        """Every object resting or lying toppled (none falling or held)."""
        return all(o.phase in ("resting", "toppled") for o in self._objs)

    def body(self, name: str) -> BodyState:
        for b in self.bodies():
            if b.name == name:
                return b
        raise KeyError(name)

    def place(self, name: str, p: ArrayLike, R: ArrayLike | None = None) -> None:
        """Put object `name` at `p` (a box's centre, a cylinder's base centre), at rest."""
        o = self._find(name)
        quat = np.array([1.0, 0.0, 0.0, 0.0])
        if R is not None:
            mujoco.mju_mat2Quat(quat, np.asarray(R, dtype=float).reshape(9))
        self.data.qpos[o.qadr : o.qadr + 3] = np.asarray(p, dtype=float)
        self.data.qpos[o.qadr + 3 : o.qadr + 7] = quat
        self.data.qvel[o.vadr : o.vadr + 6] = 0.0
        mujoco.mj_forward(self.model, self.data)


def _floats(v: Vec) -> list[float]:
    return [float(x) for x in v]
