"""The `Camera` role: a stereo rig that delivers synchronized left/right pairs.

Backends are siblings named for their medium: `SimStereoCamera` (renders the simulated
workcell, `services.control.vision.sim_camera`) and `OpenCVCamera` (two devices, one side-by-side
device or video files, `services.control.vision.opencv_camera`). `backends.py` holds
`open_camera(config)`, which picks one and imports it, and through it OpenCV, only when
asked, so pure logic and its tests never load cv2.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from services.bus.errors import TelerobotError

Image = NDArray[np.uint8]
"""A BGR image, (height, width, 3) uint8, row-major, the layout OpenCV uses."""


class CameraError(TelerobotError):
    """A camera that cannot deliver: failed to open, unplugged, end of file. Says which one."""


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """Pinhole intrinsics of one eye (px): focal lengths `fx`, `fy`, principal point `cx`, `cy`.

    Pixel coordinates follow OpenCV: u to the right, v down, the centre of pixel (row i,
    column j) at (u, v) = (j, i). Both eyes of a rectified rig share these values.
    """

    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float) -> Intrinsics:
        """Square pixels, principal point at the image centre, `fov_deg` the horizontal field."""
        fx = 0.5 * width / float(np.tan(np.radians(fov_deg) / 2.0))
        return cls(fx, fx, (width - 1) / 2.0, (height - 1) / 2.0)

    def scaled(self, sx: float, sy: float) -> Intrinsics:
        """The intrinsics after resizing the image by `sx` horizontally and `sy` vertically."""
        return Intrinsics(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5
        )


@dataclass(frozen=True, slots=True)
class StereoPair:
    """One stereo pair.

    `left`, `right`: BGR images of equal shape (height, width, 3), uint8.
    `t_ns_left`, `t_ns_right`: capture time of each eye, `time.time_ns()` of the capturing
    host (for a device: when its grab returned; for the simulator: the instant of the robot
    state it shows, the same for both eyes).
    `intrinsics` (px) and `baseline_m` (m, distance between the optical centres along the
    rig's x axis; the right eye sits at +baseline along x) describe the rectified rig.
    """

    left: Image
    right: Image
    t_ns_left: int
    t_ns_right: int
    intrinsics: Intrinsics
    baseline_m: float

    @property
    def skew_ns(self) -> int:
        """Right capture time minus left capture time (ns)."""
        return self.t_ns_right - self.t_ns_left

    @property
    def width(self) -> int:
        return int(self.left.shape[1])

    @property
    def height(self) -> int:
        return int(self.left.shape[0])


@runtime_checkable
class Camera(Protocol):
    """A stereo camera. Only the capture thread of the pipeline calls these methods.

    `open()` acquires the device (idempotent; raises `CameraError` when it cannot).
    `grab()` returns the next pair, or None when no new pair is available this time; it
    raises `CameraError` when the camera is gone (unplugged, end of file, not open).
    `close()` releases the device (idempotent; the camera may be opened again after).
    `keep_alive()` is called instead of `grab()`, at the capture rate, while nobody watches
    the stream: a device that must keep being read (its driver queue would go stale) reads
    and discards a frame without decoding it and returns True; a camera that can simply
    wait (the simulator, a file) does nothing and returns False, and is then left alone
    until someone watches. It raises `CameraError` like `grab`.
    `name` identifies the camera in events and statistics.
    """

    @property
    def name(self) -> str: ...

    def open(self) -> None: ...

    def grab(self) -> StereoPair | None: ...

    def keep_alive(self) -> bool: ...

    def close(self) -> None: ...
