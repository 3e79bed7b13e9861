"""The force-latency plot: a PNG of the documented size, drawn from the traces."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.tools.bench.plot import (
    BIN_S,
    PANEL_HEIGHT_PX,
    PLOT_WIDTH_PX,
    binned_p99,
    force_latency_plot,
)


def test_binned_p99() -> None:
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.6, 0.7])
    y = np.array([1.0, 1.0, 1.0, 5.0, 2.0, 2.0])
    centres, values = binned_p99(t, y, 0.25)
    # bins [0, .25): 1,1,1  [.25, .5): 5  [.5, .75): 2,2
    assert centres.tolist() == pytest.approx([0.125, 0.375, 0.625])
    assert values.tolist() == pytest.approx([1.0, 5.0, 2.0])
    empty = binned_p99(np.zeros(0), np.zeros(0), BIN_S)
    assert empty[0].size == 0 and empty[1].size == 0


def test_force_latency_plot_writes_a_png_of_the_right_size(tmp_path: Path) -> None:
    import cv2

    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 5.0, 5000)
    traces = {
        "force alone": (t, 0.2 + rng.exponential(0.05, t.size)),
        "with stereo 360x288@17": (t, 0.4 + rng.exponential(0.2, t.size)),
        "with stereo 640x480@30": (t[:10], np.full(10, 1.0)),
    }
    path = force_latency_plot(traces, tmp_path / "sub" / "plot.png")
    assert path.is_file()
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = cv2.imread(str(path))
    assert img is not None
    assert img.shape == (2 * PANEL_HEIGHT_PX, PLOT_WIDTH_PX, 3)
    # something was drawn besides the white background and the black axes
    colours = {tuple(int(c) for c in px) for px in img.reshape(-1, 3)[::7]}
    assert len(colours) > 20


def test_plot_of_no_data_still_writes(tmp_path: Path) -> None:
    path = force_latency_plot({}, tmp_path / "empty.png")
    assert path.is_file()
