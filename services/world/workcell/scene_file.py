"""A user's own scene from a TOML file: the `[scene]` table of a deployment names it.

    [scene]
    file = "my-cell.toml"        # a path (`~` expanded; relative to where the service runs)

The file describes what `Scene` holds, every value checked when it is read (a bad one is a
ConfigError naming it, so the service fails at start-up):

    floor_z = 0.0                # m (optional)

    [[box]]                      # a fixture (a table, a wall) or, movable, an object
    name = "table"
    center = [0.60, 0.0, 0.20]   # m, world (z up)
    size = [0.50, 0.90, 0.40]    # m, full edge lengths
    color = [60, 90, 140]        # BGR 0…255 (optional)
    movable = false              # optional; true: the gripper may pick it up

    [[cylinder]]                 # upright; movable with liquid: an open bottle
    name = "bottle"
    base = [0.55, 0.25, 0.40]    # m, centre of its base
    radius = 0.035
    height = 0.20
    movable = true
    liquid_height_m = 0.18       # optional, ≤ height

The workcell (its MuJoCo cell), the vision service's simulated cameras and the console's 3D
view read the same `[scene]`, so what is simulated is what is drawn.
deploy/scenes/standard.toml is the standard scene written this way (`default_scene()`).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from services.bus.errors import ConfigError
from services.world.workcell.scene import Box, Cylinder, Scene

MAX_EXTENT_M = 20.0
"""No coordinate or size beyond this (m): a cell, not a typo in millimetres."""
MAX_SOLIDS = 64
"""Solids per scene: each is a body in the physics and a shape in every view."""
MAX_NAME = 64
BOX_COLOR = (160, 160, 160)
CYLINDER_COLOR = (200, 140, 60)
"""The colours a solid without `color` gets (scene.Box's and scene.Cylinder's)."""

_BOX_KEYS = {"name", "center", "size", "color", "movable"}
_CYLINDER_KEYS = {"name", "base", "radius", "height", "color", "movable", "liquid_height_m"}
_TOP_KEYS = {"floor_z", "box", "cylinder"}


def deploy_scene(deploy: Mapping[str, Any]) -> Scene | None:
    """The scene a deployment's `[scene]` table names (None: no table, the standard one)."""
    table = deploy.get("scene")
    if table is None:
        return None
    if not isinstance(table, Mapping):
        raise ConfigError("scene", "must be a table with `file`")
    unknown = sorted(set(table) - {"file"})
    if unknown:
        raise ConfigError(f"scene.{unknown[0]}", "unknown key; [scene] has only `file`")
    path = table.get("file")
    if not isinstance(path, str) or not path:
        raise ConfigError("scene.file", "must be the path of a scene TOML")
    return load_scene(path)


def load_scene(path: str | Path) -> Scene:
    """The `Scene` in the TOML file at `path` (see the module docstring); ConfigError naming
    the file and the value when anything is wrong."""
    p = Path(path).expanduser()
    try:
        with p.open("rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError("scene.file", f"no such file {str(p)!r}") from None
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigError("scene.file", f"{p}: {e}") from None
    return scene_of(data, where=str(p))


def scene_of(data: Mapping[str, Any], where: str = "scene") -> Scene:
    """The `Scene` of a parsed scene file (`where` names it in errors)."""
    _only(data, _TOP_KEYS, where)
    floor_z = _number(data.get("floor_z", 0.0), f"{where}: floor_z")
    boxes = [_box(b, f"{where}: box[{i}]") for i, b in enumerate(_list(data, "box", where))]
    cylinders = [
        _cylinder(c, f"{where}: cylinder[{i}]")
        for i, c in enumerate(_list(data, "cylinder", where))
    ]
    solids: list[Box | Cylinder] = [*boxes, *cylinders]
    if not solids:
        raise ConfigError("scene.file", f"{where}: no [[box]] or [[cylinder]]")
    if len(solids) > MAX_SOLIDS:
        raise ConfigError("scene.file", f"{where}: {len(solids)} solids, at most {MAX_SOLIDS}")
    seen: set[str] = set()
    for s in solids:
        if s.name in seen:
            raise ConfigError("scene.file", f"{where}: two solids are called {s.name!r}")
        seen.add(s.name)
    return Scene(floor_z=floor_z, boxes=tuple(boxes), cylinders=tuple(cylinders))


def _box(t: Any, where: str) -> Box:
    t = _table(t, where)
    _only(t, _BOX_KEYS, where)
    return Box(
        name=_name(t, where),
        center=_point(t, "center", where),
        size=_size3(t, "size", where),
        color=_color(t, where, BOX_COLOR),
        movable=_flag(t, "movable", where),
    )


def _cylinder(t: Any, where: str) -> Cylinder:
    t = _table(t, where)
    _only(t, _CYLINDER_KEYS, where)
    height = _length(t, "height", where)
    liquid = _number(t.get("liquid_height_m", 0.0), f"{where}.liquid_height_m")
    if not 0.0 <= liquid <= height:
        raise ConfigError("scene.file", f"{where}.liquid_height_m: {liquid:g} not in [0, height]")
    return Cylinder(
        name=_name(t, where),
        base=_point(t, "base", where),
        radius=_length(t, "radius", where),
        height=height,
        color=_color(t, where, CYLINDER_COLOR),
        movable=_flag(t, "movable", where),
        liquid_height_m=liquid,
    )


def _list(data: Mapping[str, Any], key: str, where: str) -> list[Any]:
    v = data.get(key, [])
    if not isinstance(v, list):
        raise ConfigError("scene.file", f"{where}: {key} must be [[{key}]] tables")
    return v


def _table(t: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(t, Mapping):
        raise ConfigError("scene.file", f"{where}: must be a table")
    return t


def _only(t: Mapping[str, Any], keys: set[str], where: str) -> None:
    unknown = sorted(set(t) - keys)
    if unknown:
        name = str(unknown[0])[:MAX_NAME]
        raise ConfigError("scene.file", f"{where}: unknown key {name!r}; known: {sorted(keys)}")


def _name(t: Mapping[str, Any], where: str) -> str:
    v = t.get("name")
    if not isinstance(v, str) or not 0 < len(v) <= MAX_NAME or not v.isprintable():
        raise ConfigError("scene.file", f"{where}.name: must be 1–{MAX_NAME} printable characters")
    return v


def _number(v: Any, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ConfigError("scene.file", f"{what}: must be a finite number")
    if abs(v) > MAX_EXTENT_M:
        raise ConfigError("scene.file", f"{what}: {v:g} m is beyond {MAX_EXTENT_M:g} m")
    return float(v)


def _length(t: Mapping[str, Any], key: str, where: str) -> float:
    v = _number(t.get(key), f"{where}.{key}")
    if not v > 0.0:
        raise ConfigError("scene.file", f"{where}.{key}: must be > 0 m")
    return v


def _triple(t: Mapping[str, Any], key: str, where: str) -> list[float]:
    v = t.get(key)
    if not isinstance(v, list) or len(v) != 3:
        raise ConfigError("scene.file", f"{where}.{key}: must be 3 numbers")
    return [_number(x, f"{where}.{key}") for x in v]


def _point(t: Mapping[str, Any], key: str, where: str) -> tuple[float, float, float]:
    x, y, z = _triple(t, key, where)
    return (x, y, z)


def _size3(t: Mapping[str, Any], key: str, where: str) -> tuple[float, float, float]:
    x, y, z = _triple(t, key, where)
    if not min(x, y, z) > 0.0:
        raise ConfigError("scene.file", f"{where}.{key}: every edge must be > 0 m")
    return (x, y, z)


def _color(t: Mapping[str, Any], where: str, default: tuple[int, int, int]) -> tuple[int, int, int]:
    v = t.get("color")
    if v is None:
        return default
    ok = isinstance(v, list) and len(v) == 3
    if not ok or not all(
        isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= 255 for c in v
    ):
        raise ConfigError("scene.file", f"{where}.color: must be 3 integers 0…255 (BGR)")
    return (v[0], v[1], v[2])


def _flag(t: Mapping[str, Any], key: str, where: str) -> bool:
    v = t.get(key, False)
    if not isinstance(v, bool):
        raise ConfigError("scene.file", f"{where}.{key}: must be true or false")
    return v
