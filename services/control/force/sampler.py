"""The sensing thread: read the sensor every TimerValue, hand samples off without blocking.

The paper's force sensing component (§2.1.3) is a thread of its own, created with *normal*
priority and idle until sensing is triggered; its period (TimerValue) and priority
(SensorThreadPriority) can be changed while it runs. Here:

- the sampling thread sleeps to absolute deadlines (`MonotonicClock`), so the period does
  not drift; it sleeps until the deadline, and spins the last `spin_us` only where a
  real-time policy (SCHED_FIFO/RR) was asked for and granted; a tick that ends after the
  next deadline but before the one after it (a short stall: a late wake-up, a preempted
  put) is followed at once by the missed deadline's tick (`caught_up`; once in a row, so
  an overloaded loop still sleeps), and a tick that ends later counts the deadlines it
  missed as overruns and skips them rather than bursting to catch up;
- `handoff="inline"` (the force service's): `publish` runs on the sampling thread, right
  after the reading (a Zenoh put of pre-encoded bytes, ~10 µs): no hand-off, no thread
  wake-up per sample; a publish that blocks shows as overruns. `handoff="queue"`: each
  sample goes into a bounded deque that a publisher thread drains, so a slow or blocked
  `publish` never delays sampling; when the deque is full the oldest sample is dropped and
  counted (force feedback wants the newest);
- events (stale sensor, recovery, errors) always go through the publisher thread, so the
  sampling thread never blocks on them;
- the achieved rate is measured from the timestamps of real samples over a sliding window.
"""

from __future__ import annotations

import ctypes
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, Literal, Protocol, TypeVar

from services.bus.bounds import short
from services.bus.errors import TelerobotError
from services.control.force.events import EventSink, EventThrottle, ignore_event
from services.control.force.priority import (
    PRIORITY_LEVELS,
    PriorityLevel,
    PriorityReport,
    apply_thread_priority,
)

S = TypeVar("S")
Handoff = Literal["inline", "queue"]
HANDOFFS: tuple[Handoff, ...] = ("inline", "queue")

PERIOD_MIN_MS = 0.2
PERIOD_MAX_MS = 1000.0
STOP_TIMEOUT_S = 2.0


class SamplerClock(Protocol):
    """Time for the sampling loop: a monotonic clock and a sleep to an absolute deadline."""

    def now_ns(self) -> int:
        """Monotonic time (ns)."""
        ...

    def sleep_until(self, deadline_ns: int, interrupted: Callable[[], bool]) -> None:
        """Return at `deadline_ns` (monotonic ns), or earlier once `interrupted()` is true."""
        ...


class MonotonicClock:
    """perf_counter_ns (CLOCK_MONOTONIC); sleeps to the deadline, spins only under RT.

    `time.sleep` wakes some 50–100 µs late under SCHED_OTHER (timer slack, wake-up latency);
    that lateness is measured (`late_max_us`) and costs nothing. A final spin of `spin_us`
    with `sleep(0)` would cut it, at the price of a busy core (~10 % at 1 kHz): it is used
    only while `realtime` is set, which the sampler does when a real-time policy was asked
    for and granted (`highest` → SCHED_FIFO), where the spin also cannot starve the
    thread's own wake-up. Sleeps are cut into `max_chunk_ms` pieces so a stop or a period
    change is seen quickly even at long periods.
    """

    def __init__(self, spin_us: float = 100.0, max_chunk_ms: float = 20.0) -> None:
        self._spin_ns = int(spin_us * 1_000)
        self._chunk_ns = int(max_chunk_ms * 1_000_000)
        self.realtime = False

    def now_ns(self) -> int:
        return time.perf_counter_ns()

    def sleep_until(self, deadline_ns: int, interrupted: Callable[[], bool]) -> None:
        spin_ns = self._spin_ns if self.realtime else 0
        while True:
            sleep_ns = deadline_ns - spin_ns - time.perf_counter_ns()
            if sleep_ns <= 0:
                break
            if sleep_ns <= self._chunk_ns:  # the last piece: no second look at the clock
                time.sleep(sleep_ns / 1e9)
                if not spin_ns:
                    return
                break
            time.sleep(self._chunk_ns / 1e9)
            if interrupted():
                return
        while time.perf_counter_ns() < deadline_ns:
            time.sleep(0)


TIMER_SLACK_NS = 1_000
"""The sampling thread's timer slack (Linux; the default is 50 µs): its sleeps end at the
deadline instead of up to 50 µs after it, at no CPU cost."""


def _tighten_timer_slack() -> None:
    """prctl(PR_SET_TIMERSLACK) for the calling thread; silently nothing elsewhere."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(29, ctypes.c_ulong(TIMER_SLACK_NS), 0, 0, 0)  # PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        return


@dataclass(frozen=True, slots=True)
class SamplerStats:
    """A snapshot of the sampler. Counts are since construction; `rate_hz` is measured."""

    running: bool
    period_ms: float
    priority: PriorityReport
    rate_hz: float
    samples: int
    ticks: int
    empty: int
    overruns: int
    caught_up: int
    drops: int
    published: int
    publish_errors: int
    read_errors: int
    event_drops: int
    stale: bool
    late_max_us: float
    last_error: str

    def as_dict(self) -> dict[str, Any]:
        return {
            "running": self.running,
            "period_ms": self.period_ms,
            "priority": self.priority.requested,
            "priority_applied": self.priority.as_dict(),
            "rate_hz": self.rate_hz,
            "samples": self.samples,
            "ticks": self.ticks,
            "empty": self.empty,
            "overruns": self.overruns,
            "caught_up": self.caught_up,
            "drops": self.drops,
            "published": self.published,
            "publish_errors": self.publish_errors,
            "read_errors": self.read_errors,
            "event_drops": self.event_drops,
            "stale": self.stale,
            "late_max_us": self.late_max_us,
            "last_error": self.last_error,
        }


def check_period_ms(period_ms: float) -> float:
    """`period_ms` as a float within [PERIOD_MIN_MS, PERIOD_MAX_MS], or ValueError."""
    if isinstance(period_ms, bool) or not isinstance(period_ms, int | float):
        raise ValueError(f"period_ms: expected a number, got {period_ms!r}")
    p = float(period_ms)
    if not PERIOD_MIN_MS <= p <= PERIOD_MAX_MS:  # also refuses NaN
        raise ValueError(f"period_ms: must be within {PERIOD_MIN_MS}…{PERIOD_MAX_MS} ms, got {p}")
    return p


class Sampler(Generic[S]):
    """Call `acquire()` every `period_ms` on a dedicated thread; `publish` each sample.

    `acquire` runs on the sampling thread only and returns a sample or None (no new data).
    It may raise OSError or TelerobotError for a device failure (counted, reported, the loop
    goes on, a continued failure shows as `stale`); any other exception is a bug: it is
    reported as an `error` event and sampling stops. `publish(sample)` runs on the sampling
    thread (`handoff="inline"`: it must not block for long; its failures are counted) or on
    the publisher thread (`handoff="queue"`: it may block); `on_event(kind, message,
    data)` runs on the publisher thread and may block.

    The sampling thread exists from construction (idle, at `priority`) until `close()`;
    `start()`/`stop()` trigger and halt sensing; `set_period_ms()` and `set_priority()` act
    on the running thread. A sensor without new data for `stale_after_periods` periods
    raises one `stale` event, and one `recovered` event when data returns.
    """

    def __init__(
        self,
        acquire: Callable[[], S | None],
        publish: Callable[[S], None],
        *,
        period_ms: float = 1.0,
        priority: PriorityLevel = "normal",
        on_event: EventSink = ignore_event,
        queue_len: int = 256,
        handoff: Handoff = "queue",
        stale_after_periods: int = 5,
        rate_window_s: float = 1.0,
        clock: SamplerClock | None = None,
        name: str = "force-sampler",
    ) -> None:
        if queue_len < 1:
            raise ValueError("queue_len must be ≥ 1")
        if handoff not in HANDOFFS:
            raise ValueError(f"handoff: one of {list(HANDOFFS)}, got {handoff!r}")
        self._inline = handoff == "inline"
        if not 1 <= stale_after_periods <= 10:
            raise ValueError("stale_after_periods must be within 1…10")
        if priority not in PRIORITY_LEVELS:
            raise ValueError(f"priority: one of {list(PRIORITY_LEVELS)}, got {priority!r}")
        self._acquire = acquire
        self._publish = publish
        self._emit = on_event
        self._clock: SamplerClock = clock or MonotonicClock()
        self._period_ns = round(check_period_ms(period_ms) * 1e6)
        self._slow_ns: int | None = None
        self._period_changed = False
        self._stale_after = stale_after_periods
        self._rate_window_ns = int(rate_window_s * 1e9)

        self._cond = threading.Condition()
        self._want_run = False
        self._closed = False
        self._idle = True
        self._tid = 0
        self._tid_ready = threading.Event()

        self._queue: deque[S] = deque(maxlen=queue_len)
        self._events: deque[tuple[str, str, dict[str, Any]]] = deque(maxlen=256)
        self._q_cond = threading.Condition()
        self._stamps: deque[int] = deque(maxlen=16384)
        self._started_ns = 0
        self._error_events = EventThrottle(self.post_event, interval_s=1.0)

        self._samples = 0
        self._ticks = 0
        self._empty = 0
        self._overruns = 0
        self._caught_up = 0
        self._drops = 0
        self._published = 0
        self._publish_errors = 0
        self._read_errors = 0
        self._event_drops = 0
        self._stale = False
        self._late_max_ns = 0
        self._last_error = ""

        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._publisher = threading.Thread(target=self._drain, name=f"{name}-pub", daemon=True)
        self._thread.start()
        self._publisher.start()
        self._tid_ready.wait()
        self._priority = self.set_priority(priority)

    # --- control (any thread) ---------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._want_run

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def native_id(self) -> int:
        """The sampling thread's OS id (Linux task id)."""
        return self._tid

    @property
    def period_ms(self) -> float:
        return self._period_ns / 1e6

    @property
    def priority(self) -> PriorityReport:
        return self._priority

    def start(self) -> None:
        """Trigger sensing (no-op when already running)."""
        with self._cond:
            if self._closed:
                raise RuntimeError("sampler is closed")
            if self._want_run:
                return
            self._last_error = ""
            self._want_run = True
            self._cond.notify_all()

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> bool:
        """Halt sensing; True once the sampling loop is idle (acquire no longer runs)."""
        with self._cond:
            self._want_run = False
            return self._cond.wait_for(lambda: self._idle, timeout=timeout_s)

    def close(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Stop, end both threads; samples and events already queued are still delivered."""
        self.stop(timeout_s)
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        with self._q_cond:
            self._q_cond.notify_all()
        self._thread.join(timeout_s)
        self._publisher.join(timeout_s)

    def set_period_ms(self, period_ms: float) -> None:
        """New TimerValue; the next deadline is one new period after the last tick."""
        self._period_ns = round(check_period_ms(period_ms) * 1e6)
        self._period_changed = True

    def set_slow(self, slow_ms: float | None) -> None:
        """Sample every `slow_ms` (never faster than the period) while the samples go to
        nobody and the sensor need not be read at its rate (a simulated one); None: the
        period again, the next sample at once."""
        slow = None if slow_ms is None else round(check_period_ms(slow_ms) * 1e6)
        if slow != self._slow_ns:
            self._slow_ns = slow
            self._period_changed = True

    @property
    def slow(self) -> bool:
        return self._slow_ns is not None and self._slow_ns > self._period_ns

    def set_priority(self, level: PriorityLevel) -> PriorityReport:
        """New SensorThreadPriority for the sampling thread; returns what was applied."""
        if level not in PRIORITY_LEVELS:
            raise ValueError(f"priority: one of {list(PRIORITY_LEVELS)}, got {level!r}")
        report = apply_thread_priority(self._tid, level)
        self._priority = report
        if isinstance(self._clock, MonotonicClock):
            self._clock.realtime = level == "highest" and report.policy in (
                "SCHED_FIFO",
                "SCHED_RR",
            )
        return report

    def post_event(self, kind: str, message: str, data: dict[str, Any]) -> None:
        """Queue an event for the publisher thread; never blocks (drops the oldest if full)."""
        with self._q_cond:
            if len(self._events) == self._events.maxlen:
                self._event_drops += 1
            self._events.append((kind, message, data))
            self._q_cond.notify()

    def rate_hz(self) -> float:
        """Samples per second over the last `rate_window_s` (≥ 10 periods), from timestamps."""
        if not self._want_run:
            return 0.0
        now = self._clock.now_ns()
        window = max(self._rate_window_ns, 10 * self._period_ns)
        # list(deque) runs in C without releasing the GIL: a consistent copy, no lock.
        recent = [t for t in list(self._stamps) if now - t <= window]
        if len(recent) < 2:
            return 0.0
        if now - self._started_ns >= window:
            return len(recent) * 1e9 / window
        return (len(recent) - 1) * 1e9 / max(recent[-1] - recent[0], 1)

    def stats(self) -> SamplerStats:
        return SamplerStats(
            running=self._want_run,
            period_ms=self.period_ms,
            priority=self._priority,
            rate_hz=self.rate_hz(),
            samples=self._samples,
            ticks=self._ticks,
            empty=self._empty,
            overruns=self._overruns,
            caught_up=self._caught_up,
            drops=self._drops,
            published=self._published,
            publish_errors=self._publish_errors,
            read_errors=self._read_errors,
            event_drops=self._event_drops,
            stale=self._stale,
            late_max_us=self._late_max_ns / 1e3,
            last_error=self._last_error,
        )

    # --- sampling thread --------------------------------------------------------------

    def _run(self) -> None:
        self._tid = threading.get_native_id()
        _tighten_timer_slack()
        self._tid_ready.set()
        while True:
            with self._cond:
                self._idle = True
                self._cond.notify_all()
                self._cond.wait_for(lambda: self._want_run or self._closed)
                if self._closed:
                    return
                self._idle = False
            self._loop()

    def _interrupted(self) -> bool:
        return not self._want_run or self._closed or self._period_changed

    def _loop(self) -> None:
        # Hot: one pass per period. Bound methods in locals, no lock, no call that is not
        # needed: every bytecode here runs 1 000 times a second, usually with cold caches.
        clock = self._clock
        now_ns, sleep_until, interrupted = clock.now_ns, clock.sleep_until, self._interrupted
        acquire, publish, inline = self._acquire, self._publish, self._inline
        stamp = self._stamps.append
        next_ns = now_ns()
        last_tick_ns = next_ns
        last_data_ns = next_ns
        self._started_ns = next_ns
        self._stale = False
        self._period_changed = False
        self._stamps.clear()
        caught_up = False
        while True:
            sleep_until(next_ns, interrupted)
            if not self._want_run or self._closed:
                return
            slow = self._slow_ns
            period_ns = self._period_ns if slow is None else max(self._period_ns, slow)
            if self._period_changed:
                self._period_changed = False
                next_ns = last_tick_ns + period_ns
                if now_ns() < next_ns:
                    continue
            late = now_ns() - next_ns
            if late > self._late_max_ns:
                self._late_max_ns = late
            last_tick_ns = next_ns

            try:
                item = acquire()
            except (OSError, TelerobotError) as e:
                self._read_failed(e)
                item = None
            except Exception as e:  # a bug, not a device failure: stop, publish no garbage
                self._fatal(e)
                return
            now = now_ns()
            self._ticks += 1
            if item is None:
                self._empty += 1
                stalled_ns = now - last_data_ns
                if not self._stale and stalled_ns >= self._stale_after * period_ns:
                    self._stale = True
                    never = self._samples == 0
                    self.post_event(
                        "stale",
                        (
                            "the force sensor has sent nothing since sampling started "
                            f"({stalled_ns / 1e6:.1f} ms): is it connected, powered and "
                            "configured (port, host)?"
                        )
                        if never
                        else f"no data from the force sensor for {stalled_ns / 1e6:.1f} ms",
                        {"stale": True, "periods": stalled_ns / period_ns, "never": never},
                    )
            else:
                if self._stale:
                    self._stale = False
                    self.post_event(
                        "recovered",
                        f"force sensor data back after {(now - last_data_ns) / 1e6:.1f} ms",
                        {"stale": False, "stalled_ms": (now - last_data_ns) / 1e6},
                    )
                last_data_ns = now
                self._samples += 1
                stamp(now)
                if inline:
                    try:
                        publish(item)
                        self._published += 1
                    except Exception as e:  # a failed put must not end sampling
                        self._publish_failed(e)
                    now = now_ns()  # a slow put makes this tick late, honestly
                else:
                    self._handoff(item)

            next_ns += period_ns
            if now >= next_ns:
                if now < next_ns + period_ns and not caught_up:
                    # One deadline passed during this tick (a short stall): its sample is
                    # taken at once, and the schedule goes on from it. Once in a row only.
                    caught_up = True
                    self._caught_up += 1
                    continue
                missed = (now - next_ns) // period_ns + 1
                self._overruns += missed
                next_ns += missed * period_ns
            caught_up = False

    def _read_failed(self, e: Exception) -> None:
        self._read_errors += 1
        self._error_events(
            "error", f"force sensor read failed: {e}", {"read_errors": self._read_errors}
        )

    def _fatal(self, e: Exception) -> None:
        self._last_error = f"{type(e).__name__}: {e}"
        self._want_run = False
        self.post_event(
            "error",
            f"force sampling stopped: {self._last_error}",
            {"fatal": True, "error": self._last_error},
        )

    def _handoff(self, item: S) -> None:
        with self._q_cond:
            if len(self._queue) == self._queue.maxlen:
                self._drops += 1
            self._queue.append(item)
            self._q_cond.notify()

    # --- publisher thread -------------------------------------------------------------

    def _drain(self) -> None:
        while True:
            with self._q_cond:
                self._q_cond.wait_for(lambda: bool(self._queue or self._events or self._closed))
                if not self._queue and not self._events:
                    return
                items = list(self._queue)
                self._queue.clear()
                events = list(self._events)
                self._events.clear()
            for kind, message, data in events:
                try:
                    self._emit(kind, message, data)
                except Exception:  # the bus is down: counting is all that is left to do
                    self._publish_errors += 1
            for item in items:
                self._publish_one(item)

    def _publish_one(self, item: S) -> None:
        try:
            self._publish(item)
            self._published += 1
        except Exception as e:  # a failed put must not end publishing
            self._publish_failed(e)

    def _publish_failed(self, e: Exception) -> None:
        self._publish_errors += 1
        self._error_events(
            "error",
            f"force publish failed: {short(str(e))}",
            {"publish_errors": self._publish_errors},
        )
