"""Taking a stream whose newest message supersedes the older ones (operator commands): at
once in Zenoh's callback while the reader keeps up, in batches on a thread of its own when
it falls behind.

Why both (README, "Commands at 1 kHz: the intake, measured against the code before it"):

- **Inline** is the fastest way in: Zenoh's thread is already awake with the sample, so
  nothing waits for another thread to be scheduled. On a loaded 2-core host a reader thread
  woken per sample wakes about a millisecond late now and then, and at 1 kHz the next
  command is already there.
- **A thread of our own** is what keeps the delay bounded (ZENOH_NOTES pitfall 1): a reader
  slower than its stream, left in the callback, makes every later sample queue behind it in
  Zenoh, with no bound. A callback that starts within `BACKLOG_GAP_NS` of the last one's
  return found the sample queued in Zenoh; a pair sent together (a master's late tick) is
  still handled at once, but once the callbacks have run back to back for
  `BACKLOG_BUDGET_NS` the reader is falling behind: from then on, until a gap shows it
  caught up, a sample is only stored, as is one that arrives while the thread handles a
  batch. The thread takes what piled up in one batch, the newest superseding the rest.

Order is kept: every batch is handled under one lock, in arrival order. What waits is
bounded (`depth`, the oldest dropped and counted)."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

S = TypeVar("S")
M = TypeVar("M")

BACKLOG_GAP_NS = 100_000
"""A sample whose callback starts sooner than this after the previous one returned was
queued in Zenoh meanwhile. Commands at 1 kHz leave about 0.7 ms between callbacks; a
queue, a few microseconds."""
BACKLOG_BUDGET_NS = 2_000_000
"""How long callbacks may run back to back (each sample queued behind the last) before the
rest go to the thread: the most a sample waits in Zenoh behind inline work."""


class Intake(Generic[S, M]):
    """`on_sample` is Zenoh's callback; `on_batch(msgs)` gets the decoded messages (those
    `decode` did not refuse with None) in arrival order, never two batches at once.

    Counters: `inline` (samples handled in the callback), `handed` (stored for the thread),
    `dropped` (the oldest, beyond `depth` waiting), `batches`."""

    def __init__(
        self,
        name: str,
        decode: Callable[[S], M | None],
        on_batch: Callable[[tuple[M, ...]], None],
        on_error: Callable[[], None],
        depth: int = 64,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self._decode = decode
        self._on_batch = on_batch
        self._on_error = on_error
        self._clock = clock
        self._pending: deque[S] = deque(maxlen=depth)
        self._pending_lock = threading.Lock()
        self._busy = threading.Lock()
        """Held while a batch is handled: one at a time, in order."""
        self._wake = threading.Event()
        self._last_return_ns = -BACKLOG_GAP_NS
        self._run_start_ns = 0
        """When the callbacks began to run back to back."""
        self._closed = False
        self.inline = 0
        self.handed = 0
        self.dropped = 0
        self.batches = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def on_sample(self, sample: S) -> None:
        if self._closed:
            return
        start = self._clock()
        with self._pending_lock:
            if len(self._pending) == self._pending.maxlen:
                self.dropped += 1
            self._pending.append(sample)
        try:
            if start - self._last_return_ns >= BACKLOG_GAP_NS:
                self._run_start_ns = start  # nothing was queued: caught up
            keeping_up = start - self._run_start_ns < BACKLOG_BUDGET_NS
            if keeping_up and self._busy.acquire(blocking=False):
                try:
                    self.inline += 1
                    self._drain()
                finally:
                    self._busy.release()
            else:
                self.handed += 1
                self._wake.set()
        finally:
            self._last_return_ns = self._clock()

    def close(self) -> None:
        """Stop the thread (what still waits is not handled)."""
        self._closed = True
        self._wake.set()

    @property
    def thread(self) -> threading.Thread:
        return self._thread

    @property
    def busy(self) -> bool:
        """A batch is being handled."""
        return self._busy.locked()

    def _run(self) -> None:
        while True:
            self._wake.wait()
            if self._closed:
                return
            self._wake.clear()
            with self._busy:
                self._drain()

    def _drain(self) -> None:
        """Handle what waits, until nothing does (the caller holds `_busy`)."""
        while not self._closed:
            with self._pending_lock:
                if not self._pending:
                    return
                samples = tuple(self._pending)
                self._pending.clear()
            try:
                msgs = tuple(m for m in map(self._decode, samples) if m is not None)
                if not msgs:
                    continue
                self.batches += 1
                self._on_batch(msgs)
            except Exception:  # a bug is reported; the stream and the thread keep going
                self._on_error()


__all__ = ["BACKLOG_BUDGET_NS", "BACKLOG_GAP_NS", "Intake"]
