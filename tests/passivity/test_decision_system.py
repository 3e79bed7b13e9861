"""The decision server with `passivity = true`, with the simulated puma and force sensor: a
master that puts no energy into the channel cannot press the tool into the table; once its
energy arrives, the motion into the contact goes on (until the supervisor's contact limit),
and the slave's energies go out on `robot/passivity/slave`."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

from services.bus import keys
from services.bus.messages import PassivityState
from tests.decision.test_system import TOP, Cell, make_cell  # noqa: F401  (a fixture)

pytestmark = [pytest.mark.system, pytest.mark.timeout(90)]


def test_the_slave_does_not_press_without_the_operator_s_energy(
    make_cell: Callable[..., Cell],  # noqa: F811
) -> None:
    cell = make_cell(passivity=True)
    seen: list[PassivityState] = []
    lock = threading.Lock()

    def keep(m: PassivityState) -> None:
        with lock:
            seen.append(m)

    cell.console.subscribe(keys.PASSIVITY_SLAVE, keep)
    energy = cell.console.publisher(keys.PASSIVITY_MASTER)
    m = cell.master("m1")
    start_z = float(cell.tool_p()[2])
    depth = start_z - (TOP - 0.01)  # the hand asks for 1 cm into the table

    def down(t: float) -> tuple[float, float, float]:
        return (0.0, 0.0, -min(0.1 * t, depth))

    m.engage_new(down)
    # Free motion costs nothing: the tool comes down to the table and touches it.
    touching = cell.robot(lambda s: s.tool_p[2] < TOP + 0.006, 15.0)
    n = cell.puma_cmds.count()
    cell.puma_cmds.wait_more(n, 250, 10.0)  # 0.5 s of the master pushing on
    held = cell.robot(lambda s: s.seq > touching.seq)
    f_held = float(np.linalg.norm(cell.call("sensor_read")["f"]))
    assert f_held < 40.0  # the supervisor's contact limit was never needed
    assert held.tool_p[2] > TOP  # the probe (5 mm radius) did not go through the table top
    with lock:
        mine = [s for s in seen if s.master == "m1"]
    assert mine and mine[-1].side == "slave" and mine[-1].engage == m.engage
    assert cell.decision.passivity is not None
    assert cell.decision.passivity.pc.telemetry.active_steps > 0
    # The operator's energy arrives: the tool presses on, to the contact limit.
    stop = threading.Event()

    def pay() -> None:
        k = 0
        while not stop.is_set():
            k += 1
            energy.put(
                PassivityState(
                    seq=k, t_ns=time.time_ns(), master="m1", engage=m.engage, side="master",
                    enabled=True, e_in=100.0, e_out=0.0, dissipated_j=0.0, gain=0.0,
                    active_steps=0,
                )
            )  # fmt: skip
            stop.wait(0.01)

    payer = threading.Thread(target=pay, daemon=True)
    payer.start()
    try:
        ev = cell.events.wait(lambda e: e.kind == "contact" and e.source == "decision", 10.0)
        assert ev.data is not None and ev.data["force_n"] > 40.0
    finally:
        stop.set()
        payer.join(timeout=2.0)
