"""The console draws the arm the arm service describes (robot/arm/description), from its
URDF's visuals: one node per visual, placed where `LinkPoses` puts its link at the state's q
composed with the visual's placement in that link; the skeleton when the visuals cannot be
found here (logged once); nothing until a description arrives (and the status panel says
so); a new model rebuilds the arm, a new tool moves only the tool. The page part is checked
through what a browser receives (`FakeBrowser(decode=True)`)."""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pinocchio as pin
import pytest

from services.bus import keys
from services.bus.messages import ArmDescription, RobotState
from services.bus.streams import Publisher
from services.control.arm.links import LinkPoses
from services.control.arm.model import ArmModel, load_model
from services.frontends.console.app import Console
from services.frontends.console.arm import Cylinder, arm_layout
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.poses import MIN_SEGMENT_M
from services.geometry import R_from_wxyz
from tests.conftest import ready_state

from .support import FakeBrowser, gui_uuid, wait_until

FR3 = load_model("fr3")
PUMA = load_model("puma560")
ROOT = "/arm/model/"
TOL = 1e-6


def describe(arm: ArmModel, seq: int = 1, **changes: Any) -> ArmDescription:
    """The description the arm service publishes for `arm`, with `changes`."""
    return ArmDescription(seq=seq, t_ns=time.time_ns(), **{**arm.description(), **changes})


def state_at(model: ArmModel, q: tuple[float, ...], seq: int, tool_p: Any = None) -> RobotState:
    """robot/state as the arm sends it at q (the tool placed by the model's eMt, or at
    `tool_p` from the flange)."""
    kin = model.kinematics()
    oMe = kin.fk_flange(q)
    eMt = pin.SE3(np.asarray(model.tool_R).reshape(3, 3), np.asarray(tool_p or model.tool_p))
    return ready_state(seq, time.time_ns(), q, oMe * eMt, oMe)


def expected_visuals(model: ArmModel, q: tuple[float, ...]) -> dict[str, pin.SE3]:
    """visual name → its world pose at q: LinkPoses of its link composed with its placement
    in that link (Pinocchio's placement is in the link's joint frame)."""
    pm = model.pin_model()
    at = LinkPoses(model).poses(q)
    out = {}
    for obj in model.geometry().geometryObjects:
        link = pm.frames[obj.parentFrame]
        out[obj.name] = at[link.name] * link.placement.actInv(obj.placement)
    return out


def skeleton_segments(origins: Any) -> list[tuple[Any, Any]]:
    """The skeleton's segments: consecutive points of `link_origins`, coincident ones left
    out (a spherical wrist's)."""
    return [
        (a, b) for a, b in itertools.pairwise(origins) if np.linalg.norm(b - a) >= MIN_SEGMENT_M
    ]


def _local(node: dict[str, Any]) -> pin.SE3:
    return pin.SE3(R_from_wxyz(node["wxyz"]), np.asarray(node["position"], dtype=float))


def world_pose(browser: FakeBrowser, name: str) -> pin.SE3:
    """A node's pose in the world: its ancestors' poses composed with its own."""
    parts = name.strip("/").split("/")
    M = pin.SE3.Identity()
    for i in range(len(parts)):
        node = browser.node("/" + "/".join(parts[: i + 1]))
        if node:  # viser may leave an ancestor implicit (identity)
            M = M * _local(node)
    return M


def part_nodes(browser: FakeBrowser) -> dict[str, str]:
    """part name → node name, for every shape of the drawn arm (under `/arm/model/`, the
    joints' nodes being frames)."""
    return {
        name.rsplit("/", 1)[1]: name
        for name, node in browser.nodes(ROOT).items()
        if node.get("type") != "FrameMessage"
    }


def same(a: pin.SE3, b: pin.SE3) -> bool:
    return bool(
        np.allclose(a.translation, b.translation, atol=TOL)
        and np.allclose(a.rotation, b.rotation, atol=TOL)
    )


def arm_status(browser: FakeBrowser) -> str:
    """The status panel's arm line as the page last got it."""
    content = browser.gui(gui_uuid(browser, 'id="tr-arm"')).get("content", "")
    start = content.index('id="tr-arm"')
    return str(content[start : content.index("</span>", start)])


# --- pure -----------------------------------------------------------------------------------
@pytest.mark.parametrize("model", [FR3, PUMA], ids=["fr3", "puma560"])
def test_the_layout_has_one_part_per_visual_at_its_link_pose(model: ArmModel) -> None:
    layout = arm_layout(describe(model))
    assert layout.kind == "visuals" and layout.n == model.n
    visuals = [o.name for o in model.geometry().geometryObjects]
    assert sorted(p.visual for p in layout.parts) == sorted(visuals)
    rng = np.random.default_rng(7)
    for q in (model.home, tuple(rng.uniform(model.q_lo, model.q_hi))):
        at = layout.poses.poses(q)
        want = expected_visuals(model, q)
        for p in layout.parts:
            drawn = at[layout.groups[p.group].link] * pin.SE3(R_from_wxyz(p.wxyz), np.array(p.p))
            assert same(drawn, want[p.visual]), p.visual


def test_a_model_whose_meshes_are_not_here_is_a_skeleton_of_its_joints() -> None:
    layout = arm_layout(describe(FR3, model="my_fr3"))  # a user's model: no meshes here
    assert layout.kind == "skeleton" and "could not be found" in layout.why
    q = FR3.home
    origins = FR3.kinematics().link_origins(q)
    at = layout.poses.poses(q)
    ends = []
    for p in layout.parts:
        if isinstance(p.shape, Cylinder):
            M = at[layout.groups[p.group].link] * pin.SE3(R_from_wxyz(p.wxyz), np.array(p.p))
            half = np.array([0.0, 0.0, 0.5 * p.shape.length])
            ends.append((M.act(-half), M.act(half)))
    segments = skeleton_segments(origins)
    assert len(ends) == len(segments)
    for (a, b), (u, v) in zip(segments, ends, strict=True):
        assert np.allclose(a, u, atol=TOL) and np.allclose(b, v, atol=TOL)


# --- the page -------------------------------------------------------------------------------
@dataclass
class Page:
    console: Console
    browser: FakeBrowser
    described: Publisher[ArmDescription]
    states: Publisher[RobotState]
    seq: int = 0

    def show(self, st: RobotState) -> None:
        """Publish st as the next robot/state (again and again while waiting: the console
        draws the newest, and the first ones may go before its subscription is matched)."""
        self.seq += 1
        self.states.put(replace(st, seq=self.seq, t_ns=time.time_ns()))

    def drawn(self, st: RobotState, pred: Callable[[], bool], timeout_s: float = 20.0) -> bool:
        """Keep showing st until `pred` holds (or the deadline)."""

        def shown() -> bool:
            self.show(st)
            return pred()

        return bool(wait_until(shown, timeout_s, poll_s=0.05))


@pytest.fixture
def page(net: Any) -> Iterator[Page]:
    arm = net.node("arm")
    described = arm.publisher(keys.ARM_DESCRIPTION, cache=1)
    states = arm.publisher(keys.STATE)
    console = Console(net.node("console"), ConsoleConfig(port=0, shadows=False, gui_rate_hz=20.0))
    try:
        with FakeBrowser(console.port, decode=True) as browser:
            yield Page(console, browser, described, states)
    finally:
        console.close()


def visuals_at(page: Page, model: ArmModel, q: tuple[float, ...]) -> Callable[[], bool]:
    """Whether the page has one node per visual of `model` (named as the visual: the
    shipped models' names need no escaping), each at its world pose at q."""
    want = expected_visuals(model, q)

    def check() -> bool:
        nodes = part_nodes(page.browser)
        return set(nodes) == set(want) and all(
            same(world_pose(page.browser, nodes[v]), M) for v, M in want.items()
        )

    return check


@pytest.mark.system
@pytest.mark.timeout(120)
@pytest.mark.parametrize("model", [FR3, PUMA], ids=["fr3", "puma560"])
def test_the_page_draws_the_described_arm_and_moves_it_with_q(page: Page, model: ArmModel) -> None:
    page.described.put(describe(model))
    q1 = model.home
    q2 = tuple(float(x) for x in np.clip(np.add(q1, 0.3), model.q_lo, model.q_hi))
    assert page.drawn(state_at(model, q1, 0), visuals_at(page, model, q1)), part_nodes(page.browser)
    assert len(part_nodes(page.browser)) == len(model.geometry().geometryObjects)
    assert page.drawn(state_at(model, q2, 0), visuals_at(page, model, q2))
    assert wait_until(lambda: 'data-arm="visuals"' in arm_status(page.browser), 10.0)
    assert f'data-model="{model.name}"' in arm_status(page.browser)
    assert page.console.arm_builds == 1 and page.console.gui_errors == 0


@pytest.mark.system
@pytest.mark.timeout(120)
def test_without_a_description_no_arm_is_drawn_and_the_panel_says_so(page: Page) -> None:
    st = state_at(FR3, FR3.home, 0)

    # The tool frame follows the state (it is the state's tool pose, not the model's)...
    def tool_frame_at_the_state() -> bool:
        at = page.browser.node("/arm/tool_frame").get("position", ())
        return len(at) == 3 and np.allclose(at, st.tool_p, atol=TOL)  # () until drawn

    assert page.drawn(st, tool_frame_at_the_state)
    # ...and no arm is drawn: there is no model to draw until the arm describes one.
    assert wait_until(lambda: 'data-arm="none"' in arm_status(page.browser), 10.0)
    assert "no arm drawn" in arm_status(page.browser)
    assert page.browser.nodes(ROOT) == {} and page.console.arm is None
    assert page.console.gui_errors == 0


@pytest.mark.system
@pytest.mark.timeout(120)
def test_meshes_not_found_fall_back_to_the_skeleton_logged_once(
    page: Page, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="telerobot.console")
    page.described.put(describe(FR3, model="my_fr3"))
    q = FR3.home
    origins = FR3.kinematics().link_origins(q)
    segments = skeleton_segments(origins)

    def skeleton() -> bool:
        cylinders = {
            name: node
            for name, node in page.browser.nodes(ROOT).items()
            if node.get("type") == "CylinderMessage" and "position" in node
        }
        if len(cylinders) != len(segments):
            return False
        ends = []
        for name, node in sorted(
            cylinders.items(), key=lambda kv: int(kv[0].rsplit("/link", 1)[1])
        ):
            M = world_pose(page.browser, name)
            half = np.array([0.0, 0.0, 0.5 * float(node["height"])])
            ends.append((M.act(-half), M.act(half)))
        return all(
            np.allclose(a, u, atol=TOL) and np.allclose(b, v, atol=TOL)
            for (a, b), (u, v) in zip(segments, ends, strict=True)
        )

    assert page.drawn(state_at(FR3, q, 0), skeleton), page.browser.nodes(ROOT)
    assert wait_until(lambda: 'data-arm="skeleton"' in arm_status(page.browser), 10.0)
    # The same arm described again (another tool, say): no second warning.
    page.described.put(describe(FR3, seq=2, model="my_fr3", eMt={"p": [0, 0, 0.2], "R": I9}))
    assert wait_until(
        lambda: page.console.arm_description is not None and page.console.arm_description.seq == 2
    )
    warnings = [r for r in caplog.records if "skeleton" in r.getMessage()]
    assert len(warnings) == 1, [r.getMessage() for r in caplog.records]
    assert page.console.gui_errors == 0


I9 = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]


@pytest.mark.system
@pytest.mark.timeout(120)
def test_a_new_tool_moves_the_tool_and_a_new_model_redraws_the_arm(page: Page) -> None:
    page.described.put(describe(FR3))
    q = FR3.home
    assert page.drawn(state_at(FR3, q, 0), visuals_at(page, FR3, q))

    # set_tool: the description changes its eMt, the state its tool pose; the arm is not
    # rebuilt, the tool (flange → tool point) is drawn 0.2 m long.
    page.described.put(describe(FR3, seq=2, eMt={"p": [0.0, 0.0, 0.2], "R": list(FR3.tool_R)}))
    longer = state_at(FR3, q, 0, tool_p=(0.0, 0.0, 0.2))
    assert page.drawn(
        longer,
        lambda: page.browser.node("/arm/tool_frame/tool").get("height") == pytest.approx(0.2),
    ), page.browser.node("/arm/tool_frame/tool")
    assert page.console.arm_builds == 1
    tool = world_pose(page.browser, "/arm/tool_frame/tool")
    assert np.allclose(tool.translation, np.add(longer.tool_p, longer.flange_p) / 2, atol=TOL)

    # The arm restarts with another model: its states (6 joints) may come before its
    # description and are not drawn on the FR3; the PUMA replaces the FR3 on the page.
    puma = state_at(PUMA, PUMA.home, 0)
    for _ in range(5):
        page.show(puma)
    # (A restarted arm counts from 1 again, well after: the bus's `newer` takes it as the
    # newest, tested in tests/bus. Here the same publisher goes on counting.)
    page.described.put(describe(PUMA, seq=3))
    assert page.drawn(puma, visuals_at(page, PUMA, PUMA.home)), part_nodes(page.browser)
    assert not any(name.startswith("fr3_") for name in part_nodes(page.browser))
    assert page.console.arm_builds == 2 and page.console.gui_errors == 0
