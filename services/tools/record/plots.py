"""Line plots drawn with OpenCV: axes, 1-2-5 ticks, grid, labels, legend; PNG out.

Just enough to read a session at a glance without matplotlib. cv2 is imported when a plot
is drawn, so loading the report module stays light.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

Image = NDArray[np.uint8]
BGR = tuple[int, int, int]

WHITE: BGR = (255, 255, 255)
BLACK: BGR = (0, 0, 0)
GRID: BGR = (225, 225, 225)
#: a colour-blind-friendly cycle (Okabe–Ito), BGR
PALETTE: tuple[BGR, ...] = (
    (178, 114, 0),  # blue
    (0, 94, 213),  # vermillion
    (115, 158, 0),  # bluish green
    (167, 121, 204),  # reddish purple
    (0, 159, 230),  # orange
    (233, 180, 86),  # sky blue
    (66, 228, 240),  # yellow
    (0, 0, 0),
)
FONT_SCALE = 0.45
DENSE_POINTS = 600
MARGIN_LEFT, MARGIN_RIGHT, MARGIN_TOP, MARGIN_BOTTOM = 78, 18, 34, 52


@dataclass(frozen=True, slots=True)
class Series:
    """One line: points (x[i], y[i]); `color` None takes the next palette colour; `width_px`
    0 picks 2 px, or 1 px for dense series (noise stays readable)."""

    label: str
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    color: BGR | None = None
    width_px: int = 0

    @staticmethod
    def of(
        label: str, x: ArrayLike, y: ArrayLike, color: BGR | None = None, width_px: int = 0
    ) -> Series:
        xs, ys = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
        if xs.shape != ys.shape:
            raise ValueError(f"{label}: x and y differ in length ({xs.size} vs {ys.size})")
        return Series(label, xs, ys, color, width_px)


def nice_ticks(lo: float, hi: float, max_ticks: int = 7) -> list[float]:
    """Tick values on a 1-2-5 step covering [lo, hi], at most about `max_ticks` of them."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    raw = (hi - lo) / max(1, max_ticks - 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    n = math.floor((hi - first) / step + 1e-9) + 1
    return [round(first + i * step, 12) for i in range(max(n, 0))]


def axis_range(values: Sequence[NDArray[np.float64]], min_span: float = 0.0) -> tuple[float, float]:
    """The axis limits for `values` (finite ones): their range padded by 4 %, widened about
    its centre to at least `min_span`, so that noise far below it is not blown up into
    what looks like motion."""
    finite = [v[np.isfinite(v)] for v in values]
    finite = [v for v in finite if v.size]
    if not finite:
        return 0.0, max(1.0, min_span)
    lo = float(min(v.min() for v in finite))
    hi = float(max(v.max() for v in finite))
    if hi - lo < 1e-12:
        pad = max(abs(lo) * 0.1, 1e-3, 0.5 * min_span)
        return lo - pad, hi + pad
    pad = (hi - lo) * 0.04
    lo, hi = lo - pad, hi + pad
    if hi - lo < min_span:
        c = 0.5 * (lo + hi)
        lo, hi = c - 0.5 * min_span, c + 0.5 * min_span
    return lo, hi


def break_gaps(
    x: ArrayLike, ys: Sequence[ArrayLike], max_step: float
) -> tuple[NDArray[np.float64], list[NDArray[np.float64]]]:
    """`x` and each of `ys` with a NaN point inserted wherever x jumps by more than
    `max_step`, so a line drawn through them stops at the gap instead of bridging it."""
    xs = np.asarray(x, dtype=float).ravel()
    cols = [np.asarray(y, dtype=float).ravel() for y in ys]
    if xs.size < 2 or not math.isfinite(max_step):
        return xs, cols
    at = np.nonzero(np.diff(xs) > max_step)[0] + 1
    gap_x = 0.5 * (xs[at - 1] + xs[at])
    return np.insert(xs, at, gap_x), [np.insert(c, at, np.nan) for c in cols]


def runs(ok: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """The [start, end) index ranges where `ok` holds, in order."""
    edges = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    return list(
        zip(np.nonzero(edges == 1)[0].tolist(), np.nonzero(edges == -1)[0].tolist(), strict=True)
    )


def _label(v: float, step: float) -> str:
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
    return f"{v:.{min(decimals, 6)}f}"


def panel(
    series: Sequence[Series],
    title: str,
    xlabel: str,
    ylabel: str,
    size: tuple[int, int] = (900, 360),
    equal_aspect: bool = False,
    min_span: tuple[float, float] = (0.0, 0.0),
) -> Image:
    """One plot as a BGR image of `size` (width, height) px. An axis spans at least its
    `min_span` (x, y; data units). A non-finite point breaks its line there."""
    import cv2

    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    x0, x1 = MARGIN_LEFT, w - MARGIN_RIGHT
    y0, y1 = MARGIN_TOP, h - MARGIN_BOTTOM
    font = cv2.FONT_HERSHEY_SIMPLEX
    xlo, xhi = axis_range([s.x for s in series], min_span[0])
    ylo, yhi = axis_range([s.y for s in series], min_span[1])
    if equal_aspect:
        # Same metres per pixel on both axes, so a circle looks like one.
        scale = max((xhi - xlo) / (x1 - x0), (yhi - ylo) / (y1 - y0))
        xc, yc = (xlo + xhi) / 2, (ylo + yhi) / 2
        xlo, xhi = xc - scale * (x1 - x0) / 2, xc + scale * (x1 - x0) / 2
        ylo, yhi = yc - scale * (y1 - y0) / 2, yc + scale * (y1 - y0) / 2

    def px(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.int32]:
        u = x0 + (x - xlo) / (xhi - xlo) * (x1 - x0)
        v = y1 - (y - ylo) / (yhi - ylo) * (y1 - y0)
        return np.stack([u, v], axis=-1).round().astype(np.int32)

    xt, yt = nice_ticks(xlo, xhi), nice_ticks(ylo, yhi)
    xstep = xt[1] - xt[0] if len(xt) > 1 else 1.0
    ystep = yt[1] - yt[0] if len(yt) > 1 else 1.0
    for t in xt:
        u = round(x0 + (t - xlo) / (xhi - xlo) * (x1 - x0))
        cv2.line(img, (u, y0), (u, y1), GRID, 1)
        cv2.line(img, (u, y1), (u, y1 + 5), BLACK, 1)
        text = _label(t, xstep)
        (tw, th), _ = cv2.getTextSize(text, font, FONT_SCALE, 1)
        cv2.putText(img, text, (u - tw // 2, y1 + 8 + th), font, FONT_SCALE, BLACK, 1, cv2.LINE_AA)
    for t in yt:
        v = round(y1 - (t - ylo) / (yhi - ylo) * (y1 - y0))
        cv2.line(img, (x0, v), (x1, v), GRID, 1)
        cv2.line(img, (x0 - 5, v), (x0, v), BLACK, 1)
        text = _label(t, ystep)
        (tw, th), _ = cv2.getTextSize(text, font, FONT_SCALE, 1)
        cv2.putText(img, text, (x0 - 8 - tw, v + th // 2), font, FONT_SCALE, BLACK, 1, cv2.LINE_AA)
    cv2.rectangle(img, (x0, y0), (x1, y1), BLACK, 1)

    plotted = 0
    for i, s in enumerate(series):
        color = s.color or PALETTE[i % len(PALETTE)]
        ok = np.isfinite(s.x) & np.isfinite(s.y)
        if ok.sum() == 0:
            continue
        sub = img[y0 : y1 + 1, x0 : x1 + 1]
        width = s.width_px or (1 if int(ok.sum()) > DENSE_POINTS else 2)
        for a, b in runs(ok):
            pts = px(s.x[a:b], s.y[a:b])
            shifted = (pts - np.array([x0, y0], np.int32)).reshape(-1, 1, 2)
            if len(pts) == 1:
                cv2.circle(sub, tuple(int(c) for c in shifted[0, 0]), 3, color, -1, cv2.LINE_AA)
            else:
                cv2.polylines(sub, [shifted], False, color, width, cv2.LINE_AA)
        plotted += 1
    if plotted == 0:
        cv2.putText(
            img, "no data", ((x0 + x1) // 2 - 30, (y0 + y1) // 2), font, 0.6, BLACK, 1, cv2.LINE_AA
        )

    (tw, th), _ = cv2.getTextSize(title, font, 0.55, 1)
    cv2.putText(img, title, ((w - tw) // 2, y0 - 12), font, 0.55, BLACK, 1, cv2.LINE_AA)
    (tw, th), _ = cv2.getTextSize(xlabel, font, FONT_SCALE, 1)
    cv2.putText(img, xlabel, ((x0 + x1 - tw) // 2, h - 10), font, FONT_SCALE, BLACK, 1, cv2.LINE_AA)
    _vertical_text(img, ylabel, 14, (y0 + y1) // 2)
    _legend(img, series, x1 - 8, y0 + 8)
    return img


def _vertical_text(img: Image, text: str, x: int, yc: int) -> None:
    """`text` rotated 90° counter-clockwise, its baseline at column `x`, centred on `yc`."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    (tw, th), base = cv2.getTextSize(text, font, FONT_SCALE, 1)
    tile = np.full((th + base + 2, tw + 2, 3), 255, np.uint8)
    cv2.putText(tile, text, (1, th + 1), font, FONT_SCALE, BLACK, 1, cv2.LINE_AA)
    rot = cv2.rotate(tile, cv2.ROTATE_90_COUNTERCLOCKWISE)
    rh, rw = rot.shape[:2]
    top = max(0, yc - rh // 2)
    left = max(0, x - rw // 2)
    rh, rw = min(rh, img.shape[0] - top), min(rw, img.shape[1] - left)
    img[top : top + rh, left : left + rw] = np.minimum(
        img[top : top + rh, left : left + rw], rot[:rh, :rw]
    )


def _legend(img: Image, series: Sequence[Series], right: int, top: int) -> None:
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    labels = [(s.label, s.color or PALETTE[i % len(PALETTE)]) for i, s in enumerate(series)]
    labels = [(t, c) for t, c in labels if t]
    if not labels:
        return
    width = max(cv2.getTextSize(t, font, FONT_SCALE, 1)[0][0] for t, _ in labels) + 40
    row = 18
    left = right - width
    cv2.rectangle(img, (left, top), (right, top + row * len(labels) + 6), WHITE, -1)
    cv2.rectangle(img, (left, top), (right, top + row * len(labels) + 6), (160, 160, 160), 1)
    for i, (text, color) in enumerate(labels):
        y = top + 14 + i * row
        cv2.line(img, (left + 6, y - 4), (left + 28, y - 4), color, 2, cv2.LINE_AA)
        cv2.putText(img, text, (left + 34, y), font, FONT_SCALE, BLACK, 1, cv2.LINE_AA)


def stack(images: Sequence[Image], horizontal: bool = False) -> Image:
    """Panels side by side (`horizontal`) or one above the other, padded to a common size."""
    if horizontal:
        h = max(i.shape[0] for i in images)
        return np.hstack([_pad(i, h, i.shape[1]) for i in images])
    w = max(i.shape[1] for i in images)
    return np.vstack([_pad(i, i.shape[0], w) for i in images])


def _pad(img: Image, h: int, w: int) -> Image:
    out = np.full((h, w, 3), 255, np.uint8)
    out[: img.shape[0], : img.shape[1]] = img
    return out


def save_png(path: str | Path, img: Any) -> Path:
    """Write `img` as PNG (creating the folder); the path."""
    import cv2

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(p), img):
        raise OSError(f"could not write {p}")
    return p
