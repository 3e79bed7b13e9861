"""A fixed-rate loop that reports when it runs late (after loop-rate-limiters' RateLimiter)."""

from __future__ import annotations

import time
from collections.abc import Callable


class RateLoop:
    """Sleep to absolute deadlines at `rate_hz`; count and report late ticks.

    `sleep()` waits until the next tick. A tick later than `late_tolerance` periods counts as
    late; `on_late(late_s, n_late)` is then called (at most once per `report_interval_s`),
    and the schedule is re-anchored instead of bursting to catch up.
    """

    def __init__(
        self,
        rate_hz: float,
        on_late: Callable[[float, int], None] | None = None,
        late_tolerance: float = 1.0,
        report_interval_s: float = 1.0,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError("rate_hz must be > 0")
        self.period_s = 1.0 / rate_hz
        self.on_late = on_late
        self.late_tolerance = late_tolerance
        self.report_interval_s = report_interval_s
        self.ticks = 0
        self.late = 0
        self._next = time.perf_counter() + self.period_s
        self._last_report = -1e9

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.period_s

    def set_rate(self, rate_hz: float) -> None:
        if not rate_hz > 0:
            raise ValueError("rate_hz must be > 0")
        self.period_s = 1.0 / rate_hz
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
                self._next = now + self.period_s
                if self.on_late is not None and now - self._last_report >= self.report_interval_s:
                    self._last_report = now
                    self.on_late(lateness, self.late)
            else:
                self._next += self.period_s
        self.ticks += 1
        return lateness
