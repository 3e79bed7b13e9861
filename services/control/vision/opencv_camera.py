"""`OpenCVCamera`: real stereo cameras or recordings through `cv2.VideoCapture`.

Sources: two devices or files (left, right), or one side-by-side stereo device or file
whose frame holds the left eye in its left half and the right eye in its right half.
Both captures are grabbed first and decoded after (`VideoCapture.grab()` then
`retrieve()`), so the skew between the eyes is one grab, not one grab plus one decode.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence

import cv2
import numpy as np

from services.control.vision.camera import CameraError, Image, Intrinsics, StereoPair

Source = int | str


class OpenCVCamera:
    """A stereo camera read with OpenCV.

    `sources`: 1 (side-by-side) or 2 (left, right) device indices, device paths or video
    files. Output images are `width` × `height` per eye (px), resized when the source
    differs. `intrinsics` (px) are those of the output images; without them they are
    guessed from the horizontal field of view `fov_deg` (square pixels, centred principal
    point). `baseline_m` is reported as given. Files play one frame per `grab`; at their
    end `grab` raises `CameraError` unless `loop`, which rewinds them together.
    """

    def __init__(
        self,
        sources: Sequence[Source],
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        intrinsics: Intrinsics | None = None,
        fov_deg: float = 60.0,
        baseline_m: float = 0.065,
        loop: bool = False,
    ) -> None:
        if len(sources) not in (1, 2):
            raise CameraError(f"opencv camera: give 1 or 2 sources, not {len(sources)}")
        self.sources: tuple[Source, ...] = tuple(_normalise(s) for s in sources)
        self.width = width
        self.height = height
        self.fps = fps
        self.intrinsics = intrinsics or Intrinsics.from_fov(width, height, fov_deg)
        self.baseline_m = baseline_m
        self.loop = loop
        self._caps: list[cv2.VideoCapture] = []

    @property
    def name(self) -> str:
        return "opencv:" + ",".join(str(s) for s in self.sources)

    @property
    def side_by_side(self) -> bool:
        return len(self.sources) == 1

    def open(self) -> None:
        """Open every source; raises `CameraError` naming the one that fails."""
        if self._caps:
            return
        caps: list[cv2.VideoCapture] = []
        try:
            for src in self.sources:
                if _is_file(src) and not os.path.isfile(str(src)):
                    raise CameraError(f"{self.name}: no such video file {src!r}")
                cap = cv2.VideoCapture(src)
                caps.append(cap)
                if not cap.isOpened():
                    raise CameraError(f"{self.name}: cannot open {_describe(src)}")
                if not _is_file(src):
                    per_source_width = self.width * (2 if self.side_by_side else 1)
                    cap.set(cv2.CAP_PROP_FRAME_WIDTH, per_source_width)
                    cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
                    cap.set(cv2.CAP_PROP_FPS, self.fps)
                    # A one-frame driver queue: stale frames would add latency, not data.
                    cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        except CameraError:
            for cap in caps:
                cap.release()
            raise
        self._caps = caps

    def close(self) -> None:
        caps, self._caps = self._caps, []
        for cap in caps:
            cap.release()

    def grab(self) -> StereoPair:
        if not self._caps:
            raise CameraError(f"{self.name}: grab() before open()")
        stamps = self._grab_all()
        frames: list[Image] = []
        for cap, src in zip(self._caps, self.sources, strict=True):
            ok, frame = cap.retrieve()
            if not ok or frame is None or frame.size == 0:
                raise CameraError(f"{self.name}: cannot decode a frame from {_describe(src)}")
            frames.append(_to_bgr(np.asarray(frame), self.name))
        if self.side_by_side:
            full = frames[0]
            half = full.shape[1] // 2
            frames = [full[:, :half], full[:, half : 2 * half]]
            stamps = [stamps[0], stamps[0]]
        left, right = (self._fit(f) for f in frames)
        return StereoPair(left, right, stamps[0], stamps[-1], self.intrinsics, self.baseline_m)

    def keep_alive(self) -> bool:
        """Devices: grab (not decode) a frame from each, so their one-frame driver queue
        stays fresh and the next `grab` returns a current picture; True. Files: nothing,
        playback pauses where it is; False."""
        if not self._caps:
            raise CameraError(f"{self.name}: keep_alive() before open()")
        if all(_is_file(s) for s in self.sources):
            return False
        self._grab_all()
        return True

    def _grab_all(self) -> list[int]:
        """Grab every source back to back; returns each grab's completion time (ns)."""
        for attempt in range(2):
            stamps: list[int] = []
            failed: Source | None = None
            for cap, src in zip(self._caps, self.sources, strict=True):
                if not cap.grab():
                    failed = src
                    break
                stamps.append(time.time_ns())
            if failed is None:
                return stamps
            if not (attempt == 0 and self.loop and all(_is_file(s) for s in self.sources)):
                break
            for cap in self._caps:
                cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        assert failed is not None
        if _is_file(failed):
            raise CameraError(f"{self.name}: end of file {failed!r}")
        raise CameraError(f"{self.name}: no frame from {_describe(failed)} (disconnected?)")

    def _fit(self, img: Image) -> Image:
        if img.shape[1] == self.width and img.shape[0] == self.height:
            return np.ascontiguousarray(img)
        shrink = img.shape[1] > self.width
        interp = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        out = cv2.resize(img, (self.width, self.height), interpolation=interp)
        return np.asarray(out, dtype=np.uint8)


def _normalise(src: Source) -> Source:
    if isinstance(src, str) and src.strip().isdigit():
        return int(src)
    return src


def _is_file(src: Source) -> bool:
    return isinstance(src, str) and not src.startswith("/dev/") and "://" not in src


def _describe(src: Source) -> str:
    if isinstance(src, int):
        return f"video device {src}"
    return f"video file {src!r}" if _is_file(src) else f"video source {src!r}"


def _to_bgr(frame: np.ndarray, name: str) -> Image:
    if frame.dtype != np.uint8:
        raise CameraError(f"{name}: frames of type {frame.dtype} are not supported (uint8 only)")
    if frame.ndim == 2:
        return np.asarray(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
    if frame.ndim == 3 and frame.shape[2] == 4:
        return np.asarray(cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR), dtype=np.uint8)
    if frame.ndim == 3 and frame.shape[2] == 3:
        return frame
    raise CameraError(f"{name}: unexpected frame shape {frame.shape}")
