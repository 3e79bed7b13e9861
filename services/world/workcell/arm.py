"""The arm as the physics needs it, from the arm's description (`robot/arm/description`).

The workcell's physics builds the arm into the cell from what the arm service describes: its
URDF, joint names, flange frame, the tool in use (eMt), its named `home`, and where the
URDF's `package://` meshes are on this host (the `packages` extension). `DescribedArm`
holds exactly that; an `ArmModel` (services/control/arm/model.py) has the same attributes,
so either builds the cell (`build_cell`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from services.bus.messages import ArmDescription


@dataclass(frozen=True, slots=True, eq=False)
class DescribedArm:
    """What `build_cell` reads of an arm (names as on `ArmModel`)."""

    name: str
    path: Path
    urdf: str
    joint_names: tuple[str, ...]
    flange_frame: str
    tool_p: tuple[float, float, float]
    tool_R: tuple[float, ...]
    home: tuple[float, ...]
    package_dirs: dict[str, Path]

    @property
    def n(self) -> int:
        return len(self.joint_names)

    @property
    def folder(self) -> Path:
        return self.path.parent

    @classmethod
    def of(cls, desc: ArmDescription) -> DescribedArm:
        """The arm a (validated) description describes."""
        packages = {k: Path(v) for k, v in (desc.packages or {}).items()}
        named = desc.named or {}
        joints = tuple(str(j["name"]) for j in desc.joints)
        home = named.get("home") or [0.5 * (j["lo"] + j["hi"]) for j in desc.joints]
        folder = next(iter(packages.values()), Path("."))
        p, R = desc.eMt["p"], desc.eMt["R"]
        return cls(
            name=desc.model,
            path=folder / f"<description of {desc.model}>",
            urdf=desc.urdf,
            joint_names=joints,
            flange_frame=desc.flange_frame,
            tool_p=(float(p[0]), float(p[1]), float(p[2])),
            tool_R=tuple(float(x) for x in R),
            home=tuple(float(x) for x in home),
            package_dirs=packages,
        )
