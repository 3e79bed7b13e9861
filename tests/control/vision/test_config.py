from __future__ import annotations

from typing import Any

import pytest

from services.bus.errors import ConfigError
from services.control.vision.config import VisionConfig, parse_size


def test_defaults_are_the_documented_stream() -> None:
    c = VisionConfig()
    assert (c.camera, c.width, c.height, c.fps, c.encoding) == ("sim", 640, 480, 30.0, "jpeg")
    assert c.jpeg_quality == 80 and c.baseline_m == 0.065
    assert c.period_s == pytest.approx(1 / 30)


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"camera": "webcam"}, "vision.camera"),
        ({"width": 0}, "vision.width"),
        ({"height": 100_000}, "vision.height"),
        ({"width": 640.0}, "vision.width"),
        ({"fps": 0.0}, "vision.fps"),
        ({"fps": float("nan")}, "vision.fps"),
        ({"fps": 1000.0}, "vision.fps"),
        ({"encoding": "png"}, "vision.encoding"),
        ({"jpeg_quality": 0}, "vision.jpeg_quality"),
        ({"jpeg_quality": 101}, "vision.jpeg_quality"),
        ({"baseline_m": -0.065}, "vision.baseline_m"),
        ({"baseline_m": 65.0}, "vision.baseline_m"),
        ({"rig_position_m": (1.0, 2.0)}, "vision.rig_position_m"),
        ({"rig_target_m": (0.0, float("inf"), 0.0)}, "vision.rig_target_m"),
        ({"rig_target_m": (1.8, 0.0, 1.35)}, "vision.rig_target_m"),
        ({"rig_target_m": (1.8, 0.0, 0.0)}, "vision.rig_target_m"),
        ({"fov_deg": 180.0}, "vision.fov_deg"),
        ({"intrinsics": (500.0, 500.0, 320.0)}, "vision.intrinsics"),
        ({"intrinsics": (-1.0, 500.0, 320.0, 240.0)}, "vision.intrinsics"),
        ({"camera": "opencv"}, "vision.devices"),
        ({"camera": "opencv", "devices": (0,), "files": ("a.avi",)}, "vision.devices"),
        ({"camera": "opencv", "devices": (0, 1, 2)}, "vision.devices"),
        ({"camera": "opencv", "files": ("a", "b", "c")}, "vision.files"),
        ({"devices": (True,)}, "vision.devices"),
        ({"reopen_s": 0.0}, "vision.reopen_s"),
    ],
)
def test_bad_values_name_their_key(kwargs: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError) as err:
        VisionConfig(**kwargs)
    assert err.value.key == key


def test_opencv_sources_are_accepted() -> None:
    assert VisionConfig(camera="opencv", devices=(0, 1)).devices == (0, 1)
    assert VisionConfig(camera="opencv", files=("sbs.avi",)).files == ("sbs.avi",)


def test_parse_size() -> None:
    assert parse_size("640x480") == (640, 480)
    assert parse_size(" 1280 X 720 ") == (1280, 720)
    assert parse_size("320×240") == (320, 240)
    for bad in ("640", "640x", "x480", "640x480x3", "-640x480", "8x8", "a x b"):
        with pytest.raises(ConfigError) as err:
            parse_size(bad)
        assert err.value.key == "vision.size"


def test_from_mapping_reads_a_toml_table() -> None:
    c = VisionConfig.from_mapping(
        {"camera": "opencv", "size": "320x240", "devices": [0, 1], "fps": 15.0}
    )
    assert (c.width, c.height, c.devices, c.fps) == (320, 240, (0, 1), 15.0)


def test_from_mapping_rejects_a_misspelt_key() -> None:
    with pytest.raises(ConfigError) as err:
        VisionConfig.from_mapping({"jpeg_qualty": 90})
    assert err.value.key == "vision.jpeg_qualty"
