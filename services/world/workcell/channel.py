"""The arm's hand-off to the physics in one process: `sim/arm/cmd` and `sim/arm/state`
without the bus.

With `[arm] sim_physics = "embedded"` (the sim profile, docs/sim.md) the arm service runs
the workcell service in its own process, and the arm's `sim` driver and the physics pass
the very messages they would publish through an `ArmChannel`: the newest setpoint one
way, the newest joints the other, each kept with its arrival time on the monotonic clock
as `Latest.read()` gives it. Nothing is encoded, nothing crosses a socket; the workcell
still publishes `sim/arm/state` for the force service's `sim` sensor and anyone watching.
"""

from __future__ import annotations

import time
from typing import Generic, TypeVar

from services.world.workcell.messages import SimArmCmd, SimArmState

M = TypeVar("M")


class Slot(Generic[M]):
    """The newest message and when it was put (`time.monotonic_ns()`): one writer, any
    readers. A put replaces the pair in one assignment, so a reader sees one whole."""

    def __init__(self) -> None:
        self._item: tuple[M, int] | None = None

    def put(self, msg: M) -> None:
        self._item = (msg, time.monotonic_ns())

    def read(self) -> tuple[M, int] | None:
        """(the newest message, its arrival ns), or None before the first."""
        return self._item


class ArmChannel:
    """`cmd`: the driver's setpoints to the physics; `state`: the physics' joints back."""

    def __init__(self) -> None:
        self.cmd: Slot[SimArmCmd] = Slot()
        self.state: Slot[SimArmState] = Slot()
