"""Video that gives way first: the stereo stream's level, lowered from what its receivers
report of arrival and age, so a thin or long link carries force and commands before video.

Zenoh's congestion control is the first line (video is `DATA_LOW`, dropped on congestion:
keys.STEREO_*); this is the second. A receiver (the console, `telerobot bench link`) counts
the pairs it gets and their age and reports it on `vision/arrival` once a second
(`ArrivalMeter`, `VideoArrival`); the vision service's `VideoAdapter` reads the worst fresh
report and moves along a ladder of levels: JPEG quality first, then the image size, then
the rate (`ladder`). It goes one level down (two when far off: `FAR`) when the video
queues (its age p90 rises more than `queue_ms` above the lowest age seen, which is the
link's own delay: the difference cancels any offset between the two hosts' clocks) or when
under `MIN_ARRIVAL` of the pairs sent arrive, and one level up after `up_s` of good
reports. Each change is an event
(`video_level`) and shows in `vision/stats` (`data.level`, …) and the console's link panel.

With no fresh report (nobody reports: a plain subscriber, a recorder) the level holds.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass
from typing import Annotated, ClassVar

from services.bus.keys import Delivery, QoS, Topic
from services.bus.messages import Count, Message, Name, Range

AgeMs = Annotated[float, Range(0.0, 3_600_000.0)]
Fps = Annotated[float, Range(0.0, 1000.0)]


@dataclass(frozen=True, slots=True)
class VideoArrival(Message):
    """`vision/arrival` (extension, docs/protocol-extensions.md): what one receiver of the
    stereo stream got over its last `window_s`: `pairs` (left eyes received), `fps`, the
    age of a pair on arrival (`age_p50_ms`, `age_p90_ms`: arrival time − its `t_ns`, on the
    two hosts' clocks) and `lost` (pair numbers missing between the first and the last
    received: the link's drops and the pipeline's alike)."""

    name: ClassVar[str] = "VideoArrival"
    seq: Count
    t_ns: Count
    receiver: Name
    window_s: Annotated[float, Range(0.1, 60.0)]
    pairs: Count
    fps: Fps
    age_p50_ms: AgeMs
    age_p90_ms: AgeMs
    lost: Count


VIDEO_ARRIVAL = Topic(
    "vision/arrival", VideoArrival, QoS.STATE, latest_wins=True, delivery=Delivery.BEST_EFFORT
)
"""1 Hz from each receiver that reports; best-effort and INTERACTIVE_HIGH: a lost report is
replaced by the next a second later, and it rides the uncongested direction."""

WINDOW_S = 2.0
"""What a report covers."""
FRESH_S = 3.0
"""A report older than this counts for nothing."""
MIN_ARRIVAL = 0.8
"""Fewer than this share of the pairs sent arriving is a link that cannot carry the level."""
GOOD_ARRIVAL = 0.95
DOWN_HOLD_S = 1.0
"""After a change, the next step down waits this long. A report still covers pairs of the
level before (WINDOW_S), so going down may overshoot by a level or two: the safe way, since
the video is what gives way; going up waits `up_s` of good reports."""
FAR = 0.5
"""Under this share of the pairs arriving, or a queue of 4 × the budget, two levels at once:
on a link far too thin (2 Mbit/s for VGA stereo at 30 fps) one level a second is too slow."""
FLOOR_S = 60.0
"""The lowest age (the link's own delay) is the minimum of the p50s of this long."""


@dataclass(frozen=True, slots=True)
class Level:
    """One rung: JPEG `quality` (1…100), `scale` of each side (1, ½), and `stride` (every
    stride-th capture tick: the rate divided by it)."""

    quality: int
    scale: float
    stride: int

    def size(self, width: int, height: int) -> tuple[int, int]:
        return max(16, round(width * self.scale)), max(16, round(height * self.scale))


def ladder(jpeg_quality: int) -> tuple[Level, ...]:
    """The levels from the configured one down: quality (to 60, 40, 25, never above the
    configured), then half the size, then half and a quarter of the rate."""
    qualities = [jpeg_quality, *(q for q in (60, 40, 25) if q < jpeg_quality)]
    low = qualities[-1]
    return (
        *(Level(q, 1.0, 1) for q in qualities),
        Level(low, 0.5, 1),
        Level(low, 0.5, 2),
        Level(low, 0.5, 4),
    )


class ArrivalMeter:
    """A receiver's side: `on_pair(seq, t_ns, rx_ns)` per pair (one eye's frame), `report`
    once a second. Memory: the pairs of the last WINDOW_S (bounded by MAX_PAIRS)."""

    MAX_PAIRS = 4096

    def __init__(self, receiver: str, window_s: float = WINDOW_S) -> None:
        self.receiver = receiver
        self.window_s = window_s
        self._pairs: deque[tuple[int, int, int]] = deque(maxlen=self.MAX_PAIRS)
        self._seq = 0
        self._since_ns = 0
        """When the pairs began to arrive (after none for a window): a report of a stream
        that began within its window counts its rate over the time since then."""

    def on_pair(self, seq: int, t_ns: int, rx_ns: int) -> None:
        if not self._pairs or rx_ns - self._pairs[-1][0] > self.window_s * 1e9:
            self._since_ns = rx_ns
        self._pairs.append((rx_ns, seq, t_ns))

    def report(self, now_ns: int | None = None) -> VideoArrival | None:
        """The figures of the last window; None when no pair arrived in it."""
        now_ns = time.time_ns() if now_ns is None else now_ns
        start = now_ns - int(self.window_s * 1e9)
        while self._pairs and self._pairs[0][0] < start:
            self._pairs.popleft()
        pairs = list(self._pairs)
        if not pairs:
            return None
        ages = sorted(max(0.0, (rx - t) / 1e6) for rx, _, t in pairs)
        seqs = {s for _, s, _ in pairs}
        span = max(seqs) - min(seqs) + 1
        covered_s = min(self.window_s, max(0.5, (now_ns - self._since_ns) / 1e9))
        self._seq += 1
        return VideoArrival(
            seq=self._seq,
            t_ns=now_ns,
            receiver=self.receiver[:128],
            window_s=self.window_s,
            pairs=len(seqs),
            fps=min(1000.0, len(seqs) / covered_s),
            age_p50_ms=min(3_600_000.0, _pct(ages, 0.5)),
            age_p90_ms=min(3_600_000.0, _pct(ages, 0.9)),
            lost=span - len(seqs),
        )


def _pct(xs: list[float], q: float) -> float:
    return xs[min(len(xs) - 1, int(q * len(xs)))]


@dataclass(frozen=True, slots=True)
class Change:
    """A decision of the adapter: from level `old` to `new`, and why."""

    old: int
    new: int
    reason: str


class VideoAdapter:
    """The vision service's side (pure: the caller gives the time). `offer(report, rx_s)`
    stores a receiver's report; `update(now_s, sent_fps)` returns a Change or None."""

    def __init__(self, levels: tuple[Level, ...], queue_ms: float, up_s: float) -> None:
        if not levels:
            raise ValueError("no levels")
        self.levels = levels
        self.queue_ms = queue_ms
        self.up_s = up_s
        self.level = 0
        self._reports: dict[str, tuple[VideoArrival, float]] = {}
        self._floor: dict[str, deque[tuple[float, float]]] = {}
        self._changed_s = -math.inf
        self._good_since: float | None = None
        self.last: dict[str, float | str] = {}

    @property
    def current(self) -> Level:
        return self.levels[self.level]

    def offer(self, report: VideoArrival, rx_s: float) -> None:
        self._reports[report.receiver] = (report, rx_s)
        floor = self._floor.setdefault(report.receiver, deque(maxlen=256))
        floor.append((rx_s, report.age_p50_ms))

    def forget(self) -> None:
        """Nobody watches: the next viewer starts from the top level."""
        self._reports.clear()
        self._floor.clear()
        self.level, self._changed_s, self._good_since = 0, -math.inf, None

    def update(self, now_s: float, sent_fps: float) -> Change | None:
        fresh = [(r, rx) for r, rx in self._reports.values() if now_s - rx <= FRESH_S]
        if not fresh:
            self._good_since = None
            self.last = {"state": "no reports"}
            return None
        worst_queue, worst_arrival, who = 0.0, 1.0, ""
        for report, _ in fresh:
            floor = self._floor[report.receiver]
            while floor and now_s - floor[0][0] > FLOOR_S:
                floor.popleft()
            base = min(a for _, a in floor) if floor else report.age_p50_ms
            queue = max(0.0, report.age_p90_ms - base)
            arrival = min(1.0, report.fps / sent_fps) if sent_fps > 0.5 else 1.0
            if queue > worst_queue or arrival < worst_arrival:
                who = report.receiver
            worst_queue, worst_arrival = max(worst_queue, queue), min(worst_arrival, arrival)
        self.last = {"queue_ms": worst_queue, "arrival": worst_arrival, "receiver": who}
        bad = worst_queue > self.queue_ms or worst_arrival < MIN_ARRIVAL
        good = worst_queue < self.queue_ms / 3.0 and worst_arrival >= GOOD_ARRIVAL
        if bad:
            self._good_since = None
            if self.level + 1 < len(self.levels) and now_s - self._changed_s >= DOWN_HOLD_S:
                far = worst_arrival < FAR or worst_queue > 4.0 * self.queue_ms
                step = 2 if far else 1
                why = (
                    f"{who}: video queues {worst_queue:.0f} ms above the link's delay"
                    if worst_queue > self.queue_ms
                    else f"{who}: {100 * worst_arrival:.0f} % of the pairs sent arrive"
                )
                return self._move(min(len(self.levels) - 1, self.level + step), now_s, why)
            return None
        if not good:
            self._good_since = None
            return None
        if self._good_since is None:
            self._good_since = now_s
        if self.level > 0 and now_s - max(self._good_since, self._changed_s) >= self.up_s:
            self._good_since = now_s
            return self._move(self.level - 1, now_s, f"the link carried level {self.level}")
        return None

    def _move(self, new: int, now_s: float, reason: str) -> Change:
        change = Change(self.level, new, reason)
        self.level, self._changed_s = new, now_s
        return change
