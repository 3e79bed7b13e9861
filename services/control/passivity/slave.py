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

An impact faster than one tick overdraws the budget; what the workcell gives back as the
target backs out repays it first (`recovered_j`). What it does not give back (the contact's
damping kept it) is forgiven once the tool is out of contact (`forgiven_j`, reported by the
benches as energy generated, never hidden): left owing, the port held the budget below zero
for good, every re-entry at the master's speed overdrew again, the master was sent nothing
and the hand felt nothing, and the operator pushed 6 cm past a wall the tool only grazed
(the simulated loop with this port, 700 ms, no guarded approach: docs/passivity.md, "An
impact the workcell does not repay").

Supervisor's own corrections (a contact retraction above its force limit, a hold) are not
the operator's channel: while `supervised` is true, energy flowing into the robot is not
credited to the channel (`excluded_j` counts it), energy flowing out still is
(conservative).

Yielding to the hand (`yield_m_s_n` > 0; off by default): the master reports the force it
was asked to show and the force it let the hand feel (`asked_n`, `shown_n`, newtons at the
tool). With its reservoir empty the master shows the hand what it pushes with and no more,
and a tool that pressed harder at the touch stays harder: nothing moves, so nothing refills
the reservoir. The port then backs the target out along the contact force at
`yield_m_s_n` × the excess, the energy the workcell gives back meanwhile excluded (handed to
the master it let the display push the hand out and the hand lunge back in: 40 N peaks in 2
runs of 6), and the offset is given back into the contact only slowly and only while the
tool presses no harder than the hand feels (docs/passivity.md, "Yielding to the hand").
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
(repaying an overdraw needs the contact to relax, not the arm to leave), and never outside
the point where the contact began: backed out past it, the tool left the surface, the
display went blank a round trip later and the hand sank (the simulated loop with this
port, 3-DoF at 200 ms: the contact came and went in 3 seeds of 6, 0 of 6 since). Where it
began is the tool's position at the first sample with a contact force
(`SlavePort.backoff_m`)."""
OWING_CLEAR_M = 0.005
"""Out of contact, the offset is given back at the drift's speed only away from the last
contact's surface, or while the target stays this far (m) out of it (the tool back on the
master's mapping once the operator has let go: left owing, it stayed 38 mm off in the
simulated 3-DoF loop at 700 ms, seed 1); towards the surface near it, at DRIFT_CONTACT_M_S
only: a second touch that slow is no impact. Until 2026-12-04 the drift towards it was held
back altogether when the contact was left owing (the tool then stayed 0.2–0.3 mm above the
MuJoCo table for the rest of the hold while the operator pressed on, feeling nothing), and
was free otherwise (at 3 cm/s the target then stepped 1.7–3 mm below the table within a
tick and the tool struck it again): docs/passivity.md, "On the MuJoCo cell"."""
YIELD_M_S_N = 5e-5
"""The yield rate measured (m/s per N, `[decision] passivity_yield_m_s_n`; off by default):
0.25 mm/s for 5 N, which sheds 5 N/s against the link bench's 20 kN/m table."""
DRIFT_CONTACT_M_S = 0.001
"""Towards the surface just left (OWING_CLEAR_M), and with the yield on into a contact, the
offset is given back at this speed at most (m/s; 20 N/s against the link bench's 20 kN/m
table), in contact only while the tool presses no harder than the hand feels: the yield's
offset given back at the free-space 3 cm/s pressed the tool to 32 N at 700 ms. Not with the
yield off: there, held in contact, the offset built up at the touch (the hand's figures a
round trip late) was given back at 3 cm/s whenever the force dipped under the dead band,
and the tool struck the table at 49–71 N in 4 runs of 18 at 200 ms (0 of 20 without the
rule, 2026-11-27)."""
YIELD_MAX_M_S = 0.002
"""The fastest the target backs out for the operator (m/s)."""
YIELD_MIN_N = 0.5
"""An excess below this (N) is not yielded: the master's limiter catching up with the force."""
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
    `yield_m_s_n`: the yield to the hand (0: off); `asked_n` / `shown_n`: the master's
    last figures for this engagement (None: not known, no yield); `yielding`: the last
    `correct` yielded; `yielded_m`: how far the target was backed out so far.
    `yield_max_rtt_s`: the yield runs only for a contact that began while the link's round
    trip `rtt_s` (set by the owner; None: not measured) was at most this (inf: whatever the
    link); whether it runs is decided out of contact and kept through the contact
    (`yield_on`), so a round trip that changes mid-contact switches nothing.
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
    forgiven_j: float = 0.0
    yield_m_s_n: float = 0.0
    asked_n: float | None = None
    shown_n: float | None = None
    yielding: bool = False
    yielded_m: float = 0.0
    yield_max_rtt_s: float = math.inf
    rtt_s: float | None = None
    yield_on: bool | None = None
    _in_contact: bool = False
    _surface: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    _f_prev: tuple[float, ...] | None = None
    _p_prev: tuple[float, ...] | None = None

    @property
    def budget_j(self) -> float:
        """Energy the robot may still put into the workcell (< 0: overdrawn; the target
        then backs out along the force until the workcell has given the excess back, and
        what it has not when the tool is out of contact is forgiven; out of contact the drift
        goes back towards that surface near it only slowly, OWING_CLEAR_M)."""
        return self.remote.e_in - self.observer.e_out + self.recovered_j + self.forgiven_j

    def reset(self, epoch: int) -> None:
        """A new operator engagement: energies from zero, no offset."""
        self.observer.reset()
        self.remote.reset(epoch)
        self.recovered_j = 0.0
        self.excluded_j = 0.0
        self.clipped_j = 0.0
        self.forgiven_j = 0.0
        self._in_contact = False
        self._surface = None
        self.asked_n = self.shown_n = None
        self.yielding = False
        self.yielded_m = 0.0
        self.yield_on = None
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
            if (supervised or self.yielding) and e > 0.0:
                # The supervisor's motion, or the port's own yield to the operator: not the
                # operator's channel (a yield that handed the workcell's energy to the master
                # let it push the hand back out, and the hand lunged in when it ran out).
                self.excluded_j += e
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
            if not any(fs) and self.budget_j < 0.0:
                # Out of contact: the workcell has given back all it will; the rest of the
                # overdraw was one tick's impact, sampled late (module docstring).
                self.forgiven_j -= self.budget_j
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
        f_n = math.sqrt(ff)
        if ff > 0.0 and not self._in_contact:
            # Where the contact was first felt: an arm that overruns a touch (its
            # braking lag) goes on past it, and backing out to it sheds that. The last
            # tool out of contact instead lifts the tool off (one tick of approach): in
            # the simulated 3-DoF loop at 200 ms, 1 seed of 6 stable against 6 of 6.
            touch = tuple(float(x) for x in p_now)
            self._surface = (touch, tuple(fi / f_n for fi in f))
        self._in_contact = ff > 0.0
        if ff == 0.0 or self.yield_on is None:
            self.yield_on = self._link_allows_yield()
        yields = self.yield_on
        excess = self.withheld_n(f_n)
        self.yielding = yields and excess >= YIELD_MIN_N
        comp = self._drift_step(dt_s, DRIFT_CONTACT_M_S if yields and ff > 0.0 else self.drift_m_s)
        over = yields and self.shown_n is not None and f_n > self.shown_n + YIELD_MIN_N
        if (self.yielding or over) and dot(f, comp) < 0.0:
            # With the yield on, not back into the contact while the tool presses harder
            # than the operator feels (the force now against what the hand held, late by
            # the link): given back regardless, the offset the operator had pushed past a
            # clamped target pressed the tool to 32 N at 700 ms, the hand feeling 5.
            comp = [0.0] * len(comp)
        if any(comp) and ff == 0.0 and self._surface is not None:
            tried = [w + c for w, c in zip(want, comp, strict=True)]
            if not self._clear_of_surface(tried, comp):
                # Going back towards the surface just left, near it: slowly, at
                # DRIFT_CONTACT_M_S (OWING_CLEAR_M says why).
                comp = self._drift_step(dt_s, DRIFT_CONTACT_M_S)
        if any(comp):
            tried = [w + c for w, c in zip(want, comp, strict=True)]
            # Free in free space unless overdrawn; in contact, while the budget pays.
            pays = budget >= 0.0 if ff == 0.0 else self._committed(f, tried, p_now) <= budget
            if pays:
                want = tried
        alpha = 0.0
        if ff > 0.0:
            e_next = self._committed(f, want, p_now)
            if e_next > budget + TOLERANCE_J:
                alpha = (e_next - budget) / ff
                # Never more than MAX_BACKOFF_M outside the tool (alpha·|f|² is the energy),
                # nor outside where this contact began: the tool stays on the surface.
                norm = math.sqrt(ff)
                out_m = -e_next / norm  # where `want` is now, along the force, from the tool
                alpha = min(alpha, max(self.backoff_m(f, p_now) - out_m, 0.0) / norm)
                want = [w + alpha * fi for w, fi in zip(want, f, strict=True)]
                self.telemetry.dissipated_j += alpha * ff
                self.telemetry.active_steps += 1
        self.telemetry.last_gain = alpha
        if self.yielding:
            want = self._yield(want, p_now, f, f_n, excess, dt_s)
        self.offset = [w - float(t) for w, t in zip(want, target, strict=True)]
        return want

    def _link_allows_yield(self) -> bool:
        """The yield is on and the round trip known to be short enough for it (or not
        asked about): at 700 ms it pulled the force down towards what the hand had felt a
        round trip before, and the operator pressed it back up (docs/passivity.md)."""
        if self.yield_m_s_n <= 0.0:
            return False
        if self.yield_max_rtt_s == math.inf:
            return True
        return self.rtt_s is not None and self.rtt_s <= self.yield_max_rtt_s

    def withheld_n(self, f_n: float) -> float:
        """The force the tool presses with now (`f_n`, N) beyond what the operator feels:
        `min(f_n, asked_n) − shown_n` (0 without the master's figures). The master's are
        late by the link, but `shown_n` is what the hand holds, which changes slowly; `asked_n`
        only keeps a force the master could not display anyway (its own limit) from being
        yielded. As the tool yields, the excess falls with the force now, not a round trip
        later, so the yield stops at what the hand is shown; at long delays that trails the
        force itself, and the yield pulls the force down towards it (docs/passivity.md)."""
        if self.asked_n is None or self.shown_n is None:
            return 0.0
        return max(min(f_n, self.asked_n) - self.shown_n, 0.0)

    def _yield(
        self,
        want: list[float],
        p_now: Sequence[float],
        f: Sequence[float],
        f_n: float,
        excess: float,
        dt_s: float,
    ) -> list[float]:
        """The target moved out along the contact force by `yield_m_s_n` × `excess` (the
        force the operator is not shown, N) × dt_s, at most `YIELD_MAX_M_S` × dt_s and never
        past `MAX_BACKOFF_M` outside the tool: the tool presses no harder than the operator
        feels. Passive: it only backs out, and what the workcell gives back meanwhile is
        not the channel's (`observe` excludes it)."""
        u = [fi / f_n for fi in f]
        out_m = math.fsum(ui * (w - p) for ui, w, p in zip(u, want, p_now, strict=True))
        step = min(self.yield_m_s_n * excess, YIELD_MAX_M_S) * dt_s
        step = min(step, max(MAX_BACKOFF_M - out_m, 0.0))
        if step <= 0.0:
            return want
        self.yielded_m += step
        return [w + step * ui for w, ui in zip(want, u, strict=True)]

    def _clear_of_surface(self, tried: Sequence[float], comp: Sequence[float]) -> bool:
        """The drift `comp` leads away from the last contact's surface, or leaves the target
        `tried` at least OWING_CLEAR_M out of it (no surface known: never)."""
        if self._surface is None:
            return False
        p_c, n = self._surface
        if dot(n, comp) >= 0.0:
            return True
        return math.fsum(ni * (t - c) for ni, t, c in zip(n, tried, p_c, strict=True)) >= (
            OWING_CLEAR_M
        )

    def backoff_m(self, f: Sequence[float], p_now: Sequence[float]) -> float:
        """How far outside the tool at `p_now`, along the force `f`, the target may go:
        MAX_BACKOFF_M, and no further than where this contact began (the tool's position at
        its first sample with a contact force: how deep the tool is past that point)."""
        norm = math.sqrt(dot(f, f))
        if not self._in_contact or self._surface is None or norm == 0.0:
            return MAX_BACKOFF_M
        touch = self._surface[0]
        depth = math.fsum(fi * (c - p) for fi, c, p in zip(f, touch, p_now, strict=True))
        return min(MAX_BACKOFF_M, max(depth / norm, 0.0))

    @staticmethod
    def _committed(f: Sequence[float], target: Sequence[float], p_now: Sequence[float]) -> float:
        """The energy the robot puts into the workcell going from p_now to target under f."""
        return -math.fsum(fi * (t - p) for fi, t, p in zip(f, target, p_now, strict=True))

    def _drift_step(self, dt_s: float, speed_m_s: float) -> list[float]:
        """The step that gives back the offset at `speed_m_s` (at most `drift_m_s`)."""
        n = math.sqrt(dot(self.offset, self.offset))
        speed = min(speed_m_s, self.drift_m_s)
        if speed <= 0.0 or n == 0.0 or not (dt_s > 0.0):
            return [0.0] * len(self.offset)
        k = min(1.0, speed * dt_s / n)
        return [-k * o for o in self.offset]
