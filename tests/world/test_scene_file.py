"""A user's own scene from a TOML file (`[scene] file`): deploy/scenes/standard.toml is the
standard scene, every bad value fails at start-up naming it, and the workcell, the simulated cameras
and the console all take the one the deployment names."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from services.bus.config import load_deploy
from services.bus.errors import ConfigError
from services.control.arm.model import load_model
from services.control.vision.backends import open_camera
from services.control.vision.config import VisionConfig
from services.control.vision.sim_camera import SimStereoCamera
from services.world.workcell.engine import CellPhysics
from services.world.workcell.scene import Box, Cylinder, default_scene
from services.world.workcell.scene_file import deploy_scene, load_scene, scene_of

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "deploy" / "scenes" / "standard.toml"


def _same(a: Box | Cylinder, b: Box | Cylinder) -> bool:
    """Equal, floats to 1e-12 (0.4 + 0.025 is 0.42500000000000004 in the code's scene)."""
    for f in a.__dataclass_fields__:
        x, y = getattr(a, f), getattr(b, f)
        if isinstance(x, tuple) and x and isinstance(x[0], float):
            if not all(math.isclose(u, v, abs_tol=1e-12) for u, v in zip(x, y, strict=True)):
                return False
        elif isinstance(x, float):
            if not math.isclose(x, y, abs_tol=1e-12):
                return False
        elif x != y:
            return False
    return type(a) is type(b)


def test_the_shipped_scene_file_is_the_standard_scene() -> None:
    got, want = load_scene(SHIPPED), default_scene()
    assert [s.name for s in got.solids()] == [s.name for s in want.solids()]
    assert all(_same(a, b) for a, b in zip(got.solids(), want.solids(), strict=True))
    assert got.floor_z == want.floor_z


def _one_box(**box: Any) -> dict[str, Any]:
    return {"box": [{"name": "table", "center": [0.6, 0.0, 0.2], "size": [0.5, 0.9, 0.4], **box}]}


@pytest.mark.parametrize(
    ("data", "says"),
    [
        ({}, "no [[box]] or [[cylinder]]"),
        ({"boxes": []}, "unknown key 'boxes'"),
        (_one_box(colour=[1, 2, 3]), "box[0]: unknown key 'colour'"),
        (_one_box(size=[0.5, 0.0, 0.4]), "box[0].size: every edge must be > 0 m"),
        (_one_box(size=[0.5, 0.9]), "box[0].size: must be 3 numbers"),
        (_one_box(center=[0.6, math.nan, 0.2]), "box[0].center: must be a finite number"),
        (_one_box(center=[600.0, 0.0, 0.2]), "box[0].center: 600 m is beyond 20 m"),
        (_one_box(center=[0.6, True, 0.2]), "box[0].center: must be a finite number"),
        (_one_box(color=[0, 0, 256]), "box[0].color: must be 3 integers 0…255"),
        (_one_box(movable="yes"), "box[0].movable: must be true or false"),
        (_one_box(name=""), "box[0].name: must be 1–64 printable characters"),
        (_one_box(name="x" * 65), "box[0].name: must be 1–64 printable characters"),
        ({"box": [*_one_box()["box"], *_one_box()["box"]]}, "two solids are called 'table'"),
        ({"box": [{"name": "b"} for _ in range(65)]}, "box[0].center: must be 3 numbers"),
        (
            {"cylinder": [{"name": "c", "base": [0, 0, 0], "radius": 0.03, "height": 0.2,
                           "liquid_height_m": 0.3}]},
            "cylinder[0].liquid_height_m: 0.3 not in [0, height]",
        ),
        (
            {"cylinder": [{"name": "c", "base": [0, 0, 0], "radius": -0.03, "height": 0.2}]},
            "cylinder[0].radius: must be > 0 m",
        ),
        ({"box": {"name": "t"}}, "box must be [[box]] tables"),
        ({"box": ["table"]}, "box[0]: must be a table"),
    ],
)  # fmt: skip
def test_every_bad_value_is_refused_naming_it(data: dict[str, Any], says: str) -> None:
    with pytest.raises(ConfigError) as e:
        scene_of(data, where="s.toml")
    assert e.value.key == "scene.file"
    assert says in str(e.value), str(e.value)


def test_too_many_solids_are_refused() -> None:
    boxes = [
        {"name": f"b{i}", "center": [0.0, 0.0, 0.1 * i], "size": [0.05, 0.05, 0.05]}
        for i in range(65)
    ]
    with pytest.raises(ConfigError, match="65 solids, at most 64"):
        scene_of({"box": boxes})


def test_the_deploy_table_names_the_file_and_nothing_else(tmp_path: Path) -> None:
    assert deploy_scene({}) is None  # no [scene]: the standard one
    with pytest.raises(ConfigError) as e:
        deploy_scene({"scene": {"file": str(tmp_path / "nope.toml")}})
    assert e.value.key == "scene.file" and "no such file" in str(e.value)
    with pytest.raises(ConfigError) as e:
        deploy_scene({"scene": {"path": "x.toml"}})
    assert e.value.key == "scene.path"
    with pytest.raises(ConfigError) as e:
        deploy_scene({"scene": {"file": ""}})
    assert e.value.key == "scene.file"
    broken = tmp_path / "broken.toml"
    broken.write_text("[[box]\n")
    with pytest.raises(ConfigError, match=r"broken\.toml"):
        load_scene(broken)


def test_a_profile_with_a_scene_gives_it_to_the_physics_and_the_cameras(tmp_path: Path) -> None:
    """A table moved and a fourth block added: `[scene] file` in the deployment file is
    accepted and what the workcell and the simulated cameras build from."""
    text = SHIPPED.read_text().replace("center = [0.6, 0.0, 0.2]", "center = [0.65, 0.05, 0.2]")
    text += '\n[[box]]\nname = "block3"\ncenter = [0.5, 0.1, 0.425]\nsize = [0.05, 0.05, 0.05]\n'
    text += "movable = true\n"
    scene_path = tmp_path / "cell.toml"
    scene_path.write_text(text)
    profile = tmp_path / "sim.toml"
    profile.write_text(f'[scene]\nfile = "{scene_path}"\n')
    scene = deploy_scene(load_deploy(profile))
    assert scene is not None
    assert scene.box("table").center == (0.65, 0.05, 0.2)
    assert [s.name for s in scene.movables()] == ["block0", "block1", "block2", "block3", "bottle"]
    cam = open_camera(VisionConfig(), scene)
    assert isinstance(cam, SimStereoCamera) and cam.scene is scene


def test_the_workcell_builds_the_scene_it_is_given() -> None:
    scene = load_scene(SHIPPED)
    extra = Box("block3", center=(0.5, 0.1, 0.425), size=(0.05, 0.05, 0.05), movable=True)
    scene = replace(scene, boxes=(*scene.boxes, extra))
    ph = CellPhysics(load_model("puma560"), scene)
    ph.step(200)
    b = ph.body("block3")
    assert b.phase == "resting" and b.on == "table", b
    assert abs(b.p[2] - 0.425) < 2e-3


@pytest.mark.parametrize(
    "main",
    [
        "services.world.workcell.__main__",
        "services.control.vision.__main__",
        "services.frontends.console.__main__",
    ],
)
def test_each_service_that_draws_or_simulates_the_cell_reads_the_scene(
    main: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The workcell, vision (sim camera) and the console read `[scene]` at start-up: a bad
    file stops each before it opens a session, naming the value (exit 2)."""
    import importlib
    import signal

    bad = tmp_path / "cell.toml"
    bad.write_text('[[box]]\nname = "t"\ncenter = [0, 0, 0]\nsize = [1, 1, -1]\n')
    profile = tmp_path / "sim.toml"
    profile.write_text(f'[vision]\ncamera = "sim"\n\n[scene]\nfile = "{bad}"\n')
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        status = importlib.import_module(main).main(["--config", str(profile)])
    finally:
        for s, h in saved.items():
            signal.signal(s, h)
    assert status == 2
    err = capsys.readouterr().err
    assert "scene.file" in err and "box[0].size: every edge must be > 0 m" in err, err
