"""The bench's figure: force latency over time, alone and with each stereo setting.

Drawn with OpenCV through `services.tools.record.plots` (no matplotlib): one panel of every
sample's one-way latency against time since its phase began, and one of the p99 per
`BIN_S` window, which shows the tail the cloud of samples hides. cv2 is imported only here.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from services.tools.record.plots import Series, panel, save_png, stack

PLOT_WIDTH_PX = 1000
PANEL_HEIGHT_PX = 340
BIN_S = 0.25

Trace = tuple[NDArray[np.float64], NDArray[np.float64]]
"""(time since the phase began (s), latency (ms)) per sample."""


def binned_p99(t_s: NDArray[np.float64], y: NDArray[np.float64], bin_s: float) -> Trace:
    """The 99th percentile of `y` in each `bin_s` window of `t_s` (bin centres, values);
    empty windows are left out."""
    if t_s.size == 0:
        return np.zeros(0), np.zeros(0)
    idx = np.floor(t_s / bin_s).astype(np.int64)
    centres, values = [], []
    for b in np.unique(idx):
        sel = y[idx == b]
        centres.append((b + 0.5) * bin_s)
        values.append(float(np.percentile(sel, 99.0)))
    return np.asarray(centres), np.asarray(values)


def force_latency_plot(traces: Mapping[str, Trace], path: str | Path) -> Path:
    """Write the PNG (PLOT_WIDTH_PX × 2·PANEL_HEIGHT_PX) for the named traces; the path."""
    raw = [Series.of(name, t, y, width_px=1) for name, (t, y) in traces.items()]
    binned = [
        Series.of(name, *binned_p99(np.asarray(t), np.asarray(y), BIN_S))
        for name, (t, y) in traces.items()
    ]
    top = panel(
        raw,
        "robot/force one-way latency at the master side (every sample)",
        "time since the phase began (s)",
        "latency (ms)",
        size=(PLOT_WIDTH_PX, PANEL_HEIGHT_PX),
    )
    bottom = panel(
        binned,
        f"p99 per {BIN_S * 1e3:.0f} ms window",
        "time since the phase began (s)",
        "p99 latency (ms)",
        size=(PLOT_WIDTH_PX, PANEL_HEIGHT_PX),
    )
    return save_png(path, stack([top, bottom]))
