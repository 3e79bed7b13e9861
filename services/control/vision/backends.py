"""`open_camera(config)`: the camera a `VisionConfig` names, built and not opened.

`BACKENDS` names each `vision.camera` backend's class, imported, and through it OpenCV,
only when that backend is built; `camera_options` maps the configuration to the class's
constructor arguments. The pipeline opens the camera in its capture thread, so a camera that
fails to open is reported as an event and retried instead of stopping the service.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from services.bus.registry import BackendRegistry
from services.control.vision.camera import Camera, Intrinsics
from services.control.vision.config import VisionConfig

if TYPE_CHECKING:
    from services.world.workcell.scene import Scene

BACKENDS: BackendRegistry[Camera] = BackendRegistry(
    "vision.camera",
    "camera",
    {
        "sim": "services.control.vision.sim_camera:SimStereoCamera",
        "opencv": "services.control.vision.opencv_camera:OpenCVCamera",
    },
)
"""Backend name (`vision.camera`) → class, constructed with `camera_options(config)`."""


def camera_options(config: VisionConfig, scene: Scene | None = None) -> dict[str, Any]:
    """The constructor arguments of the backend `config.camera` (`scene`: what the
    simulated cameras look at, None for the standard workcell)."""
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
    return {"config": config} if scene is None else {"config": config, "scene": scene}


def open_camera(config: VisionConfig, scene: Scene | None = None) -> Camera:
    """The camera `config.camera` with its options, not yet opened (`Camera.open`).

    Raises ConfigError("vision.camera", …) for a name without a backend (a `VisionConfig`
    built the ordinary way has refused it already).
    """
    return BACKENDS.build(config.camera, camera_options(config, scene))
