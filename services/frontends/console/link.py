"""The console's "Link" panel and its report of the video it gets (issue 41).

`LinkMeter` is fed from Zenoh's threads (force samples, left-eye frames) and the poller
(the round trip of a call to the vision service); `view()` is what the panel shows: the
round trip, the share of force samples lost on the way (gaps in `seq`), and the video as it
arrives (pairs/s, age) with the level the vision service reports on `vision/stats`
(`data.level`, adapt.py). `report()` is the `vision/arrival` message the poller publishes
once a second while video is watched, from which the vision service adapts its level.

Pure: tested without a page (`link_html` escapes what came off the bus).
"""

from __future__ import annotations

import html
import statistics
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from services.bus.messages import VisionStats
from services.control.vision.adapt import ArrivalMeter, VideoArrival

LOSS_WINDOW_S = 2.0
RTT_SAMPLES = 8
"""The round trip shown is the median of the last calls (one per poll)."""


@dataclass(frozen=True, slots=True)
class LinkView:
    """What the link panel shows (None: not measured yet)."""

    rtt_ms: float | None
    force_loss: float | None
    """The share of force samples missing in the last LOSS_WINDOW_S (0 … 1)."""
    video_fps: float | None
    video_age_ms: float | None
    level: int | None
    levels: int | None
    quality: int | None
    size: tuple[int, int] | None


class LinkMeter:
    """Thread-safe: callbacks add, the GUI and the poller read."""

    def __init__(self, receiver: str) -> None:
        self._lock = threading.Lock()
        self._force: deque[tuple[float, int]] = deque(maxlen=8192)
        self._rtt: deque[float] = deque(maxlen=RTT_SAMPLES)
        self.arrival = ArrivalMeter(receiver)
        self._last_report: VideoArrival | None = None

    def on_force(self, seq: int, rx_s: float) -> None:
        with self._lock:
            self._force.append((rx_s, seq))

    def on_frame(self, seq: int, t_ns: int, rx_ns: int) -> None:
        with self._lock:
            self.arrival.on_pair(seq, t_ns, rx_ns)

    def on_rtt(self, rtt_ms: float) -> None:
        with self._lock:
            self._rtt.append(rtt_ms)

    def report(self, now_ns: int | None = None) -> VideoArrival | None:
        """The `vision/arrival` report of the last window (None: no pair in it)."""
        with self._lock:
            r = self.arrival.report(now_ns)
            self._last_report = r
            return r

    def force_loss(self, now_s: float) -> float | None:
        with self._lock:
            while self._force and self._force[0][0] < now_s - LOSS_WINDOW_S:
                self._force.popleft()
            seqs = {s for _, s in self._force}
        if len(seqs) < 2:
            return None
        span = max(seqs) - min(seqs) + 1
        return 1.0 - len(seqs) / span

    def view(self, stats: VisionStats | None, now_s: float | None = None) -> LinkView:
        now_s = time.monotonic() if now_s is None else now_s
        with self._lock:
            rtt = statistics.median(self._rtt) if self._rtt else None
            last = self._last_report
        data: dict[str, Any] = (stats.data or {}) if stats is not None else {}
        level = data.get("level")
        levels = data.get("levels")
        quality = data.get("quality")
        return LinkView(
            rtt_ms=rtt,
            force_loss=self.force_loss(now_s),
            video_fps=last.fps if last is not None else None,
            video_age_ms=last.age_p50_ms if last is not None else None,
            level=level if isinstance(level, int) else None,
            levels=levels if isinstance(levels, int) else None,
            quality=quality if isinstance(quality, int) else None,
            size=(stats.width, stats.height) if stats is not None else None,
        )


def _cell(value: str | None) -> str:
    return html.escape(value) if value is not None else "–"


def link_html(v: LinkView) -> str:
    """The Link panel: rows with stable ids (`tr-link-rtt`, `tr-link-loss`,
    `tr-link-video`, `tr-link-level`; `data-level` on the last)."""
    rows = [
        ("round trip (ms)", "tr-link-rtt", None if v.rtt_ms is None else f"{v.rtt_ms:.0f}"),
        (
            "force lost",
            "tr-link-loss",
            None if v.force_loss is None else f"{100.0 * v.force_loss:.1f} %",
        ),
        (
            "video arriving",
            "tr-link-video",
            None
            if v.video_fps is None
            else f"{v.video_fps:.1f} pairs/s, {v.video_age_ms or 0.0:.0f} ms old",
        ),
    ]
    level = None
    if v.level is not None:
        of = f"/{v.levels - 1}" if v.levels else ""
        size = f", {v.size[0]}x{v.size[1]}" if v.size is not None else ""
        q = f", JPEG {v.quality}" if v.quality is not None else ""
        level = f"{v.level}{of}{q}{size}"
    rows.append(("video level", "tr-link-level", level))
    cells = "".join(
        f'<tr><td>{html.escape(name)}</td><td id="{rid}">{_cell(val)}</td></tr>'
        for name, rid, val in rows
    )
    data_level = "" if v.level is None else str(v.level)
    return f'<table id="tr-link" data-level="{data_level}" style="font-size:0.8em">{cells}</table>'
