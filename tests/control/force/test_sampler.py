"""The sensing thread: deadlines, overruns, stale detection, non-blocking handoff, priority.

Scheduling is checked on a virtual clock (exact values, no wall-clock assertions); the
real clock is used where only counts and order matter.
"""

from __future__ import annotations

import itertools
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from services.control.force.priority import level_of, read_thread_priority, supported
from services.control.force.sampler import PERIOD_MAX_MS, PERIOD_MIN_MS, Sampler, check_period_ms
from tests.conftest import wait_until
from tests.control.force.helpers import Events

MS = 1_000_000


class VirtualClock:
    """Time that passes only when the sampler sleeps (or a test advances it)."""

    def __init__(self) -> None:
        self.t = 0

    def now_ns(self) -> int:
        return self.t

    def sleep_until(self, deadline_ns: int, interrupted: Callable[[], bool]) -> None:
        time.sleep(0.0001)  # let the other threads run; virtual time itself jumps
        if interrupted():
            return
        self.t = max(self.t, deadline_ns)


class Script:
    """An acquire() that records its tick times and returns what `data(tick)` says."""

    def __init__(
        self, clock: VirtualClock, data: Callable[[int], int | None] = lambda k: k
    ) -> None:
        self.clock = clock
        self.data = data
        self.ticks: list[int] = []
        self.advance_ns = 0

    def __call__(self) -> int | None:
        self.ticks.append(self.clock.t)
        self.clock.t += self.advance_ns
        return self.data(len(self.ticks))


@pytest.fixture
def closing() -> Iterator[list[Sampler[Any]]]:
    made: list[Sampler[Any]] = []
    yield made
    for s in made:
        s.close()


def virtual_sampler(
    closing: list[Sampler[Any]], script_data: Callable[[int], int | None] = lambda k: k, **kw: Any
) -> tuple[Sampler[int], Script, list[int], Events]:
    clock = VirtualClock()
    script = Script(clock, script_data)
    out: list[int] = []
    events = Events()
    s: Sampler[int] = Sampler(script, out.append, on_event=events, clock=clock, **kw)
    closing.append(s)
    return s, script, out, events


def diffs(xs: list[int]) -> list[int]:
    return [b - a for a, b in itertools.pairwise(xs)]


def test_ticks_on_absolute_deadlines(closing: list[Sampler[Any]]) -> None:
    s, script, out, _ = virtual_sampler(closing, period_ms=1.0)
    s.start()
    assert wait_until(lambda: len(script.ticks) >= 100)
    s.stop()
    assert set(diffs(script.ticks)) == {1 * MS}
    st = s.stats()
    assert st.overruns == 0 and st.drops == 0
    assert wait_until(lambda: len(out) == st.samples)
    assert out == list(range(1, st.samples + 1))


def test_period_change_takes_effect_from_the_last_tick(closing: list[Sampler[Any]]) -> None:
    s, script, _, _ = virtual_sampler(closing, period_ms=1.0)
    s.start()
    assert wait_until(lambda: len(script.ticks) >= 50)
    s.set_period_ms(5.0)
    assert s.period_ms == 5.0 and s.stats().period_ms == 5.0
    n = len(script.ticks)
    assert wait_until(lambda: len(script.ticks) >= n + 50)
    s.set_period_ms(0.5)
    n = len(script.ticks)
    assert wait_until(lambda: len(script.ticks) >= n + 50)
    s.stop()
    d = diffs(script.ticks)
    # 1 ms steps, then 5 ms steps, then 0.5 ms steps: each change once, in that order.
    runs = [d[0]] + [b for a, b in itertools.pairwise(d) if a != b]
    assert runs == [1 * MS, 5 * MS, MS // 2]


def test_slow_sampling_while_unused_and_the_period_again_at_once(
    closing: list[Sampler[Any]],
) -> None:
    """`set_slow(10)`: a tick every 10 ms, the configured period kept (and reported);
    `set_slow(None)`: 1 ms steps again, the first one at once (not 10 ms later); a slow
    period below the period changes nothing."""
    s, script, _, _ = virtual_sampler(closing, period_ms=1.0)
    s.start()
    assert wait_until(lambda: len(script.ticks) >= 20)
    s.set_slow(10.0)
    assert s.slow and s.period_ms == 1.0 and s.stats().period_ms == 1.0
    n = len(script.ticks)
    assert wait_until(lambda: len(script.ticks) >= n + 20)
    s.set_slow(None)
    assert not s.slow
    n = len(script.ticks)
    assert wait_until(lambda: len(script.ticks) >= n + 20)
    s.set_slow(0.5)  # faster than the period: the period rules
    assert not s.slow
    n = len(script.ticks)
    assert wait_until(lambda: len(script.ticks) >= n + 20)
    s.stop()
    d = diffs(script.ticks)
    runs = [d[0]] + [b for a, b in itertools.pairwise(d) if a != b]
    # 1 ms, then 10 ms; back to 1 ms steps with the first one ≤ 1 ms after the last slow tick
    assert runs[:2] == [1 * MS, 10 * MS]
    assert all(x <= MS for x in runs[2:]) and runs[-1] == 1 * MS
    assert s.stats().overruns == 0


def test_overruns_count_missed_deadlines_and_do_not_burst(closing: list[Sampler[Any]]) -> None:
    s, script, _, _ = virtual_sampler(closing, period_ms=2.0)
    script.advance_ns = 5 * MS  # every read takes 2.5 periods
    s.start()
    assert wait_until(lambda: len(script.ticks) >= 20)
    s.stop()
    st = s.stats()
    # Each tick misses 2 deadlines; the next tick is on the schedule, 3 periods later.
    assert st.overruns == 2 * st.ticks
    assert set(diffs(script.ticks)) == {6 * MS}


def test_a_short_stall_is_caught_up_once_and_the_schedule_kept(
    closing: list[Sampler[Any]],
) -> None:
    """A read that stalls 1.5 periods (a late wake-up, a preempted put): the deadline that
    passed meanwhile is sampled at once, then the grid goes on, no sample lost. A stall in
    the catch-up itself is not caught up again (an overloaded loop still sleeps)."""
    stalls = {10: 3 * MS // 2, 30: 3 * MS // 2, 31: 4 * MS // 5}  # tick number: its read
    clock = VirtualClock()
    ticks: list[int] = []

    def acquire() -> int:
        ticks.append(clock.t)
        clock.t += stalls.get(len(ticks), 0)
        return len(ticks)

    s: Sampler[int] = Sampler(acquire, lambda x: None, period_ms=1.0, clock=clock)
    closing.append(s)
    s.start()
    assert wait_until(lambda: len(ticks) >= 60)
    s.stop()
    t = ticks
    # Tick 10 (index 9) starts at 9 ms and ends at 10.5: the 10 ms deadline is sampled at
    # once (10.5), the 11 ms one on time.
    assert t[9:12] == [9 * MS, 10 * MS + MS // 2, 11 * MS]
    # Ticks 30 and 31 both stall: 31 is the catch-up of 30's stall and ends at 31.3 ms; the
    # 31 ms deadline is skipped (an overrun), the grid resumes at 32 ms.
    assert t[29:33] == [29 * MS, 30 * MS + MS // 2, 32 * MS, 33 * MS]
    st = s.stats()
    assert (st.caught_up, st.overruns) == (2, 1)
    assert set(diffs(t[33:])) == {1 * MS}


def test_stale_once_per_stall_within_ten_periods(closing: list[Sampler[Any]]) -> None:
    def data(k: int) -> int | None:
        return None if 11 <= k <= 40 or 61 <= k <= 200 else k

    s, script, _, events = virtual_sampler(closing, data, period_ms=1.0, stale_after_periods=5)
    s.start()
    assert wait_until(lambda: len(script.ticks) >= 260)
    s.stop()
    assert wait_until(lambda: len(events.of("recovered")) == 2)
    kinds = [k for k in events.kinds() if k in ("stale", "recovered")]
    assert kinds == ["stale", "recovered", "stale", "recovered"]
    for _, _, data_ in events.of("stale"):
        assert data_["stale"] is True and 5 <= data_["periods"] <= 10
    assert events.of("recovered")[0][2]["stalled_ms"] == pytest.approx(31.0)
    assert s.stats().empty == 30 + 140


def test_rate_is_measured_from_sample_times(closing: list[Sampler[Any]]) -> None:
    # Every other tick has data: 500 samples/s at a 1 ms period.
    s, script, _, _ = virtual_sampler(
        closing, lambda k: k if k % 2 else None, period_ms=1.0, stale_after_periods=10
    )
    s.start()
    assert wait_until(lambda: len(script.ticks) >= 2500)
    assert 499.0 <= s.rate_hz() <= 501.0  # ±1 sample in the 1 s window
    s.stop()
    assert s.rate_hz() == 0.0


def test_device_errors_are_counted_and_bugs_stop_sampling(closing: list[Sampler[Any]]) -> None:
    def data(k: int) -> int | None:
        if k <= 3:
            raise OSError("link down")
        if k == 10:
            raise ZeroDivisionError("a bug")
        return k

    s, _script, out, events = virtual_sampler(closing, data, period_ms=1.0)
    s.start()
    assert wait_until(lambda: not s.running)
    st = s.stats()
    assert st.read_errors == 3
    assert st.samples == 6  # ticks 4…9
    assert "ZeroDivisionError" in st.last_error
    assert wait_until(lambda: any(d.get("fatal") for _, _, d in events.of("error")))
    # Device errors are rate-limited to one event a second; the bug is always reported.
    assert len(events.of("error")) == 2
    assert wait_until(lambda: len(out) == 6)


def test_publish_blocking_never_stalls_sampling(closing: list[Sampler[Any]]) -> None:
    gate = threading.Event()
    out: list[int] = []
    seq = iter(range(1, 1_000_000))

    def publish(x: int) -> None:
        gate.wait()
        out.append(x)

    s: Sampler[int] = Sampler(lambda: next(seq), publish, period_ms=1.0, queue_len=8)
    closing.append(s)
    s.start()
    assert wait_until(lambda: s.stats().samples >= 100, what="sampling while publish is blocked")
    assert out == [] and s.stats().drops > 0
    gate.set()
    s.stop()
    st = s.stats()
    assert wait_until(lambda: len(out) + s.stats().drops == st.samples)
    assert out == sorted(out) and len(set(out)) == len(out)
    assert out[0] == 1 and out[-1] == st.samples  # oldest dropped, newest kept


def test_one_kilohertz_two_thousand_samples_no_gaps(closing: list[Sampler[Any]]) -> None:
    seq = iter(range(1, 1_000_000))
    out: list[int] = []
    s: Sampler[int] = Sampler(lambda: next(seq), out.append, period_ms=1.0)
    closing.append(s)
    s.start()
    assert wait_until(lambda: len(out) >= 2000, timeout_s=30.0)
    s.stop()
    assert out[:2000] == list(range(1, 2001))
    assert s.stats().drops == 0


@pytest.mark.skipif(not supported(), reason="per-thread priority is Linux-only")
def test_priority_changes_apply_to_the_sampling_thread(closing: list[Sampler[Any]]) -> None:
    s: Sampler[int] = Sampler(lambda: 1, lambda x: None, period_ms=1.0, priority="below_normal")
    closing.append(s)
    assert s.priority.applied == "below_normal"
    assert os.getpriority(os.PRIO_PROCESS, s.native_id) == 5
    s.start()
    for level in ("lowest", "highest", "normal"):
        report = s.set_priority(level)
        policy, nice, _ = read_thread_priority(s.native_id)
        assert (report.policy, report.nice) == (policy, nice)
        assert report.applied == level_of(policy, nice)
        assert s.stats().priority == report
    with pytest.raises(ValueError, match="priority"):
        s.set_priority("realtime")  # type: ignore[arg-type]


def test_stop_start_close(closing: list[Sampler[Any]]) -> None:
    s, script, _, _ = virtual_sampler(closing, period_ms=1.0)
    assert not s.running and s.stats().rate_hz == 0.0
    s.start()
    s.start()  # idempotent
    assert wait_until(lambda: len(script.ticks) >= 5)
    assert s.stop() is True
    n = len(script.ticks)
    assert not s.running
    s.start()
    assert wait_until(lambda: len(script.ticks) >= n + 5)
    s.close()
    with pytest.raises(RuntimeError, match="closed"):
        s.start()


@pytest.mark.parametrize(
    "bad", [0.0, 0.1, PERIOD_MAX_MS + 1, float("nan"), float("inf"), True, "1"]
)
def test_period_bounds(bad: Any) -> None:
    with pytest.raises(ValueError, match="period_ms"):
        check_period_ms(bad)
    assert check_period_ms(PERIOD_MIN_MS) == PERIOD_MIN_MS
    assert check_period_ms(2) == 2.0


def test_inline_handoff_publishes_on_the_sampling_thread(closing: list[Sampler[Any]]) -> None:
    seq = iter(range(1, 1_000_000))
    out: list[tuple[int, int]] = []
    s: Sampler[int] = Sampler(
        lambda: next(seq),
        lambda x: out.append((x, threading.get_native_id())),
        period_ms=1.0,
        handoff="inline",
    )
    closing.append(s)
    s.start()
    assert wait_until(lambda: len(out) >= 300)
    s.stop()
    st = s.stats()
    assert [x for x, _ in out] == list(range(1, st.samples + 1))
    assert {tid for _, tid in out} == {s.native_id}  # no hand-off to another thread
    assert st.published == st.samples and st.drops == 0


def test_inline_publish_that_blocks_shows_as_overruns(closing: list[Sampler[Any]]) -> None:
    clock = VirtualClock()
    seq = iter(range(1, 1_000_000))
    out: list[int] = []
    ticks: list[int] = []

    def acquire() -> int:
        ticks.append(clock.t)
        return next(seq)

    def slow_publish(x: int) -> None:
        clock.t += 5 * MS  # every put takes 2.5 periods
        out.append(x)

    s: Sampler[int] = Sampler(acquire, slow_publish, period_ms=2.0, clock=clock, handoff="inline")
    closing.append(s)
    s.start()
    assert wait_until(lambda: len(ticks) >= 20)
    s.stop()
    st = s.stats()
    assert st.overruns == 2 * st.ticks  # each tick misses 2 deadlines, honestly counted
    assert set(diffs(ticks)) == {6 * MS}  # and the schedule resumes without a burst
    assert out == list(range(1, st.samples + 1))


def test_inline_publish_errors_are_counted_and_sampling_goes_on(
    closing: list[Sampler[Any]],
) -> None:
    seq = iter(range(1, 1_000_000))
    events = Events()

    def publish(x: int) -> None:
        if x % 2:
            raise RuntimeError("session closed")

    s: Sampler[int] = Sampler(
        lambda: next(seq), publish, period_ms=1.0, handoff="inline", on_event=events
    )
    closing.append(s)
    s.start()
    assert wait_until(lambda: s.stats().samples >= 20)
    s.stop()
    st = s.stats()
    assert st.publish_errors + st.published == st.samples
    assert st.publish_errors == (st.samples + 1) // 2
    assert wait_until(lambda: len(events.of("error")) >= 1)
    assert "session closed" in events.of("error")[0][1]


def test_unknown_handoff_is_refused() -> None:
    with pytest.raises(ValueError, match="handoff"):
        Sampler(lambda: 1, lambda x: None, handoff="thread")  # type: ignore[arg-type]


class _FakeTime:
    """Stands in for the sampler module's `time`: a clock that moves only by sleeps."""

    def __init__(self) -> None:
        self.t = 0
        self.sleeps: list[float] = []

    def perf_counter_ns(self) -> int:
        self.t += 1_000  # each reading of the clock costs 1 µs
        return self.t

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.t += int(s * 1e9) + 60_000  # woken 60 µs late, as under SCHED_OTHER


def test_the_clock_sleeps_to_the_deadline_and_spins_only_under_realtime(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import services.control.force.sampler as sampler_mod

    fake = _FakeTime()
    monkeypatch.setattr(sampler_mod, "time", fake)
    clock = sampler_mod.MonotonicClock(spin_us=100.0)
    assert clock.realtime is False
    clock.sleep_until(1 * MS, lambda: False)
    assert fake.sleeps and 0.0 not in fake.sleeps  # no sleep(0) spin by default
    assert fake.t >= 1 * MS
    fake.sleeps.clear()
    clock.realtime = True
    clock.sleep_until(fake.t + 1 * MS, lambda: False)
    assert fake.sleeps[0] == pytest.approx(0.0009 - 1e-6, abs=2e-6)  # to 100 µs before
    assert 0.0 in fake.sleeps  # then the spin


@pytest.mark.skipif(not supported(), reason="per-thread priority is Linux-only")
def test_realtime_spin_follows_what_the_kernel_granted(closing: list[Sampler[Any]]) -> None:
    from services.control.force.sampler import MonotonicClock

    clock = MonotonicClock()
    s: Sampler[int] = Sampler(lambda: 1, lambda x: None, period_ms=1.0, clock=clock)
    closing.append(s)
    assert clock.realtime is False  # "normal": never spins
    report = s.set_priority("highest")
    assert clock.realtime == (report.policy in ("SCHED_FIFO", "SCHED_RR"))
    s.set_priority("normal")
    assert clock.realtime is False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="timer slack is Linux's")
def test_the_sampling_thread_has_a_tight_timer_slack(closing: list[Sampler[Any]]) -> None:
    import ctypes

    from services.control.force.sampler import TIMER_SLACK_NS

    libc = ctypes.CDLL(None)
    main_slack = libc.prctl(30, 0, 0, 0, 0)  # PR_GET_TIMERSLACK
    seen: list[int] = []
    s: Sampler[int] = Sampler(
        lambda: seen.append(libc.prctl(30, 0, 0, 0, 0)) or 1,
        lambda x: None,
        handoff="inline",
    )
    closing.append(s)
    s.start()
    assert wait_until(lambda: len(seen) >= 1)
    s.stop()
    assert seen[0] == TIMER_SLACK_NS
    assert libc.prctl(30, 0, 0, 0, 0) == main_slack  # the sampling thread's only
