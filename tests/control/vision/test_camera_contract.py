"""One contract, every backend: what the pipeline relies on from a `Camera`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from services.bus.errors import ConfigError
from services.control.vision import backends
from services.control.vision.backends import camera_options, open_camera
from services.control.vision.camera import Camera, CameraError, Intrinsics
from services.control.vision.config import CAMERAS, VisionConfig

from .fakes import FakeCamera, write_video

W, H = 32, 24


def _sim(tmp: Path) -> Camera:
    return open_camera(VisionConfig(width=W, height=H))


def _opencv_pair(tmp: Path) -> Camera:
    frames = [np.full((H, W, 3), 40 * i, np.uint8) for i in range(4)]
    files = (str(write_video(tmp / "l.avi", frames)), str(write_video(tmp / "r.avi", frames)))
    return open_camera(VisionConfig(camera="opencv", files=files, width=W, height=H))


def _opencv_sbs(tmp: Path) -> Camera:
    frames = [np.full((H, 2 * W, 3), 40 * i, np.uint8) for i in range(4)]
    path = str(write_video(tmp / "sbs.avi", frames))
    return open_camera(VisionConfig(camera="opencv", files=(path,), width=W, height=H))


def _fake(tmp: Path) -> Camera:
    return FakeCamera(W, H)


BACKENDS: dict[str, Callable[[Path], Camera]] = {
    "sim": _sim,
    "opencv-pair": _opencv_pair,
    "opencv-side-by-side": _opencv_sbs,
    "fake": _fake,
}


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_camera_contract(backend: str, tmp_path: Path) -> None:
    cam = BACKENDS[backend](tmp_path)
    assert isinstance(cam, Camera)
    assert isinstance(cam.name, str) and cam.name
    cam.open()
    cam.open()  # idempotent
    try:
        pair = cam.grab()
        assert pair is not None
        assert pair.left.shape == pair.right.shape == (H, W, 3)
        assert pair.left.dtype == pair.right.dtype == np.uint8
        assert pair.t_ns_right >= pair.t_ns_left > 0
        k = pair.intrinsics
        assert k.fx > 0 and k.fy > 0 and 0 <= k.cx < W and 0 <= k.cy < H
        assert pair.baseline_m > 0
        # Simulators and files wait while nobody watches (only devices keep reading).
        assert cam.keep_alive() is False
    finally:
        cam.close()
    cam.close()  # idempotent
    with pytest.raises(CameraError):
        cam.grab()
    with pytest.raises(CameraError):
        cam.keep_alive()
    cam.open()  # a closed camera can be opened again
    try:
        assert cam.grab() is not None
    finally:
        cam.close()


def test_every_camera_kind_has_a_backend() -> None:
    assert set(backends.BACKENDS.names) == set(CAMERAS)


def test_camera_options_from_the_config() -> None:
    cfg = VisionConfig()
    assert camera_options(cfg) == {"config": cfg}
    files = ("l.avi", "r.avi")
    k = (70.0, 71.0, 31.0, 23.0)
    opts = camera_options(
        VisionConfig(camera="opencv", files=files, width=W, height=H, intrinsics=k, fps=15.0)
    )
    assert opts == {
        "sources": files,
        "width": W,
        "height": H,
        "fps": 15.0,
        "intrinsics": Intrinsics(*k),
        "fov_deg": VisionConfig().fov_deg,
        "baseline_m": VisionConfig().baseline_m,
        "loop": False,
    }


def test_unknown_kind_is_a_config_error() -> None:
    config = VisionConfig()
    object.__setattr__(config, "camera", "kinect")  # past VisionConfig's own check
    with pytest.raises(ConfigError) as err:
        open_camera(config)
    assert err.value.key == "vision.camera"


def test_pure_modules_do_not_load_opencv() -> None:
    import subprocess
    import sys

    code = (
        "import sys, services.control.vision.camera, services.control.vision.config\n"
        "import services.control.vision.rig, services.control.vision.pipeline\n"
        "import services.control.vision.backends\n"
        "sys.exit('cv2' in sys.modules)"
    )
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0
