"""`FrankaParams`: what the libfranka driver sets on the robot and interpolates within, read
from the model folder's `franka.toml` (beside its `arm.toml`; the FR3's ships with it).

Every table and key is required and checked (a vector of the wrong length, a value that is
not a finite positive number): a bad file fails at start-up naming `arm.model`, the file and
the key, like the model itself.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.bus.errors import ConfigError
from services.control.arm.model import ArmModel

FILE = "franka.toml"
KEY = "arm.model"
Floats = tuple[float, ...]


@dataclass(frozen=True, slots=True)
class FrankaParams:
    """Collision thresholds (libfranka `setCollisionBehavior`: joint torques N·m, Cartesian
    forces N and torques N·m), impedances (`setJointImpedance` N·m/rad, `setCartesianImpedance`
    N/m and N·m/rad), the interpolator's joint limits (rad/s, rad/s², rad/s³) and the hand's
    full width (m) and speed (m/s)."""

    lower_torque_nm: Floats
    upper_torque_nm: Floats
    lower_force: Floats
    upper_force: Floats
    joint_impedance: Floats
    cartesian_impedance: Floats
    velocity_rad_s: Floats
    accel_rad_s2: Floats
    jerk_rad_s3: Floats
    gripper_max_width_m: float
    gripper_speed_m_s: float

    def wire(self) -> dict[str, Any]:
        """As plain lists, for the real-time process's `configure` and `start` requests."""
        return {
            "lower_torque": list(self.lower_torque_nm),
            "upper_torque": list(self.upper_torque_nm),
            "lower_force": list(self.lower_force),
            "upper_force": list(self.upper_force),
            "joint_impedance": list(self.joint_impedance),
            "cartesian_impedance": list(self.cartesian_impedance),
        }


def load_params(model: ArmModel) -> FrankaParams:
    """The `franka.toml` beside `model`'s arm.toml, checked for its n joints."""
    path = model.folder / FILE
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(
            KEY,
            f"{path}: missing — the libfranka driver needs the robot's collision thresholds, "
            "impedances and interpolator limits (see docs/franka.md)",
        ) from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(KEY, f"{path}: {e}") from None
    n = model.n
    if n != 7:
        raise ConfigError("arm.driver", f"libfranka drives 7-joint arms, {model.name} has {n}")
    tables = {"collision", "impedance", "interpolator", "gripper"}
    for name in data:
        if name not in tables:
            raise ConfigError(KEY, f"{path}: unknown table [{name}]")
    col = _table(
        data,
        "collision",
        path,
        {"lower_torque_nm", "upper_torque_nm", "lower_force", "upper_force"},
    )
    imp = _table(data, "impedance", path, {"joint_nm_rad", "cartesian"})
    itp = _table(data, "interpolator", path, {"velocity_rad_s", "accel_rad_s2", "jerk_rad_s3"})
    grip = _table(data, "gripper", path, {"max_width_m", "speed_m_s"})
    return FrankaParams(
        lower_torque_nm=_vec(col, "collision", "lower_torque_nm", 7, path),
        upper_torque_nm=_vec(col, "collision", "upper_torque_nm", 7, path),
        lower_force=_vec(col, "collision", "lower_force", 6, path),
        upper_force=_vec(col, "collision", "upper_force", 6, path),
        joint_impedance=_vec(imp, "impedance", "joint_nm_rad", 7, path),
        cartesian_impedance=_vec(imp, "impedance", "cartesian", 6, path),
        velocity_rad_s=_vec(itp, "interpolator", "velocity_rad_s", 7, path),
        accel_rad_s2=_vec(itp, "interpolator", "accel_rad_s2", 7, path),
        jerk_rad_s3=_vec(itp, "interpolator", "jerk_rad_s3", 7, path),
        gripper_max_width_m=_vec(grip, "gripper", "max_width_m", 0, path)[0],
        gripper_speed_m_s=_vec(grip, "gripper", "speed_m_s", 0, path)[0],
    )


def _table(data: dict[str, Any], name: str, path: Path, keys: set[str]) -> dict[str, Any]:
    t = data.get(name)
    if not isinstance(t, dict):
        raise ConfigError(KEY, f"{path}: [{name}] missing")
    for k in t:
        if k not in keys:
            raise ConfigError(
                KEY, f"{path}: [{name}] {k}: unknown key (known: {', '.join(sorted(keys))})"
            )
    for k in sorted(keys):
        if k not in t:
            raise ConfigError(KEY, f"{path}: [{name}] {k}: required")
    return t


def _vec(t: dict[str, Any], table: str, key: str, n: int, path: Path) -> Floats:
    """`n` finite positive numbers (n = 0: one number)."""
    v = t[key]
    values = [v] if n == 0 else v
    where = f"{path}: [{table}] {key}"
    if not isinstance(values, list) or (n and len(values) != n):
        raise ConfigError(KEY, f"{where}: must be {n or 1} numbers")
    out = []
    for x in values:
        if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x) or x <= 0:
            raise ConfigError(KEY, f"{where}: every value must be a finite number > 0")
        out.append(float(x))
    return tuple(out)
