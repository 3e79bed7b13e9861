"""The fault suite's eyes on the bus, and the pure analyses of what it saw.

`Observer` is an in-process Node that records every robot/state, the arrival of every
robot/force sample and every robot/events message. The analyses are pure functions of the
recorded messages, unit-tested in test_observe.py: when the arm came to rest, whether a
step between two states was a jump, and whether a source's events are contiguous.

`record(name, **numbers)` collects the figures each test measured; `write_results()` merges
them into artifacts/faults.json (docs/faults.md copies them from there).
"""

from __future__ import annotations

import fcntl
import itertools
import json
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.bus import keys
from services.bus.config import Mode, NodeConfig
from services.bus.messages import Event, ForceSample, RobotState
from services.bus.node import Node
from tests.faults.procs import LOOPBACK_LISTEN, REPO

ARTIFACT = REPO / "artifacts" / "faults.json"
REST_TOL_RAD = 1e-6
"""Joints within this of their final value count as at rest (the sim servo converges
exponentially; 1 µrad is ~1 µm at the tool)."""
STEP_EPS_M = 1e-6

RESULTS: dict[str, dict[str, Any]] = {}


def record(name: str, **numbers: Any) -> None:
    """Keep a test's measured figures, print them (pytest -s shows them), save them."""
    RESULTS.setdefault(name, {}).update(numbers)
    print(f"[faults] {name}: {json.dumps(numbers, sort_keys=True)}")
    write_results()


def write_results(path: Path = ARTIFACT) -> None:
    """Merge RESULTS into the JSON file (other test modules write their own entries).

    Under a lock and by rename: test modules may run in parallel pytest workers, and a
    read-merge-write that interleaves with another would lose its entries.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            old = json.loads(path.read_text())
        except (OSError, ValueError):
            old = {}
        if not isinstance(old, dict):
            old = {}
        old.update(RESULTS)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(old, indent=2, sort_keys=True) + "\n")
        tmp.replace(path)


# --- pure analyses ------------------------------------------------------------------------


def rest_start(qs: Sequence[Sequence[float]], tol_rad: float = REST_TOL_RAD) -> int:
    """The first index from which every joint vector stays within `tol_rad` of the last one
    (len(qs) − 1 when only the last is; 0 for an empty or constant sequence)."""
    if not qs:
        return 0
    q = np.asarray(qs, dtype=float)
    dev = np.max(np.abs(q - q[-1]), axis=1)
    moving = np.flatnonzero(dev > tol_rad)
    return int(moving[-1]) + 1 if moving.size else 0


@dataclass(frozen=True, slots=True)
class Steps:
    """Tool-point steps between consecutive states: the largest (m), the largest as a
    fraction of what the speed limit allows, and how many exceeded it (jumps)."""

    n: int
    max_step_m: float
    max_ratio: float
    jumps: int


def tool_steps(
    states: Sequence[RobotState],
    max_speed_m_s: float,
    state_period_s: float,
    sample_period_s: float = 0.0,
    read_age_s: float = 0.0,
) -> Steps:
    """Compare each step of `tool_p` with `max_speed_m_s` × the time between the two states.

    The time allowed is the larger of the sender's clock difference and the number of state
    periods between their `seq`s (a dropped state leaves a longer step; a late publish loop
    bunches states in time, never steps). An arm whose joints are read more slowly than
    states are sent (a serial controller's cycle) moves in steps of one reading: each change
    of position is allowed `sample_period_s` of motion at least. A state is stamped when it
    is sent, but its joints were read up to `read_age_s` before (the arm reads them once per
    control tick): the readings of two states may be that much further apart than their
    stamps, so an arm at its speed limit is allowed that much more motion. A step above what
    is allowed plus STEP_EPS_M is a jump."""
    worst, ratio, jumps, n = 0.0, 0.0, 0, 0
    for a, b in itertools.pairwise(states):
        if b.seq <= a.seq:
            continue  # a restarted arm counts from 1: not a step of one motion
        step = float(np.linalg.norm(np.subtract(b.tool_p, a.tool_p)))
        dt_s = max((b.t_ns - a.t_ns) / 1e9, (b.seq - a.seq) * state_period_s, sample_period_s)
        allowed = max_speed_m_s * (dt_s + read_age_s) + STEP_EPS_M
        n += 1
        worst = max(worst, step)
        ratio = max(ratio, step / allowed)
        if step > allowed:
            jumps += 1
    return Steps(n, worst, ratio, jumps)


@dataclass(frozen=True, slots=True)
class SourceSeqs:
    """One event source's seqs as received: `segments` (a restarted node starts again at 1),
    `lost` (seqs skipped inside a segment), `disorder` (repeated or out-of-order seqs)."""

    received: int
    segments: int
    lost: int
    disorder: int
    first: int
    last: int


def event_continuity(events: Sequence[Event]) -> dict[str, SourceSeqs]:
    """Per source: are the received seqs 1, 2, 3, … (again from 1 after each restart)?"""
    seqs: dict[str, list[int]] = {}
    for ev in events:
        seqs.setdefault(ev.source, []).append(ev.seq)
    out: dict[str, SourceSeqs] = {}
    for source, ss in seqs.items():
        segments, lost, disorder = 1, 0, 0
        prev = ss[0]
        lost += max(0, prev - 1)  # the first one of a source seen from the start is 1
        for s in ss[1:]:
            if s == prev + 1:
                pass
            elif s == 1:
                segments += 1
            elif s > prev + 1:
                lost += s - prev - 1
            else:
                disorder += 1
                continue
            prev = s
        out[source] = SourceSeqs(len(ss), segments, lost, disorder, ss[0], ss[-1])
    return out


def count_between(times: Sequence[float], t0: float, t1: float) -> int:
    """How many of the sorted `times` fall in [t0, t1)."""
    a = np.searchsorted(np.asarray(times), t0, side="left")
    b = np.searchsorted(np.asarray(times), t1, side="left")
    return int(b - a)


# --- the observer -------------------------------------------------------------------------


@dataclass
class _Log:
    states: list[RobotState] = field(default_factory=list)
    force_t: list[float] = field(default_factory=list)
    force_seq: list[int] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)


class Observer:
    """An in-process node on the router at `endpoint`, recording the streams.

    mode "peer" (default) also meshes with the other peers directly, so it stays connected
    to the services while the router is down; a "client" sees only what the router routes.
    Callbacks append under one condition and notify; readers copy under it.
    """

    def __init__(self, endpoint: str, name: str = "faults", mode: Mode = "peer") -> None:
        listen = (LOOPBACK_LISTEN,) if mode == "peer" else ()
        self.node = Node(name, NodeConfig(mode=mode, connect=(endpoint,), listen=listen))
        self._cond = threading.Condition()
        self._log = _Log()
        self.node.subscribe(keys.STATE, self._on_state)
        self.node.subscribe(keys.FORCE, self._on_force)
        self.node.subscribe(keys.EVENTS, self._on_event)

    # Zenoh's threads: append and notify only.
    def _on_state(self, msg: RobotState) -> None:
        with self._cond:
            self._log.states.append(msg)
            self._cond.notify_all()

    def _on_force(self, msg: ForceSample) -> None:
        with self._cond:
            self._log.force_t.append(time.monotonic())
            self._log.force_seq.append(msg.seq)
            self._cond.notify_all()

    def _on_event(self, ev: Event) -> None:
        with self._cond:
            self._log.events.append(ev)
            self._cond.notify_all()

    # --- reading ---------------------------------------------------------------------
    def states(self, start: int = 0) -> list[RobotState]:
        with self._cond:
            return self._log.states[start:]

    def n_states(self) -> int:
        with self._cond:
            return len(self._log.states)

    def latest_state(self) -> RobotState | None:
        with self._cond:
            return self._log.states[-1] if self._log.states else None

    def force_times(self) -> list[float]:
        with self._cond:
            return list(self._log.force_t)

    def force_seqs(self, start: int = 0) -> list[int]:
        with self._cond:
            return self._log.force_seq[start:]

    def n_force(self) -> int:
        with self._cond:
            return len(self._log.force_t)

    def events(self, start: int = 0) -> list[Event]:
        with self._cond:
            return self._log.events[start:]

    def n_events(self) -> int:
        with self._cond:
            return len(self._log.events)

    # --- waiting (deadlines, never bare sleeps) --------------------------------------
    def wait(self, pred: Callable[[], bool], timeout_s: float) -> bool:
        """Wait until `pred()` (called under the lock, on every new message) or the deadline."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not pred():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.05))
            return True

    def wait_states(self, n: int, start: int, timeout_s: float) -> list[RobotState]:
        """At least `n` states after index `start` (fewer if the deadline passes)."""
        self.wait(lambda: len(self._log.states) - start >= n, timeout_s)
        return self.states(start)

    def wait_state(
        self, pred: Callable[[RobotState], bool], start: int, timeout_s: float
    ) -> RobotState | None:
        """The first state after index `start` that satisfies `pred` (None at the deadline)."""
        found: list[RobotState] = []

        def seen() -> bool:
            found[:] = [s for s in self._log.states[start:] if pred(s)][:1]
            return bool(found)

        self.wait(seen, timeout_s)
        return found[0] if found else None

    def wait_force(self, n: int, start: int, timeout_s: float) -> int:
        self.wait(lambda: len(self._log.force_t) - start >= n, timeout_s)
        return self.n_force() - start

    def wait_event(self, pred: Callable[[Event], bool], start: int, timeout_s: float) -> Event:
        found: list[Event] = []

        def seen() -> bool:
            found[:] = [e for e in self._log.events[start:] if pred(e)]
            return bool(found)

        if not self.wait(seen, timeout_s):
            recent = [(e.source, e.kind, e.message[:60]) for e in self.events(start)][-12:]
            raise AssertionError(f"no such event within {timeout_s} s; recent: {recent}")
        return found[0]

    def wait_rest(
        self, start: int, quiet_s: float, deadline_s: float
    ) -> tuple[int, list[RobotState]] | None:
        """Wait until the arm has been at rest for `quiet_s` (in the sender's time), the rest
        having begun within `deadline_s` of now. Returns (index of the first state at rest,
        counted from `start`; the states from `start`), or None if it did not come to rest."""
        t_end = time.monotonic() + deadline_s + quiet_s
        while True:
            states = self.states(start)
            if states:
                r = rest_start([s.q for s in states])
                if (states[-1].t_ns - states[r].t_ns) / 1e9 >= quiet_s:
                    return r, states
            if time.monotonic() >= t_end:
                return None
            self.wait_states(len(states) + 25, start, 0.2)

    def close(self) -> None:
        self.node.close()
