from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from services.control.vision.camera import CameraError
from services.control.vision.config import VisionConfig
from services.control.vision.sim_camera import SimStereoCamera
from services.world.workcell.scene import TABLE, default_scene

from .fakes import marker_centroid

TOOL_DOWN = np.diag([1.0, -1.0, -1.0])


def arm_to(tool_p: NDArray[np.float64] | tuple[float, float, float]) -> NDArray[np.float64]:
    """Hand-made link points: pedestal, a shoulder, an elbow, and the flange 0.2 m above
    the tool point (tool pointing down), frames 4…6 at the wrist centre as on a PUMA."""
    tool = np.asarray(tool_p, dtype=float)
    wrist = tool + np.array([0.0, 0.0, 0.2])
    shoulder = np.array([0.0, 0.0, 0.67183])
    elbow = 0.5 * (shoulder + wrist) + np.array([0.0, 0.0, 0.25])
    return np.array(
        [(0.0, 0.0, 0.0), shoulder, elbow, elbow + np.array([0.0, -0.15, 0.0]), wrist, wrist, wrist]
    )


@pytest.fixture(scope="module")
def cam() -> SimStereoCamera:
    c = SimStereoCamera(VisionConfig())
    c.open()
    return c


def test_grab_before_open_is_a_camera_error() -> None:
    with pytest.raises(CameraError, match="open"):
        SimStereoCamera(VisionConfig(width=32, height=24)).grab()


def test_pair_shape_and_stereo(cam: SimStereoCamera) -> None:
    cam.clear_robot()
    pair = cam.grab()
    assert pair.left.shape == pair.right.shape == (480, 640, 3)
    assert pair.left.dtype == np.uint8
    assert pair.t_ns_left == pair.t_ns_right  # both eyes show the same instant
    assert pair.baseline_m == 0.065
    assert not np.array_equal(pair.left, pair.right)  # two viewpoints
    assert marker_centroid(pair.left) is None


def test_static_depth_is_the_true_depth(cam: SimStereoCamera) -> None:
    renderer = cam._renderer
    assert renderer is not None
    eye = renderer.left
    top_centre = np.array([TABLE.center[0], TABLE.center[1], TABLE.top_z])
    uv, z = eye.camera.project(top_centre)
    u, v = (round(x) for x in uv[0])
    # Min-pooled over supersamples: at most one pixel's footprint nearer.
    assert eye.depth[v, u] == pytest.approx(z[0], abs=0.01)
    assert math.isinf(eye.depth[0, 0])  # the top-left corner sees the wall


@pytest.mark.parametrize("lateral_m", [0.0, 0.08])
def test_tool_toward_cameras_shows_the_predicted_disparity(
    cam: SimStereoCamera, lateral_m: float
) -> None:
    cfg = cam.config
    centre = np.asarray(cfg.rig_position_m)
    forward = np.asarray(cfg.rig_target_m) - centre
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    fx = 0.5 * cfg.width / math.tan(math.radians(cfg.fov_deg) / 2)
    disparities = []
    for depth_m in (1.3, 0.8):
        tool = centre + depth_m * forward + lateral_m * right
        cam.set_robot(arm_to(tool), tool, TOOL_DOWN)
        pair = cam.grab()
        left, right_c = marker_centroid(pair.left), marker_centroid(pair.right)
        assert left is not None and right_c is not None
        expected = fx * cfg.baseline_m / depth_m
        disparity = left[0] - right_c[0]
        assert disparity == pytest.approx(expected, abs=1.0)
        assert left[1] == pytest.approx(right_c[1], abs=0.5)  # rectified: same row
        disparities.append(disparity)
    assert disparities[1] > disparities[0] + 10.0


def test_table_hides_what_is_behind_it(cam: SimStereoCamera) -> None:
    behind = np.array([0.2, 0.0, 0.2])  # behind the table and below its top
    cam.set_robot(arm_to(behind), behind, TOOL_DOWN)
    pair = cam.grab()
    assert marker_centroid(pair.left) is None and marker_centroid(pair.right) is None
    above = np.array([0.6, 0.0, 0.55])
    cam.set_robot(arm_to(above), above, TOOL_DOWN)
    pair = cam.grab()
    assert marker_centroid(pair.left) is not None and marker_centroid(pair.right) is not None


def test_tool_casts_a_shadow_on_the_table(cam: SimStereoCamera) -> None:
    tool = np.array([0.62, 0.12, 0.5])
    cam.set_robot(arm_to(tool), tool, TOOL_DOWN, grip=0.0)
    pair = cam.grab()
    renderer = cam._renderer
    assert renderer is not None
    uv, _ = renderer.left.camera.project((0.62, 0.12, TABLE.top_z))
    u, v = (round(x) for x in uv[0])
    assert (pair.left[v, u].astype(int) < renderer.left.background[v, u].astype(int) - 10).all()


def test_set_robot_rejects_bad_input_and_keeps_the_last_pose(cam: SimStereoCamera) -> None:
    tool = np.array([0.6, 0.0, 0.55])
    cam.set_robot(arm_to(tool), tool, TOOL_DOWN.reshape(9), grip=1.0)
    good = cam.grab().left
    bad_points = arm_to(tool)
    bad_points[3, 1] = float("nan")
    for args in (
        (bad_points, tool, TOOL_DOWN, None),
        (arm_to(tool)[:1], tool, TOOL_DOWN, None),
        (arm_to(tool), tool[:2], TOOL_DOWN, None),
        (arm_to(tool), tool, np.eye(2), None),
        (arm_to(tool), tool, TOOL_DOWN, 1.5),
    ):
        with pytest.raises(ValueError):
            cam.set_robot(*args)
    assert np.array_equal(cam.grab().left, good)


@functools.cache
def _tiny_cam() -> SimStereoCamera:
    c = SimStereoCamera(VisionConfig(width=64, height=48), supersample=1)
    c.open()
    return c


_coord = st.one_of(
    st.floats(-3.0, 4.0, allow_nan=False),
    st.sampled_from([1.8, 1.8325, 1.7675, 0.0, 1.35]),  # on the eyes' centres
)
_point = st.tuples(_coord, _coord, _coord)


@settings(max_examples=60, deadline=None)
@given(st.lists(_point, min_size=8, max_size=8), st.none() | st.floats(0.0, 1.0))
def test_any_pose_renders_even_behind_or_through_the_cameras(
    points: list[tuple[float, float, float]], grip: float | None
) -> None:
    """Near-plane clipping: links behind, through or touching the lenses never crash."""
    cam = _tiny_cam()
    cam.set_robot(np.array(points[:7]), np.array(points[7]), TOOL_DOWN, grip)
    pair = cam.grab()
    assert pair.left.shape == pair.right.shape == (48, 64, 3)
    assert pair.left.dtype == np.uint8


def test_set_scene_rerenders_the_background() -> None:
    cam = SimStereoCamera(VisionConfig(width=64, height=48), supersample=1)
    cam.open()
    before = cam.grab().left
    scene = default_scene()
    cam.set_scene(type(scene)(boxes=(), cylinders=()))
    after = cam.grab().left
    assert not np.array_equal(before, after)
    assert cam.scene.boxes == ()
