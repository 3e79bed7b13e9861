"""Passivity controllers of the two ports (TDPA, position–force architecture).

Master side (impedance causality: velocity in, force out): a variable damper on the
displayed force, `f' = f − β·v`, with β ≥ 0 chosen so that the energy the channel gives the
operator never exceeds the energy the slave side put into it (`MasterPassivity`).

Slave side (admittance causality: force in, motion out): a correction of the commanded
displacement along the environment force, `dx' = dx + α·f_env`, α ≥ 0, so that the energy the
robot puts into the environment never exceeds the energy the operator put into the channel
(`SlavePassivity`). The corrections add up to an offset between where the master says and
where the slave goes (position drift); `drift_m_s` gives it back at a bounded speed, and
only with energy to spare, so the drift compensation adds no energy either.

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

from services.passivity.observer import EnergyObserver, RemoteEnergy, dot

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

    `step(f, v, dt_s)` takes the force about to be displayed on the hand (N, master frame),
    the hand velocity (m/s) and the tick (s); returns the force to display. `remote` holds
    the slave's input energy as received; `observer.e_in` is what the master sends.
    """

    observer: EnergyObserver = field(default_factory=EnergyObserver)
    remote: RemoteEnergy = field(default_factory=RemoteEnergy)
    telemetry: PortTelemetry = field(default_factory=PortTelemetry)

    def reset(self, epoch: int) -> None:
        """A new engagement: count from zero, listen for the slave's values of `epoch`."""
        self.observer.reset()
        self.remote.reset(epoch)
        self.telemetry.last_gain = 0.0

    @property
    def budget_j(self) -> float:
        """Energy the channel may still give the operator."""
        return self.remote.e_in - self.observer.e_out

    def step(self, f: Sequence[float], v: Sequence[float], dt_s: float) -> list[float]:
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ValueError("dt_s must be positive and finite")
        out = [float(x) for x in f]
        p_out = dot(out, v)
        beta = 0.0
        if p_out > 0.0:
            allowed = max(self.budget_j, 0.0) / dt_s
            vv = dot(v, v)
            if p_out * dt_s > allowed * dt_s + TOLERANCE_J and vv > 0.0:
                beta = (p_out - allowed) / vv
                out = [fi - beta * vi for fi, vi in zip(out, v, strict=True)]
                self.telemetry.dissipated_j += beta * vv * dt_s
                self.telemetry.active_steps += 1
        self.telemetry.last_gain = beta
        self.observer.record(-dot(out, v) * dt_s)
        return out


@dataclass(slots=True)
class SlavePassivity:
    """Slave-side TDPA: observer of the slave port and position-correcting controller.

    `step(f_env, dx)` takes the force the environment applies to the tool (N, world frame)
    and the displacement the master commands for this step (m, world frame); returns the
    displacement to carry out. `offset` is the sum of corrections so far (slave − master).
    drift_m_s: the speed at which the offset is given back when energy allows (0: never).
    """

    drift_m_s: float = 0.0
    observer: EnergyObserver = field(default_factory=EnergyObserver)
    remote: RemoteEnergy = field(default_factory=RemoteEnergy)
    telemetry: PortTelemetry = field(default_factory=PortTelemetry)
    offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])

    def reset(self, epoch: int) -> None:
        """A new engagement: its start pose already includes the offset, which restarts at 0."""
        self.observer.reset()
        self.remote.reset(epoch)
        self.offset = [0.0] * len(self.offset)
        self.telemetry.last_gain = 0.0

    @property
    def budget_j(self) -> float:
        """Energy the robot may still put into the environment."""
        return self.remote.e_in - self.observer.e_out

    def step(self, f_env: Sequence[float], dx: Sequence[float], dt_s: float) -> list[float]:
        if len(dx) != len(self.offset):
            self.offset = [0.0] * len(dx)
        f = [float(x) for x in f_env]
        budget = max(self.budget_j, 0.0)
        want = [float(x) for x in dx]
        comp = self._drift_step(dt_s)
        if any(comp):
            tried = [w + c for w, c in zip(want, comp, strict=True)]
            if max(-dot(f, tried), 0.0) <= budget:
                want = tried
        e_out = -dot(f, want)
        alpha = 0.0
        if e_out > budget + TOLERANCE_J:
            ff = dot(f, f)
            if ff > 0.0:
                alpha = (e_out - budget) / ff
                want = [w + alpha * fi for w, fi in zip(want, f, strict=True)]
                self.telemetry.dissipated_j += alpha * ff
                self.telemetry.active_steps += 1
        self.telemetry.last_gain = alpha
        self.observer.record(dot(f, want))
        self.offset = [o + w - d for o, w, d in zip(self.offset, want, dx, strict=True)]
        return want

    def _drift_step(self, dt_s: float) -> list[float]:
        """The step that gives back the offset at `drift_m_s` at most."""
        n = math.sqrt(dot(self.offset, self.offset))
        if self.drift_m_s <= 0.0 or n == 0.0 or not (dt_s > 0.0):
            return [0.0] * len(self.offset)
        k = min(1.0, self.drift_m_s * dt_s / n)
        return [-k * o for o in self.offset]
