"""The command intake (services/bus/intake.py) on its own: samples are fed to its callback
by the test's threads, on a clock the test sets, so which path each sample takes is decided
by the test, not by the machine's timing."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

import pytest

from services.bus.intake import BACKLOG_BUDGET_NS, BACKLOG_GAP_NS, Intake
from tests.conftest import wait_until

DEADLINE_S = 10.0
MS = 1_000_000


class Clock:
    def __init__(self) -> None:
        self.now = 10 * MS

    def __call__(self) -> int:
        return self.now


class Reader:
    """Records each batch (its seqs and the thread it ran on); blocks on `gate` while
    handling a batch that holds `block_at`."""

    def __init__(self, block_at: int | None = None, fail_at: int | None = None) -> None:
        self.batches: list[tuple[int, ...]] = []
        self.threads: list[threading.Thread] = []
        self.block_at, self.fail_at = block_at, fail_at
        self.blocked = threading.Event()
        self.gate = threading.Event()
        self.errors = 0

    def on_batch(self, msgs: tuple[int, ...]) -> None:
        if self.fail_at in msgs:
            raise ValueError("handler bug")
        self.batches.append(msgs)
        self.threads.append(threading.current_thread())
        if self.block_at in msgs:
            self.blocked.set()
            assert self.gate.wait(DEADLINE_S)

    def on_error(self) -> None:
        self.errors += 1

    def seqs(self) -> list[int]:
        return [s for b in self.batches for s in b]


def valid(sample: int) -> int | None:
    """Negative samples stand for payloads the codec refuses."""
    return sample if sample >= 0 else None


Make = Callable[..., Intake[int, int]]


@pytest.fixture
def make() -> Iterator[Make]:
    made: list[Intake[int, int]] = []

    def build(reader: Reader, clock: Clock, depth: int = 64) -> Intake[int, int]:
        intake: Intake[int, int] = Intake(
            "test-intake", valid, reader.on_batch, reader.on_error, depth, clock
        )
        made.append(intake)
        return intake

    yield build
    for intake in made:
        intake.close()


def from_thread(fn: Callable[[], None]) -> None:
    """Run `fn` on another thread and require it to return (a callback that blocked on a
    busy reader would stall Zenoh)."""
    t = threading.Thread(target=fn, daemon=True)
    t.start()
    t.join(DEADLINE_S)
    assert not t.is_alive(), "the callback blocked"


def test_a_reader_that_keeps_up_handles_each_sample_in_the_callback(make: Make) -> None:
    clock, reader = Clock(), Reader()
    intake = make(reader, clock)
    for seq in range(1, 6):
        intake.on_sample(seq)
        clock.now += MS  # 1 kHz: the callback before returned long ago
    assert reader.batches == [(1,), (2,), (3,), (4,), (5,)]
    assert all(t is threading.current_thread() for t in reader.threads)
    assert (intake.inline, intake.handed, intake.dropped) == (5, 0, 0)


QUEUED_NS = BACKLOG_GAP_NS // 2
"""Between one callback's return and the next one's start when Zenoh had it queued."""
INLINE_RUN = BACKLOG_BUDGET_NS // QUEUED_NS
"""How many samples queued back to back are handled at once before the rest are handed."""


def back_to_back(intake: Intake[int, int], clock: Clock, seqs: range) -> None:
    for seq in seqs:
        intake.on_sample(seq)
        clock.now += QUEUED_NS


def test_a_pair_queued_together_is_still_handled_at_once(make: Make) -> None:
    clock, reader = Clock(), Reader()
    intake = make(reader, clock)
    back_to_back(intake, clock, range(1, 3))  # a master's late tick sent two together
    assert reader.batches == [(1,), (2,)]  # one tick each: none superseded
    assert all(t is threading.current_thread() for t in reader.threads)
    assert (intake.inline, intake.handed) == (2, 0)


def test_a_reader_falling_behind_hands_the_rest_to_its_thread_in_order(make: Make) -> None:
    clock, reader = Clock(), Reader()
    intake = make(reader, clock)
    n = INLINE_RUN + 20
    back_to_back(intake, clock, range(1, n + 1))
    assert wait_until(lambda: len(reader.seqs()) == n, DEADLINE_S)
    assert reader.seqs() == list(range(1, n + 1))
    assert reader.batches[:INLINE_RUN] == [(seq,) for seq in range(1, INLINE_RUN + 1)]
    assert all(t is threading.current_thread() for t in reader.threads[:INLINE_RUN])
    assert all(t is intake.thread for t in reader.threads[INLINE_RUN:])
    assert (intake.inline, intake.handed) == (INLINE_RUN, 20)
    assert wait_until(lambda: not intake.busy, DEADLINE_S)
    clock.now += MS  # a gap: it caught up, and the next is handled at once again
    intake.on_sample(n + 1)
    assert reader.batches[-1] == (n + 1,) and reader.threads[-1] is threading.current_thread()


def test_a_busy_reader_never_blocks_the_callback_and_gets_the_pile_at_once(make: Make) -> None:
    clock, reader = Clock(), Reader(block_at=INLINE_RUN + 1)
    intake = make(reader, clock)
    back_to_back(intake, clock, range(1, INLINE_RUN + 2))  # the last to the thread, which blocks
    assert reader.blocked.wait(DEADLINE_S)
    pile = range(INLINE_RUN + 2, INLINE_RUN + 12)

    def arrivals() -> None:
        for seq in pile:
            clock.now += MS  # keeping up by the clock, but the reader is busy
            intake.on_sample(seq)

    from_thread(arrivals)
    assert intake.handed == 11
    reader.gate.set()
    assert wait_until(lambda: len(reader.seqs()) == INLINE_RUN + 11, DEADLINE_S)
    assert reader.batches[-2:] == [(INLINE_RUN + 1,), tuple(pile)]
    assert wait_until(lambda: not intake.busy, DEADLINE_S)
    clock.now += MS
    intake.on_sample(0)  # caught up: in the callback again
    assert reader.batches[-1] == (0,) and reader.threads[-1] is threading.current_thread()


def test_what_waits_is_bounded_and_the_oldest_dropped(make: Make) -> None:
    clock, reader = Clock(), Reader(block_at=INLINE_RUN + 1)
    intake = make(reader, clock, depth=4)
    back_to_back(intake, clock, range(1, INLINE_RUN + 2))
    assert reader.blocked.wait(DEADLINE_S)
    from_thread(lambda: back_to_back(intake, clock, range(100, 110)))
    assert intake.dropped == 6
    reader.gate.set()
    assert wait_until(lambda: reader.seqs()[-1:] == [109], DEADLINE_S)
    assert reader.batches[-1] == (106, 107, 108, 109)


def test_refused_samples_are_left_out_and_a_batch_of_none_is_not_handled(make: Make) -> None:
    clock, reader = Clock(), Reader()
    intake = make(reader, clock)
    for seq in (1, -1, 2):
        intake.on_sample(seq)
        clock.now += MS
    assert reader.batches == [(1,), (2,)]
    assert intake.batches == 2


def test_a_failing_handler_is_reported_and_the_stream_flows(make: Make) -> None:
    clock, reader = Clock(), Reader(fail_at=2)
    intake = make(reader, clock)
    for seq in (1, 2, 3):
        intake.on_sample(seq)
        clock.now += MS
    assert reader.errors == 1 and reader.batches == [(1,), (3,)]


def test_a_decoder_bug_is_reported_and_the_thread_goes_on(make: Make) -> None:
    clock, reader = Clock(), Reader()

    def decode(sample: int) -> int | None:
        if sample == 99:
            raise RuntimeError("decoder bug")
        return sample

    intake: Intake[int, int] = Intake("t", decode, reader.on_batch, reader.on_error, 64, clock)
    try:
        back_to_back(intake, clock, range(1, INLINE_RUN + 1))
        back_to_back(intake, clock, range(99, 100))  # past the budget: on the thread
        assert wait_until(lambda: reader.errors == 1, DEADLINE_S)
        back_to_back(intake, clock, range(200, 201))  # still queued: the thread again
        assert wait_until(lambda: reader.seqs()[-1:] == [200], DEADLINE_S)
        assert intake.thread.is_alive()
    finally:
        intake.close()


def test_close_stops_the_thread_and_later_samples_are_ignored(make: Make) -> None:
    clock, reader = Clock(), Reader()
    intake = make(reader, clock)
    intake.on_sample(1)
    intake.close()
    intake.thread.join(DEADLINE_S)
    assert not intake.thread.is_alive()
    clock.now += MS
    intake.on_sample(2)
    assert reader.batches == [(1,)]
