"""What the console shows of time-domain passivity (docs/passivity.md): per port the observed
energies, the reservoir, the controller's action, and whether TDPA is acting.

Pure functions of the newest `PassivityState` of each side (`robot/passivity/master`,
`robot/passivity/slave`) and when they arrived, so they are tested without a page. The
reservoir of a port is what its controller bounds its output by: the other side's `e_in`
for the same engagement (same master, same `engage`; another engagement's counts for
nothing, as in `RemoteEnergy`) minus this port's own `e_out`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

from services.bus.messages import PassivityState

Side = Literal["master", "slave"]
SIDES: tuple[Side, ...] = ("master", "slave")

FRESH_S = 1.0
"""A side whose newest figures are older than this is not shown: both sides publish only
while they observe an engagement (and not at all with passivity off)."""
ACTING_HOLD_S = 0.5
"""A controller that acted within this time is shown as acting: a single damped tick stays
visible, and the console, which takes the figures downsampled, still sees it through
`active_steps`."""


@dataclass(frozen=True, slots=True)
class PortSeen:
    """The newest figures of one side as the console received them: `rx_s` and `acted_s`
    (when its controller was last seen acting; -inf: never) on this process's monotonic
    clock."""

    msg: PassivityState
    rx_s: float
    acted_s: float = -math.inf

    def after(self, msg: PassivityState, rx_s: float) -> PortSeen:
        """The record once `msg` (newer, same side) arrived at `rx_s`: acting when its gain is
        non-zero or its count of acting steps grew within the same engagement."""
        old = self.msg
        same = (old.master, old.engage) == (msg.master, msg.engage)
        acted = msg.gain > 0.0 or (
            msg.active_steps > (old.active_steps if same else 0) and msg.active_steps > 0
        )
        return PortSeen(msg, rx_s, rx_s if acted else self.acted_s)

    @staticmethod
    def first(msg: PassivityState, rx_s: float) -> PortSeen:
        acted = msg.gain > 0.0 or msg.active_steps > 0
        return PortSeen(msg, rx_s, rx_s if acted else -math.inf)


def newer(old: PassivityState, msg: PassivityState) -> bool:
    """Latest-wins: a higher `seq`, or a later `t_ns` (the sender restarted its count)."""
    return msg.seq > old.seq or msg.t_ns > old.t_ns


@dataclass(frozen=True, slots=True)
class PortFigures:
    """One port as shown. Energies in J; `gain` is the controller's last action: the
    master's damping β (N·s/m) or the slave's correction α (m/N)."""

    side: Side
    master: str
    engage: int
    enabled: bool
    e_in_j: float
    e_out_j: float
    remote_in_j: float | None
    """The other side's e_in for this engagement (None: none received)."""
    gain: float
    dissipated_j: float
    active_steps: int
    acting: bool
    asked_n: float | None = None
    shown_n: float | None = None
    """The master's: the force it was asked to display and the one the hand felt, N at the
    tool (None: the slave, or not reported)."""
    repaid_j: float | None = None
    forgiven_j: float | None = None
    """The slave's: what the workcell repaid of its overdraws, and what was forgiven (energy
    the channel created; None: the master, or not reported)."""
    rot_e_in_j: float | None = None
    rot_e_out_j: float | None = None
    """The side's rotational port (moment × rotation), when it runs one (None: it does not)."""
    rtt_ms: float | None = None
    """The round trip this side measured to the other and back (ms; None: not measured)."""

    @property
    def reservoir_j(self) -> float:
        """remote e_in − own e_out: what this port may still give out (< 0: it gave more)."""
        return (self.remote_in_j or 0.0) - self.e_out_j


@dataclass(frozen=True, slots=True)
class TdpaView:
    """The fresh ports (master first); no port: nothing to show (passivity off or idle)."""

    ports: tuple[PortFigures, ...]

    @property
    def state(self) -> Literal["none", "observing", "inactive", "active"]:
        """none: no figures; observing: the controllers are off (figures only); inactive:
        on, nothing to do (the channel is passive); active: a controller is acting."""
        if not self.ports:
            return "none"
        if any(p.acting and p.enabled for p in self.ports):
            return "active"
        return "inactive" if any(p.enabled for p in self.ports) else "observing"

    def port(self, side: Side) -> PortFigures | None:
        return next((p for p in self.ports if p.side == side), None)


def tdpa_view(seen: Mapping[str, PortSeen], now_s: float) -> TdpaView:
    """The view of the newest figures of each side (`seen`: side → record) at `now_s`."""
    fresh = {s: seen[s] for s in SIDES if s in seen and now_s - seen[s].rx_s <= FRESH_S}
    ports = []
    for side in SIDES:
        rec = fresh.get(side)
        if rec is None:
            continue
        m = rec.msg
        other = fresh.get("slave" if side == "master" else "master")
        remote = None
        if other is not None and (other.msg.master, other.msg.engage) == (m.master, m.engage):
            remote = other.msg.e_in
        ports.append(
            PortFigures(
                side=side,
                master=m.master,
                engage=m.engage,
                enabled=m.enabled,
                e_in_j=m.e_in,
                e_out_j=m.e_out,
                remote_in_j=remote,
                gain=m.gain,
                dissipated_j=m.dissipated_j,
                active_steps=m.active_steps,
                acting=now_s - rec.acted_s <= ACTING_HOLD_S,
                asked_n=m.asked_n,
                shown_n=m.shown_n,
                repaid_j=m.repaid_j,
                forgiven_j=m.forgiven_j,
                rot_e_in_j=m.rot_e_in,
                rot_e_out_j=m.rot_e_out,
                rtt_ms=m.rtt_ms,
            )
        )
    return TdpaView(tuple(ports))


def plot_row(view: TdpaView) -> tuple[float, float, float, float]:
    """The plotted values: (master reservoir, slave reservoir, master dissipated, slave
    dissipated), J; a port without figures counts 0."""
    m, s = view.port("master"), view.port("slave")
    return (
        m.reservoir_j if m else 0.0,
        s.reservoir_j if s else 0.0,
        m.dissipated_j if m else 0.0,
        s.dissipated_j if s else 0.0,
    )
