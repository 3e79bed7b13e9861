"""The slave port as the real services see it: measured motion, timestamped samples.

On the bus the wrist force (robot/force) and the tool position (robot/state) arrive as two
streams of timestamped samples, each late by its own amount, and the arm follows its
target with a lag of its own (speed and acceleration limits). Pairing the newest force with
the newest position, or with the commanded step, credits the channel with energy that never
crossed the port (the arm retreating under a force sample that lags its motion). Here both
are interpolated at one instant, the newest both streams cover, so the observed power
`f·dx` uses the motion that really happened while that force acted (`TimedHistory`,
`SlavePort.observe`).

The controller works on the target position, not on the step (`SlavePort.correct`): the
energy the robot may still put into the workcell, if it reaches its target, is
`-f·(target − p_now)`; when that exceeds the budget (the master's input energy minus the
slave's observed output), the target is moved back along the contact force until it does
not. A target behind the measured tool (an arm catching up with a target that was ahead
when the contact began) is pulled back as well, so the arm stops at the first touch when
the operator sent no energy. In free space (`f = 0`) nothing changes. The corrections add
up to an offset (slave − master) given back at `drift_m_s` when the budget pays for it.

Supervisor's own corrections (a contact retraction above its force limit, a hold) are not
the operator's channel: while `supervised` is true, energy flowing into the robot is not
credited to the channel (`excluded_j` counts it), energy flowing out still is
(conservative).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

from services.control.passivity.controller import TOLERANCE_J, PortTelemetry
from services.control.passivity.observer import EnergyObserver, RemoteEnergy, dot

DEADBAND_N = 1.0
"""A wrist force below this is sensor noise, not contact: the slave port sees none (the
energy of a motion against less than 1 N goes unobserved; with noise counted instead, its
random direction would hold back free motion). At or above it the decision re-sends the
target every tick, so the slave port corrects it between the operator's commands."""
MIN_FORCE_N = 1e-3
"""A force below this is no contact for the controller (its direction means nothing)."""
MAX_BACKOFF_M = 0.002
"""The farthest the controller puts the target outside the measured tool, along the force
(repaying an overdraw needs the contact to relax, not the arm to leave)."""
HISTORY_LEN = 64
"""Samples kept per stream (at 100–1000 Hz: 64 ms … 0.6 s, longer than any pairing gap)."""


class TimedHistory:
    """A short history of timestamped vectors; `at(t_ns)` interpolates linearly, and
    clamps to the ends (never extrapolates). Samples not newer than the newest are
    ignored (a reordered or repeated sample)."""

    def __init__(self, maxlen: int = HISTORY_LEN) -> None:
        self._items: deque[tuple[int, tuple[float, ...]]] = deque(maxlen=maxlen)

    def add(self, t_ns: int, v: Sequence[float]) -> bool:
        if self._items and t_ns <= self._items[-1][0]:
            return False
        self._items.append((t_ns, tuple(float(x) for x in v)))
        return True

    def clear(self) -> None:
        self._items.clear()

    @property
    def newest_ns(self) -> int | None:
        return self._items[-1][0] if self._items else None

    def at(self, t_ns: int) -> tuple[float, ...] | None:
        if not self._items:
            return None
        if t_ns >= self._items[-1][0]:
            return self._items[-1][1]
        if t_ns <= self._items[0][0]:
            return self._items[0][1]
        for i in range(len(self._items) - 1, 0, -1):
            t0, a = self._items[i - 1]
            if t0 <= t_ns:
                t1, b = self._items[i]
                k = (t_ns - t0) / (t1 - t0)
                return tuple(x + k * (y - x) for x, y in zip(a, b, strict=True))
        return self._items[0][1]


@dataclass(slots=True)
class SlavePort:
    """Slave-side TDPA on measured, timestamped motion (see the module docstring).

    `observe(f, p, supervised)`: the environment force on the tool (N, world) and the tool
    position (m, world) at one instant, later than the previous call's. `correct(target,
    p_now, f)`: the target position (m, world) to send in place of the master's.
    """

    enabled: bool = True
    drift_m_s: float = 0.01
    observer: EnergyObserver = field(default_factory=EnergyObserver)
    remote: RemoteEnergy = field(default_factory=RemoteEnergy)
    telemetry: PortTelemetry = field(default_factory=PortTelemetry)
    offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    excluded_j: float = 0.0
    recovered_j: float = 0.0
    clipped_j: float = 0.0
    _f_prev: tuple[float, ...] | None = None
    _p_prev: tuple[float, ...] | None = None

    @property
    def budget_j(self) -> float:
        """Energy the robot may still put into the workcell (< 0: overdrawn; the target
        then backs out along the force until the workcell has given the excess back)."""
        return self.remote.e_in - self.observer.e_out + self.recovered_j

    def reset(self, epoch: int) -> None:
        """A new operator engagement: energies from zero, no offset."""
        self.observer.reset()
        self.remote.reset(epoch)
        self.recovered_j = 0.0
        self.excluded_j = 0.0
        self.clipped_j = 0.0
        self.rebase()
        self.telemetry.last_gain = 0.0

    def rebase(self) -> None:
        """A new start pose of the arm (it contains the offset): the offset restarts at 0
        and the next observation starts afresh (what the arm did meanwhile was not ours)."""
        self.offset = [0.0] * len(self.offset)
        self.restart()

    def restart(self) -> None:
        """Forget the previous sample: the next `observe` only sets the starting point."""
        self._f_prev = None
        self._p_prev = None

    def observe(self, f: Sequence[float], p: Sequence[float], supervised: bool = False) -> float:
        """Record the energy of the interval since the previous sample (mean force × the
        measured displacement); returns it (J, > 0 into the channel)."""
        fs = tuple(float(x) for x in f)
        ps = tuple(float(x) for x in p)
        e = 0.0
        if self._p_prev is not None and self._f_prev is not None:
            f_mid = [(a + b) / 2 for a, b in zip(fs, self._f_prev, strict=True)]
            dx = [a - b for a, b in zip(ps, self._p_prev, strict=True)]
            e = dot(f_mid, dx)
            if e > 0.0 and self.budget_j < 0.0:
                # Energy reflection: what the workcell gives back first repays what the slave
                # overdrew (an impact faster than one tick); it never reaches the master.
                pay = min(e, -self.budget_j)
                self.recovered_j += pay
                e -= pay
            if supervised and e > 0.0:
                self.excluded_j += e  # the supervisor's motion, not the operator's channel
                e = 0.0
            if e > 0.0:
                # The workcell is passive: it never gives back more than it was given.
                # More than that is the sensing lag (a force that lags the motion looks
                # like an active spring), never energy for the master to release.
                back = self.observer.e_in + self.recovered_j + self.excluded_j
                over = min(e, max(back + e - self.observer.e_out, 0.0))
                self.clipped_j += over
                e -= over
            self.observer.record(e)
        self._f_prev, self._p_prev = fs, ps
        return e

    def correct(
        self,
        target: Sequence[float],
        p_now: Sequence[float],
        f: Sequence[float],
        dt_s: float,
    ) -> list[float]:
        """The target to send (m, world) for the master's `target`, with the tool at
        `p_now` under the environment force `f` (N, world; zero in free space)."""
        want = [float(t) + o for t, o in zip(target, self.offset, strict=True)]
        if not self.enabled:
            return [float(t) for t in target]
        budget = self.budget_j
        ff = dot(f, f)
        if ff < MIN_FORCE_N**2:
            f, ff = [0.0] * len(want), 0.0
        comp = self._drift_step(dt_s)
        if any(comp):
            tried = [w + c for w, c in zip(want, comp, strict=True)]
            # Free in free space, unless overdrawn (it would only lead to the next impact).
            if (ff == 0.0 and budget >= 0.0) or self._committed(f, tried, p_now) <= budget:
                want = tried
        alpha = 0.0
        if ff > 0.0:
            e_next = self._committed(f, want, p_now)
            if e_next > budget + TOLERANCE_J:
                alpha = (e_next - budget) / ff
                # Never more than MAX_BACKOFF_M outside the tool (alpha·|f|² is the energy).
                norm = math.sqrt(ff)
                out_m = -e_next / norm  # where `want` is now, along the force, from the tool
                alpha = min(alpha, max(MAX_BACKOFF_M - out_m, 0.0) / norm)
                want = [w + alpha * fi for w, fi in zip(want, f, strict=True)]
                self.telemetry.dissipated_j += alpha * ff
                self.telemetry.active_steps += 1
        self.telemetry.last_gain = alpha
        self.offset = [w - float(t) for w, t in zip(want, target, strict=True)]
        return want

    @staticmethod
    def _committed(f: Sequence[float], target: Sequence[float], p_now: Sequence[float]) -> float:
        """The energy the robot puts into the workcell going from p_now to target under f."""
        return -math.fsum(fi * (t - p) for fi, t, p in zip(f, target, p_now, strict=True))

    def _drift_step(self, dt_s: float) -> list[float]:
        n = math.sqrt(dot(self.offset, self.offset))
        if self.drift_m_s <= 0.0 or n == 0.0 or not (dt_s > 0.0):
            return [0.0] * len(self.offset)
        k = min(1.0, self.drift_m_s * dt_s / n)
        return [-k * o for o in self.offset]
