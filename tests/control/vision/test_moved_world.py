"""The sim cameras draw the workcell's live state: moved, stacked, tilted, filled objects."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.bus.errors import ProtocolError
from services.bus.messages import vec
from services.control.arm.model import load_model
from services.control.vision.config import VisionConfig
from services.control.vision.objects import (
    LIQUID_BGR,
    SPILL_BGR,
    STILL_P_M,
    STILL_R,
    ObjectPose,
    composite,
    steady,
)
from services.control.vision.service import VisionService
from services.control.vision.sim_camera import SimStereoCamera
from services.geometry import rot_x
from services.world.workcell.engine import CellPhysics
from services.world.workcell.messages import M3_PER_ML, WORKCELL_STATE, WorkcellState, object_map
from services.world.workcell.scene import BLOCK_SIZE_M, TABLE, default_scene
from tests.conftest import wait_until

SCENE = default_scene()
TOP = TABLE.top_z
H = BLOCK_SIZE_M
BOTTLE = SCENE.cylinder("bottle")
FULL_ML = math.pi * BOTTLE.radius**2 * BOTTLE.liquid_height_m / M3_PER_ML


def _rx(deg: float) -> np.ndarray:
    return rot_x(math.radians(deg))


def _obj(kind: str, p: Any, size: Any, R: Any = None, **extra: Any) -> dict[str, Any]:
    R = np.eye(3) if R is None else np.asarray(R)
    return {
        "kind": kind,
        "p": list(vec(p)),
        "R": list(vec(R)),
        "size": list(vec(size)),
        "phase": "resting",
        "on": "table",
        "tilt_deg": 0.0,
        "max_tilt_deg": 0.0,
        **extra,
    }


def state(objects: dict[str, dict[str, Any]], seq: int = 1) -> WorkcellState:
    return WorkcellState(
        seq=seq, t_ns=seq, tool_p=(0.5, 0.0, 0.8), grip=0.0, held="", objects=objects
    )


STACK_XY = (0.50, -0.20)
STACKED = {f"block{i}": _obj("box", (*STACK_XY, TOP + H / 2 + i * H), (H, H, H)) for i in range(3)}
BOTTLE_UPRIGHT = _obj(
    "cylinder",
    BOTTLE.base,
    (2 * BOTTLE.radius, 2 * BOTTLE.radius, BOTTLE.height),
    liquid_ml=FULL_ML,
    spilled_ml=0.0,
)


def _cos(pixel: np.ndarray, bgr: tuple[int, int, int]) -> float:
    a = pixel.astype(float)
    b = np.asarray(bgr, float)
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12))


@pytest.fixture(scope="module")
def cam() -> SimStereoCamera:
    c = SimStereoCamera(VisionConfig(), scene=SCENE)
    c.open()
    return c


def _pixel(cam: SimStereoCamera, p: Any) -> tuple[int, int]:
    """Where the left eye's intrinsics put world point `p`."""
    renderer = cam._renderer
    assert renderer is not None
    uv, z = renderer.left.camera.project(np.asarray(p, float))
    assert z[0] > 0
    u, v = (round(float(x)) for x in uv[0])
    assert 0 <= u < cam.config.width and 0 <= v < cam.config.height
    return u, v


def test_stacked_blocks_are_drawn_stacked_and_their_old_places_show_the_table(
    cam: SimStereoCamera,
) -> None:
    cam.clear_robot()
    before = cam.grab().left
    # Before any state: the blocks where the scene description puts them.
    for b in SCENE.movables():
        if b.name.startswith("block"):
            u, v = _pixel(cam, (b.center[0], b.center[1], b.top_z))  # type: ignore[union-attr]
            assert _cos(before[v, u], b.color) > 0.99, b.name
    cam.set_workcell(state({**STACKED, "bottle": BOTTLE_UPRIGHT}))
    img = cam.grab().left
    for i in range(3):
        block = SCENE.box(f"block{i}")
        top = TOP + (i + 1) * H
        # The top face of the top block, and the camera-facing side (+x) of each block.
        points = [(STACK_XY[0] + H / 2, STACK_XY[1], top - H / 2)]
        if i == 2:
            points.append((*STACK_XY, top))
        for p in points:
            u, v = _pixel(cam, p)
            assert _cos(img[v, u], block.color) > 0.99, (block.name, p, img[v, u])
    # Where blocks 1 and 2 stood, the table top is seen again.
    for name in ("block1", "block2"):
        old = SCENE.box(name)
        u, v = _pixel(cam, (old.center[0], old.center[1], TOP))
        assert _cos(before[v, u], old.color) > 0.99
        assert _cos(img[v, u], TABLE.color) > 0.995, (name, img[v, u])
        assert _cos(img[v, u], old.color) < 0.95


def _stack(ph: CellPhysics, name: str, onto: str) -> None:
    """Put `name` 3 mm above `onto` and let MuJoCo's physics settle it there."""
    t = ph.body(onto)
    ph.place(name, t.p + np.array([0.0, 0.0, H + 0.003]))
    ph.step(400)
    assert ph.body(name).on == onto


def test_after_a_physical_stacking_the_image_shows_the_column(cam: SimStereoCamera) -> None:
    """The cell's physics (MuJoCo) settles block1 on block0 and block2 on block1; its state
    drawn: each block's colour where its simulated pose projects, the table where block 1
    and block 2 stood."""
    cam.clear_robot()
    ph = CellPhysics(load_model("puma560"), SCENE)
    _stack(ph, "block1", "block0")
    _stack(ph, "block2", "block1")
    msg = WorkcellState(
        seq=1,
        t_ns=1,
        tool_p=(0.5, 0.0, 0.8),
        grip=0.0,
        held="",
        objects={b.name: object_map(b) for b in ph.bodies()},
    )
    cam.set_workcell(msg)
    img = cam.grab().left
    for level, name in enumerate(("block0", "block1", "block2")):
        p = ph.body(name).p
        assert p[2] == pytest.approx(TOP + H / 2 + level * H, abs=1e-3)  # soft contacts
        side = p + np.array([H / 2, 0.0, 0.0])  # the face towards the cameras
        u, v = _pixel(cam, side)
        assert _cos(img[v, u], SCENE.box(name).color) > 0.99, (name, img[v, u])
    u, v = _pixel(cam, ph.body("block2").p + np.array([0.0, 0.0, H / 2]))
    assert _cos(img[v, u], SCENE.box("block2").color) > 0.99
    for name in ("block1", "block2"):
        old = SCENE.box(name)
        u, v = _pixel(cam, (old.center[0], old.center[1], TOP))
        assert _cos(img[v, u], TABLE.color) > 0.995, (name, img[v, u])


def test_only_what_moved_is_ray_cast_again(cam: SimStereoCamera) -> None:
    cam.clear_robot()
    renderer = cam._renderer
    assert renderer is not None
    first = {**STACKED, "bottle": BOTTLE_UPRIGHT}
    cam.set_workcell(state(first))
    cam.grab()
    n0 = renderer.left.recasts
    for seq in range(2, 6):  # the same poses again: nothing is re-cast
        cam.set_workcell(state(first, seq))
        cam.grab()
    assert renderer.left.recasts == n0
    carried = dict(first)
    carried["block2"] = _obj("box", (0.55, 0.0, 0.6), (H, H, H))
    cam.set_workcell(state(carried, 7))
    cam.grab()
    assert renderer.left.recasts == n0 + 1
    assert renderer.right.recasts == renderer.left.recasts


def test_a_resting_object_is_not_ray_cast_again_for_the_solvers_jitter(
    cam: SimStereoCamera,
) -> None:
    """MuJoCo's resting objects move by micrometres and rock by ~1e-4 of a rotation entry
    from state to state: they stay drawn where they were, pixel for pixel, and are not
    ray-cast again; a move past STILL_P_M is drawn at once."""
    cam.clear_robot()
    renderer = cam._renderer
    assert renderer is not None
    first = {**STACKED, "bottle": BOTTLE_UPRIGHT}
    cam.set_workcell(state(first, 20))
    img0 = cam.grab().left
    n0 = (renderer.left.recasts, renderer.right.recasts)
    rng = np.random.default_rng(7)
    for seq in range(21, 41):
        jittered = {
            name: {
                **o,
                "p": list(np.asarray(o["p"]) + rng.uniform(-0.9, 0.9, 3) * STILL_P_M),
                "R": list(vec(rot_x(rng.uniform(-0.9, 0.9) * STILL_R))),
            }
            for name, o in first.items()
        }
        cam.set_workcell(state(jittered, seq))
        assert np.array_equal(cam.grab().left, img0), seq
    assert (renderer.left.recasts, renderer.right.recasts) == n0
    block = first["block2"]
    moved = {
        **first,
        "block2": {**block, "p": list(np.asarray(block["p"]) + np.array([3 * STILL_P_M, 0, 0]))},
    }
    cam.set_workcell(state(moved, 41))
    assert not np.array_equal(cam.grab().left, img0)
    assert (renderer.left.recasts, renderer.right.recasts) == (n0[0] + 1, n0[1] + 1)


def test_steady_keeps_only_what_is_still_and_otherwise_the_same() -> None:
    def pose(**kw: Any) -> ObjectPose:
        base: dict[str, Any] = {
            "name": "bottle",
            "kind": "cylinder",
            "p": np.array([0.5, 0.1, TOP]),
            "R": np.eye(3),
            "size": np.array([0.06, 0.06, 0.2]),
            "color": (10, 20, 30),
            "liquid_m": 0.1,
        }
        return ObjectPose(**{**base, **kw})

    drawn = (pose(), pose(name="block0", kind="box"))
    nudged = (pose(p=drawn[0].p + 0.5 * STILL_P_M), pose(name="block0", kind="box"))
    assert steady(drawn, nudged) is drawn
    assert steady(None, nudged) is nudged
    for changed in (
        pose(p=drawn[0].p + np.array([0.0, 0.0, 2 * STILL_P_M])),
        pose(R=rot_x(4 * STILL_R)),
        pose(liquid_m=0.09),  # poured: the level is drawn at once
        pose(size=np.array([0.06, 0.06, 0.21])),
        pose(color=(11, 20, 30)),
        pose(kind="box"),
    ):
        got = steady(drawn, (changed, drawn[1]))
        assert got[0] is changed and got[1] is drawn[1]
    new = pose(name="block9", kind="box")
    assert steady(drawn, (*drawn, new)) == (*drawn, new)
    assert steady(drawn, drawn[1:]) == drawn[1:]  # one gone


def test_tilted_bottle_and_its_liquid_level(cam: SimStereoCamera) -> None:
    cam.clear_robot()
    base = np.asarray(BOTTLE.base)
    r, h = BOTTLE.radius, BOTTLE.height
    half = _obj("cylinder", base, (2 * r, 2 * r, h), liquid_ml=FULL_ML / 2, spilled_ml=0.0)
    cam.set_workcell(state({**STACKED, "bottle": half}))
    img = cam.grab().left
    level = BOTTLE.liquid_height_m / 2
    # The camera-facing side (+x) of the wall: liquid below the level, the bottle above.
    u, v = _pixel(cam, base + np.array([r, 0.0, 0.5 * level]))
    assert _cos(img[v, u], LIQUID_BGR) > 0.99, img[v, u]
    assert _cos(img[v, u], BOTTLE.color) < 0.9, img[v, u]
    u, v = _pixel(cam, base + np.array([r, 0.0, level + 0.5 * (h - level)]))
    assert _cos(img[v, u], BOTTLE.color) > 0.99, img[v, u]
    assert _cos(img[v, u], LIQUID_BGR) < 0.9, img[v, u]
    # Tilted 60° about x (towards −y): its old upright top is empty, its axis is seen.
    R = _rx(60.0)
    tilted = _obj("cylinder", base, (2 * r, 2 * r, h), R=R, liquid_ml=0.0, spilled_ml=400.0)
    cam.set_workcell(state({**STACKED, "bottle": tilted}, 2))
    img = cam.grab().left
    u, v = _pixel(cam, base + np.array([0.0, 0.0, 0.9 * h]))
    assert _cos(img[v, u], BOTTLE.color) < 0.97, img[v, u]
    u, v = _pixel(cam, base + R @ (r, 0.0, 0.7 * h))
    assert _cos(img[v, u], BOTTLE.color) > 0.99, img[v, u]


def test_spilled_liquid_lies_where_it_fell_and_dries_on_reset() -> None:
    cam = SimStereoCamera(VisionConfig(), scene=SCENE)
    cam.open()
    cam.clear_robot()
    base = np.asarray(BOTTLE.base)
    r, h = BOTTLE.radius, BOTTLE.height
    R = _rx(60.0)  # tilted towards −y: the lowest point of the rim is at y ≈ 0.06

    def bottle(spilled_ml: float) -> dict[str, Any]:
        return _obj(
            "cylinder", base, (2 * r, 2 * r, h), R=R, liquid_ml=100.0, spilled_ml=spilled_ml
        )

    mouth = base + R @ np.array([0.0, 0.0, h])
    rim = mouth + r * np.array([0.0, -0.5, -math.sqrt(3) / 2])
    spot = (rim[0] + 0.04, rim[1], TOP)  # on the table, on the cameras' side of the drop
    cam.set_workcell(state({**STACKED, "bottle": bottle(0.0)}, 1))
    u, v = _pixel(cam, spot)
    assert _cos(cam.grab().left[v, u], TABLE.color) > 0.995
    cam.set_workcell(state({**STACKED, "bottle": bottle(150.0)}, 2))
    cam.set_workcell(state({**STACKED, "bottle": bottle(200.0)}, 3))
    (puddle,) = cam._spills.puddles
    assert (puddle.x, puddle.y, puddle.z) == pytest.approx((rim[0], rim[1], TOP), abs=1e-9)
    assert puddle.volume_ml == pytest.approx(200.0)
    assert _cos(cam.grab().left[v, u], SPILL_BGR) > 0.99
    cam.set_workcell(state({**STACKED, "bottle": bottle(0.0)}, 4))  # the workcell was reset
    assert cam._spills.puddles == []
    assert _cos(cam.grab().left[v, u], TABLE.color) > 0.995


def test_bad_object_states_are_refused_and_the_last_poses_kept(cam: SimStereoCamera) -> None:
    cam.clear_robot()
    cam.set_workcell(state({**STACKED, "bottle": BOTTLE_UPRIGHT}))
    good = cam.grab().left
    huge = _obj("box", (0.5, 0.0, 0.5), (50.0, 1.0, 1.0))
    far = _obj("box", (1e6, 0.0, 0.5), (H, H, H))
    skew = _obj("box", (0.5, 0.0, 0.5), (H, H, H), R=2 * np.eye(3))
    for bad in (huge, far, skew):
        with pytest.raises(ValueError):
            cam.set_workcell(state({"block0": bad}))
    with pytest.raises(ProtocolError, match=r"objects\.block0"):
        cam.set_workcell(state({"block0": {"kind": "box"}}))
    assert np.array_equal(cam.grab().left, good)


def test_vision_service_draws_published_workcell_state(net) -> None:
    vision_node = net.node("vision")
    workcell = net.node("workcell")
    svc = VisionService(vision_node, VisionConfig(width=160, height=120, fps=20.0))
    camera = svc.camera
    assert isinstance(camera, SimStereoCamera)
    pub = workcell.publisher(WORKCELL_STATE)
    try:
        pub.put(state({**STACKED, "bottle": BOTTLE_UPRIGHT}, 1))
        assert wait_until(lambda: camera._objects is not None, what="workcell/state drawn")
        objects = camera._objects
        assert objects is not None
        got = {o.name: o.p for o in objects}
        for name, m in STACKED.items():
            assert np.allclose(got[name], m["p"])
        # A malformed object is rejected with an event, the last poses kept.
        pub.put(state({"block0": _obj("box", (0.5, 0.0, 0.5), (99.0, H, H))}, 2))
        assert wait_until(lambda: WORKCELL_STATE.key in vision_node.rejected, what="rejection")
        assert camera._objects is objects
    finally:
        svc.close()


_xy = st.tuples(st.floats(0.3, 0.8), st.floats(-0.4, 0.4))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2), _xy, st.floats(0.0, 90.0)), min_size=1, max_size=6))
def test_redrawing_only_what_moved_equals_drawing_everything(
    moves: list[tuple[int, tuple[float, float], float]],
) -> None:
    """Patching the moved objects' regions in place gives the same image and depth as
    compositing every object over the static background from scratch."""
    cam = _tiny_cam()
    renderer = cam._renderer
    assert renderer is not None
    objects = {**STACKED, "bottle": BOTTLE_UPRIGHT}
    for seq, (i, (x, y), tilt) in enumerate(moves, start=1):
        objects = dict(objects)
        objects[f"block{i}"] = _obj("box", (x, y, TOP + H / 2), (H, H, H), R=_rx(tilt))
        cam.set_workcell(state(objects, seq))
        cam.grab()
    eye = renderer.left
    layers = [ly for ly in eye._layers.values() if ly is not None]
    img, depth = composite(eye.static_background, eye.static_depth, layers)
    assert np.array_equal(eye.background, img)
    assert np.array_equal(eye.depth, depth)


@functools.cache
def _tiny_cam() -> SimStereoCamera:
    c = SimStereoCamera(VisionConfig(width=64, height=48), scene=SCENE, supersample=1)
    c.open()
    return c
