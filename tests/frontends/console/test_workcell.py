"""The console's 3D scene follows `workcell/state` (#22): the object nodes the page is sent
sit at the poses the workcell publishes (moved, stacked, tilted), the bottle's liquid and a
spill are drawn, and the gripper's fingers follow robot/state's `grip`. The pure part is
tested against hand-worked cases; the page part through what a browser receives
(`FakeBrowser(decode=True)` unpacks viser's wire format)."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus import keys
from services.bus.errors import ProtocolError
from services.bus.node import Node
from services.control.vision.objects import Spills
from services.frontends.console.app import Console
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.view3d import FINGER_HOLDING_COLOR
from services.frontends.console.workcell import (
    FINGER_SIZE_M,
    GRIPPER_OPEN_M,
    finger_offsets,
    object_node,
    puddle_nodes,
)
from services.geometry import R_from_wxyz, rot_x
from services.world.workcell.messages import WORKCELL_STATE, ObjectView, WorkcellState, objects_of
from services.world.workcell.scene import BLOCK_SIZE_M, TABLE, default_scene

from .support import FakeBrowser, ready_state, wait_until

SCENE = default_scene()
TOP = TABLE.top_z
H = BLOCK_SIZE_M


def _rot_x(deg: float) -> np.ndarray:
    return rot_x(math.radians(deg))


def _obj(
    kind: str,
    p: tuple[float, float, float],
    R: np.ndarray,
    size: tuple[float, float, float],
    phase: str = "resting",
    **extra: Any,
) -> dict[str, Any]:
    return {
        "kind": kind,
        "p": list(p),
        "R": [float(x) for x in np.asarray(R).ravel()],
        "size": list(size),
        "phase": phase,
        "on": "table",
        "tilt_deg": 0.0,
        "max_tilt_deg": 0.0,
        **extra,
    }


BOTTLE_TILT_DEG = 40.0
LIQUID_ML = 300.0
SPILLED_ML = 150.0


def stacked_state(seq: int) -> WorkcellState:
    """Task 2's end: block2 on block1 on block0 at block0's place; block1 turned 30° about z;
    the bottle held, tilted 40° about x, with some liquid spilled."""
    b0 = SCENE.box("block0").center
    c30, s30 = math.cos(math.radians(30)), math.sin(math.radians(30))
    yaw = np.array([[c30, -s30, 0], [s30, c30, 0], [0, 0, 1]])
    objects = {
        "block0": _obj("box", b0, np.eye(3), (H, H, H)),
        "block1": _obj("box", (b0[0], b0[1], b0[2] + H), yaw, (H, H, H)),
        "block2": _obj("box", (b0[0], b0[1], b0[2] + 2 * H), np.eye(3), (H, H, H)),
        "bottle": _obj(
            "cylinder",
            (0.50, 0.20, TOP + 0.10),
            _rot_x(BOTTLE_TILT_DEG),
            (0.07, 0.07, 0.20),
            phase="held",
            liquid_ml=LIQUID_ML,
            spilled_ml=SPILLED_ML,
        ),
    }
    return WorkcellState(
        seq=seq,
        t_ns=time.time_ns(),
        tool_p=(0.5, 0.2, 0.8),
        grip=1.0,
        held="bottle",
        objects=objects,
    )


# --- pure -----------------------------------------------------------------------------------
def test_a_box_is_drawn_at_its_centre_and_orientation() -> None:
    views = objects_of(stacked_state(1))
    node = object_node(SCENE, views["block1"])
    b0 = SCENE.box("block0").center
    assert node.position == pytest.approx((b0[0], b0[1], b0[2] + H))
    R = R_from_wxyz(node.wxyz)
    assert np.allclose(R, np.asarray(stacked_state(1).objects["block1"]["R"]).reshape(3, 3))
    assert node.liquid_height_m == 0.0


def test_a_tilted_bottle_is_drawn_about_its_centre_with_its_liquid() -> None:
    v = objects_of(stacked_state(1))["bottle"]
    node = object_node(SCENE, v)
    bottle = SCENE.cylinder("bottle")
    # Its centre is half its height up its own (tilted) axis from its base.
    axis = _rot_x(BOTTLE_TILT_DEG)[:, 2]
    assert np.allclose(node.position, np.asarray(v.p) + 0.5 * bottle.height * axis)
    assert np.allclose(R_from_wxyz(node.wxyz), _rot_x(BOTTLE_TILT_DEG))
    # 300 ml in a 3.5 cm radius: 7.80 cm of liquid, from the bottle's bottom up.
    h = LIQUID_ML * 1e-6 / (math.pi * bottle.radius**2)
    assert node.liquid_height_m == pytest.approx(h)
    assert node.liquid_z_m == pytest.approx(-0.5 * bottle.height + 0.5 * h)


def test_spilled_liquid_lies_where_the_video_puts_it() -> None:
    views = objects_of(stacked_state(1))
    video = Spills(SCENE)
    video.update(views)
    spills = Spills(SCENE)
    spills.update(views)
    (puddle,) = puddle_nodes(spills)
    (disc,) = video.objects()
    assert puddle.position[:2] == pytest.approx(tuple(disc.p[:2]))
    assert puddle.position[2] == pytest.approx(TOP + 0.001)  # on the table, 2 mm thick
    assert puddle.radius_m == pytest.approx(0.5 * disc.size[0])
    # A reset (less spilled than before) dries it.
    dry = dict(views)
    dry["bottle"] = replace(views["bottle"], spilled_ml=0.0)
    spills.update(dry)
    assert puddle_nodes(spills) == ()


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"kind": "cylinder"}, "objects.block0.kind"),
        ({"p": [0.5, 0.0, 1e6]}, "objects.block0.p"),
    ],
)
def test_an_object_that_does_not_fit_the_scene_is_refused(
    change: dict[str, Any], field: str
) -> None:
    st = stacked_state(1)
    objects = dict(st.objects)
    objects["block0"] = {**objects["block0"], **change}
    views: dict[str, ObjectView] = objects_of(replace(st, objects=objects))
    with pytest.raises(ProtocolError) as e:
        object_node(SCENE, views["block0"])
    assert e.value.field == field


def test_an_unknown_object_is_refused() -> None:
    st = stacked_state(1)
    views = objects_of(replace(st, objects={"ghost": st.objects["block0"]}))
    with pytest.raises(ProtocolError, match="not an object of the scene"):
        object_node(SCENE, views["ghost"])


def test_the_fingers_close_with_the_grip() -> None:
    assert finger_offsets(None) is None
    opened, closed = finger_offsets(0.0), finger_offsets(1.0)
    assert opened is not None and closed is not None
    assert opened[0][1] - opened[1][1] == pytest.approx(GRIPPER_OPEN_M + FINGER_SIZE_M[1])
    assert closed[0][1] - closed[1][1] == pytest.approx(FINGER_SIZE_M[1])  # touching
    assert finger_offsets(7.0) == closed  # clamped


# --- through the page -----------------------------------------------------------------------


@dataclass
class Page:
    console: Console
    pub: Node


@pytest.fixture
def page(net: Any) -> Iterator[Page]:
    console = Console(net.node("console"), ConsoleConfig(port=0, shadows=False, gui_rate_hz=20.0))
    try:
        yield Page(console, net.node("workcell"))
    finally:
        console.close()


def _at(browser: FakeBrowser, name: str, position: np.ndarray, wxyz: np.ndarray) -> bool:
    n = browser.node(name)
    if "position" not in n:
        return False
    q = np.asarray(n.get("wxyz", (1.0, 0.0, 0.0, 0.0)))
    same_rot = np.allclose(q, wxyz, atol=1e-6) or np.allclose(q, -wxyz, atol=1e-6)
    return bool(np.allclose(n["position"], position, atol=1e-6) and same_rot)


@pytest.mark.system
@pytest.mark.timeout(120)
def test_the_page_moves_the_objects_to_the_workcell_state(page: Page) -> None:
    console = page.console
    state_pub = page.pub.publisher(WORKCELL_STATE)
    robot_pub = page.pub.publisher(keys.STATE)
    with FakeBrowser(console.port, decode=True) as browser:
        assert wait_until(lambda: console.mirror.watching[0], 10.0), "the page never went live"
        # Before any workcell/state the page shows the scene as described.
        b1 = SCENE.box("block1")
        assert wait_until(lambda: "position" in browser.node("/workcell/block1"), 10.0)
        assert browser.node("/workcell/block1")["position"] == pytest.approx(b1.center)

        st = stacked_state(1)
        robot = replace(ready_state(1, (0.5, 0.2, 0.8)), grip=1.0)
        seq = 1
        views = objects_of(st)

        def published_and_drawn() -> bool:
            nonlocal seq
            seq += 1
            state_pub.put(replace(st, seq=seq))
            robot_pub.put(replace(robot, seq=seq))
            return all(
                _at(
                    browser,
                    f"/workcell/{name}",
                    object_node(SCENE, v).position,  # type: ignore[arg-type]
                    np.asarray(object_node(SCENE, v).wxyz),
                )
                for name, v in views.items()
            )

        assert wait_until(published_and_drawn, 20.0, poll_s=0.05), {
            name: browser.node(f"/workcell/{name}") for name in views
        }
        # The objects sit at the published poses: block2 two blocks above block0.
        b0 = np.asarray(browser.node("/workcell/block0")["position"])
        b2 = np.asarray(browser.node("/workcell/block2")["position"])
        assert np.allclose(b2 - b0, (0.0, 0.0, 2 * H))
        bottle = object_node(SCENE, views["bottle"])
        spills = Spills(SCENE)
        spills.update(views)
        (puddle,) = puddle_nodes(spills)
        assert wait_until(
            lambda: (
                browser.node("/workcell/bottle/liquid").get("height")
                == pytest.approx(bottle.liquid_height_m)
                and browser.node("/workcell/spill0").get("radius") == pytest.approx(puddle.radius_m)
                and "position" in browser.node("/workcell/spill0")
            ),
            10.0,
        ), (browser.node("/workcell/bottle/liquid"), browser.node("/workcell/spill0"))
        assert browser.node("/workcell/spill0")["position"] == pytest.approx(puddle.position)
        # The gripper is closed on what it holds.
        closed = finger_offsets(1.0)
        assert closed is not None
        assert wait_until(
            lambda: (
                browser.node("/arm/tool_frame/finger_l").get("position") == pytest.approx(closed[0])
                and browser.node("/arm/tool_frame/finger_l").get("visible") is True
            ),
            10.0,
        ), browser.node("/arm/tool_frame/finger_l")
        # ...and shown holding it.
        assert wait_until(
            lambda: (
                tuple(browser.node("/arm/tool_frame/finger_r").get("color", ()))
                == FINGER_HOLDING_COLOR
            ),
            10.0,
        ), browser.node("/arm/tool_frame/finger_r")
        assert console.gui_errors == 0


@pytest.mark.system
@pytest.mark.timeout(120)
def test_the_page_follows_the_real_workcell_service(net: Any) -> None:
    """End to end: the workcell service's own physics moves a block (it starts 40 cm above
    another part of the table and falls onto it) and the page's node lands where the
    workcell has it, not where the scene description (which the page starts from) has it."""
    from services.control.arm.model import load_model
    from services.world.workcell.config import WorkcellConfig
    from services.world.workcell.service import WorkcellService

    b0 = SCENE.box("block0").center
    rest = (0.68, 0.12, b0[2])
    start = (rest[0], rest[1], rest[2] + 0.40)
    assert np.linalg.norm(np.subtract(rest, b0)) > 0.1  # the page starts with it elsewhere
    workcell = WorkcellService(
        net.node("workcell"),
        WorkcellConfig(),
        scene=SCENE.moved({"block0": start}),
        arm=load_model("puma560"),
    )
    console = Console(net.node("console"), ConsoleConfig(port=0, shadows=False, gui_rate_hz=20.0))
    watcher = net.node("watcher").subscribe(WORKCELL_STATE)
    try:
        with FakeBrowser(console.port, decode=True) as browser:
            landed = watcher.wait_for(
                lambda s: (
                    s.objects["block0"]["phase"] == "resting"
                    and abs(s.objects["block0"]["p"][2] - b0[2]) < 5e-4  # MuJoCo's contact
                ),
                20.0,
            )
            assert landed is not None, "the block never landed"

            where = landed.objects["block0"]["p"]  # where the physics has it (it may bounce)
            assert np.linalg.norm(np.subtract(where, rest)) < 0.02

            def at_rest() -> bool:  # the node may exist before its first position arrives
                position = browser.node("/workcell/block0").get("position")
                return position is not None and np.allclose(position, where, atol=1e-3)

            assert wait_until(at_rest, 20.0), browser.node("/workcell/block0")
            assert console.workcell_drawn > 0 and console.gui_errors == 0
    finally:
        console.close()
        workcell.close()


@given(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(allow_nan=True, allow_infinity=True),
)
def test_any_liquid_figures_draw_a_bounded_liquid(liquid: float, spilled: float) -> None:
    v = objects_of(stacked_state(1))["bottle"]
    node = object_node(SCENE, replace(v, liquid_ml=liquid, spilled_ml=spilled))
    bottle = SCENE.cylinder("bottle")
    assert 0.0 <= node.liquid_height_m <= bottle.height
    assert -0.5 * bottle.height <= node.liquid_z_m <= 0.0
    assert all(math.isfinite(x) for x in node.position)
