"""A block the tool pushes moves in MuJoCo, in the console's 3D view and in the video: the
whole robot side in this process (the SimCell, as the sim profile runs it: the arm on the
cell's physics in memory), the vision service's simulated camera and the console with a page
connected, on one private network. The tool is moved by `move_pose` calls through the
decision, as a script of a lab would; nothing is published by hand."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
import pytest

from services.bus import keys
from services.bus.messages import RobotState, StereoFrame
from services.bus.node import Node
from services.control.vision.config import VisionConfig
from services.control.vision.service import VisionService
from services.control.vision.sim_camera import SimStereoCamera
from services.frontends.console.app import Console
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.workcell import object_node
from services.tools.cell.sim import SimCell, light_cell
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState, objects_of
from services.world.workcell.scene import BLOCK_SIZE_M, TABLE, default_scene
from tests.conftest import Net, wait_until
from tests.frontends.console.support import FakeBrowser

pytestmark = pytest.mark.system

SCENE = default_scene()
BLOCK = "block2"
MOVE_TIMEOUT_S = 60.0
CHANGED_LEVEL = 40
"""A pixel differs when one of its colours does by more than this (JPEG noise is a few)."""


class LeftEye:
    """The newest decoded left-eye picture and how many came."""

    def __init__(self, node: Node) -> None:
        self._lock = threading.Lock()
        self.count = 0
        self.image: np.ndarray | None = None
        node.subscribe(keys.STEREO_L, self._on_frame)

    def _on_frame(self, f: StereoFrame) -> None:
        img = cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR)
        with self._lock:
            self.image, self.count = img, self.count + 1

    def next_after(self, timeout_s: float = 20.0) -> np.ndarray:
        """A picture rendered after this call (two frames on: one may be in flight)."""
        with self._lock:
            start = self.count
        assert wait_until(lambda: self.count >= start + 2, timeout_s), "no new video frame"
        with self._lock:
            assert self.image is not None
            return self.image


@pytest.fixture
def cell(net: Net) -> Iterator[SimCell]:
    sim = light_cell(net.node, "puma560")
    try:
        sim.start()
        yield sim
    finally:
        sim.close()


def _changed(a: np.ndarray, b: np.ndarray) -> int:
    assert a.shape == b.shape, (a.shape, b.shape)
    diff = np.abs(a.astype(int) - b.astype(int)).max(axis=2)  # the largest of B, G, R
    return int(np.count_nonzero(diff > CHANGED_LEVEL))


@pytest.mark.timeout(240)
def test_a_pushed_block_moves_in_the_console_and_in_the_video(cell: SimCell, net: Net) -> None:
    vision = VisionService(
        net.node("vision"), VisionConfig(width=640, height=480, fps=10.0, adapt=False)
    )
    console = Console(net.node("console"), ConsoleConfig(port=0, shadows=False, gui_rate_hz=20.0))
    try:
        op = net.node("lab-script")
        ws = op.latest(WORKCELL_STATE)
        state = op.latest(keys.STATE)
        eye = LeftEye(op)
        events: list[str] = []
        op.subscribe(keys.EVENTS, lambda e: events.append(f"{e.source}: {e.kind}: {e.message}"))
        with FakeBrowser(console.port, decode=True) as browser:
            assert wait_until(lambda: ws.read() is not None and state.read() is not None, 20.0)
            st: RobotState = state.read()[0]  # type: ignore[index]
            home_p, tool_R = np.asarray(st.tool_p), list(st.tool_R)
            start = _block(ws.read()[0])  # type: ignore[index]
            assert wait_until(lambda: _drawn(browser, ws.read()[0]), 20.0), "not drawn"  # type: ignore[index]
            before = eye.next_after()
            # Rendering is deterministic: with nothing moving, the next picture is the same.
            assert _changed(before, eye.next_after()) <= 5

            def move(p: np.ndarray, speed: float) -> None:
                args = {"p": [float(x) for x in p], "R": tool_R, "speed": speed, "wait": True}
                reply = op.call("decision", "move_pose", args, MOVE_TIMEOUT_S)
                said = [e for e in events if ": status: " not in e][-4:]
                assert reply.get("completed") is True, (p, reply.get("reason"), said)

            # The open fingers (apart along x) down beside the block, the near one 5 cm from its
            # centre; a slow sweep along −x, towards the arm's base (1.5 cm/s: a push, not a
            # strike the decision's contact watch would stop); up, and back home.
            low = TABLE.top_z + BLOCK_SIZE_M + 0.005  # the palm clears the block, the fingers not
            for p, speed in (
                ((start[0] + 0.09, start[1], low + 0.05), 1.0),
                ((start[0] + 0.09, start[1], low), 0.2),
                ((start[0] + 0.02, start[1], low), 0.03),
                ((start[0] + 0.02, start[1], low + 0.1), 0.2),
                (tuple(home_p), 1.0),
            ):
                move(np.asarray(p), speed)

            # MuJoCo moved it: slid along −x on the table, upright, resting.
            def settled() -> bool:
                views = objects_of(ws.read()[0])  # type: ignore[index]
                return views[BLOCK].phase == "resting"

            assert wait_until(settled, 20.0)
            now: WorkcellState = ws.read()[0]  # type: ignore[index]
            end = _block(now)
            moved = start - end
            assert moved[0] > 0.03 and abs(moved[1]) < 0.02, (start, end)
            assert abs(end[2] - start[2]) < 1e-3, (start, end)  # on the table still
            assert objects_of(now)[BLOCK].tilt_deg < 5.0
            # The console's page shows it where the physics has it ...
            assert wait_until(lambda: _drawn(browser, ws.read()[0]), 20.0), (  # type: ignore[index]
                browser.node(f"/workcell/{BLOCK}"),
                end,
            )
            # ... the camera draws it there, and the picture, the arm back where it was, has
            # changed where the block was and is.
            camera = vision.camera
            assert isinstance(camera, SimStereoCamera)
            assert wait_until(lambda: _camera_has(camera, end), 20.0)
            after = eye.next_after()
            # (about 570 pixels of 640×480 here; a frame with nothing moved: 0)
            assert _changed(before, after) >= 200, _changed(before, after)
    finally:
        console.close()
        vision.close()


def _block(ws: WorkcellState) -> np.ndarray:
    return np.asarray(objects_of(ws)[BLOCK].p, dtype=float)


def _drawn(browser: FakeBrowser, ws: WorkcellState) -> bool:
    """The page's block node is where `ws` (the newest state) puts it."""
    node: dict[str, Any] = browser.node(f"/workcell/{BLOCK}")
    want = object_node(SCENE, objects_of(ws)[BLOCK])
    return "position" in node and bool(np.allclose(node["position"], want.position, atol=1e-4))


def _camera_has(camera: SimStereoCamera, p: np.ndarray) -> bool:
    objects = camera._objects
    if objects is None:
        return False
    got = {o.name: np.asarray(o.p) for o in objects}
    return BLOCK in got and bool(np.allclose(got[BLOCK], p, atol=1e-4))
