"""Configuration of the vision service, read once at start-up into a frozen dataclass."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, NoReturn, get_args

from services.bus.config import section
from services.bus.errors import ConfigError
from services.geometry import V3

CameraKind = Literal["sim", "opencv"]
Encoding = Literal["jpeg", "bgr8"]
ENCODINGS: tuple[str, ...] = get_args(Encoding)
CAMERAS: tuple[str, ...] = get_args(CameraKind)

MAX_SIZE_PX = 8192
MAX_FPS = 240.0


@dataclass(frozen=True, slots=True)
class VisionConfig:
    """Settings of the stereo vision service.

    camera: "sim" renders the simulated workcell, "opencv" reads `devices` or `files`.
    width, height (px): size of ONE eye's image; fps: the fixed capture rate (pairs/s).
    encoding: "jpeg" (quality `jpeg_quality`, 1…100) or raw "bgr8".
    baseline_m: distance between the two optical centres (m).
    rig_position_m, rig_target_m (world, m): where the simulated rig's centre stands and the
      point it looks at; both eyes share this orientation, the rig's x axis is horizontal.
      The defaults frame the whole table top and the arm above it, seen from in front.
    fov_deg: horizontal field of view of one eye, used by the simulator and to guess the
      intrinsics of a real camera when `intrinsics` (fx, fy, cx, cy in px, for the output
      size) is not given.
    devices: one (side-by-side stereo) or two (left, right) OpenCV device indices or paths.
    files: one (side-by-side) or two (left, right) video files, played one frame per tick;
      `loop_files` rewinds them at the end instead of reporting end of file.
    reopen_s: how long the pipeline waits before reopening a failed camera (s).
    adapt: lower the video's level (JPEG quality, then size, then rate: adapt.py) when its
      receivers report it queueing or lost on the link, and raise it back when they report
      it carried; false keeps `jpeg_quality`, the size and `fps` whatever the link.
    adapt_queue_ms: how far a pair's age p90 may rise above the link's own delay before
      the level goes down (10 … 10 000 ms).
    adapt_up_s: how long the reports must be good before the level goes up (1 … 600 s).
    """

    camera: CameraKind = "sim"
    width: int = 640
    height: int = 480
    fps: float = 30.0
    encoding: Encoding = "jpeg"
    jpeg_quality: int = 80
    baseline_m: float = 0.065
    rig_position_m: V3 = (1.8, 0.0, 1.35)
    rig_target_m: V3 = (0.5, 0.0, 0.55)
    fov_deg: float = 60.0
    intrinsics: tuple[float, float, float, float] | None = None
    devices: tuple[int | str, ...] = ()
    files: tuple[str, ...] = ()
    loop_files: bool = False
    reopen_s: float = 1.0
    adapt: bool = True
    adapt_queue_ms: float = 150.0
    adapt_up_s: float = 8.0

    def __post_init__(self) -> None:
        if self.camera not in CAMERAS:
            _fail("camera", f"{self.camera!r} is not one of {CAMERAS}")
        for key in ("width", "height"):
            v = getattr(self, key)
            if not isinstance(v, int) or isinstance(v, bool) or not 16 <= v <= MAX_SIZE_PX:
                _fail(key, f"{v!r} must be an integer in 16…{MAX_SIZE_PX} px")
        if not _finite(self.fps) or not 0.0 < self.fps <= MAX_FPS:
            _fail("fps", f"{self.fps!r} must be in (0, {MAX_FPS}]")
        if self.encoding not in ENCODINGS:
            _fail("encoding", f"{self.encoding!r} is not one of {ENCODINGS}")
        q = self.jpeg_quality
        if not isinstance(q, int) or isinstance(q, bool) or not 1 <= q <= 100:
            _fail("jpeg_quality", f"{q!r} must be an integer in 1…100")
        if not _finite(self.baseline_m) or not 0.0 < self.baseline_m <= 1.0:
            _fail("baseline_m", f"{self.baseline_m!r} must be in (0, 1] m")
        for key in ("rig_position_m", "rig_target_m"):
            v = getattr(self, key)
            if not isinstance(v, tuple) or len(v) != 3 or not all(_finite(x) for x in v):
                _fail(key, f"{v!r} must be 3 finite numbers (m)")
        look = [t - p for t, p in zip(self.rig_target_m, self.rig_position_m, strict=True)]
        norm = math.sqrt(sum(x * x for x in look))
        if norm < 1e-3:
            _fail("rig_target_m", "must differ from rig_position_m")
        elif math.hypot(look[0], look[1]) < 1e-3 * norm:
            _fail(
                "rig_target_m", "the rig cannot look straight up or down (its x axis is horizontal)"
            )
        if not _finite(self.fov_deg) or not 1.0 <= self.fov_deg <= 170.0:
            _fail("fov_deg", f"{self.fov_deg!r} must be in 1…170 degrees")
        if self.intrinsics is not None:
            k = self.intrinsics
            if not isinstance(k, tuple) or len(k) != 4 or not all(_finite(x) for x in k):
                _fail("intrinsics", f"{k!r} must be 4 finite numbers fx, fy, cx, cy (px)")
            elif k[0] <= 0 or k[1] <= 0:
                _fail("intrinsics", "fx and fy must be > 0 px")
        if not isinstance(self.devices, tuple) or not all(
            isinstance(d, int | str) and not isinstance(d, bool) for d in self.devices
        ):
            _fail("devices", f"{self.devices!r} must be device indices or paths")
        if not isinstance(self.files, tuple) or not all(isinstance(f, str) for f in self.files):
            _fail("files", f"{self.files!r} must be file paths")
        if self.camera == "opencv":
            if bool(self.devices) == bool(self.files):
                _fail("devices", "camera 'opencv' needs exactly one of devices or files")
            sources = self.devices or self.files
            if len(sources) not in (1, 2):
                key = "devices" if self.devices else "files"
                _fail(key, "give 1 (side-by-side stereo) or 2 (left, right) sources")
        if not _finite(self.reopen_s) or not 0.0 < self.reopen_s <= 60.0:
            _fail("reopen_s", f"{self.reopen_s!r} must be in (0, 60] s")
        if not isinstance(self.adapt, bool):
            _fail("adapt", f"{self.adapt!r} must be true or false")
        if not _finite(self.adapt_queue_ms) or not 10.0 <= self.adapt_queue_ms <= 10_000.0:
            _fail("adapt_queue_ms", f"{self.adapt_queue_ms!r} must be in 10 … 10000 ms")
        if not _finite(self.adapt_up_s) or not 1.0 <= self.adapt_up_s <= 600.0:
            _fail("adapt_up_s", f"{self.adapt_up_s!r} must be in 1 … 600 s")

    @property
    def period_s(self) -> float:
        """The capture period (s)."""
        return 1.0 / self.fps

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any]) -> VisionConfig:
        """Build from a TOML-like table with the bus's one config reader
        (`services.bus.config.section`); an unknown key or a bad value raises `ConfigError`
        naming `vision.<key>`. `size = "640x480"` may stand for width and height."""
        values = dict(table)
        if "size" in values:
            values["width"], values["height"] = parse_size(str(values.pop("size")))
        return section(cls, values, "vision")


_SIZE = re.compile(r"^\s*(\d+)\s*[xX×]\s*(\d+)\s*$")


def parse_size(text: str) -> tuple[int, int]:
    """Parse "640x480" (also "640X480", "640×480") into (width, height) in px."""
    m = _SIZE.match(text)
    if m is None:
        raise ConfigError("vision.size", f"{text!r} is not WIDTHxHEIGHT, e.g. 640x480")
    width, height = int(m.group(1)), int(m.group(2))
    if not (16 <= width <= MAX_SIZE_PX and 16 <= height <= MAX_SIZE_PX):
        raise ConfigError("vision.size", f"{text!r}: each side must be in 16…{MAX_SIZE_PX} px")
    return width, height


def _finite(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _fail(key: str, message: str) -> NoReturn:
    raise ConfigError(f"vision.{key}", message)
