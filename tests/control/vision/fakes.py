"""Test doubles and helpers shared by the vision tests."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from services.control.vision.camera import CameraError, Intrinsics, StereoPair

MAGENTA = np.array([255, 0, 255], dtype=np.uint8)


class FakeCamera:
    """A tiny stereo camera under the test's control.

    Each pair's pixels carry its frame number (mod 256). `fail` (an exception instance)
    makes grab raise it; `starve` makes grab return None; `fail_open` makes open raise.
    `device` makes it a camera that must keep being read while nobody watches
    (`keep_alive` returns True and counts `keep_alives`), like a real device.
    """

    def __init__(self, width: int = 16, height: int = 16, skew_ns: int = 1_000) -> None:
        self.width, self.height, self.skew_ns = width, height, skew_ns
        self.frames = 0
        self.open_calls = 0
        self.close_calls = 0
        self.is_open = False
        self.fail: Exception | None = None
        self.starve = False
        self.fail_open = False
        self.device = False
        self.keep_alives = 0
        self._lock = threading.Lock()

    @property
    def name(self) -> str:
        return "fake"

    def open(self) -> None:
        with self._lock:
            self.open_calls += 1
            if self.fail_open:
                raise CameraError("fake: no such device")
            self.is_open = True

    def close(self) -> None:
        with self._lock:
            self.close_calls += 1
            self.is_open = False

    def keep_alive(self) -> bool:
        if not self.is_open:
            raise CameraError("fake: not open")
        if self.fail is not None:
            raise self.fail
        self.keep_alives += 1
        return self.device

    def grab(self) -> StereoPair | None:
        if not self.is_open:
            raise CameraError("fake: not open")
        if self.fail is not None:
            raise self.fail
        if self.starve:
            return None
        self.frames += 1
        img = np.full((self.height, self.width, 3), self.frames % 256, np.uint8)
        t = time.time_ns()
        k = Intrinsics(20.0, 20.0, (self.width - 1) / 2, (self.height - 1) / 2)
        return StereoPair(img, img.copy(), t, t + self.skew_ns, k, 0.065)


class Recorder:
    """Collects publish() and emit() calls from the pipeline's threads."""

    def __init__(self) -> None:
        self.pairs: list[tuple[dict[str, Any], dict[str, Any]]] = []
        self.events: list[tuple[str, str, dict[str, Any]]] = []
        self._lock = threading.Lock()

    def publish(self, left: dict[str, Any], right: dict[str, Any]) -> None:
        with self._lock:
            self.pairs.append((left, right))

    def emit(self, kind: str, message: str, data: dict[str, Any]) -> None:
        with self._lock:
            self.events.append((kind, message, data))

    def kinds(self) -> list[str]:
        with self._lock:
            return [e[0] for e in self.events]


def marker_centroid(img: NDArray[np.uint8]) -> tuple[float, float] | None:
    """(u, v) centroid (px) of the pure-magenta tool marker, None when it is not visible."""
    mask = np.all(img == MAGENTA, axis=2)
    if not mask.any():
        return None
    v, u = np.nonzero(mask)
    return float(u.mean()), float(v.mean())


def write_video(path: Path, frames: list[NDArray[np.uint8]], fps: float = 30.0) -> Path:
    """Write `frames` (BGR, equal sizes) as MJPG in an .avi file."""
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened(), "this OpenCV build cannot write MJPG .avi"
    for f in frames:
        writer.write(f)
    writer.release()
    return path
