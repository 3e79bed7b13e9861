"""A fixed-rate loop that reports when it runs late (after loop-rate-limiters' RateLimiter)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

#: a late loop is summarized at most this often (counts and worst), never once per tick:
#: on a loaded machine a 100 Hz loop can be late hundreds of times a minute, and a log
#: made of "late" lines hides the messages that matter (issue 23, item 7).
REPORT_INTERVAL_S = 10.0

log = logging.getLogger("telerobot.rate")


class RateLoop:
    """Sleep to absolute deadlines at `rate_hz`; count and summarize late ticks.

    `sleep()` waits until the next tick. A tick later than `late_tolerance` periods counts
    as late and the schedule is re-anchored instead of bursting to catch up. Lateness is
    summarized, at most once per `report_interval_s`: the first late tick of a quiet spell
    is reported at once, later ones are gathered and reported together (count and worst)
    when the interval has passed. The report goes to `on_late(worst_s, n_late)` (the
    worst lateness since the previous report, the late ticks since start) when given,
    else, for a loop with a `name`, to the log as one warning; an unnamed loop without
    `on_late` only counts. `stats()` gives the totals for a service's `status`.
    """

    def __init__(
        self,
        rate_hz: float,
        on_late: Callable[[float, int], None] | None = None,
        late_tolerance: float = 1.0,
        report_interval_s: float = REPORT_INTERVAL_S,
        name: str = "",
    ) -> None:
        if not rate_hz > 0:
            raise ValueError("rate_hz must be > 0")
        if not report_interval_s >= 0:
            raise ValueError("report_interval_s must be ≥ 0")
        self.period_s = 1.0 / rate_hz
        self.on_late = on_late
        self.late_tolerance = late_tolerance
        self.report_interval_s = report_interval_s
        self.name = name
        self.ticks = 0
        self.late = 0
        self.worst_late_s = 0.0
        self.reports = 0
        self._next = time.perf_counter() + self.period_s
        self._last_report = -1e9
        self._window_late = 0
        self._window_worst_s = 0.0

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.period_s

    def set_rate(self, rate_hz: float) -> None:
        if not rate_hz > 0:
            raise ValueError("rate_hz must be > 0")
        self.period_s = 1.0 / rate_hz
        self.reanchor()

    def reanchor(self) -> None:
        """The next tick one period from now (a loop that paused on purpose: not late)."""
        self._next = time.perf_counter() + self.period_s

    def sleep(self) -> float:
        """Wait for the next tick; returns the seconds it was late (0.0 when on time)."""
        now = time.perf_counter()
        wait = self._next - now
        if wait > 0:
            time.sleep(wait)
            lateness = 0.0
            self._next += self.period_s
        else:
            lateness = -wait
            if lateness > self.late_tolerance * self.period_s:
                self.late += 1
                self.worst_late_s = max(self.worst_late_s, lateness)
                self._window_late += 1
                self._window_worst_s = max(self._window_worst_s, lateness)
                self._next = now + self.period_s
            else:
                self._next += self.period_s
        if self._window_late and now - self._last_report >= self.report_interval_s:
            self._report(now)
        self.ticks += 1
        return lateness

    def _report(self, now: float) -> None:
        worst, n = self._window_worst_s, self._window_late
        self._window_late, self._window_worst_s = 0, 0.0
        first = self._last_report < 0
        self._last_report = now
        self.reports += 1
        if self.on_late is not None:
            self.on_late(worst, self.late)
            return
        if not self.name:
            return
        since = "" if first else f" in the last {self.report_interval_s:.0f} s"
        log.warning(
            "%s loop late: %d tick%s%s, worst %.1f ms (%d of %d ticks late since start)",
            self.name,
            n,
            "" if n == 1 else "s",
            since,
            worst * 1e3,
            self.late,
            self.ticks + 1,
        )

    def stats(self) -> dict[str, Any]:
        """Totals since start, for a service's `status`: ticks, late ticks, worst lateness."""
        return {
            "rate_hz": self.rate_hz,
            "ticks": self.ticks,
            "late": self.late,
            "worst_late_ms": round(self.worst_late_s * 1e3, 3),
        }
