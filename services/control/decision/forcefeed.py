"""robot/force for the decision server, only while the arm moves or may start to.

The decision needs the wrist force to supervise a motion (the contact filter, compliance, a
task's guards, a forwarded motion's watch), not while the system is idle; receiving 1 kHz of
force for nothing costs this process, the router and (with no other subscriber) the force
service itself, which follows its matching status. `ForceFeed` holds the `Latest` of
robot/force and subscribes it while the supervisor follows an operator, runs a task or
watches a motion, while a caller pins it (a task starting from idle), and while an
engagement waits for it (`warm`). Not thread-safe: the service calls it under its lock.
"""

from __future__ import annotations

import threading
import time

from services.bus.keys import FORCE
from services.bus.messages import ForceSample, OperatorCommand
from services.bus.node import Node
from services.control.decision.supervisor import Mode, Supervisor
from services.control.decision.watchdogs import fresh

FORCE_WAIT_S = 1.0
"""How long an engagement or a task started while idle waits for robot/force to flow."""
WARM_KEEP_S = 2.0
"""How long the subscription made for an engagement stays if that engagement never starts."""
FORCE_POLL_S = 0.002
"""How often a task starting while idle looks for the first sample."""


class ForceFeed:
    """The decision's robot/force subscription (see the module docstring)."""

    def __init__(self, node: Node) -> None:
        self.latest = node.latest(FORCE, watch=False)
        self.pins = 0  # callers that need robot/force whatever the mode
        self._warm_since_ns: int | None = None  # subscribed for an engagement, none yet

    @property
    def watching(self) -> bool:
        return self.latest.watching

    def read(self) -> tuple[ForceSample, int] | None:
        return self.latest.read()

    def update(self, sup: Supervisor, now_ns: int) -> None:
        """Subscribe while teleoperation or a task runs, a forwarded motion is watched, a
        caller pins it or an engagement waits for it (for at most WARM_KEEP_S, or until it
        starts); drop it otherwise, so an idle system (masters alive but not engaged
        included) neither sends, forwards nor receives 1 kHz of force for nobody."""
        engaged = sup.mode in (Mode.FOLLOW, Mode.TASK)
        warm = self._warm_since_ns
        if warm is not None and (engaged or now_ns - warm > WARM_KEEP_S * 1e9):
            self._warm_since_ns = warm = None
        need = warm is not None or self.pins > 0 or engaged or sup.watch is not None
        if need != self.latest.watching:
            self.latest.watch(need)

    def warm(self, commands: tuple[OperatorCommand, ...], now_ns: int) -> bool:
        """Whether robot/force is being brought up for an engagement (Inputs.force_warming).

        An active command while unsubscribed subscribes and starts the wait; the supervisor
        then defers (never refuses) a new engagement until a sample sent since is in, at
        most FORCE_WAIT_S (a master repeats its command at ≥ 50 Hz, so it starts a tick or
        two later); after that the rules for a stale stream apply. The subscription stays
        until the engagement starts (or WARM_KEEP_S), whichever tick saw the stream back:
        a timer tick between two commands must not drop it again."""
        if not self.latest.watching and any(c.active for c in commands):
            self._warm_since_ns = now_ns
            self.latest.watch(True)
        warm = self._warm_since_ns
        if warm is None:
            return False
        got = self.latest.read()
        if got is not None and got[1] >= warm:
            return False  # the stream is back
        return now_ns - warm <= FORCE_WAIT_S * 1e9

    def wait_fresh(self, cond: threading.Condition, stale_ms: float, timeout_s: float) -> bool:
        """Wait (holding `cond`, which the wait releases) until a sample no older than
        `stale_ms` is in, polling Zenoh's ring every FORCE_POLL_S."""
        deadline = time.monotonic() + timeout_s
        while True:
            got = self.latest.read()
            if got is not None and fresh(stale_ms, time.monotonic_ns(), got[1]):
                return True
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            cond.wait(min(left, FORCE_POLL_S))
