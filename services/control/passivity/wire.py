"""One port's PassivityState, from either side's controller (docs/protocol-extensions.md)."""

from __future__ import annotations

import time
from typing import Literal

from services.bus.messages import PassivityState
from services.control.passivity.controller import MasterPassivity, SlavePassivity
from services.control.passivity.slave import SlavePort


def passivity_state(
    seq: int,
    master: str,
    engage: int,
    side: Literal["master", "slave"],
    pc: MasterPassivity | SlavePassivity | SlavePort,
    force_scale: float = 0.0,
    rot: MasterPassivity | SlavePort | None = None,
    echo: tuple[int, int] | None = None,
    rtt_s: float | None = None,
) -> PassivityState:
    """What the port at `side` has observed and done since `engage` began. force_scale: the
    master display's (operator N per tool N; > 0: the master's asked and shown forces go
    along, as newtons at the tool). The decision's port also sends what the workcell repaid
    of its overdraws and what it forgave. rot: the side's rotational port, when it runs
    one (its energies go as `rot_e_in`, `rot_e_out`, `rot_dissipated_j`). echo: the other
    side's newest `t_ns` and how long it was held (`RoundTrip.echo`); rtt_s: the round trip
    this side measured (s), sent as `rtt_ms`."""
    t = pc.telemetry
    asked = shown = repaid = forgiven = None
    if isinstance(pc, MasterPassivity) and force_scale > 0.0:
        asked, shown = pc.asked_n / force_scale, pc.shown_n / force_scale
    if isinstance(pc, SlavePort):
        repaid, forgiven = pc.recovered_j, pc.forgiven_j
    return PassivityState(
        seq=seq,
        t_ns=time.time_ns(),
        master=master,
        engage=engage,
        side=side,
        enabled=pc.enabled,
        e_in=pc.observer.e_in,
        e_out=pc.observer.e_out,
        dissipated_j=t.dissipated_j,
        gain=t.last_gain,
        active_steps=t.active_steps,
        asked_n=asked,
        shown_n=shown,
        repaid_j=repaid,
        forgiven_j=forgiven,
        rot_e_in=None if rot is None else rot.observer.e_in,
        rot_e_out=None if rot is None else rot.observer.e_out,
        rot_dissipated_j=None if rot is None else rot.telemetry.dissipated_j,
        echo_t_ns=None if echo is None else echo[0],
        echo_age_ns=None if echo is None else echo[1],
        rtt_ms=None if rtt_s is None else min(rtt_s * 1e3, 60_000.0),
    )
