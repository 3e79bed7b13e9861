"""The simulated wrist sensor: contact with the live workcell, through eq. (4) inverted.

Each `read()` takes the latest tool pose (from robot/state, via `update_pose`), the contact
force of the workcell on a probe sphere at the tool point, the weight of the tool and of
what the gripper carries (and its inertia), an optional external push and small noise, and
turns that wrench (tool frame) into the six sensing signals with the inverse of eq. (4):
the simulated elastic wrist deflects, and the service recovers the wrench with the forward
eq. (4) exactly as on the real wrist.

The world is the workcell's scene at the poses of the latest `workcell/state`
(`update_workcell`): a moved block is touched where it now is, a carried one weighs on the
wrist. Everything that changes only with a message (the tool frame's rotation, the weights
in the tool frame, the placed scene geometry) is computed when the message arrives; a
sample costs the contact query, the noise and eq. (4) in plain floats.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike

from services.control.force.events import EventSink, ignore_event
from services.control.force.gravity import ToolLoad
from services.control.force.kernel import (
    F3,
    M3,
    ZERO3,
    WristKernel,
    cross,
    mat9,
    mul,
    transpose,
    vec3,
    weight_wrench,
)
from services.control.force.model import Vec, WristModel, as_rotation
from services.control.force.sensors import Reading, SensorError, Six
from services.control.force.world import (
    BASE_POINTS,
    CarriedLoad,
    ContactWorld,
    Pose,
    carried_mass_kg,
    surface_points,
)
from services.geometry import log9, mul9
from services.world.workcell.messages import ObjectView
from services.world.workcell.scene import Scene, default_scene

NOISE_BLOCK = 256
"""Samples' worth of Gaussian noise drawn at once."""
ACCEL_MAX_MPS2 = 20.0
"""The tool acceleration estimate is clipped to this (m/s²): a timestamp glitch in
robot/state must not read as a kilonewton."""
ACCEL_TAU_S = 0.03
"""Low-pass time constant (s) of the acceleration estimate (second differences of the
tool position at the robot/state rate are noisy)."""
ACCEL_DT_RANGE_S = (2e-4, 0.1)
"""robot/state intervals outside this (s) restart the acceleration estimate."""


class _Accel:
    """The tool point's acceleration (world, m/s²) from successive robot/state positions."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._p: F3 | None = None
        self._t = 0
        self._v: F3 | None = None
        self.a: F3 = ZERO3

    def update(self, p: F3, t_ns: int) -> F3:
        lo, hi = ACCEL_DT_RANGE_S
        if self._p is None or not lo <= (t_ns - self._t) * 1e-9 <= hi:
            self.reset()
            self._p, self._t = p, t_ns
            return self.a
        dt = (t_ns - self._t) * 1e-9
        v = ((p[0] - self._p[0]) / dt, (p[1] - self._p[1]) / dt, (p[2] - self._p[2]) / dt)
        if self._v is not None:
            k = dt / (ACCEL_TAU_S + dt)
            a = self.a
            raw = ((v[0] - self._v[0]) / dt, (v[1] - self._v[1]) / dt, (v[2] - self._v[2]) / dt)
            a = tuple(  # type: ignore[assignment]
                min(ACCEL_MAX_MPS2, max(-ACCEL_MAX_MPS2, a[i] + k * (raw[i] - a[i])))
                for i in range(3)
            )
            self.a = a
        self._p, self._t, self._v = p, t_ns, v
        return self.a


class SimSensor:
    """A simulated compliant wrist in the simulated workcell.

    `model` is the physical truth of the simulated wrist (its calibration, stiffness and
    placements); the service's own model may differ, as it may on a real wrist. `load` is
    the tool's weight. Noise is Gaussian, `noise_n` (N) per force axis and `noise_nm` (N·m)
    per moment axis. Contact moments about the tool point are zero: the probe is a sphere
    of `probe_radius_m` centred on the tool point. Without a pose there is nothing to
    sense: `read()` returns None until the first `update_pose`.

    A carried object (`update_workcell` with `held`) adds m·(g − a) at its centre of mass:
    its weight, and with `inertia` its inertial force from the tool's acceleration
    (estimated from the robot/state stream). Its mass comes from the scene description:
    `block_density_kg_m3` × a box's volume, or `bottle_mass_kg` plus the liquid left. With
    `carried_contact`, what it touches (a table, a block under it) pushes on the wrist
    through it, at its corners and base centre.

    `torsion_nm_rad` > 0: the tool's contact resists a turn about its normal, as a tool
    seated in a socket or a tip that does not slip: while the probe touches, the turn
    about the contact normal since the touch began meets a moment −k·angle about that
    normal (at the tool point); out of contact it is forgotten. 0 (default): a contact has
    no moment, as above. What a rotational passivity port is measured against
    (docs/passivity.md, "Rotations").
    """

    #: its data is computed, not streamed by a device: sampled slower while unused
    may_idle = True

    def __init__(
        self,
        model: WristModel | None = None,
        load: ToolLoad | None = None,
        scene: Scene | None = None,
        *,
        noise_n: float = 0.0,
        noise_nm: float = 0.0,
        probe_radius_m: float = 0.005,
        seed: int | None = None,
        block_density_kg_m3: float = 700.0,
        bottle_mass_kg: float = 0.1,
        inertia: bool = True,
        carried_contact: bool = True,
        torsion_nm_rad: float = 0.0,
        on_event: EventSink = ignore_event,
    ) -> None:
        if not (noise_n >= 0.0 and noise_nm >= 0.0 and probe_radius_m >= 0.0):
            raise ValueError("noise_n, noise_nm and probe_radius_m must be ≥ 0")
        if not (block_density_kg_m3 >= 0.0 and bottle_mass_kg >= 0.0):
            raise ValueError("block_density_kg_m3 and bottle_mass_kg must be ≥ 0")
        if not 0.0 <= torsion_nm_rad < math.inf:
            raise ValueError("torsion_nm_rad must be ≥ 0 and finite")
        self._torsion = torsion_nm_rad
        self._seated: M3 | None = None  # the tool's orientation when the touch began
        self.on_event = on_event
        self._model = model or WristModel()
        self._kernel = WristKernel(self._model)
        self._load = load or ToolLoad()
        self._scene = scene or default_scene()
        self._noise_n = noise_n
        self._noise_nm = noise_nm
        self._radius_m = probe_radius_m
        self._density = block_density_kg_m3
        self._bottle_kg = bottle_mass_kg
        self._inertia = inertia
        self._carried_contact = carried_contact
        self._rng = np.random.default_rng(seed)
        self._noise: list[float] = []
        self._noise_at = 0
        self._lock = threading.Lock()  # pose and world updates come from two bus threads
        self._world = ContactWorld.build(self._scene, probe_radius_m)
        self._carried: CarriedLoad | None = None
        self._accel = _Accel()
        # Per pose: (p, Rᵀ, the weights' force and moment in the tool frame).
        self._pose: tuple[F3, M3, F3, F3] | None = None
        self._R: M3 | None = None
        self._push: tuple[F3, F3] = (ZERO3, ZERO3)
        self._open = False
        self._count = 0

    @property
    def name(self) -> str:
        return "sim"

    @property
    def bad(self) -> int:
        return 0

    @property
    def gaps(self) -> int:
        return 0

    @property
    def model(self) -> WristModel:
        return self._model

    @property
    def world(self) -> ContactWorld:
        return self._world

    @property
    def acceleration(self) -> F3:
        """The tool point's estimated acceleration (m/s², world) from robot/state."""
        return self._accel.a

    @property
    def carried(self) -> CarriedLoad | None:
        """What the gripper holds now (None: nothing)."""
        return self._carried

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def update_pose(self, tool_p: ArrayLike, tool_R: ArrayLike, t_ns: int | None = None) -> None:
        """The tool frame in the world (m; R world←tool), from robot/state at `t_ns`
        (the state's own time stamp, ns; None: no acceleration estimate)."""
        p = vec3(tool_p)
        R = mat9(as_rotation(tool_R, "tool_R"))
        self._set_pose(p, R, t_ns)

    def update_pose_checked(self, p: F3, R: M3, t_ns: int | None = None) -> None:
        """`update_pose` for a pose already validated (a decoded RobotState)."""
        self._set_pose(p, R, t_ns)

    def _set_pose(self, p: F3, R: M3, t_ns: int | None) -> None:
        with self._lock:
            a = self._accel.update(p, t_ns) if t_ns is not None else ZERO3
            self._R = R
            f, c = self._weights(R, a)
            self._pose = (p, transpose(R), f, c)

    def _weights(self, R: M3, a: F3) -> tuple[F3, F3]:
        """The tool's and the carried object's weight (and inertia), tool frame."""
        load = self._load
        f, c = weight_wrench(load.mass_kg, load.gravity_mps2, vec3(load.com_m), R)
        held = self._carried
        if held is None or held.mass_kg == 0.0:
            return f, c
        g = self._load.gravity_mps2
        m = held.mass_kg
        if not self._inertia:
            a = ZERO3
        # m (g⃗ − a⃗) in the world, then in the tool frame.
        fo = mul(transpose(R), -m * a[0], -m * a[1], -m * (g + a[2]))
        co = cross(held.com_t, fo)
        return (f[0] + fo[0], f[1] + fo[1], f[2] + fo[2]), (
            c[0] + co[0],
            c[1] + co[1],
            c[2] + co[2],
        )

    def update_workcell(self, objects: Mapping[str, ObjectView], held: str, tool_p: F3) -> None:
        """The workcell's objects now (a validated `workcell/state`): contact uses their
        poses; `held` (the gripper's object, "" for none) weighs on the wrist. `tool_p` is
        the tool point the workcell stepped with (m, world): the carried object's centre of
        mass is placed relative to it."""
        poses = {n: Pose(vec3(o.p), mat9(o.R)) for n, o in objects.items()}
        world = ContactWorld.build(self._scene, self._radius_m, poses, exclude=held)
        carried: CarriedLoad | None = None
        if held and held in objects:
            obj = objects[held]
            try:
                solid = self._scene.solid(held)
            except KeyError:
                solid = None
            if solid is not None:
                mass = carried_mass_kg(solid, obj.liquid_ml, self._density, self._bottle_kg)
                with self._lock:
                    R = self._R
                if R is not None:
                    Rt = transpose(R)
                    tx, ty, tz = tool_p

                    def in_tool(x: F3) -> F3:
                        return mul(Rt, x[0] - tx, x[1] - ty, x[2] - tz)

                    pts = surface_points(obj.kind, vec3(obj.p), mat9(obj.R), vec3(obj.size))
                    points = tuple(in_tool(x) for x in pts) if self._carried_contact else ()
                    centre = in_tool(vec3(obj.centre))
                    reach = max((math.dist(q, centre) for q in points), default=0.0)
                    carried = CarriedLoad(held, mass, centre, points, centre, reach)
                else:
                    carried = CarriedLoad(held, mass)
        with self._lock:
            self._world = world
            self._carried = carried
            if self._R is not None and self._pose is not None:
                f, c = self._weights(self._R, self._accel.a)
                p, Rt, _, _ = self._pose
                self._pose = (p, Rt, f, c)

    def set_tool(self, p_et: ArrayLike, R_et: ArrayLike) -> None:
        """The simulated tool is mounted at a new placement eMt in the flange frame."""
        self._model = self._model.with_tool(p_et, R_et)
        self._kernel = WristKernel(self._model)

    def push(self, f_t: ArrayLike, c_t: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        """An extra external wrench on the tool (N, N·m about the tool point, tool frame),
        e.g. a hand pushing the tool; zero to release."""
        self._push = (vec3(f_t), vec3(c_t))

    def wrench_t(self) -> tuple[Vec, Vec] | None:
        """The noiseless wrench on the tool now (tool frame, weights included); None: no pose."""
        w = self._wrench()
        if w is None:
            return None
        return np.array(w[0]), np.array(w[1])

    def _wrench(self) -> tuple[F3, F3] | None:
        pose = self._pose
        if pose is None:
            return None
        p, Rt, wf, wc = pose
        world = self._world
        fw = world.force(p[0], p[1], p[2])
        ft = mul(Rt, *fw)
        (px, py, pz), (qx, qy, qz) = self._push
        f = (ft[0] + wf[0] + px, ft[1] + wf[1] + py, ft[2] + wf[2] + pz)
        c = (wc[0] + qx, wc[1] + qy, wc[2] + qz)
        if self._torsion > 0.0:
            tc = self._twist(fw, transpose(Rt))
            c = (c[0] + tc[0], c[1] + tc[1], c[2] + tc[2])
        held = self._carried
        if held is None or not held.points_t:
            return f, c
        # What the carried object touches pushes on the wrist through it: each surface
        # point is a point probe of stiffness k / 5, so its base (4 corners or rim points
        # and its centre) pressed flat onto a surface gives k · depth.
        R = transpose(Rt)
        cw = mul(R, *held.centre_t)
        near = world.near(p[0] + cw[0], p[1] + cw[1], p[2] + cw[2], held.reach_m)
        if near is None:  # in free space: one rotation and a bounds test per solid
            return f, c
        share = 1.0 / BASE_POINTS
        fx = fy = fz = mx = my = mz = 0.0
        for q in held.points_t:
            qw = mul(R, *q)
            g = world.point_force(near, p[0] + qw[0], p[1] + qw[1], p[2] + qw[2])
            if g[0] or g[1] or g[2]:
                fx += share * g[0]
                fy += share * g[1]
                fz += share * g[2]
                mx += share * (qw[1] * g[2] - qw[2] * g[1])
                my += share * (qw[2] * g[0] - qw[0] * g[2])
                mz += share * (qw[0] * g[1] - qw[1] * g[0])
        if not (fx or fy or fz):
            return f, c
        ct, mt = mul(Rt, fx, fy, fz), mul(Rt, mx, my, mz)
        return (
            (f[0] + ct[0], f[1] + ct[1], f[2] + ct[2]),
            (c[0] + mt[0], c[1] + mt[1], c[2] + mt[2]),
        )

    def _twist(self, fw: F3, R: M3) -> F3:
        """The contact's moment against a turn about its normal (tool frame, N·m), or zero
        out of contact; remembers the orientation at the touch (`torsion_nm_rad`)."""
        norm = math.sqrt(fw[0] * fw[0] + fw[1] * fw[1] + fw[2] * fw[2])
        if norm == 0.0:
            self._seated = None
            return ZERO3
        if self._seated is None:
            self._seated = R
            return ZERO3
        n = (fw[0] / norm, fw[1] / norm, fw[2] / norm)
        # The turn since the touch, a spatial rotation vector: log(R·R_seatedᵀ).
        w = log9(mul9(R, transpose(self._seated)))
        k = -self._torsion * (w[0] * n[0] + w[1] * n[1] + w[2] * n[2])
        return mul(transpose(R), k * n[0], k * n[1], k * n[2])

    def read(self) -> Reading | None:
        if not self._open:
            raise SensorError("sim sensor is not open")
        w = self._wrench()
        if w is None:
            return None
        f, c = w
        if self._noise_n > 0.0 or self._noise_nm > 0.0:
            i = self._noise_at
            if i >= len(self._noise):
                # Unit normals drawn NOISE_BLOCK samples at a time: one numpy call per
                # block instead of six Python gauss() calls (~6 µs) per sample.
                self._noise = self._rng.standard_normal(6 * NOISE_BLOCK).tolist()
                i = 0
            self._noise_at = i + 6
            z, sn, sm = self._noise, self._noise_n, self._noise_nm
            f = (f[0] + sn * z[i], f[1] + sn * z[i + 1], f[2] + sn * z[i + 2])
            c = (c[0] + sm * z[i + 3], c[1] + sm * z[i + 4], c[2] + sm * z[i + 5])
        values: Six = self._kernel.signals_from_wrench(f, c)
        self._count += 1
        return Reading("signals", values, self._count)
