"""Energy observers: the energy that crossed one port of the communication channel.

Ryu & Hannaford's passivity observer split by direction (Ryu, Artigas, Preusche 2010,
"A passivity-based controller for bilateral teleoperation with time-varying delay"): at
each port the power is split into what flows *into* the channel (`e_in`) and what flows
*out* of it (`e_out`); both are cumulative, never decrease, in joules. The channel is
passive iff what leaves it at one port never exceeds what entered it at the other:
`e_out_master ≤ e_in_slave` and `e_out_slave ≤ e_in_master` (each side knows the other's
`e_in` only late, which is conservative because both only grow).

Sign conventions (used everywhere in this package):
- master port: `f` is the force the device applies to the operator's hand, `dx` the hand's
  displacement; `f·dx > 0` is energy out of the channel (it pushed the hand along).
- slave port: `f` is the force the environment applies to the tool, `dx` the commanded
  displacement of the tool; `-f·dx > 0` is energy out of the channel (the robot pushed
  into the environment).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

Vector = Sequence[float]


def dot(a: Vector, b: Vector) -> float:
    """a·b for equal-length vectors (plain floats: called every tick)."""
    return math.fsum(x * y for x, y in zip(a, b, strict=True))


@dataclass(slots=True)
class EnergyObserver:
    """Cumulative input and output energy (J) of one port; `record(e)` adds one step.

    e > 0 entered the channel, e < 0 left it. Non-finite steps raise ValueError (the caller
    validated its inputs; a NaN here is a programmer error and must not poison the sums).
    """

    e_in: float = 0.0
    e_out: float = 0.0

    def record(self, e_j: float) -> None:
        if not math.isfinite(e_j):
            raise ValueError("energy step must be finite")
        if e_j >= 0.0:
            self.e_in += e_j
        else:
            self.e_out -= e_j

    @property
    def net_j(self) -> float:
        """Energy stored in (> 0) or drawn from (< 0) the channel through this port alone."""
        return self.e_in - self.e_out

    def reset(self) -> None:
        self.e_in = 0.0
        self.e_out = 0.0


@dataclass(slots=True)
class RemoteEnergy:
    """The other side's cumulative input energy as received over the link.

    Values only grow, so a late, lost or reordered message is harmless: the newest value is
    the largest, and an old one is a conservative bound. Values of another epoch (the
    engagement number) are ignored; `reset(epoch)` starts a new one at zero.
    """

    epoch: int = 0
    e_in: float = 0.0
    received: int = 0
    ignored: int = 0

    def update(self, epoch: int, e_in_j: float) -> bool:
        """Take a received value; False (and counted) when it is of another epoch, negative
        or not finite."""
        if epoch != self.epoch or not math.isfinite(e_in_j) or e_in_j < 0.0:
            self.ignored += 1
            return False
        self.received += 1
        if e_in_j > self.e_in:
            self.e_in = e_in_j
        return True

    def reset(self, epoch: int) -> None:
        self.epoch = epoch
        self.e_in = 0.0
