"""`bench_render`: how long the simulated rig takes to render and encode a pair.

Run as `python -m services.tools.bench.render [N]`; prints the result as JSON. Not a phase of
`telerobot bench`: the vision service's own figure (docs/vision.md).
"""

from __future__ import annotations

import json
import math
import sys
import time
from typing import Any

import numpy as np

from services.control.arm.model import load_model
from services.control.vision.config import VisionConfig
from services.control.vision.pipeline import encode_image
from services.control.vision.sim_camera import SimStereoCamera


def bench_render(n: int = 100, config: VisionConfig | None = None) -> dict[str, Any]:
    """Render and JPEG-encode `n` pairs of the default workcell with the default arm moving.

    Returns ms per pair (p50, mean, max) for rendering both eyes and for encoding both,
    the mean JPEG bytes per pair, the time to open the camera (ray-casting the static
    scene) and the pair rate one core could sustain.
    """
    cfg = config if config is not None else VisionConfig()
    model = load_model()  # the default model, at home
    kin = model.kinematics()
    links0 = kin.link_origins(model.home)
    tool = kin.fk_tool(model.home)
    cam = SimStereoCamera(cfg)
    t0 = time.perf_counter()
    cam.open()
    open_s = time.perf_counter() - t0
    render_ms: list[float] = []
    encode_ms: list[float] = []
    sizes: list[int] = []
    try:
        for i in range(n):
            # Sweep the wrist and tool so the arm's screen area changes from frame to frame.
            off = np.array([0.0, 0.15 * math.sin(i / 7.0), 0.08 * math.cos(i / 5.0)])
            links = links0.copy()
            links[-3:] += off
            grip = 0.5 + 0.5 * math.sin(i / 3.0)
            cam.set_robot(links, tool.translation + off, tool.rotation, grip)
            t0 = time.perf_counter()
            pair = cam.grab()
            t1 = time.perf_counter()
            data = [encode_image(img, "jpeg", cfg.jpeg_quality) for img in (pair.left, pair.right)]
            t2 = time.perf_counter()
            render_ms.append((t1 - t0) * 1e3)
            encode_ms.append((t2 - t1) * 1e3)
            sizes.append(sum(len(d) for d in data))
    finally:
        cam.close()
    r50, e50 = float(np.median(render_ms)), float(np.median(encode_ms))
    return {
        "pairs": n,
        "width": cfg.width,
        "height": cfg.height,
        "open_s": open_s,
        "render_ms_p50": r50,
        "render_ms_mean": float(np.mean(render_ms)),
        "render_ms_max": float(np.max(render_ms)),
        "encode_ms_p50": e50,
        "encode_ms_mean": float(np.mean(encode_ms)),
        "encode_ms_max": float(np.max(encode_ms)),
        "jpeg_bytes_per_pair": float(np.mean(sizes)),
        "pairs_per_s_one_core": 1e3 / (r50 + e50),
    }


if __name__ == "__main__":
    print(json.dumps(bench_render(int(sys.argv[1]) if len(sys.argv) > 1 else 100), indent=2))
