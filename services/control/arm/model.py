"""The arm as data: an `ArmModel` loaded from a model file (TOML) and the URDF it names.

A model is a folder holding `arm.toml` and its URDF (with meshes, licence and source): the
shipped ones are under `models/` (`puma560`, `fr3`, `ur5e`); a user's own arm is the path of
its TOML. The URDF gives the kinematic chain from `base_frame` to `flange_frame`, the joints'
names, position and velocity limits (`<limit>`) and the visuals; the TOML gives what a URDF
lacks: acceleration limits, the limits the arm plans with, the default tool, named
configurations, the step bound of a streamed target, where the arm stands in the cell, the
supervised workspace, and the analytic IK plug-in where one exists (the PUMA 560's).

Every other service learns all of this from the arm's `describe` / `robot/arm/description`
(`ArmModel.description`), never from constants of its own.

A bad model fails at start-up with a `ConfigError` whose key is `arm.model` and whose
message names the file and the element: a URDF that is not well-formed, a chain with the
wrong number of joints, a missing flange frame, a joint without limits, a TOML key that is
misspelt or a value of the wrong size.

Units: m, rad, s. Joint vectors have the model's n joints, joint 1 first (base outwards).
"""

from __future__ import annotations

import math
import tomllib
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from services.bus.config import section
from services.bus.errors import ConfigError
from services.geometry import M9, V3, is_rotation, rotation_problem

MODELS_DIR = Path(__file__).parent / "models"
SHIPPED: tuple[str, ...] = ("puma560", "fr3", "ur5e")
DEFAULT_MODEL = "puma560"
MODEL_FILE = "arm.toml"
MAX_JOINTS = 32
"""The most joints a model may have (the wire's joint vectors are bounded by it too)."""
MAX_URDF_BYTES = 1 << 20
"""A URDF larger than this is refused (the description carries its text on the wire)."""
KEY = "arm.model"


# --- the model file's tables (read strictly: an unknown key is an error naming it) ---------


@dataclass(frozen=True, slots=True)
class _ModelTable:
    name: str
    urdf: str
    joints: int
    flange_frame: str
    base_frame: str = ""
    packages: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class _MountTable:
    """Where the URDF's root stands in the world (the cell): a fixed joint from a new root
    link `frame` (the world frame R_w) to the URDF's root, at `xyz` (m) and `rpy` (rad)."""

    frame: str = "world"
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class _LimitsTable:
    max_accel_rad_s2: tuple[float, ...]
    speed_rad_s: tuple[float, ...] = ()
    accel_rad_s2: tuple[float, ...] = ()
    max_target_step_m: float = 0.05
    max_target_step_rad: float = 0.35


@dataclass(frozen=True, slots=True)
class _ToolTable:
    p: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class _WorkspaceTable:
    min: tuple[float, float, float]
    max: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class _IkTable:
    analytic: str = ""
    posture: str = "home"


@dataclass(frozen=True, slots=True)
class _GripperTable:
    joints: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class _ModelFile:
    model: _ModelTable
    limits: _LimitsTable
    named: dict[str, tuple[float, ...]]
    tool: _ToolTable = field(default_factory=_ToolTable)
    mount: _MountTable | None = None
    workspace: _WorkspaceTable | None = None
    ik: _IkTable = field(default_factory=_IkTable)
    gripper: _GripperTable = field(default_factory=_GripperTable)


# --- the model ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class JointSpec:
    """One joint of the arm: its URDF name, position limits (rad), and the speed (rad/s,
    the URDF's `velocity`) and acceleration (rad/s², the model file's) it is capable of."""

    name: str
    lo: float
    hi: float
    max_speed: float
    max_accel: float


@dataclass(frozen=True, slots=True, eq=False)
class ArmModel:
    """A loaded arm (see the module docstring). Immutable; `pin_model()` builds a fresh
    Pinocchio model for each user (Pinocchio's data is per thread)."""

    name: str
    path: Path
    """The model file (arm.toml)."""
    urdf: str = field(repr=False)
    """The URDF text the kinematics is built from (with the mount joint when there is one):
    what `describe` serves."""
    base_frame: str
    flange_frame: str
    joints: tuple[JointSpec, ...]
    plan_speed_rad_s: tuple[float, ...]
    """The joint speeds the arm plans and filters with (≤ each joint's max_speed)."""
    plan_accel_rad_s2: tuple[float, ...]
    tool_p: V3
    tool_R: M9
    """The default tool placement eMt in the flange frame."""
    named: dict[str, tuple[float, ...]]
    """Named configurations (rad), `home` among them."""
    max_target_step_m: float
    max_target_step_rad: float
    reach_m: float
    """An upper bound of the tool point's distance from the world origin (m), for the
    default tool: the sum of the chain's link offsets and the tool's."""
    workspace_min: V3 | None
    workspace_max: V3 | None
    analytic_ik: str | None
    """`module:Class` of the analytic IK plug-in, or None (numerical IK)."""
    posture: str
    """The named configuration the numerical IK's null-space task keeps a redundant arm
    near."""
    grip_joints: tuple[str, ...]
    package_dirs: dict[str, Path]
    """package:// roots of the URDF's meshes."""
    locked: dict[str, float]
    """Joints of the URDF that are not on the chain (fingers): held at these values."""

    @property
    def n(self) -> int:
        return len(self.joints)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @property
    def q_lo(self) -> tuple[float, ...]:
        return tuple(j.lo for j in self.joints)

    @property
    def q_hi(self) -> tuple[float, ...]:
        return tuple(j.hi for j in self.joints)

    @property
    def home(self) -> tuple[float, ...]:
        return self.named["home"]

    @property
    def redundant(self) -> bool:
        return self.n > 6

    @property
    def folder(self) -> Path:
        return self.path.parent

    def pin_model(self) -> pin.Model:
        """The Pinocchio model of the chain (joints off the chain locked), built anew."""
        return _reduced(_build(self.urdf, self.path), self.joint_names, self.locked)

    def geometry(self, kind: pin.GeometryType = pin.GeometryType.VISUAL) -> pin.GeometryModel:
        """The URDF's visual (or collision) geometry on the chain's model, meshes resolved
        from the model's package roots. For drawing; raises ConfigError if a mesh file is
        missing."""
        full = _build(self.urdf, self.path)
        # package:// URIs resolved here (Pinocchio would want each package in a folder of
        # its own name); a relative path is relative to the model's folder.
        text = self.urdf
        for name, folder in self.package_dirs.items():
            text = text.replace(f"package://{name}/", f"{folder}/")
        try:
            geom = pin.buildGeomFromUrdfString(full, text, kind, package_dirs=[str(self.folder)])
        except (RuntimeError, ValueError) as e:
            raise ConfigError(KEY, f"{self.path}: the URDF's meshes: {_short(e)}") from None
        ids = [full.getJointId(n) for n in full.names[1:] if n in self.locked]
        q = _neutral_with(full, self.locked)
        _, reduced = pin.buildReducedModel(full, geom, ids, q)
        return reduced

    def kinematics(self) -> Any:
        """A new kinematics instance for this model (one per thread): the analytic plug-in
        where the model has one, else numerical (services.control.arm.kinematics)."""
        from services.control.arm.kinematics import make_kinematics

        return make_kinematics(self)

    def check_joints(
        self, key: str, q: Any, in_limits: bool = True, where: str = ""
    ) -> tuple[float, ...]:
        """`q` as n finite floats (within the limits if `in_limits`), else ConfigError(key),
        its message led by `where`."""
        lead = f"{where}: " if where else ""
        if not isinstance(q, list | tuple) or len(q) != self.n:
            raise ConfigError(key, f"{lead}must be {self.n} numbers for {self.name}, joint 1 first")
        out = []
        for j, (x, spec) in enumerate(zip(q, self.joints, strict=True)):
            if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
                raise ConfigError(key, f"{lead}joint {j + 1} ({spec.name}) must be a finite number")
            if in_limits and not spec.lo <= x <= spec.hi:
                raise ConfigError(
                    key, f"{lead}joint {j + 1} ({spec.name}) = {x} outside [{spec.lo}, {spec.hi}]"
                )
            out.append(float(x))
        return tuple(out)

    def description(self, tool_p: V3 | None = None, tool_R: M9 | None = None) -> dict[str, Any]:
        """The ArmDescription of PROTOCOL.md §1 for the tool in use (default: the model's),
        with the extensions of docs/protocol-extensions.md."""
        p = self.tool_p if tool_p is None else tool_p
        R = self.tool_R if tool_R is None else tool_R
        out: dict[str, Any] = {
            "model": self.name,
            "n": self.n,
            "joints": [
                {
                    "name": j.name,
                    "lo": j.lo,
                    "hi": j.hi,
                    "max_speed": j.max_speed,
                    "max_accel": j.max_accel,
                }
                for j in self.joints
            ],
            "base_frame": self.base_frame,
            "flange_frame": self.flange_frame,
            "urdf": self.urdf,
            "eMt": {"p": list(p), "R": list(R)},
            "analytic_ik": self.analytic_ik is not None,
            "grip": bool(self.grip_joints),
            "named": {k: list(v) for k, v in self.named.items()},
            "reach_m": self.reach_m,
            "max_target_step_m": self.max_target_step_m,
            "max_target_step_rad": self.max_target_step_rad,
        }
        if self.package_dirs:
            out["packages"] = {k: str(v) for k, v in self.package_dirs.items()}
        if self.workspace_min is not None and self.workspace_max is not None:
            out["workspace"] = {"min": list(self.workspace_min), "max": list(self.workspace_max)}
        return out


# --- loading ------------------------------------------------------------------------------


def model_path(spec: str | Path) -> Path:
    """The model file a name or path means: a shipped model's name, a folder holding an
    arm.toml, or a TOML file. ConfigError("arm.model") when there is none."""
    text = str(spec)
    if text in SHIPPED:
        return MODELS_DIR / text / MODEL_FILE
    p = Path(text).expanduser()
    if p.is_dir():
        p = p / MODEL_FILE
    if p.suffix != ".toml" or not p.is_file():
        raise ConfigError(
            KEY, f"{text!r}: no such model (shipped: {', '.join(SHIPPED)}; or the path of an "
            "arm's TOML next to its URDF)"
        )  # fmt: skip
    return p


_CACHE: dict[Path, ArmModel] = {}


def load_model(spec: str | Path = DEFAULT_MODEL) -> ArmModel:
    """The ArmModel of a shipped name or a TOML path (loaded once per process)."""
    path = model_path(spec).resolve()
    model = _CACHE.get(path)
    if model is None:
        model = _CACHE[path] = _load(path)
    return model


def _load(path: Path) -> ArmModel:
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(KEY, f"{path}: {e}") from None
    try:
        spec = section(_ModelFile, data, "")
    except ConfigError as e:
        raise ConfigError(KEY, f"{path}: [{e.key.lstrip('.')}] {e.reason}") from None
    m = spec.model
    urdf_path = (path.parent / m.urdf).resolve()
    try:
        raw = urdf_path.read_bytes()
    except OSError as e:
        raise ConfigError(KEY, f"{path}: [model] urdf: {urdf_path}: {e.strerror}") from None
    if len(raw) > MAX_URDF_BYTES:
        raise ConfigError(KEY, f"{urdf_path}: larger than {MAX_URDF_BYTES} bytes")
    try:
        root = ET.fromstring(raw)
    except ET.ParseError as e:
        raise ConfigError(KEY, f"{urdf_path}: not well-formed XML ({e})") from None
    if root.tag != "robot":
        raise ConfigError(KEY, f"{urdf_path}: the root element is <{root.tag}>, not <robot>")
    urdf_root = _root_link(root, urdf_path)
    base = urdf_root
    if spec.mount is not None:
        base = _mount(root, urdf_root, spec.mount, urdf_path)
    if m.base_frame and m.base_frame != base:
        raise ConfigError(
            KEY, f"{path}: [model] base_frame {m.base_frame!r} is not the URDF's root ({base!r})"
        )
    chain = _chain(root, base, m.flange_frame, urdf_path)
    if len(chain) != m.joints:
        names = ", ".join(j.get("name", "?") for j in chain)
        raise ConfigError(
            KEY,
            f"{urdf_path}: {len(chain)} moving joints from {base!r} to {m.flange_frame!r} "
            f"({names}), but {path.name} says joints = {m.joints}",
        )
    if not 1 <= m.joints <= MAX_JOINTS:
        raise ConfigError(KEY, f"{path}: [model] joints must be 1 … {MAX_JOINTS}")
    n = m.joints
    lim = spec.limits
    accel = _n_positive(path, "limits.max_accel_rad_s2", lim.max_accel_rad_s2, n)
    joints = tuple(_joint_spec(j, a, urdf_path) for j, a in zip(chain, accel, strict=True))
    speeds = tuple(j.max_speed for j in joints)
    plan_speed = _n_positive(path, "limits.speed_rad_s", lim.speed_rad_s or speeds, n, speeds)
    plan_accel = _n_positive(path, "limits.accel_rad_s2", lim.accel_rad_s2 or accel, n, accel)
    text = ET.tostring(root, encoding="unicode")
    locked = _locked(root, chain, spec.gripper.joints, urdf_path)
    tool_R = _rpy_matrix(spec.tool.rpy)
    model = ArmModel(
        name=m.name,
        path=path,
        urdf=text,
        base_frame=base,
        flange_frame=m.flange_frame,
        joints=joints,
        plan_speed_rad_s=plan_speed,
        plan_accel_rad_s2=plan_accel,
        tool_p=spec.tool.p,
        tool_R=tool_R,
        named={},
        max_target_step_m=_positive(path, "limits.max_target_step_m", lim.max_target_step_m),
        max_target_step_rad=_positive(path, "limits.max_target_step_rad", lim.max_target_step_rad),
        reach_m=0.0,
        workspace_min=spec.workspace.min if spec.workspace else None,
        workspace_max=spec.workspace.max if spec.workspace else None,
        analytic_ik=spec.ik.analytic or None,
        posture=spec.ik.posture,
        grip_joints=spec.gripper.joints,
        package_dirs={k: (path.parent / v).resolve() for k, v in m.packages.items()},
        locked=locked,
    )
    # Pinocchio must build it, and the named configurations must fit it.
    pm = model.pin_model()
    if not pm.existFrame(m.flange_frame):
        raise ConfigError(KEY, f"{urdf_path}: no frame {m.flange_frame!r} after the build")
    named = {
        k: model.check_joints(KEY, list(v), where=f"{path}: [named] {k}")
        for k, v in spec.named.items()
    }
    if "home" not in named:
        raise ConfigError(KEY, f"{path}: [named] needs a `home` configuration")
    if model.posture not in named:
        raise ConfigError(KEY, f"{path}: [ik] posture {model.posture!r} is not in [named]")
    if spec.workspace is not None and not all(
        a < b for a, b in zip(spec.workspace.min, spec.workspace.max, strict=True)
    ):
        raise ConfigError(KEY, f"{path}: [workspace] every min must be below its max")
    object.__setattr__(model, "named", named)
    object.__setattr__(model, "reach_m", _reach(pm, m.flange_frame, spec.tool.p))
    return model


def _short(e: BaseException, n: int = 300) -> str:
    s = str(e).strip().splitlines()
    text = s[0] if s else type(e).__name__
    return text if len(text) <= n else text[: n - 1] + "…"


def _root_link(root: ET.Element, urdf: Path) -> str:
    links = [e.get("name") for e in root.findall("link")]
    if not links or any(not name for name in links):
        raise ConfigError(KEY, f"{urdf}: a <link> without a name, or no <link> at all")
    children = {c.get("link") for j in root.findall("joint") for c in j.findall("child")}
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise ConfigError(KEY, f"{urdf}: {len(roots)} root links ({', '.join(map(str, roots))})")
    return str(roots[0])


def _mount(root: ET.Element, urdf_root: str, mount: _MountTable, urdf: Path) -> str:
    if any(e.get("name") == mount.frame for e in root.findall("link")):
        raise ConfigError(KEY, f"{urdf}: [mount] frame {mount.frame!r} is already a link")
    link = ET.Element("link", {"name": mount.frame})
    joint = ET.Element("joint", {"name": f"{mount.frame}_mount", "type": "fixed"})
    ET.SubElement(joint, "parent", {"link": mount.frame})
    ET.SubElement(joint, "child", {"link": urdf_root})
    ET.SubElement(
        joint,
        "origin",
        {"xyz": " ".join(map(repr, mount.xyz)), "rpy": " ".join(map(repr, mount.rpy))},
    )
    root.insert(0, joint)
    root.insert(0, link)
    return mount.frame


def _chain(root: ET.Element, base: str, flange: str, urdf: Path) -> list[ET.Element]:
    """The moving joints from `base` to the link `flange`, base first."""
    by_child: dict[str, ET.Element] = {}
    for j in root.findall("joint"):
        c, pa = j.find("child"), j.find("parent")
        if c is None or pa is None or not c.get("link") or not pa.get("link"):
            raise ConfigError(KEY, f"{urdf}: <joint name={j.get('name')!r}> needs parent and child")
        by_child[str(c.get("link"))] = j
    if not any(e.get("name") == flange for e in root.findall("link")):
        raise ConfigError(KEY, f"{urdf}: no <link name={flange!r}> (the model's flange_frame)")
    chain: list[ET.Element] = []
    link = flange
    while link != base:
        found = by_child.get(link)
        if found is None:
            raise ConfigError(KEY, f"{urdf}: {flange!r} does not hang from {base!r}")
        j = found
        kind = j.get("type")
        if kind not in ("fixed", "revolute"):
            raise ConfigError(
                KEY,
                f"{urdf}: <joint name={j.get('name')!r} type={kind!r}> on the arm's chain: "
                "only revolute (with <limit>) and fixed joints are supported",
            )
        if kind == "revolute":
            chain.append(j)
        link = str(j.find("parent").get("link"))  # type: ignore[union-attr]
    chain.reverse()
    return chain


def _joint_spec(j: ET.Element, accel: float, urdf: Path) -> JointSpec:
    name = str(j.get("name"))
    lim = j.find("limit")
    where = f"{urdf}: <joint name={name!r}>"
    if lim is None:
        raise ConfigError(KEY, f"{where} has no <limit>")
    values: dict[str, float] = {}
    for attr in ("lower", "upper", "velocity"):
        try:
            values[attr] = float(lim.get(attr, "nan"))
        except ValueError:
            values[attr] = math.nan
        if not math.isfinite(values[attr]):
            raise ConfigError(KEY, f"{where} <limit {attr}=…> missing or not a number")
    lo, hi, v = values["lower"], values["upper"], values["velocity"]
    if not lo < hi or hi - lo > 4 * math.pi + 1e-9 or v <= 0.0:
        raise ConfigError(KEY, f"{where} <limit>: needs lower < upper within 4π and velocity > 0")
    return JointSpec(name, lo, hi, v, accel)


def _locked(
    root: ET.Element, chain: list[ET.Element], grip: tuple[str, ...], urdf: Path
) -> dict[str, float]:
    """Every moving joint off the chain (a gripper's fingers), held at 0 or its lower limit."""
    on_chain = {j.get("name") for j in chain}
    out: dict[str, float] = {}
    names = set()
    for j in root.findall("joint"):
        name = str(j.get("name"))
        names.add(name)
        if j.get("type") == "fixed" or name in on_chain:
            continue
        lim = j.find("limit")
        lo = float(lim.get("lower", "0")) if lim is not None else 0.0
        out[name] = lo if lo > 0.0 else 0.0
    for g in grip:
        if g not in names:
            raise ConfigError(KEY, f"{urdf}: the gripper's joint {g!r} is not in the URDF")
    return out


def _n_positive(
    path: Path,
    key: str,
    values: tuple[float, ...],
    n: int,
    at_most: tuple[float, ...] | None = None,
) -> tuple[float, ...]:
    if len(values) != n:
        raise ConfigError(KEY, f"{path}: [{key.replace('.', '] ', 1)} must be {n} numbers")
    for j, x in enumerate(values):
        if not (math.isfinite(x) and x > 0.0):
            raise ConfigError(KEY, f"{path}: [{key.replace('.', '] ', 1)}: joint {j + 1} ≤ 0")
        if at_most is not None and x > at_most[j] * (1 + 1e-12):
            raise ConfigError(
                KEY,
                f"{path}: [{key.replace('.', '] ', 1)}: joint {j + 1} above what it can do "
                f"({at_most[j]})",
            )
    return tuple(float(x) for x in values)


def _positive(path: Path, key: str, x: float) -> float:
    if not (math.isfinite(x) and x > 0.0):
        raise ConfigError(KEY, f"{path}: [{key.replace('.', '] ', 1)} must be > 0")
    return float(x)


def _rpy_matrix(rpy: tuple[float, float, float]) -> M9:
    R = pin.rpy.rpyToMatrix(*rpy)
    if rotation_problem(R) is not None or not is_rotation(R):
        raise ConfigError(KEY, "[tool] rpy is not a rotation")
    return tuple(float(x) for x in np.asarray(R).reshape(9))  # type: ignore[return-value]


def _build(urdf: str, path: Path) -> pin.Model:
    try:
        return pin.buildModelFromXML(urdf)
    except (RuntimeError, ValueError) as e:
        raise ConfigError(KEY, f"{path}: Pinocchio cannot build the URDF: {_short(e)}") from None


def _neutral_with(full: pin.Model, locked: dict[str, float]) -> np.ndarray:
    q = pin.neutral(full)
    for name, value in locked.items():
        jid = full.getJointId(name)
        if jid < full.njoints:
            q[full.joints[jid].idx_q] = value
    return q


def _reduced(full: pin.Model, chain: tuple[str, ...], locked: dict[str, float]) -> pin.Model:
    ids = [full.getJointId(n) for n in full.names[1:] if n not in chain]
    reduced = pin.buildReducedModel(full, ids, _neutral_with(full, locked)) if ids else full
    names = tuple(reduced.names[1:])
    if names != chain or reduced.nq != len(chain):
        raise ConfigError(KEY, f"the chain's joints {chain} built as {names} (nq {reduced.nq})")
    return reduced


def _reach(model: pin.Model, flange: str, tool_p: V3) -> float:
    """Sum of the joints' placement offsets and the flange's and tool's: a bound of how far
    from the world origin the tool point can be."""
    placements = model.jointPlacements
    total = sum(float(np.linalg.norm(placements[i].translation)) for i in range(1, model.njoints))
    frame = model.frames[model.getFrameId(flange)]
    total += float(np.linalg.norm(frame.placement.translation))
    return round(total + math.hypot(*tool_p), 6)


def model_from_description(desc: Any) -> ArmModel:
    """The ArmModel a peer described (an `ArmDescription`, from `robot/arm/description` or
    `describe`): what a consumer needs to draw the arm or compute the pose of every link —
    its chain, limits, frames and visuals — from the description alone. The meshes of a
    shipped model are found in this checkout's copy of it; another model's are not (its
    visuals are then left out: `geometry` raises). ConfigError("arm.model") when the URDF
    does not build."""
    where = Path(f"<description of {desc.model}>")
    try:
        root = ET.fromstring(desc.urdf)
    except ET.ParseError as e:
        raise ConfigError(KEY, f"{where}: the URDF is not well-formed XML ({e})") from None
    chain = _chain(root, desc.base_frame, desc.flange_frame, where)
    names = [str(j.get("name")) for j in chain]
    if names != [j["name"] for j in desc.joints]:
        raise ConfigError(KEY, f"{where}: the URDF's chain {names} is not the joints described")
    shipped = MODELS_DIR / desc.model / MODEL_FILE if desc.model in SHIPPED else None
    packages = load_model(desc.model).package_dirs if shipped is not None else {}
    p, R = desc.eMt["p"], desc.eMt["R"]
    named = {k: tuple(float(x) for x in v) for k, v in (desc.named or {}).items()}
    ws = desc.workspace or {}
    model = ArmModel(
        name=desc.model,
        path=shipped if shipped is not None else where,
        urdf=desc.urdf,
        base_frame=desc.base_frame,
        flange_frame=desc.flange_frame,
        joints=tuple(
            JointSpec(
                str(j["name"]),
                float(j["lo"]),
                float(j["hi"]),
                float(j["max_speed"]),
                float(j["max_accel"]),
            )
            for j in desc.joints
        ),
        plan_speed_rad_s=tuple(float(j["max_speed"]) for j in desc.joints),
        plan_accel_rad_s2=tuple(float(j["max_accel"]) for j in desc.joints),
        tool_p=(float(p[0]), float(p[1]), float(p[2])),
        tool_R=tuple(float(x) for x in R),  # type: ignore[arg-type]
        named=named or {"home": tuple(0.5 * (j["lo"] + j["hi"]) for j in desc.joints)},
        max_target_step_m=float(desc.max_target_step_m or 0.05),
        max_target_step_rad=float(desc.max_target_step_rad or 0.35),
        reach_m=float(desc.reach_m or 0.0),
        workspace_min=tuple(ws["min"]) if "min" in ws else None,
        workspace_max=tuple(ws["max"]) if "max" in ws else None,
        analytic_ik=None,
        posture="home" if "home" in named or not named else next(iter(named)),
        grip_joints=(),
        package_dirs=packages,
        locked=_locked(root, chain, (), where),
    )
    model.pin_model()  # it must build
    return model
