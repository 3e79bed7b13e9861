from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.control.vision.camera import Intrinsics
from services.control.vision.config import VisionConfig
from services.control.vision.rig import StereoRig


def test_look_at_gives_a_rectified_rig() -> None:
    rig = StereoRig.from_config(VisionConfig())
    R = rig.wRc
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert R[2, 0] == pytest.approx(0.0, abs=1e-12)  # x axis horizontal
    assert R[2, 1] < 0.0  # image "down" points down in the world for a level rig
    # The eyes share orientation and sit baseline apart along the rig's x axis.
    assert np.array_equal(rig.left.wRc, rig.right.wRc)
    delta = rig.right.position_m - rig.left.position_m
    assert np.allclose(delta, 0.065 * R[:, 0])
    assert np.allclose(rig.center_m, (1.8, 0.0, 1.35))


def test_target_projects_to_the_principal_point() -> None:
    cfg = VisionConfig()
    rig = StereoRig.from_config(cfg)
    uv_l, z = rig.left.project(cfg.rig_target_m)
    k = rig.intrinsics
    # The target is on the rig centre's axis, half a baseline to the left eye's right.
    assert uv_l[0, 1] == pytest.approx(k.cy)
    assert uv_l[0, 0] - k.cx == pytest.approx(k.fx * 0.0325 / z[0])


def test_intrinsics_from_fov() -> None:
    k = Intrinsics.from_fov(640, 480, 90.0)
    assert (k.fx, k.fy, k.cx, k.cy) == pytest.approx((320.0, 320.0, 319.5, 239.5))
    half = k.scaled(0.5, 0.5)
    assert (half.fx, half.cx, half.cy) == pytest.approx((160.0, 159.5, 119.5))


@given(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(0.3, 5.0), st.floats(0.01, 0.3))
def test_disparity_is_fx_b_over_z(x: float, y: float, depth_m: float, baseline_m: float) -> None:
    """The pinhole stereo relation u_l − u_r = fx·B/Z, v_l = v_r, for any point ahead."""
    rig = StereoRig.look_at(
        (1.8, 0.0, 1.35), (0.5, 0.0, 0.55), baseline_m, Intrinsics(500, 480, 320, 240), 640, 480
    )
    p = rig.center_m + rig.wRc @ np.array([x, y, depth_m])
    (ul, vl), (ur, vr) = rig.left.project(p)[0][0], rig.right.project(p)[0][0]
    assert ul - ur == pytest.approx(500 * baseline_m / depth_m, rel=1e-9)
    assert vl == pytest.approx(vr, abs=1e-9)
    assert rig.disparity_px(p) == pytest.approx(ul - ur, rel=1e-9)
