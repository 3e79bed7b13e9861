"""Stereo frames for the page: decode one eye, compose the chosen view, throttle the rate.

`compose` is pure numpy; `decode` imports cv2 only when a JPEG arrives, so the console's
logic and its tests load no image library.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray

from services.bus.messages import StereoFrame

ViewMode = Literal["side-by-side", "left", "right", "anaglyph", "off"]
VIEW_MODES: tuple[str, ...] = get_args(ViewMode)

Image = NDArray[np.uint8]


def decode(frame: StereoFrame) -> Image:
    """One eye as an RGB image (height, width, 3), uint8. Raises ValueError on bad data."""
    if frame.encoding == "bgr8":
        expected = frame.width * frame.height * 3
        if len(frame.data) != expected:
            raise ValueError(f"bgr8 frame of {len(frame.data)} bytes, expected {expected}")
        bgr: Image = np.frombuffer(frame.data, dtype=np.uint8).reshape(frame.height, frame.width, 3)
    else:
        import cv2

        decoded = cv2.imdecode(np.frombuffer(frame.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if decoded is None:
            raise ValueError("undecodable JPEG")
        bgr = np.asarray(decoded, dtype=np.uint8)
    return np.ascontiguousarray(bgr[:, :, ::-1])


def _crop_pair(left: Image, right: Image) -> tuple[Image, Image]:
    h = min(left.shape[0], right.shape[0])
    w = min(left.shape[1], right.shape[1])
    return left[:h, :w], right[:h, :w]


def compose(
    left: Image | None, right: Image | None, mode: ViewMode, max_width_px: int
) -> Image | None:
    """The image to show for `mode`, at most `max_width_px` wide (decimated by an integer
    step, which keeps it cheap), or None when the eyes it needs are missing.

    side-by-side: left | right. anaglyph (red–cyan glasses): red from the left eye, green
    and blue from the right, so each eye of the viewer sees its camera's image."""
    if mode == "off":
        return None
    if mode == "left":
        out = left
    elif mode == "right":
        out = right
    elif left is None or right is None:
        # A pair view with one eye missing shows the eye there is rather than nothing.
        out = left if left is not None else right
    else:
        lc, rc = _crop_pair(left, right)
        if mode == "side-by-side":
            out = np.concatenate([lc, rc], axis=1)
        else:
            out = rc.copy()
            out[:, :, 0] = lc[:, :, 0]
    if out is None:
        return None
    step = max(1, -(-out.shape[1] // max_width_px))
    return np.ascontiguousarray(out[::step, ::step]) if step > 1 else out


class FrameGate:
    """Lets a frame through at most `rate_hz` times a second (the browser gets ~10–15 fps
    whatever the camera's rate), and only when a new pair arrived."""

    def __init__(self, rate_hz: float) -> None:
        if not rate_hz > 0:
            raise ValueError("rate_hz must be > 0")
        self.period_s = 1.0 / rate_hz
        self._next_s = -1e18
        self._last_key: tuple[int, int] | None = None
        self.passed = 0

    def due(self, now_s: float, key: tuple[int, int]) -> bool:
        """True if a frame identified by `key` (left seq, right seq) should be sent at time
        `now_s` (monotonic, s); counts it as sent."""
        if key == self._last_key or now_s < self._next_s:
            return False
        # Anchored to the previous slot, so ticks coarser than the period still average
        # rate_hz; after a pause at most one frame comes early, never a burst.
        self._next_s = max(self._next_s + self.period_s, now_s + 0.5 * self.period_s)
        self._last_key = key
        self.passed += 1
        return True

    def reset(self) -> None:
        """Send the next frame whatever its key (the view mode changed)."""
        self._last_key = None
