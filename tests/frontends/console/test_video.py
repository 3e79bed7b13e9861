"""Stereo frames for the page: decoding, the four views, decimation and the rate gate."""

from __future__ import annotations

import numpy as np
import pytest

from services.bus.messages import StereoFrame
from services.frontends.console.video import FrameGate, compose, decode


def _frame(img_bgr: np.ndarray, encoding: str = "bgr8", eye: str = "l") -> StereoFrame:
    if encoding == "jpeg":
        import cv2

        ok, buf = cv2.imencode(".jpg", img_bgr, [int(cv2.IMWRITE_JPEG_QUALITY), 95])
        assert ok
        data = buf.tobytes()
    else:
        data = img_bgr.tobytes()
    h, w = img_bgr.shape[:2]
    return StereoFrame(seq=1, t_ns=1, eye=eye, width=w, height=h, encoding=encoding, data=data)  # type: ignore[arg-type]


def _solid(h: int, w: int, rgb: tuple[int, int, int]) -> np.ndarray:
    img = np.zeros((h, w, 3), dtype=np.uint8)
    img[:, :] = rgb
    return img


def test_decode_bgr8_and_jpeg_give_rgb() -> None:
    bgr = _solid(32, 48, (10, 100, 200))  # B, G, R
    out = decode(_frame(bgr))
    assert out.shape == (32, 48, 3)
    assert tuple(out[0, 0]) == (200, 100, 10)
    out = decode(_frame(bgr, "jpeg"))
    assert out.shape == (32, 48, 3)
    assert np.abs(out[16, 24].astype(int) - (200, 100, 10)).max() <= 4


def test_decode_refuses_bad_data() -> None:
    bgr = _solid(8, 8, (1, 2, 3))
    bad = StereoFrame(seq=1, t_ns=1, eye="l", width=8, height=8, encoding="jpeg", data=b"nope")
    with pytest.raises(ValueError):
        decode(bad)
    short = StereoFrame(
        seq=1, t_ns=1, eye="l", width=8, height=8, encoding="bgr8", data=bgr.tobytes()[:-1]
    )
    with pytest.raises(ValueError):
        decode(short)


def test_the_views() -> None:
    left, right = _solid(4, 6, (200, 10, 20)), _solid(4, 6, (30, 150, 250))
    assert compose(left, right, "left", 640) is left
    assert compose(left, right, "right", 640) is right
    sbs = compose(left, right, "side-by-side", 640)
    assert sbs is not None and sbs.shape == (4, 12, 3)
    assert tuple(sbs[0, 0]) == (200, 10, 20) and tuple(sbs[0, 11]) == (30, 150, 250)
    ana = compose(left, right, "anaglyph", 640)
    assert ana is not None and ana.shape == (4, 6, 3)
    # Red from the left eye, green and blue from the right (red–cyan glasses).
    assert tuple(ana[2, 3]) == (200, 150, 250)
    assert compose(left, right, "off", 640) is None


def test_a_pair_view_with_one_eye_shows_that_eye() -> None:
    left = _solid(4, 6, (1, 2, 3))
    assert compose(left, None, "side-by-side", 640) is left
    assert compose(None, left, "anaglyph", 640) is left
    assert compose(None, None, "side-by-side", 640) is None
    assert compose(None, left, "left", 640) is None


def test_eyes_of_different_sizes_are_cropped_to_the_common_part() -> None:
    out = compose(_solid(4, 6, (1, 1, 1)), _solid(5, 4, (2, 2, 2)), "side-by-side", 640)
    assert out is not None and out.shape == (4, 8, 3)


def test_wide_images_are_decimated_to_the_limit() -> None:
    left = right = np.zeros((480, 640, 3), dtype=np.uint8)
    out = compose(left, right, "side-by-side", 640)
    assert out is not None and out.shape == (240, 640, 3)
    out = compose(left, right, "side-by-side", 500)
    assert out is not None and out.shape[1] <= 500 and out.shape == (160, 427, 3)


def test_the_gate_passes_new_pairs_at_the_rate() -> None:
    gate = FrameGate(12.0)
    passed = 0
    # 30 fps camera, a 25 Hz GUI tick, 10 s of simulated time.
    for tick in range(250):
        now = tick / 25.0
        key = (int(now * 30), int(now * 30))
        passed += gate.due(now, key)
    assert 115 <= passed <= 125
    assert gate.passed == passed


def test_the_gate_never_sends_the_same_pair_twice_until_reset() -> None:
    gate = FrameGate(10.0)
    assert gate.due(0.0, (1, 1))
    assert not gate.due(1.0, (1, 1))
    gate.reset()
    assert gate.due(2.0, (1, 1))
    with pytest.raises(ValueError):
        FrameGate(0.0)
