"""The cell as one MuJoCo model, built from the descriptions the rest of the system reads.

`build_cell(arm, scene, params)` compiles:

- **the arm** from its `ArmModel`: the URDF the arm service loads (its mount joint included),
  given to MuJoCo's URDF compiler with the package roots resolved. A URDF without
  `<collision>` elements (the PUMA 560's) collides with its visuals, and a link without
  `<inertial>` gets its mass from that geometry (`arm_density_kg_m3`). Every arm joint gets a
  position servo (`kp_nm_rad`, critically damped, armature `armature_kgm2`) whose control
  range is the joint's limits, damping on the velocity error (the setpoints' own velocity
  is the reference), and gravity compensation (`gravcomp`), as a joint controller's
  feed-forward does; fingers of the URDF's own hand are inert (the cell's gripper grasps).
- **the gripper** at the tool point of the model's default tool (eMt): a palm whose centre is
  the tool point, two fingers below it on slide joints closing along the tool's x, each on a
  force-limited position servo (`grip_force_n`); its mass and centre of mass are the force
  service's tool load (`tool_mass_kg`, `tool_com_m`), so the wrist sees what it compensates.
- **the wrist force/torque sensor**: a site `wrist_ft` at the flange, in the gripper's body,
  with a `force` and a `torque` sensor (MuJoCo's: the force the gripper exerts on the flange,
  in the site's frame).
- **the workcell** from the `Scene`: the floor plane, each fixture (the table) as a static box,
  each movable block and the bottle as a free body (block density `block_density_kg_m3`; the
  bottle `bottle_mass_kg` plus its liquid at 1 g/ml).

Collision filtering (contype/conaffinity bits): the arm's links touch the table and the
objects only, never each other, the gripper or the fixed world; everything else touches
everything. Frames: the world is the cell's (z up, floor
z = 0). Units: m, kg, s, N.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

from services.bus.errors import ConfigError
from services.world.workcell.scene import Box, Cylinder, Scene

ARM_CONTYPE, ARM_CONAFFINITY = 2, 4
"""The arm's links: they touch the movable objects, not each other, the gripper (mounted on
them) or the fixed world (a pedestal stands on the floor; the FR3's stands at the table's
near edge, its base inside the table's footprint)."""
WORLD_CONTYPE, WORLD_CONAFFINITY = 5, 3
"""The movable objects: they touch everything."""
PLAIN_CONTYPE, PLAIN_CONAFFINITY = 1, 1
"""The floor, the fixtures and the gripper: everything but the arm's links."""
WRIST_SITE = "wrist_ft"
GRIPPER_BODY = "tr_gripper"
FINGERS = ("tr_finger_l", "tr_finger_r")
LIQUID_KG_PER_M3 = 1000.0
JOINT = mujoco.mjtTrn.mjTRN_JOINT


@dataclass(frozen=True, slots=True)
class PhysicsParams:
    """The MuJoCo cell's parameters (units in the names; the `[physics]` table).

    timestep_s: MuJoCo's step (1 ms: the joint servo's 1 kHz).
    kp_nm_rad: the arm joints' position servo stiffness (critically damped).
    armature_kgm2: reflected rotor inertia added to every arm joint (stability at 1 kHz).
    arm_density_kg_m3: the density of an arm link that has no `<inertial>`.
    grip_force_n: the most each finger pushes; grip_opening_m: the gap between the open
      fingers; finger_length_m: how far the fingers reach below the palm.
    tool_mass_kg, tool_com_m: the gripper's mass and centre of mass (tool frame, from the
      tool point), the force service's tool load.
    friction: sliding friction of every contact (torsional and rolling scaled from it).
    block_density_kg_m3, bottle_mass_kg: the objects' masses (the force service's).
    """

    timestep_s: float = 0.001
    kp_nm_rad: float = 3000.0
    armature_kgm2: float = 0.1
    arm_density_kg_m3: float = 1000.0
    grip_force_n: float = 20.0
    grip_opening_m: float = 0.11
    finger_length_m: float = 0.035
    tool_mass_kg: float = 0.25
    tool_com_m: tuple[float, float, float] = (0.0, 0.0, -0.1)
    friction: float = 1.0
    block_density_kg_m3: float = 700.0
    bottle_mass_kg: float = 0.1

    def __post_init__(self) -> None:
        for key in (
            "timestep_s",
            "kp_nm_rad",
            "arm_density_kg_m3",
            "grip_force_n",
            "grip_opening_m",
            "finger_length_m",
            "tool_mass_kg",
            "friction",
            "block_density_kg_m3",
        ):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"physics.{key}", f"must be a number, got {v!r}")
            if v <= 0.0:
                raise ConfigError(f"physics.{key}", f"must be > 0, got {v}")
        for key in ("armature_kgm2", "bottle_mass_kg"):
            v = getattr(self, key)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0.0):
                raise ConfigError(f"physics.{key}", f"must be ≥ 0, got {v!r}")
        if not 1e-4 <= self.timestep_s <= 0.005:
            raise ConfigError("physics.timestep_s", "must be within 0.1 … 5 ms")
        if self.grip_opening_m > 0.2:
            raise ConfigError("physics.grip_opening_m", "must be ≤ 0.2 m")
        if len(self.tool_com_m) != 3 or not all(map(math.isfinite, self.tool_com_m)):
            raise ConfigError("physics.tool_com_m", "must be 3 finite numbers")


@dataclass(frozen=True, slots=True, eq=False)
class CellModel:
    """The compiled cell and where its parts are in it (MuJoCo ids and addresses)."""

    model: Any  # mujoco.MjModel
    arm_name: str
    qpos_adr: NDArray[np.intp]
    """qpos addresses of the arm's joints, joint 1 first."""
    dof_adr: NDArray[np.intp]
    arm_actuators: NDArray[np.intp]
    arm_dampers: NDArray[np.intp]
    """Velocity actuators: the servo's damping on (v_ref − v), v_ref from the setpoints."""
    finger_qpos: NDArray[np.intp]
    finger_actuators: NDArray[np.intp]
    finger_stroke_m: float
    site: int
    """The wrist F/T site."""
    force_adr: int
    torque_adr: int
    gripper_body: int
    objects: dict[str, int] = field(default_factory=dict)
    """Movable object name → body id."""
    object_qpos: dict[str, int] = field(default_factory=dict)
    """Movable object name → qpos address of its free joint (x, y, z, qw, qx, qy, qz)."""
    fixtures: dict[str, int] = field(default_factory=dict)
    """Fixture name → geom id."""
    tool_p: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tool_R: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    """eMt: the tool point in the flange frame (where the palm's centre is)."""


def _urdf_for_mujoco(arm: Any) -> str:
    """The arm's URDF with package roots resolved and MuJoCo's compiler options."""
    text: str = arm.urdf
    for name, folder in arm.package_dirs.items():
        text = text.replace(f"package://{name}/", f"{folder}/")
    # Relative mesh paths are relative to the model's folder.
    text = re.sub(
        r'filename="(?!/)([^"]+)"', lambda m: f'filename="{arm.folder / m.group(1)}"', text
    )
    visual = "false" if "<collision" not in text else "true"
    opts = (
        f'<mujoco><compiler discardvisual="{visual}" fusestatic="false" strippath="false" '
        'balanceinertia="true" angle="radian"/></mujoco>'
    )
    i = text.index(">", text.index("<robot")) + 1
    return text[:i] + opts + text[i:]


def _rgba(bgr: tuple[int, int, int]) -> list[float]:
    return [bgr[2] / 255.0, bgr[1] / 255.0, bgr[0] / 255.0, 1.0]


def build_cell(arm: Any, scene: Scene, params: PhysicsParams | None = None) -> CellModel:
    """The cell of `arm` (an ArmModel) in `scene`, compiled (see the module docstring).
    Raises ConfigError("physics", …) naming the part MuJoCo refused."""
    p = params or PhysicsParams()
    try:
        spec = mujoco.MjSpec.from_string(_urdf_for_mujoco(arm))
    except ValueError as e:
        raise ConfigError("physics", f"{arm.path}: MuJoCo cannot load the URDF: {e}") from None
    spec.option.timestep = p.timestep_s
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.noslip_iterations = 2
    chain = set(arm.joint_names)
    # The arm: every geom collides with the world only; links without mass get it from
    # their geometry; arm joints get armature and gravity compensation.
    for body in [spec.worldbody, *spec.bodies]:
        for g in body.geoms:  # the URDF's world link included: the arm's pedestal
            g.contype, g.conaffinity = ARM_CONTYPE, ARM_CONAFFINITY
            g.friction = [p.friction, 0.005, 0.0001]
        if body is spec.worldbody or body.name == "world":
            continue
        for j in list(body.joints):
            if j.name not in chain:
                spec.delete(j)  # the URDF hand's fingers: rigid (the cell's gripper grasps)
                continue
            j.armature = p.armature_kgm2
            # The URDF's joint friction and damping are inside the joint controller's loop
            # (it compensates them): the servo's setpoint is what the joint does.
            j.frictionloss = 0.0
            j.damping = [0.0, 0.0, 0.0]
        body.gravcomp = 1.0
        if body.mass <= 0.0 and body.geoms:
            _mass_from_geoms(body, p.arm_density_kg_m3)
    for eq in list(spec.equalities):  # the URDF's mimic joints (its hand's fingers)
        if eq.name1 not in chain or eq.name2 not in chain:
            spec.delete(eq)
    flange = spec.body(arm.flange_frame)
    if flange is None:  # a frame of a fused fixed joint: the URDF importer keeps bodies
        raise ConfigError("physics", f"{arm.path}: no body {arm.flange_frame!r} in MuJoCo")
    # Below the flange the URDF's own hand (the FR3's) is drawn, not touched: the cell's
    # gripper, behind the wrist's sensor, is what touches (else a contact would reach the
    # flange without passing the sensor).
    for body in _descendants(flange):
        for g in body.geoms:
            g.contype = g.conaffinity = 0
    for name in arm.joint_names:
        j = spec.joint(name)
        act = spec.add_actuator(name=f"servo_{name}", target=name, trntype=JOINT)
        act.set_to_position(kp=p.kp_nm_rad, dampratio=1.0)
        act.ctrlrange = list(j.range)
        act.ctrllimited = True
        vel = spec.add_actuator(name=f"damper_{name}", target=name, trntype=JOINT)
        vel.set_to_velocity(kv=1.0)
    _add_gripper(spec, flange, arm, p)
    _add_scene(spec, scene, p)
    try:
        model = spec.compile()
    except ValueError as e:
        raise ConfigError("physics", f"MuJoCo refused the cell of {arm.name}: {e}") from None
    # The servo's damping acts on the velocity error (v_ref − v), not on v: the critically
    # damped gain MuJoCo computed for the position servo moves to its velocity actuator.
    for name in arm.joint_names:
        a, v = model.actuator(f"servo_{name}").id, model.actuator(f"damper_{name}").id
        kv = -float(model.actuator_biasprm[a, 2])
        model.actuator_biasprm[a, 2] = 0.0
        model.actuator_gainprm[v, 0] = kv
        model.actuator_biasprm[v, 2] = -kv
    objects = {s.name: model.body(s.name).id for s in scene.movables()}
    object_qpos = {n: int(model.jnt_qposadr[model.body_jntadr[b]]) for n, b in objects.items()}
    fixtures = {s.name: model.geom(s.name).id for s in scene.solids() if not s.movable}
    sens_f, sens_t = model.sensor("wrist_force"), model.sensor("wrist_torque")
    fing = [model.joint(f).id for f in FINGERS]
    return CellModel(
        model=model,
        arm_name=arm.name,
        qpos_adr=np.array([model.jnt_qposadr[model.joint(n).id] for n in arm.joint_names]),
        dof_adr=np.array([model.jnt_dofadr[model.joint(n).id] for n in arm.joint_names]),
        arm_actuators=np.array([model.actuator(f"servo_{n}").id for n in arm.joint_names]),
        arm_dampers=np.array([model.actuator(f"damper_{n}").id for n in arm.joint_names]),
        finger_qpos=np.array([model.jnt_qposadr[j] for j in fing]),
        finger_actuators=np.array([model.actuator(f"grip_{f}").id for f in FINGERS]),
        finger_stroke_m=_stroke(p),
        site=model.site(WRIST_SITE).id,
        force_adr=int(model.sensor_adr[sens_f.id]),
        torque_adr=int(model.sensor_adr[sens_t.id]),
        gripper_body=model.body(GRIPPER_BODY).id,
        objects=objects,
        object_qpos=object_qpos,
        fixtures=fixtures,
        tool_p=tuple(float(x) for x in arm.tool_p),  # type: ignore[arg-type]
        tool_R=tuple(float(x) for x in arm.tool_R),
    )


FINGER_T_M = 0.01
"""A finger's thickness along the closing direction (m)."""
PALM_H_M = 0.01
PAD_TORSION_M = 0.02
FINGER_DAMPING = 100.0
"""N·s/m: a closing finger moves at most grip_force_n / this (0.2 m/s), slow enough not to
pass through a block in one step."""


def _stroke(p: PhysicsParams) -> float:
    """How far each finger travels from open to touching the other (m)."""
    return 0.5 * p.grip_opening_m


def _descendants(body: Any) -> list[Any]:
    out = []
    for child in body.bodies:
        out.append(child)
        out += _descendants(child)
    return out


def _mass_from_geoms(body: Any, density: float) -> None:
    """A link's mass and inertia from its (collision) geometry at `density`."""
    for g in body.geoms:
        g.density = density
    body.explicitinertial = False


def _add_gripper(spec: Any, flange: Any, arm: Any, p: PhysicsParams) -> None:
    """The gripper's body at the flange (the F/T site, the tool's mass), and in it the tool
    frame: the palm whose face centre is the tool point, the fingers below it (+z)."""
    R = np.asarray(arm.tool_R, dtype=float).reshape(3, 3)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, R.reshape(9))
    g = flange.add_body(name=GRIPPER_BODY, pos=[0.0, 0.0, 0.0])
    g.add_site(name=WRIST_SITE, pos=[0.0, 0.0, 0.0], size=[0.01, 0.01, 0.01])
    finger_kg = 0.01
    g.mass = max(1e-3, p.tool_mass_kg - 2 * finger_kg)
    g.ipos = list(np.asarray(arm.tool_p, dtype=float) + R @ np.asarray(p.tool_com_m, dtype=float))
    g.inertia = [1e-4, 1e-4, 1e-4]
    g.explicitinertial = True
    g.gravcomp = 1.0  # the servos' feed-forward carries the tool; the wrist still weighs it
    tool = g.add_body(name="tr_tool", pos=list(arm.tool_p), quat=list(quat))
    tool.mass, tool.inertia, tool.explicitinertial = 1e-6, [1e-9] * 3, True
    tool.gravcomp = 1.0
    half_w = 0.5 * p.grip_opening_m + FINGER_T_M
    palm = tool.add_geom(
        name="tr_palm",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[half_w, 0.02, 0.5 * PALM_H_M],
        pos=[0.0, 0.0, -0.5 * PALM_H_M],
        rgba=[0.25, 0.25, 0.28, 1.0],
    )
    _world_geom(palm, p)
    palm.contype, palm.conaffinity = PLAIN_CONTYPE, PLAIN_CONAFFINITY
    palm.density = 0.0
    for name, side in zip(FINGERS, (1.0, -1.0), strict=True):
        x0 = side * (0.5 * p.grip_opening_m + 0.5 * FINGER_T_M)
        f = tool.add_body(name=name, pos=[x0, 0.0, 0.5 * p.finger_length_m])
        f.mass, f.inertia, f.explicitinertial = finger_kg, [1e-6] * 3, True
        f.gravcomp = 1.0
        j = f.add_joint(
            name=name,
            type=mujoco.mjtJoint.mjJNT_SLIDE,
            axis=[-side, 0.0, 0.0],
            range=[0.0, _stroke(p)],
            armature=0.001,
            damping=[FINGER_DAMPING, 0.0, 0.0],
        )
        j.limited = True
        geom = f.add_geom(
            name=f"{name}_pad",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.5 * FINGER_T_M, 0.012, 0.5 * p.finger_length_m],
            rgba=[0.15, 0.15, 0.15, 1.0],
        )
        _world_geom(geom, p)
        geom.contype, geom.conaffinity = PLAIN_CONTYPE, PLAIN_CONAFFINITY
        # Soft pads: they resist a held object's turn about their normal and its pivoting
        # on their face (torsional and rolling friction, m), as a real pad's patch does.
        geom.condim = 6
        geom.friction = [p.friction, PAD_TORSION_M, PAD_TORSION_M]
        act = spec.add_actuator(name=f"grip_{name}", target=name, trntype=JOINT)
        act.set_to_position(kp=2000.0, dampratio=1.0)
        act.ctrlrange = [0.0, _stroke(p)]
        act.ctrllimited = True
        act.forcerange = [-p.grip_force_n, p.grip_force_n]
        act.forcelimited = True
    sensors = (("force", mujoco.mjtSensor.mjSENS_FORCE), ("torque", mujoco.mjtSensor.mjSENS_TORQUE))
    for kind, sensor in sensors:
        spec.add_sensor(
            name=f"wrist_{kind}", type=sensor, objtype=mujoco.mjtObj.mjOBJ_SITE, objname=WRIST_SITE
        )


def _world_geom(g: Any, p: PhysicsParams) -> None:
    g.contype, g.conaffinity = WORLD_CONTYPE, WORLD_CONAFFINITY
    g.friction = [p.friction, 0.005, 0.0001]


def _add_scene(spec: Any, scene: Scene, p: PhysicsParams) -> None:
    world = spec.worldbody
    floor = world.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[3.0, 3.0, 0.1],
        pos=[0.0, 0.0, scene.floor_z],
        rgba=[0.5, 0.5, 0.5, 1.0],
    )
    _world_geom(floor, p)
    floor.contype, floor.conaffinity = PLAIN_CONTYPE, PLAIN_CONAFFINITY
    for s in scene.solids():
        if s.movable:
            _add_object(spec, s, p)
            continue
        if isinstance(s, Box):
            g = world.add_geom(
                name=s.name,
                type=mujoco.mjtGeom.mjGEOM_BOX,
                size=[0.5 * x for x in s.size],
                pos=list(s.center),
                rgba=_rgba(s.color),
            )
        else:
            g = world.add_geom(
                name=s.name,
                type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                size=[s.radius, 0.5 * s.height, 0.0],
                pos=[s.base[0], s.base[1], s.base[2] + 0.5 * s.height],
                rgba=_rgba(s.color),
            )
        _world_geom(g, p)
        g.contype, g.conaffinity = PLAIN_CONTYPE, PLAIN_CONAFFINITY


def object_mass_kg(s: Box | Cylinder, p: PhysicsParams) -> float:
    """A movable object's mass: a block of uniform density, a bottle and its liquid."""
    if isinstance(s, Box):
        return p.block_density_kg_m3 * s.size[0] * s.size[1] * s.size[2]
    liquid = math.pi * s.radius**2 * min(s.liquid_height_m, s.height)
    return p.bottle_mass_kg + LIQUID_KG_PER_M3 * liquid


def _add_object(spec: Any, s: Box | Cylinder, p: PhysicsParams) -> None:
    if isinstance(s, Box):
        b = spec.worldbody.add_body(name=s.name, pos=list(s.center))
        g = b.add_geom(
            name=s.name,
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.5 * x for x in s.size],
            rgba=_rgba(s.color),
        )
        volume = s.size[0] * s.size[1] * s.size[2]
    else:
        # The body's origin is the base centre, as workcell/state reports a cylinder.
        b = spec.worldbody.add_body(name=s.name, pos=list(s.base))
        g = b.add_geom(
            name=s.name,
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            size=[s.radius, 0.5 * s.height, 0.0],
            pos=[0.0, 0.0, 0.5 * s.height],
            rgba=_rgba(s.color),
        )
        volume = math.pi * s.radius**2 * s.height
    b.add_freejoint(name=s.name)
    _world_geom(g, p)
    g.condim = 4
    g.density = object_mass_kg(s, p) / volume
