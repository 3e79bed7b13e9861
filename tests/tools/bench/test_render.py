"""The vision rig's render bench runs and reports every figure it names."""

from __future__ import annotations

from services.control.vision.config import VisionConfig
from services.tools.bench.render import bench_render


def test_bench_render_reports_positive_times_for_every_pair() -> None:
    out = bench_render(3, VisionConfig(width=160, height=120))
    assert out["pairs"] == 3 and (out["width"], out["height"]) == (160, 120)
    for key in ("render_ms_p50", "encode_ms_p50", "jpeg_bytes_per_pair", "pairs_per_s_one_core"):
        assert out[key] > 0, key
    assert out["render_ms_max"] >= out["render_ms_p50"]
