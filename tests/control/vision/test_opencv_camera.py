from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.control.vision.backends import open_camera
from services.control.vision.camera import CameraError, Intrinsics
from services.control.vision.config import VisionConfig
from services.control.vision.opencv_camera import OpenCVCamera

from .fakes import write_video

W, H, N = 64, 48, 6
# MJPG is lossy: a flat frame comes back within a few grey levels.
TOL = 4.0


def left_level(i: int) -> int:
    return 20 + 30 * i


def right_level(i: int) -> int:
    return 235 - 30 * i


def flat(level: int, w: int = W, h: int = H) -> np.ndarray:
    return np.full((h, w, 3), level, np.uint8)


@pytest.fixture
def pair_files(tmp_path: Path) -> tuple[str, str]:
    left = write_video(tmp_path / "left.avi", [flat(left_level(i)) for i in range(N)])
    right = write_video(tmp_path / "right.avi", [flat(right_level(i)) for i in range(N)])
    return str(left), str(right)


@pytest.fixture
def sbs_file(tmp_path: Path) -> str:
    frames = [np.concatenate([flat(left_level(i)), flat(right_level(i))], axis=1) for i in range(N)]
    return str(write_video(tmp_path / "sbs.avi", frames))


def test_two_files_play_in_step_then_end(pair_files: tuple[str, str]) -> None:
    cam = OpenCVCamera(pair_files, width=W, height=H)
    cam.open()
    try:
        for i in range(N):
            pair = cam.grab()
            assert pair.left.shape == pair.right.shape == (H, W, 3)
            assert pair.left.mean() == pytest.approx(left_level(i), abs=TOL)
            assert pair.right.mean() == pytest.approx(right_level(i), abs=TOL)
            assert pair.t_ns_right >= pair.t_ns_left  # left grabbed first, then right
        with pytest.raises(CameraError, match="end of file") as err:
            cam.grab()
        assert "left.avi" in str(err.value)
    finally:
        cam.close()
        cam.close()


def test_side_by_side_file_is_split(sbs_file: str) -> None:
    cam = OpenCVCamera([sbs_file], width=W, height=H)
    cam.open()
    try:
        for i in range(N):
            pair = cam.grab()
            assert pair.left.shape == pair.right.shape == (H, W, 3)
            assert pair.left.flags["C_CONTIGUOUS"] and pair.right.flags["C_CONTIGUOUS"]
            assert pair.left.mean() == pytest.approx(left_level(i), abs=TOL)
            assert pair.right.mean() == pytest.approx(right_level(i), abs=TOL)
            assert pair.skew_ns == 0  # one sensor, one exposure
        with pytest.raises(CameraError, match="end of file"):
            cam.grab()
    finally:
        cam.close()


def test_loop_rewinds_both_files_together(pair_files: tuple[str, str]) -> None:
    cam = OpenCVCamera(pair_files, width=W, height=H, loop=True)
    cam.open()
    try:
        for _ in range(N):
            cam.grab()
        first = cam.grab()  # frame N: wrapped to frame 0
        assert first.left.mean() == pytest.approx(left_level(0), abs=TOL)
        assert first.right.mean() == pytest.approx(right_level(0), abs=TOL)
    finally:
        cam.close()


def test_resizes_to_the_configured_size_with_intrinsics_for_it(
    pair_files: tuple[str, str],
) -> None:
    cfg = VisionConfig(camera="opencv", files=pair_files, width=32, height=24, fov_deg=90.0)
    cam = open_camera(cfg)
    cam.open()
    try:
        pair = cam.grab()
        assert pair.left.shape == (24, 32, 3)
        assert pair.intrinsics == Intrinsics.from_fov(32, 24, 90.0)
    finally:
        cam.close()


def test_configured_intrinsics_are_reported(pair_files: tuple[str, str]) -> None:
    k = (70.0, 71.0, 31.0, 23.0)
    cam = open_camera(
        VisionConfig(camera="opencv", files=pair_files, width=W, height=H, intrinsics=k)
    )
    cam.open()
    try:
        assert cam.grab().intrinsics == Intrinsics(*k)
    finally:
        cam.close()


def test_missing_file_is_a_clear_error(tmp_path: Path, pair_files: tuple[str, str]) -> None:
    missing = str(tmp_path / "nope.avi")
    cam = OpenCVCamera([pair_files[0], missing], width=W, height=H)
    with pytest.raises(CameraError, match="no such video file") as err:
        cam.open()
    assert "nope.avi" in str(err.value)
    with pytest.raises(CameraError, match="before open"):
        cam.grab()


def test_absent_device_is_a_clear_error() -> None:
    cam = OpenCVCamera([97, 98], width=W, height=H)
    with pytest.raises(CameraError, match="video device 97"):
        cam.open()
    assert cam.name == "opencv:97,98"


def test_device_numbers_given_as_text_are_indices() -> None:
    assert OpenCVCamera(["0", "/dev/video1"]).sources == (0, "/dev/video1")


def test_wrong_source_count() -> None:
    with pytest.raises(CameraError):
        OpenCVCamera([])
