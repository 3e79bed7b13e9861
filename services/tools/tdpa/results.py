"""What both TDPA benches give out, one way for both: a run's measures into the JSON
document under their keys, and one delay's plot, TDPA off and on.

`sim_bench` (the simulated loop) and `link_bench` (the real services over the emulated
link) write the same keys, `passivity_<delay_ms>_<on|off>_<measure>`, and draw the same
off/on panel.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any


def put_measures(
    doc: dict[str, Any],
    delay: int,
    on: bool,
    parts: Sequence[tuple[str, Mapping[str, float | bool]]],
) -> None:
    """Each measure of a run into `doc` as `passivity_<delay>_<on|off>_<part><name>`: a
    verdict as it is, a figure rounded to 1e-6, one not measured (NaN) as null."""
    for part, measures in parts:
        for name, value in measures.items():
            key = f"passivity_{delay}_{'on' if on else 'off'}_{part}{name}"
            if isinstance(value, bool):
                doc[key] = value
            else:
                doc[key] = None if math.isnan(value) else round(float(value), 6)


def off_on_plot(
    curves: Mapping[bool, tuple[Sequence[float], Sequence[float]]],
    title: str,
    x_label: str,
    clip_n: float,
    path: Path,
    y_label: str = "force (N)",
) -> Path:
    """One PNG: force (N, clipped to 0 … clip_n; or what `y_label` says) against time, TDPA
    off and on (OpenCV); `curves[on]` = (t, f)."""
    import numpy as np

    from services.tools.record.plots import Series, panel, save_png

    series = [
        Series.of(
            f"TDPA {'on' if on else 'off'}",
            np.asarray(curves[on][0], dtype=float),
            np.clip(np.asarray(curves[on][1], dtype=float), 0.0, clip_n),
        )
        for on in (False, True)
    ]
    return save_png(path, panel(series, title, x_label, y_label, size=(900, 320)))
