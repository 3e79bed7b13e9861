"""The pipeline's output against the wire contract's codec (PROTOCOL.md §3, extensions)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from services.bus import codec
from services.bus.messages import StereoFrame, VisionStats
from services.control.vision.config import VisionConfig
from services.control.vision.pipeline import StereoPipeline
from tests.conftest import wait_until

from .fakes import FakeCamera, Recorder


def test_frames_and_stats_pass_the_codec() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0)
    rec = Recorder()
    with StereoPipeline(FakeCamera(), cfg, rec.publish, rec.emit) as pipe:
        assert wait_until(lambda: len(rec.pairs) >= 3)
        stats: dict[str, Any] = pipe.stats_fields()
    left, right = rec.pairs[-1]
    for fields in (left, right):
        frame = codec.decode(StereoFrame, codec.encode(codec.from_fields(StereoFrame, fields)))
        assert frame.seq == left["seq"] and frame.t_ns == left["t_ns"]
        assert frame.eye == fields["eye"] and frame.baseline == 0.065
        img = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape == (16, 16, 3)
    msg = codec.from_fields(VisionStats, {"seq": 1, "t_ns": 1, **stats})
    back = codec.decode(VisionStats, codec.encode(msg))
    assert back.width == 16 and back.encoding == "jpeg" and back.dropped >= 0
    assert back.data is not None and back.data["published"] >= 3
