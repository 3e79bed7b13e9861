"""Passivity controllers of the two ports (TDPA, position–force architecture).

Master side (impedance causality: velocity in, force out): a variable damper on the
displayed force, `f' = f − β·v`, with β ≥ 0 chosen so that the energy the channel gives the
operator never exceeds the energy the slave side put into it (`MasterPassivity`).

Slave side (admittance causality: force in, motion out): a correction of the commanded
displacement along the environment force, `dx' = dx + α·f_env`, α ≥ 0, so that the energy the
robot puts into the environment never exceeds the energy the operator put into the channel
(`SlavePassivity`). The corrections add up to an offset between where the master says and
where the slave goes (position drift); `drift_m_s` gives it back at a bounded speed when
the energy to spare pays for it (free in free space). `slack_m` is a backlash along the
environment force that keeps a master jittering against a clipped force from walking the
slave out of contact (holding still exchanges no energy, so it is passive too).

Sampled data: each side observes the energy of the interval just ended with what really
happened in it — the master the force it held times the hand's measured displacement, the
slave the displacement it made (the one it commanded when that is not measured) times the
mean of the forces measured at its start and end (exact for a linear spring) — and its
controller bounds the next interval with the velocity of the last one. A prediction that
falls short shows in the next observation and is paid back at once, so the observed
balance is off by at most one tick's energy, never cumulatively.

With `enabled = False` a side only observes (telemetry with the controller off).

Both follow Ryu, Artigas & Preusche (2010) in the energy-reservoir form: output energy at a
port ≤ the other port's input energy, received late over the link (`RemoteEnergy`). With no
delay and a passive environment the reservoir never runs dry and both controllers are
inactive. Each side restarts its count at a new engagement (`reset(epoch)`): then no energy
is in the channel, so nothing can be released, and the slave's offset is absorbed into the
new engagement's start pose (no jump).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from services.control.passivity.observer import EnergyObserver, RemoteEnergy, dot

TOLERANCE_J = 1e-9
"""Numeric slack (J) below which no controller acts."""


@dataclass(slots=True)
class PortTelemetry:
    """What a controller did: dissipated energy (J), how many steps it acted, the last gain."""

    dissipated_j: float = 0.0
    active_steps: int = 0
    last_gain: float = 0.0


@dataclass(slots=True)
class MasterPassivity:
    """Master-side TDPA: observer of the master port and variable-damping controller.

    `step(f, x, dt_s)` takes the force about to be displayed on the hand (N, master frame),
    the hand position now (m) and the time since the previous step (s); returns the force to
    display until the next step. `remote` holds the slave's input energy as received;
    `observer.e_in` is what the master sends.

    With `limit`, the energy-bounding force limiter (`_bound`) acts last: `mass_kg`,
    `reserve_j`, `hand_rate_n_s` and `horizon_s` shape its bound; `rise` < 1 lets a held-back
    force approach that bound by that fraction of the gap a tick instead of at once.
    `beta_max` (N·s/m) bounds the damper's gain: `β·v` then stays small at small `v`, so a
    hand drifting out by µm/s keeps its force (unbounded, the classic damper cuts all of it
    whenever the reservoir is empty). `telemetry.active_steps` counts the steps either the
    damper or the limiter acted.
    """

    enabled: bool = True
    ramp_n_s: float = 0.0
    limit: bool = False
    mass_kg: float = 0.0
    reserve_j: float = 0.0
    hand_rate_n_s: float = 0.0
    bound_current: bool = True
    damp: bool = True
    horizon_s: float = 0.0
    rise: float = 1.0
    beta_max: float = math.inf
    observer: EnergyObserver = field(default_factory=EnergyObserver)
    remote: RemoteEnergy = field(default_factory=RemoteEnergy)
    telemetry: PortTelemetry = field(default_factory=PortTelemetry)
    limited_steps: int = 0
    asked_n: float = 0.0
    shown_n: float = 0.0
    _f_held: list[float] | None = None
    _x_prev: list[float] | None = None
    _v_prev: list[float] | None = None

    def _bound(self, f: list[float], v: list[float], dt_s: float, measured: bool) -> list[float]:
        """The energy-bounding force limiter: the largest `k·f`, 0 ≤ k ≤ 1, whose work on the
        hand over the next interval fits the reservoir, at the current velocity and at the
        predicted one.

        Predicted velocity (semi-implicit device, force held over the tick):
        `v⁺ = v + a_prev·dt + (k·f − f_held)/m·dt`: the last tick's acceleration carries the
        hand's own force (assumed unchanged for one tick); the second term is what the new
        force itself does to a device of mass m (`mass_kg`; 0: not modelled). Work over the
        interval `W(k) = k·(f·w)·dt + k²·|f|²·dt²/m`, with `w = v + a_prev·dt − f_held/m·dt`;
        the bound is the larger root of `W(k) = R`. A hand pushing into the force
        (`f·w < 0`) is input: the force it holds is paid by that input, up to the root.
        """
        r = max(self.budget_j + self.reserve_j, 0.0)
        ff = dot(f, f)
        if ff <= 0.0:
            return f
        # The next interval: as long as the last one, or `horizon_s` when that is longer (a
        # loop that may run late holds the force longer than its last tick).
        h = max(dt_s, self.horizon_s)
        k = 1.0
        fv = dot(f, v) * h
        if (self.mass_kg <= 0.0 or self.bound_current) and fv > r:
            k = min(k, r / fv)
        inv_m = 1.0 / self.mass_kg if self.mass_kg > 0.0 else 0.0
        held = self._f_held if self._f_held is not None else [0.0] * len(f)
        if measured and self._v_prev is not None and len(self._v_prev) == len(v) == len(held):
            # v + a_prev·dt − f_held/m·dt: the rest of the device's force (the hand's, its
            # damping) as it was over the last tick.
            w = [
                vi + (vi - pi) / dt_s * h - hi * inv_m * h
                for vi, pi, hi in zip(v, self._v_prev, held, strict=True)
            ]
        else:
            # No acceleration known yet (first ticks): the hand's force is taken as zero.
            w = list(v)
        # The hand's force may change by up to hand_rate_n_s·dt within the tick, in the worst
        # direction (along f): that much more velocity along f by the end of it.
        b = (dot(f, w) + math.sqrt(ff) * self.hand_rate_n_s * h * inv_m * h) * h
        a = ff * h * h * inv_m
        if a + b > r:  # no slack: a tick never spends the tolerance
            # The larger root of a·k² + b·k − r = 0 (a = 0: no mass modelled, linear).
            root = (-b + math.sqrt(max(b * b + 4.0 * a * r, 0.0))) / (2.0 * a) if a > 0.0 else r / b
            k = min(k, max(root, 0.0))
        if k < 1.0 and self.rise < 1.0 and len(held) == len(f):
            # While the bound holds the force back, it rises towards the bound by `rise` of
            # the gap a tick, never at once: the bound is the force that stops an inbound
            # hand within one tick, and stopping it that hard overshoots (the device moves
            # back out a few µm, the empty reservoir then cuts the force, the hand falls in
            # again: a buzz at a third of the loop rate, measured over the link). Any k in
            # [0, bound] keeps the bound's guarantee (W(k) is convex with W(0) = 0).
            k_held = min(max(dot(held, f) / ff, 0.0), 1.0)
            if k > k_held:
                k = k_held + self.rise * (k - k_held)
        if k >= 1.0:
            return f
        self.limited_steps += 1
        return [k * fi for fi in f]

    def _ramp(self, f: list[float], dt_s: float) -> list[float]:
        """With the reservoir empty, the force grows at most `ramp_n_s`: it settles at what
        the hand holds instead of kicking the hand back a tick at a time (each kick leaks
        the energy of one tick, since the controller can only see it afterwards)."""
        held = self._f_held if self._f_held is not None else [0.0] * len(f)
        if len(held) != len(f):
            return f
        d = [a - b for a, b in zip(f, held, strict=True)]
        n = math.sqrt(dot(d, d))
        step = self.ramp_n_s * dt_s
        if n <= step or dot(f, f) <= dot(held, held):
            return f
        return [b + di * step / n for b, di in zip(held, d, strict=True)]

    def reset(self, epoch: int) -> None:
        """A new engagement: count from zero, listen for the slave's values of `epoch`."""
        self.observer.reset()
        self.remote.reset(epoch)
        self.telemetry.last_gain = 0.0
        self.asked_n = self.shown_n = 0.0
        self._f_held = None
        self._x_prev = None
        self._v_prev = None

    @property
    def budget_j(self) -> float:
        """Energy the channel may still give the operator."""
        return self.remote.e_in - self.observer.e_out

    def step(self, f: Sequence[float], x: Sequence[float], dt_s: float) -> list[float]:
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ValueError("dt_s must be positive and finite")
        xs = [float(v) for v in x]
        v = [0.0] * len(xs)
        measured = False
        if self._x_prev is not None and len(self._x_prev) == len(xs):
            dx = [a - b for a, b in zip(xs, self._x_prev, strict=True)]
            if self._f_held is not None:
                self.observer.record(-dot(self._f_held, dx))
            v = [d / dt_s for d in dx]
            measured = True
        self._x_prev = xs
        out = [float(fi) for fi in f]
        if self.enabled and self.ramp_n_s > 0.0 and self.budget_j <= TOLERANCE_J:
            out = self._ramp(out, dt_s)
        beta = 0.0
        e_next = dot(out, v) * dt_s
        budget = max(self.budget_j, 0.0)
        vv = dot(v, v)
        if self.enabled and self.damp and e_next > budget + TOLERANCE_J and vv > 0.0:
            beta = min((e_next - budget) / (vv * dt_s), self.beta_max)
            out = [fi - beta * vi for fi, vi in zip(out, v, strict=True)]
            self.telemetry.dissipated_j += beta * vv * dt_s
        self.telemetry.last_gain = beta
        limited = self.limited_steps
        if self.enabled and self.limit:
            # Last, so that whatever the damper did, the force held fits the reservoir.
            out = self._bound(out, v, dt_s, measured)
        if beta > 0.0 or self.limited_steps > limited:
            self.telemetry.active_steps += 1  # the damper or the limiter acted this step
        self._v_prev = v if measured else None
        self._f_held = out
        self.asked_n = math.sqrt(dot(f, f))
        self.shown_n = math.sqrt(dot(out, out))
        return out


@dataclass(slots=True)
class SlavePassivity:
    """Slave-side TDPA: observer of the slave port and position-correcting controller.

    `step(f_env, dx, dt_s)` takes the force the environment applies to the tool now (N, world
    frame) and the displacement the master commands for the next interval (m, world frame);
    returns the displacement to carry out. `offset` is the sum of corrections so far (slave
    − master). drift_m_s: the speed at which the offset is given back when energy allows (0:
    never). slack_m: the backlash along the environment force (0: none).
    """

    enabled: bool = True
    drift_m_s: float = 0.0
    slack_m: float = 0.0
    observer: EnergyObserver = field(default_factory=EnergyObserver)
    remote: RemoteEnergy = field(default_factory=RemoteEnergy)
    telemetry: PortTelemetry = field(default_factory=PortTelemetry)
    offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    _absorbed_m: float = 0.0
    _dx_prev: list[float] | None = None
    _f_prev: list[float] | None = None

    def reset(self, epoch: int) -> None:
        """A new engagement: its start pose already includes the offset, which restarts at 0."""
        self.observer.reset()
        self.remote.reset(epoch)
        self.offset = [0.0] * len(self.offset)
        self._absorbed_m = 0.0
        self._dx_prev = None
        self._f_prev = None
        self.telemetry.last_gain = 0.0

    def rebase(self) -> None:
        """The slave's start pose was taken afresh (same energies, new engagement of the
        arm): the offset is in that pose now."""
        self.offset = [0.0] * len(self.offset)
        self._absorbed_m = 0.0

    @property
    def budget_j(self) -> float:
        """Energy the robot may still put into the environment."""
        return self.remote.e_in - self.observer.e_out

    def step(
        self,
        f_env: Sequence[float],
        dx: Sequence[float],
        dt_s: float,
        done: Sequence[float] | None = None,
    ) -> list[float]:
        """done: the displacement the tool really made over the interval just ended, when
        it is measured (a speed-limited arm); the observer then counts it, not the command:
        only that motion crossed the port. A command the arm has not yet made (`dx` is then
        the whole motion still to come) would otherwise be counted again every tick it
        stays pending: an arm catching up at its speed limit at an impact showed twice its
        output (docs/passivity.md, "The slave's speed"), as the decision's `SlavePort`
        does not (it observes the measured motion)."""
        f = [float(x) for x in f_env]
        if self._dx_prev is not None and len(self._dx_prev) == len(f):
            f_mid = f
            if self._f_prev is not None and len(self._f_prev) == len(f):
                f_mid = [(a + b) / 2 for a, b in zip(f, self._f_prev, strict=True)]
            if done is not None and len(done) == len(f):
                e = dot(f_mid, [float(x) for x in done])
            else:
                e = dot(f_mid, self._dx_prev)
            self.observer.record(e)
        self._f_prev = f
        if len(dx) != len(self.offset):
            self.offset = [0.0] * len(dx)
        want = [float(x) for x in dx]
        if not self.enabled:
            self._dx_prev = want
            return want
        budget = max(self.budget_j, 0.0)
        want = self._absorb(want, f)
        comp = self._drift_step(dt_s)
        if any(comp):
            tried = [w + c for w, c in zip(want, comp, strict=True)]
            if max(-dot(f, tried), 0.0) <= max(budget, 0.0):
                want = tried
        e_out = -dot(f, want)
        alpha = 0.0
        ff = dot(f, f)
        if e_out > budget + TOLERANCE_J and ff > 0.0:
            alpha = (e_out - budget) / ff
            want = [w + alpha * fi for w, fi in zip(want, f, strict=True)]
            self.telemetry.dissipated_j += alpha * ff
            self.telemetry.active_steps += 1
        self.telemetry.last_gain = alpha
        self.offset = [o + w - d for o, w, d in zip(self.offset, want, dx, strict=True)]
        self._dx_prev = want
        return want

    def _absorb(self, dx: list[float], f: list[float]) -> list[float]:
        """A backlash of `slack_m` along the environment force: a step back out of the
        environment is not taken until the master has come back `slack_m` (and a step in
        first takes up what was absorbed), so the tick-rate jitter of a master held against
        a clipped force cannot walk the slave out of contact. Holding still exchanges no
        energy: passive.
        """
        ff = dot(f, f)
        if ff <= 0.0 or self.slack_m <= 0.0:
            self._absorbed_m = 0.0
            return dx
        norm = math.sqrt(ff)
        u = [fi / norm for fi in f]
        back = dot(dx, u)
        if back > 0.0:
            take = min(back, self.slack_m - self._absorbed_m)
        else:
            take = max(back, -self._absorbed_m)
        self._absorbed_m += take
        return [d - take * ui for d, ui in zip(dx, u, strict=True)]

    def _drift_step(self, dt_s: float) -> list[float]:
        """The step that gives back the offset at `drift_m_s` at most."""
        n = math.sqrt(dot(self.offset, self.offset))
        if self.drift_m_s <= 0.0 or n == 0.0 or not (dt_s > 0.0):
            return [0.0] * len(self.offset)
        k = min(1.0, self.drift_m_s * dt_s / n)
        return [-k * o for o in self.offset]
