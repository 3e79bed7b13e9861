"""The link's round trip, measured by each port from the other's echo (docs/passivity.md,
"The round trip").

Each side's PassivityState carries the `t_ns` of the newest one it had received from the
other side (`echo_t_ns`) and how long it had held it (`echo_age_ns`). When the echo of one
of this side's own messages comes back, the round trip is the time since this side sent
it, less the other side's hold: `arrival − echo_t_ns − echo_age_ns`. Both differences are
taken on one clock each (this side's wall clock for its own send and the arrival, the
other side's monotonic clock for its hold), so the two hosts' clocks need not agree. A
message arrives, for this count, when a side first reads it (each reads, once a period,
every message of the other's queued since its last read: `Latest(each=…)`, as the echo rides
on one message in many), so the round trip includes how late each side read (at most a
period of each: 2 ms at 500 Hz), never less than the link's.

The estimate is the median of the round trips of the last `window_s`, one kept every
`SAMPLE_NS` at most: over TCP a lost packet holds the stream behind it for a retransmission
(at 1 % loss, every 2 s window of a 500 Hz stream has several), so the largest of a window
measured 600 ms over a 200 ms link and 3.6 s over a 700 ms one (2026-11-27); the median
is the link's. An echo that is absurd (a round trip below zero or above `MAX_RTT_NS`: a
clock stepped, a forged or foreign echo) is ignored and counted.
"""

from __future__ import annotations

import statistics
from collections import deque

from services.bus.messages import PassivityState

WINDOW_S = 2.0
"""How long a measured round trip counts towards the estimate (s)."""
MAX_RTT_NS = 60_000_000_000
"""A round trip above this (60 s) is no measurement: ignored."""
SAMPLE_NS = 10_000_000
"""At most one round trip kept per this interval (ns): ≤ 200 in a window."""
ECHO_EVERY_NS = 100_000_000
"""A side's figures carry the echo and its round trip at most this often (ns; `carry`):
they add 52 bytes to a message. Over TCP at 700 ms and 1 % loss the master's uplink runs at
what the link carries (its figures queue 1.1–1.7 s there), and more bytes there is a longer
queue: carried on every message (26 kB/s at 500 Hz) or every 20 ms (2.6 kB/s), the press
beside a turn climbed at 3.7–11.7 N/s in 4 of 7 runs at 700 ms, against 0 of 7 with the
code before and 0 of 3 every 100 ms (0.5 kB/s; docs/passivity.md, "The round trip")."""


class RoundTrip:
    """`heard(msg, …)` with each PassivityState of the other side; `echo(now_mono_ns)` for
    this side's next one; `rtt_s(now_mono_ns)` the median round trip of the last
    `window_s` (None: none measured in it)."""

    def __init__(self, window_s: float = WINDOW_S) -> None:
        self._window_ns = int(window_s * 1e9)
        self._heard: tuple[int, int] | None = None  # (their t_ns, its arrival, monotonic)
        self._samples: deque[tuple[int, float]] = deque()  # (arrival, rtt s)
        self._median: float | None = None
        self._stale = False
        self._carried_ns: int | None = None
        self.measured = 0
        self.ignored = 0

    def heard(self, msg: PassivityState, now_wall_ns: int, now_mono_ns: int) -> None:
        """Each message of the other side, once, as it is read (`Latest(each=…)`): kept to
        echo (it arrived now), and, if it echoes one of ours, a round trip."""
        self._heard = (msg.t_ns, now_mono_ns)
        if msg.echo_t_ns is None or msg.echo_age_ns is None:
            return
        rtt_ns = now_wall_ns - msg.echo_t_ns - msg.echo_age_ns
        if not 0 <= rtt_ns <= MAX_RTT_NS:
            self.ignored += 1
            return
        self.measured += 1
        if self._samples and now_mono_ns - self._samples[-1][0] < SAMPLE_NS:
            return
        self._samples.append((now_mono_ns, rtt_ns * 1e-9))
        self._stale = True

    def echo(self, now_mono_ns: int) -> tuple[int, int] | None:
        """(echo_t_ns, echo_age_ns) for this side's next message (None: nothing heard)."""
        if self._heard is None:
            return None
        t_ns, arrival = self._heard
        return t_ns, min(max(now_mono_ns - arrival, 0), MAX_RTT_NS)

    def carry(self, now_mono_ns: int) -> tuple[tuple[int, int] | None, float | None]:
        """What this side's next message carries: (the echo, the round trip, s), or
        (None, None) within ECHO_EVERY_NS of the last message that carried them."""
        if self._carried_ns is not None and now_mono_ns - self._carried_ns < ECHO_EVERY_NS:
            return None, None
        echo = self.echo(now_mono_ns)
        if echo is not None:
            self._carried_ns = now_mono_ns
        return echo, self.rtt_s(now_mono_ns)

    def rtt_s(self, now_mono_ns: int) -> float | None:
        """The median round trip measured in the last `window_s` (s), or None."""
        while self._samples and now_mono_ns - self._samples[0][0] > self._window_ns:
            self._samples.popleft()
            self._stale = True
        if self._stale:
            self._stale = False
            self._median = statistics.median(r for _, r in self._samples) if self._samples else None
        return self._median
