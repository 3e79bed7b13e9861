"""`open_camera(config)`: the camera a `VisionConfig` names, built and not opened.

`BACKENDS` maps each `vision.camera` name to a constructor that imports its backend, and
through it OpenCV, only when called; `camera_options` is what the configuration passes to
that constructor. The pipeline opens the camera in its capture thread, so a camera that
fails to open is reported as an event and retried instead of stopping the service.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from services.bus.errors import ConfigError
from services.vision.camera import Camera, Intrinsics
from services.vision.config import CAMERAS, VisionConfig


def _sim(options: dict[str, Any]) -> Camera:
    from services.vision.sim_camera import SimStereoCamera

    return SimStereoCamera(**options)


def _opencv(options: dict[str, Any]) -> Camera:
    from services.vision.opencv_camera import OpenCVCamera

    return OpenCVCamera(**options)


BACKENDS: Mapping[str, Callable[[dict[str, Any]], Camera]] = {"sim": _sim, "opencv": _opencv}
"""Backend name (`vision.camera`) → constructor, called with `camera_options(config)`."""


def camera_options(config: VisionConfig) -> dict[str, Any]:
    """The constructor arguments of the backend `config.camera`."""
    if config.camera == "opencv":
        return {
            "sources": config.devices or config.files,
            "width": config.width,
            "height": config.height,
            "fps": config.fps,
            "intrinsics": Intrinsics(*config.intrinsics) if config.intrinsics else None,
            "fov_deg": config.fov_deg,
            "baseline_m": config.baseline_m,
            "loop": config.loop_files,
        }
    return {"config": config}


def open_camera(config: VisionConfig) -> Camera:
    """The camera `config.camera` with its options, not yet opened (`Camera.open`).

    Raises ConfigError("vision.camera", …) for a name without a backend (a `VisionConfig`
    built the ordinary way has refused it already).
    """
    construct = BACKENDS.get(config.camera)
    if construct is None:
        raise ConfigError(
            "vision.camera", f"unknown camera {config.camera!r}, expected one of {CAMERAS}"
        )
    return construct(camera_options(config))
